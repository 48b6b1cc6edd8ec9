"""The one executor of registry stages: every runner outside DVC runs a stage through it.

- :func:`run_command` runs a stage's ``cmd`` in a folder as DVC would (a subprocess, the stage's
  outputs removed first unless they persist), streaming its output to the log: what
  ``dexflow-sweep`` and the ablation suite do in each job's folder
  (:func:`dexflow.tools.sweep.run_job`).
- :func:`run_in_process` runs a stage's :class:`~dexflow.pipeline.runner.StageSpec` in this
  process with given params and layout (no interpreter start, so that its timing is the
  stage's): what ``dexflow bench pipeline`` and ``dexflow bench real`` do.

Both take a :class:`~dexflow.pipeline.registry.Stage` of :func:`~dexflow.pipeline.registry.load_stages`,
so neither knows the pipeline's order, commands or outputs but from ``dvc.yaml``.
"""

from __future__ import annotations

import json
import logging
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dexflow.io.atomic import save_json
from dexflow.pipeline.registry import Stage, stage_spec

if TYPE_CHECKING:
    from dexflow.io.layout import Layout
    from dexflow.params import PipelineParams

__all__ = [
    "TIMING_DIR",
    "record_key",
    "recorded_key",
    "remove_path",
    "run_command",
    "run_in_process",
]

TIMING_DIR = "reports/timing"  # as dexflow.io.layout has it

log = logging.getLogger("dexflow.pipeline")
_PYTHON = ("python", "python3")


def remove_path(path: Path) -> None:
    """Remove a file, a link (never what it points to) or a folder tree, if there."""
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.is_dir():
        shutil.rmtree(path)


def recorded_key(stage: Stage, folder: Path) -> str | None:
    """The key recorded with the outputs of ``stage`` in ``folder`` (:func:`record_key`), or
    None."""
    try:
        record = json.loads((folder / TIMING_DIR / f"{stage.tag}.json").read_text("utf-8"))
    except (OSError, ValueError):
        return None
    found = record.get("key") if isinstance(record, dict) else None
    return found if isinstance(found, str) else None


def record_key(stage: Stage, folder: Path, key: str) -> None:
    """Record ``key`` (:mod:`dexflow.pipeline.validity`) with the outputs ``stage`` made in
    ``folder``, in its ``reports/timing/<tag>.json`` (a dexflow stage's runner has written it
    there already; a command of another kind gets a record holding the key alone)."""
    path = folder / TIMING_DIR / f"{stage.tag}.json"
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        record = {}
    record = record if isinstance(record, dict) else {}
    if record.get("key") != key:
        save_json(path, {**record, "key": key})


def run_in_process(stage: Stage, params: PipelineParams, layout: Layout) -> dict:
    """Run ``stage`` in this process, as its script would: :func:`dexflow.pipeline.runner.run_stage`
    of its ``STAGE`` with the script's arguments in ``cmd`` (``python stages/simulate.py
    refine`` -> ``("refine",)``). Returns the stage's summary (timing included)."""
    from dexflow.pipeline.runner import run_stage

    words = shlex.split(stage.cmd)
    script = next((i for i, w in enumerate(words) if w.endswith(".py")), len(words))
    return run_stage(stage_spec(stage.name), params, layout, tuple(words[script + 1 :]))


def _command(cmd: str) -> str:
    """The stage's command with a leading ``python`` replaced by this interpreter."""
    parts = cmd.strip().split(maxsplit=1)
    if parts and parts[0] in _PYTHON:
        return " ".join([shlex.quote(sys.executable), *parts[1:]])
    return cmd


def run_command(stage: Stage, folder: Path, key: str | None = None) -> str | None:
    """Run ``stage.cmd`` in ``folder`` (a project or a sweep job), streaming its output to the
    log; on success record ``key`` (the stage's key there, computed before it ran) with its
    outputs (:func:`record_key`).

    Returns:
        None on success, else a one-line reason (exit status and the last line it printed).
    """
    for rel in stage.outputs:
        out = folder / rel
        # Never write into the project through a link; and, as DVC does, a stage writes its
        # outputs from scratch unless they persist (resumable stages).
        if out.is_symlink() or rel not in stage.persist:
            remove_path(out)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    last = ""
    with subprocess.Popen(
        _command(stage.cmd),
        shell=True,
        cwd=folder,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        bufsize=1,
    ) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip()
            if line:
                log.info("[%s] %s", stage.name, line)
                last = line
    if proc.returncode == 0:
        if key is not None:
            record_key(stage, folder, key)
        return None
    reason = f"exit status {proc.returncode}"
    return f"{reason}: {last}" if last else reason
