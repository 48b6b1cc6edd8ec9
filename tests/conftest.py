"""Shared fixtures: small, valid sequences and meshes made on the fly (no downloads)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dexflow.human.model import forward_keypoints
from dexflow.io.sequence import Sequence


def make_sequence(num_frames: int = 10, obj_mesh: str = "meshes/box.obj") -> Sequence:
    """A right hand closing slowly next to a box that slides along x."""
    angles = np.linspace(0.0, 0.6, num_frames)[:, None] * np.ones(20)
    wrist = np.repeat(np.eye(4)[None], num_frames, axis=0)
    wrist[:, :3, 3] = [0.0, 0.0, 0.1]
    pose = np.repeat(np.eye(4)[None], num_frames, axis=0)
    pose[:, 0, 3] = np.linspace(0.0, 0.05, num_frames)
    return Sequence(
        keypoints=forward_keypoints(angles, wrist),
        obj_pose=pose,
        obj_mesh=obj_mesh,
        obj_name="box",
        fps=30.0,
        source="test",
    )


@pytest.fixture
def sequence() -> Sequence:
    return make_sequence()


@pytest.fixture
def data_root(tmp_path):
    """A data root holding ``meshes/box.obj`` (a 6 x 4 x 8 cm box)."""
    (tmp_path / "meshes").mkdir()
    trimesh.creation.box(extents=(0.06, 0.04, 0.08)).export(tmp_path / "meshes" / "box.obj")
    return tmp_path


@pytest.fixture(autouse=True, scope="session")
def _asset_cache(tmp_path_factory):
    """Tests (and the stages they start) cache object assets in a folder of their own, never
    in the user's ``~/.cache/dexflow``."""
    import os

    from dexflow.objects.convex import CACHE_ENV

    previous = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(tmp_path_factory.mktemp("asset-cache"))
    yield
    if previous is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = previous


@pytest.fixture(scope="session")
def reproduced_demo(tmp_path_factory):
    """A git + DVC copy of this project with a small demo (:func:`tests.quick_pipeline.small_demo`),
    committed, then ``dvc repro``'d once: ``(folder, what dvc repro printed)``. The slow
    end-to-end tests share it and change only copies of it (:func:`tests.quick_pipeline.copy_reproduced`)."""
    import sys

    from tests import quick_pipeline as qp

    project = tmp_path_factory.mktemp("reproduced") / "project"
    qp.copy_project(project)
    qp.small_demo(project / "conf")
    qp.run([sys.executable, "-m", "dexflow.tools.cli", "params"], project, project)
    qp.run("git init -q -b main && git add -A && git commit -qm init", project)
    return project, qp.run(["dvc", "repro"], project, project)
