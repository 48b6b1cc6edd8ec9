"""Stage hand: the hand model and every file it reads, copied where DVC tracks them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from dexflow.errors import HandConfigError
from dexflow.hands.files import (
    copy_model,
    model_files,
    resolve_model_path,
    staged_spec,
)
from dexflow.hands.robot import RobotHand
from dexflow.hands.spec import load_hand_spec
from dexflow.io.layout import Layout
from dexflow.params import PipelineParams
from dexflow.stages.hand import run_hand

SHADOW = "pkg://gymnasium_robotics/envs/assets/hand/reach.xml"
ALLEGRO = "pkg://dexflow/hands/assets/allegro_right.urdf"


def test_an_mjcf_lists_its_includes_and_the_meshes_of_its_compiler_meshdir():
    files = model_files(resolve_model_path(SHADOW))
    names = [f.name for f in files]
    assert names[0] == "reach.xml"
    assert {"robot.xml", "shared.xml", "shared_asset.xml"} <= set(names)
    meshes = [f for f in files if f.suffix == ".stl"]
    assert meshes and all(
        f.parent.name == "hand" and f.parent.parent.name == "stls" for f in meshes
    )
    assert len(names) == len(set(files))


def _urdf_with_mesh(folder: Path) -> Path:
    """A one-link URDF whose collision is a mesh in a subdirectory (a user's own model)."""
    (folder / "meshes").mkdir(parents=True)
    (folder / "meshes" / "palm.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nf 1 2 3\n")
    urdf = folder / "mine.urdf"
    urdf.write_text(
        '<robot name="mine"><link name="base"><collision><geometry>'
        '<mesh filename="meshes/palm.obj"/></geometry></collision></link></robot>'
    )
    return urdf


def test_a_urdf_lists_its_meshes_and_a_missing_one_is_named(tmp_path):
    urdf = _urdf_with_mesh(tmp_path)
    assert model_files(urdf) == [urdf.resolve(), (tmp_path / "meshes/palm.obj").resolve()]
    (tmp_path / "meshes/palm.obj").unlink()
    with pytest.raises(HandConfigError, match=r"mesh filename='meshes/palm.obj'.*not found"):
        model_files(urdf)


def test_a_missing_mjcf_include_is_named(tmp_path):
    (tmp_path / "hand.xml").write_text('<mujoco><include file="parts.xml"/></mujoco>')
    with pytest.raises(HandConfigError, match=r"include file='parts.xml'.*not found"):
        model_files(tmp_path / "hand.xml")


def test_the_copy_keeps_relative_paths_and_its_record_changes_with_any_file(tmp_path):
    urdf = _urdf_with_mesh(tmp_path / "src")
    record = copy_model(str(urdf), None, tmp_path / "out")
    assert record["model"] == "model/mine.urdf" and record["source"] == str(urdf)
    assert sorted(record["files"]) == ["model/meshes/palm.obj", "model/mine.urdf"]
    assert (tmp_path / "out/model/meshes/palm.obj").read_bytes() == (
        tmp_path / "src/meshes/palm.obj"
    ).read_bytes()
    written = (tmp_path / "out/hand.json").read_text()
    assert json.loads(written) == record and str(tmp_path) not in json.dumps(record["files"])
    # An edited mesh (not the model file itself) changes what DVC hashes.
    with (tmp_path / "src/meshes/palm.obj").open("a") as f:
        f.write("v 0 0 0.01\n")
    again = copy_model(str(urdf), None, tmp_path / "out")
    assert again["files"]["model/meshes/palm.obj"] != record["files"]["model/meshes/palm.obj"]
    assert (tmp_path / "out/hand.json").read_text() != written


def test_the_stages_load_the_copy_and_refuse_a_missing_or_stale_one(tmp_path):
    params = PipelineParams()
    params.hand, _ = load_hand_spec("shadow")
    layout = Layout.of(tmp_path / "data", root=tmp_path / "project")
    with pytest.raises(HandConfigError, match=r"no copy of the hand model.*dvc repro"):
        staged_spec(params.hand, layout.hand_files.root)
    run_hand(params, layout)
    spec = staged_spec(params.hand, layout.hand_files.root)
    assert Path(spec.model).is_relative_to(layout.hand_files.root.resolve())
    # The copy gives the hand the original gives: same joints, same forward kinematics.
    copied, original = RobotHand(spec, None), RobotHand(params.hand, None)
    assert copied.joint_names == original.joint_names
    q = original.zero(3) + 0.1 * torch.rand(
        3, original.dof, generator=torch.Generator().manual_seed(0)
    )
    np.testing.assert_allclose(copied.keypoints(q), original.keypoints(q), atol=1e-12)

    other, _ = load_hand_spec("allegro")
    with pytest.raises(HandConfigError, match=r"holds a copy of hand model .*reach.xml"):
        staged_spec(other, layout.hand_files.root)


def test_an_mjcf_copy_missing_a_file_it_reads_fails_the_stage(tmp_path, monkeypatch):
    """If dexflow.hands.files missed a file an MJCF reads, the stage says so (MuJoCo compiles
    the copy) instead of a later stage failing on every sequence."""
    import dexflow.hands.files as files

    listed = files.model_files

    def without_meshes(path):
        return [f for f in listed(path) if f.suffix != ".stl"]

    monkeypatch.setattr(files, "model_files", without_meshes)
    params = PipelineParams()
    params.hand, _ = load_hand_spec("shadow")
    layout = Layout.of(tmp_path / "data", root=tmp_path / "project")
    with pytest.raises(HandConfigError, match="does not compile"):
        run_hand(params, layout)
