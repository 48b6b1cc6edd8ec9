"""Test projects: settings that make a whole pipeline cheap without leaving out any of its
code, a copy of this project to run it in, and the git + DVC environment to run it with.

The end-to-end tests check that every stage runs and hands the next one what it needs, not how
good the refined grasps are (tests/test_refine.py measures that at the defaults). Refinement at
the defaults is most of an end-to-end test's time (four rounds of 60 L-BFGS iterations); here it
runs every one of its steps (the per-finger step, the first release, a last release with its
continuation round) with fewer iterations each. And the stages run their sequences in their own
process: a worker pool's start costs more than a few short sequences take (tests/test_scale.py
and tests/test_untrusted_pipeline.py test the pools).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

REFINE = {
    "iterations": 5,
    "release_first_iterations": 5,
    "release_iterations": 10,
    "release_rounds": 1,
}


def overrides() -> list[str]:
    """The settings as Hydra overrides (for `dexflow params` and `compose_params`)."""
    return [f"refine.{key}={value}" for key, value in REFINE.items()] + ["run=sequential"]


def write_conf(conf: Path) -> None:
    """Write the settings into a copied ``conf/`` (for `dvc exp run`, which composes from it)."""
    path = conf / "refine" / "default.yaml"
    text = path.read_text()
    for key, value in REFINE.items():
        text, n = re.subn(rf"^{key}: *\S+", f"{key}: {value}", text, flags=re.M)
        assert n == 1, f"{path}: no line '{key}: ...' to set"
    path.write_text(text)
    _edit(conf / "config.yaml", "- run: local", "- run: sequential")


def small_demo(conf: Path, frames: tuple[int, int] = (40, 50)) -> None:
    """Edit a copied ``conf/`` for a two-sequence demo of one object (``frames``: its least and
    most frames), three frames tested per trajectory by stage simulate and the quick settings
    (:func:`write_conf`)."""
    _edit(conf / "demo" / "default.yaml", "objects: []", "objects: [061_foam_brick]")
    _edit(conf / "demo" / "default.yaml", "min_frames: 60", f"min_frames: {frames[0]}")
    _edit(conf / "demo" / "default.yaml", "max_frames: 150", f"max_frames: {frames[1]}")
    _edit(conf / "simulate" / "default.yaml", "max_frames: 0", "max_frames: 3")
    write_conf(conf)


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{path}: no {old!r}"
    path.write_text(text.replace(old, new))


def copy_project(dst: Path, params: bool = False) -> None:
    """This project's files as the working tree holds them (tracked and new, not ignored):
    ``conf/``, ``dexflow/``, ``stages/``, ``.dvc/`` config, ``dvc.yaml`` and the dot files
    (``params.yaml`` too if ``params``)."""
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT, capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    top = {"dvc.yaml", ".dvcignore", ".gitignore", "pyproject.toml"} | (
        {"params.yaml"} if params else set()
    )
    for rel in listed.splitlines():
        if (rel.startswith(("conf/", "dexflow/", "stages/", ".dvc/")) or rel in top) and (
            ROOT / rel
        ).is_file():
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / rel, dst / rel)


def env(project: Path | None = None) -> dict[str, str]:
    """The environment test projects run in: a git identity, DVC's analytics off and, with
    ``project``, the project's own copy of dexflow first on the path (as a sweep's jobs run)."""
    found = {**os.environ, "DVC_NO_ANALYTICS": "1", "GIT_AUTHOR_NAME": "t",
             "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}  # fmt: skip
    if project is not None:
        found["PYTHONPATH"] = os.pathsep.join([str(project), found.get("PYTHONPATH", "")])
    return found


def run(command: list[str] | str, cwd: Path, project: Path | None = None) -> str:
    """Run ``command`` (a string: through the shell) in ``cwd``; its output, asserting it
    succeeded."""
    proc = subprocess.run(command, shell=isinstance(command, str), cwd=cwd, env=env(project),
                          capture_output=True, text=True, timeout=900)  # fmt: skip
    out = proc.stdout + proc.stderr
    shown = command if isinstance(command, str) else " ".join(command)
    assert proc.returncode == 0, f"{shown} failed:\n{out}"
    return out


def copy_reproduced(reproduced: tuple[Path, str], dst: Path) -> Path:
    """A copy at ``dst`` of the project of the ``reproduced_demo`` fixture (tests/conftest.py),
    its git history and DVC cache too, for a test to change."""
    shutil.copytree(reproduced[0], dst, symlinks=True)
    return dst
