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

import logging
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dexflow.pipeline.registry import Stage, stage_spec

if TYPE_CHECKING:
    from dexflow.io.layout import Layout
    from dexflow.params import PipelineParams

__all__ = ["remove_path", "run_command", "run_in_process"]

log = logging.getLogger("dexflow.pipeline")
_PYTHON = ("python", "python3")


def remove_path(path: Path) -> None:
    """Remove a file, a link (never what it points to) or a folder tree, if there."""
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.is_dir():
        shutil.rmtree(path)


def run_in_process(stage: Stage, params: PipelineParams, layout: Layout) -> dict:
    """Run ``stage`` (``name`` or ``name@item``) in this process, as its script would:
    :func:`dexflow.pipeline.runner.run_stage` of its ``STAGE`` with the ``foreach`` item as the
    argument. Returns the stage's summary (timing included)."""
    from dexflow.pipeline.runner import run_stage

    _, _, item = stage.name.partition("@")
    return run_stage(stage_spec(stage.name), params, layout, (item,) if item else ())


def _command(cmd: str) -> str:
    """The stage's command with a leading ``python`` replaced by this interpreter."""
    parts = cmd.strip().split(maxsplit=1)
    if parts and parts[0] in _PYTHON:
        return " ".join([shlex.quote(sys.executable), *parts[1:]])
    return cmd


def run_command(stage: Stage, folder: Path) -> str | None:
    """Run ``stage.cmd`` in the job directory, streaming its output to the job's log.

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
        return None
    reason = f"exit status {proc.returncode}"
    return f"{reason}: {last}" if last else reason
