"""Every command in the README's code blocks runs, as a user would type it.

The two fresh-machine commands are checked against `.ci/run` (CI runs the test command as it
stands; the install is the same line) and their `dvc repro` is run by tests/test_pipeline.py on a
small demo. The other blocks run here for real in a copy of the project: the numpy snippet on a
sequence from the demo generator, then `dexflow convert generic`, `dvc add`, `dexflow params`,
`dvc repro`, the sweep's queue and `dexflow exp`. A code block this test does not know fails it.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from dexflow.tools.export import read_export
from tests import quick_pipeline

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", README.read_text(), flags=re.M | re.S)


def _commands(block: str) -> list[str]:
    """The block's shell commands, comments dropped."""
    lines = (line.split("  #")[0].strip() for line in block.splitlines())
    return [line for line in lines if line and not line.startswith("#")]


def _sh(command: str, cwd: Path) -> str:
    return quick_pipeline.run(command, cwd)


def test_the_readme_stays_a_front_page():
    assert len(README.read_text().splitlines()) <= 200
    for link in re.findall(r"\]\(((?:docs/|CHANGELOG|reports/)[^)#]*)", README.read_text()):
        assert (ROOT / link).exists(), f"README links to {link}, which does not exist"


def test_the_two_commands_are_the_ones_ci_runs():
    install_and_run, install_and_test = (_commands(b)[0] for b in _blocks("bash")[:2])
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    assert install_and_test == ci
    torch, package, run = (part.strip() for part in install_and_run.split("&&"))
    assert ci.startswith(f"{torch} && ") and package == "pip install -e ." and run == "dvc repro"
    assert "--extra-index-url https://download.pytorch.org/whl/cpu" in torch  # no CUDA build


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    """A git repository with this project's tracked files, quick settings (tests/quick_pipeline)
    and one short demo sequence as the user's arrays."""
    dst = tmp_path_factory.mktemp("readme") / "project"
    quick_pipeline.copy_project(dst, params=True)
    quick_pipeline.write_conf(dst / "conf")
    simulate = dst / "conf" / "simulate" / "default.yaml"
    simulate.write_text(simulate.read_text().replace("max_frames: 0", "max_frames: 2"))
    demo = dst.parent / "demo"
    _sh(f"{sys.executable} -m dexflow.tools.cli demo {demo} demo.objects=[025_mug] "
        "demo.sequences_per_object=1 demo.min_frames=40 demo.max_frames=45", dst)  # fmt: skip
    (seq,) = (demo / "sequences").glob("*.npz")
    with np.load(seq) as data:
        arrays = {"keypoints": data["keypoints"], "obj_pose": data["obj_pose"]}
        mesh = demo / str(data["obj_mesh"])
    (dst / "captures").mkdir()
    shutil.copy2(mesh, dst / "captures" / "mug.obj")
    np.savez(dst / "arrays.npz", **arrays)
    _sh("git init -q -b main && git add -A && git commit -qm init", dst)
    return dst


@pytest.mark.slow
def test_every_readme_block_runs(project):
    python_blocks, bash_blocks = _blocks("python"), _blocks("bash")
    assert len(python_blocks) == 1 and len(bash_blocks) == 5, "a new README block: test it here"

    # Bring your own data: the snippet with the user's arrays, then the commands
    arrays = dict(np.load(project / "arrays.npz"))
    cwd = os.getcwd()
    os.chdir(project)
    try:
        exec(python_blocks[0], {**arrays})
    finally:
        os.chdir(cwd)
    ran = "".join(_sh(command, project) for command in _commands(bash_blocks[2]))
    assert "Running stage 'report'" in ran and "Running stage 'demo" not in ran  # no demo to make
    summary = (project / "reports" / "summary.md").read_text()
    assert "Data: **generic**" in summary and "Sequences: 1 in the data, 1 through" in summary

    # The sweep: queued as written (running the queue is `dvc exp run`, which test_pipeline
    # runs), then the comparison of the experiments
    queue, start, compare = _commands(bash_blocks[3])
    assert start == "dvc queue start -j 2 && dvc queue status"
    _sh(queue, project)
    status = _sh("dvc queue status", project)
    assert status.count("Queued") == 4, status
    _sh("dvc queue remove --queued", project)
    out = _sh(shlex.join([sys.executable, "-m", "dexflow.tools.cli", *shlex.split(compare)[1:]]),
              project)  # fmt: skip
    assert "experiment" in out.splitlines()[0] and "SSR" in out.splitlines()[0], out

    # Export: the one sequence, read back
    (export,) = _commands(bash_blocks[4])
    _sh(export, project)
    episodes = read_export(project / "exports" / "refine.h5").episodes
    assert len(episodes) == 1 and episodes[0].q.shape[0] == arrays["keypoints"].shape[0]
