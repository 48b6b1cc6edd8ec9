"""The one key that says whether a stage's outputs are still valid.

A stage's outputs are valid for exactly what made them: its command, the values of the params
it declares and the bytes of every dep -- what DVC records for it in ``dvc.lock`` and compares
on ``dvc repro``. :func:`stage_key` digests those same three things of a registry stage
(:class:`~dexflow.pipeline.registry.Stage`), so that the runners outside DVC decide as DVC does:

- the stage runner (:func:`dexflow.pipeline.runner.run_stage`) computes the key when a stage
  starts; it is the fingerprint an interrupted run is resumed under
  (:class:`dexflow.pipeline.resume.StageOutput`: another key empties the output folder), and it
  is recorded with the finished outputs in ``reports/timing/<tag>.json`` (``key``);
- a sweep job or an ablation experiment (:func:`dexflow.tools.sweep.run_job`) keeps its own
  outputs, or reuses the project's, only where the recorded key equals the key the stage has in
  the job; a stage whose key is not recorded (outputs restored from git or the DVC cache) is run.

So a changed param, a changed dependency file (code or data) or a changed command invalidates
the outputs in every runner alike, and an upstream stage that ran again but wrote the same bytes
does not. The content-addressed cache of convex parts (:mod:`dexflow.objects.convex`) is a memo
inside stage scale_align, keyed by the mesh's bytes and the decomposition's settings; the
outputs it helps make are keyed here like any others.

A dep is read in the folder the stage runs in (the project, or a sweep job whose upstream
outputs are links to the project's or its own), else in dexflow's checkout (the code: a job
folder holds no ``dexflow/``). Folders are digested file by file (relative names and bytes),
leaving out dot-files (bookkeeping, temporaries) and ``__pycache__``.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from dexflow.pipeline.registry import Stage, lookup

__all__ = [
    "CHECKOUT",
    "RUNNING_KEY",
    "file_digest",
    "key",
    "params_values",
    "path_digest",
    "stage_key",
]

CHECKOUT = Path(__file__).resolve().parents[2]  # where dvc.yaml's dexflow/... deps live
_MISSING = "missing"
# The key of the stage this process runs, set by the stage runner while the stage runs.
RUNNING_KEY: ContextVar[str | None] = ContextVar("RUNNING_KEY", default=None)


def file_digest(path: str | Path) -> str:
    """sha1 of a file's bytes."""
    digest = hashlib.sha1()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _listed(root: Path) -> Iterable[Path]:
    """The files below ``root``, sorted, links followed (a sweep job's folder holds links to
    the project's outputs, even below a folder of its own: ``data/retarget/dexflow``)."""
    found = []
    for folder, dirs, files in os.walk(root, followlinks=True):
        dirs[:] = [d for d in dirs if not d.startswith(".") and d != "__pycache__"]
        found += [Path(folder) / f for f in files if not f.startswith(".")]
    return sorted(found, key=lambda p: p.relative_to(root).as_posix())


def path_digest(path: str | Path) -> str:
    """sha1 of a file's bytes, or of a folder's files (relative names and bytes); ``missing``
    where there is nothing."""
    path = Path(path)
    if path.is_file():
        return file_digest(path)
    if not path.is_dir():
        return _MISSING
    digest = hashlib.sha1()
    for file in _listed(path):
        digest.update(file.relative_to(path).as_posix().encode() + b"\0")
        digest.update(file_digest(file).encode() + b"\0")
    return digest.hexdigest()


def key(command: str, params: Mapping[str, Any], deps: Mapping[str, str]) -> str:
    """The key of outputs made by ``command`` with ``params`` (plain JSON values) from ``deps``
    (name -> :func:`path_digest`): sha1 of their canonical JSON."""
    text = json.dumps(
        {"cmd": command, "params": params, "deps": dict(deps)}, sort_keys=True, default=str
    )
    return hashlib.sha1(text.encode()).hexdigest()


def params_values(params_file: str | Path) -> dict[str, Any]:
    """The params a key is computed from: ``params.yaml`` loaded and validated as a stage
    loads it (:func:`dexflow.config.load_params`, the schema's defaults filled in), as plain
    values, so that the runner inside a stage and a sweep outside it read the same values."""
    import dataclasses

    from dexflow.config import load_params

    return dataclasses.asdict(load_params(params_file))


def _resolve(dep: str, folder: Path) -> Path:
    path = Path(dep)
    if path.is_absolute():
        return path
    here = folder / path
    if here.exists() or here.is_symlink():
        return here
    return CHECKOUT / path


def stage_key(stage: Stage, params: Mapping[str, Any], folder: str | Path) -> str:
    """The key of ``stage``'s outputs when it runs in ``folder`` with ``params``
    (:func:`params_values` of that folder's ``params.yaml``): its command, its declared params'
    values and its deps' digests."""
    folder = Path(folder)
    values = {}
    for name in stage.params:
        try:
            values[name] = lookup(params, name)
        except KeyError:
            values[name] = None
    deps = {dep: path_digest(_resolve(dep, folder)) for dep in stage.deps}
    return key(stage.cmd, values, deps)
