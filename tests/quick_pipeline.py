"""Settings that make a test project's whole pipeline cheap without leaving out any of its code.

The end-to-end tests check that every stage runs and hands the next one what it needs, not how
good the refined grasps are (tests/test_refine.py measures that at the defaults). Refinement at
the defaults is most of an end-to-end test's time (four rounds of 60 L-BFGS iterations); here it
runs every one of its steps (the per-finger step, the first release, a last release with its
continuation round) with fewer iterations each.
"""

from __future__ import annotations

import re
from pathlib import Path

REFINE = {
    "iterations": 5,
    "release_first_iterations": 5,
    "release_iterations": 10,
    "release_rounds": 1,
}


def overrides() -> list[str]:
    """The settings as Hydra overrides (for `dexflow params` and `compose_params`)."""
    return [f"refine.{key}={value}" for key, value in REFINE.items()]


def write_conf(conf: Path) -> None:
    """Write the settings into a copied ``conf/`` (for `dvc exp run`, which composes from it)."""
    path = conf / "refine" / "default.yaml"
    text = path.read_text()
    for key, value in REFINE.items():
        text, n = re.subn(rf"^{key}: *\S+", f"{key}: {value}", text, flags=re.M)
        assert n == 1, f"{path}: no line '{key}: ...' to set"
    path.write_text(text)
