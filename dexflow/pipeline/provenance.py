"""Where a result came from: the commit, the machine and the data, gathered offline and cheaply.

Every generated report opens with a provenance block (:func:`markdown`)::

    - commit: 8b63277c5d1e... (uncommitted changes: no)
    - machine: 3fa2c1d9e0b4 (Intel(R) Xeon(R) Processor, 2 cores, Linux 6.18 x86_64 glibc 2.36,
      Python 3.11.7, torch 2.13.0+cpu, mujoco 3.11.0, pybullet 3.2.7, numpy 2.4.6)
    - data: demo, 24 sequences, 2713 frames

one ``- key: value`` line each. A fact that cannot be found (no git, a package not installed)
reads ``unknown`` / ``not installed``.

The *commit* is the checkout dexflow is imported from; *uncommitted changes* counts tracked or
new files that differ from it, but for the pipeline's own outputs (``reports/``, ``dvc.lock``).
The *machine id* is the first 12 hex digits of the SHA-256 of the facts that can change a
result: CPU model, cores, OS, architecture, C library, Python and the versions of torch, mujoco,
pybullet and numpy (not the kernel release, not the host name). Runs with the same id are
comparable; with different ids, a difference may be the machine's.

Each stage run records its provenance beside its speeds in ``reports/timing/<tag>.json`` (not a
DVC output; :func:`stage_record`, written by :mod:`dexflow.pipeline.runner`)::

    {"frames_per_second": 53.4,
     "provenance": {"commit": ..., "dirty": false, "machine_id": ..., "machine": {...},
                    "data": {"name": "demo", "root": "data/demo", "sequences": 24, "frames": 2713}},
     "metrics_digest": "<digest of what reports/metrics/<tag>.json holds>" | null,
     "key": "<the key of the outputs the run made (dexflow.pipeline.validity)>" | null,
     "made": {"<metrics digest>": {"machine_id": ..., "commit": ..., "dirty": ...}, ...}}

``made`` keeps the last :data:`MADE_KEPT` metrics the stage wrote in this project, so that a
stage's metrics (the project's, a sweep job's, a DVC experiment's) are traced to the machine that
made them (:func:`made_by`): metrics whose digest is not there were made elsewhere, or restored
from git or the DVC cache, and their machine is not known.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "MADE_KEPT",
    "UNKNOWN",
    "code_state",
    "cpu_cores",
    "cpu_model",
    "current",
    "data_text",
    "describe_machine",
    "git_commit",
    "git_dirty",
    "machine",
    "machine_facts",
    "machine_id",
    "machine_of",
    "made_by",
    "markdown",
    "metrics_digest",
    "os_name",
    "package_version",
    "python_version",
    "read_records",
    "stage_record",
    "stages_of",
]

UNKNOWN = "unknown"
MADE_KEPT = 64
PACKAGES = ("torch", "mujoco", "pybullet", "numpy")
# The outputs of the pipeline itself: rewritten by every `dvc repro`, so no "uncommitted change".
OUTPUTS = ("reports", "dvc.lock")
_CODE = Path(__file__).resolve().parents[1]  # the dexflow package


def _git(*args: str, root: Path | None = None) -> str | None:
    """``git -C root args`` (root: dexflow's checkout), its output, or None where git is absent
    or the folder is no checkout."""
    try:
        done = subprocess.run(
            ["git", "-C", str(root or _CODE), *args],
            capture_output=True, text=True, timeout=10, check=False,
        )  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout if done.returncode == 0 else None


def git_commit(root: Path | None = None) -> str:
    """The commit checked out (40 hex digits), or ``unknown``."""
    out = _git("rev-parse", "HEAD", root=root)
    return out.strip() if out and out.strip() else UNKNOWN


def git_dirty(root: Path | None = None) -> bool | None:
    """Whether tracked or new (not ignored) files differ from the commit, outside the
    pipeline's outputs (:data:`OUTPUTS`); None where git cannot tell."""
    excluded = [f":(top,exclude){p}" for p in OUTPUTS]
    out = _git("status", "--porcelain", "--", ":(top)", *excluded, root=root)
    return None if out is None else bool(out.strip())


def code_state(root: Path | None = None) -> dict[str, Any]:
    """``{"commit": ..., "dirty": ...}`` of dexflow's checkout (or of ``root``)."""
    return {"commit": git_commit(root), "dirty": git_dirty(root)}


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, ``sysctl`` on macOS), or ``unknown``."""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("model name", "Model", "Hardware") and value.strip():
                return " ".join(value.split())
    except OSError:
        pass
    if sys.platform == "darwin":
        try:
            done = subprocess.run(["sysctl", "-n", "machdep.cpu.brand_string"],
                                  capture_output=True, text=True, timeout=10, check=False)  # fmt: skip
            if done.returncode == 0 and done.stdout.strip():
                return done.stdout.strip()
        except (OSError, subprocess.SubprocessError):
            pass
    return platform.processor() or UNKNOWN


def cpu_cores() -> int | None:
    """Logical cores of the machine (``os.cpu_count``)."""
    return os.cpu_count()


def os_name() -> str:
    """``Linux 6.18.44 x86_64 glibc 2.36``: system, release, architecture, C library."""
    libc, version = platform.libc_ver()
    parts = [platform.system() or UNKNOWN, platform.release(), platform.machine()]
    parts += [f"{libc} {version}"] if libc else []
    return " ".join(p for p in parts if p)


def python_version() -> str:
    return platform.python_version()


def package_version(name: str) -> str:
    """The installed version of distribution ``name`` (without importing it), or
    ``not installed``."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "not installed"


@functools.cache
def _machine() -> tuple[tuple[str, Any], ...]:
    libc, libc_version = platform.libc_ver()
    facts = {
        "cpu": cpu_model(),
        "cores": cpu_cores(),
        "os": os_name(),
        "system": platform.system() or UNKNOWN,
        "arch": platform.machine() or UNKNOWN,
        "libc": f"{libc} {libc_version}".strip(),
        "python": python_version(),
        **{name: package_version(name) for name in PACKAGES},
    }
    return tuple(facts.items())


def machine() -> dict[str, Any]:
    """The facts of this machine: ``cpu``, ``cores``, ``os`` (for display), ``system``,
    ``arch``, ``libc``, ``python`` and a version per package of :data:`PACKAGES`."""
    return dict(_machine())


_ID_KEYS = ("cpu", "cores", "system", "arch", "libc", "python", *PACKAGES)


def machine_id(facts: Mapping[str, Any] | None = None) -> str:
    """12 hex digits identifying ``facts`` (default: this machine) by what can change a
    result (see the module docstring)."""
    facts = machine() if facts is None else facts
    text = json.dumps({k: facts.get(k) for k in _ID_KEYS}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def describe_machine(facts: Mapping[str, Any]) -> str:
    """One line: CPU, cores, OS, Python and the package versions."""
    cores = facts.get("cores")
    parts = [str(facts.get("cpu", UNKNOWN)), f"{cores if cores else UNKNOWN} cores",
             str(facts.get("os", UNKNOWN)), f"Python {facts.get('python', UNKNOWN)}"]  # fmt: skip
    parts += [f"{name} {facts.get(name, UNKNOWN)}" for name in PACKAGES]
    return ", ".join(parts)


def current(data: Mapping[str, Any] | None = None, root: Path | None = None) -> dict[str, Any]:
    """This process's provenance: ``commit``, ``dirty``, ``machine_id``, ``machine`` (facts)
    and ``data`` (as given: ``name``, ``root``, ``sequences``, ``frames``)."""
    facts = machine()
    return {**code_state(root), "machine_id": machine_id(facts), "machine": facts,
            "data": dict(data or {})}  # fmt: skip


def metrics_digest(metrics: Any) -> str:
    """SHA-256 of a metrics file's content as parsed (``json.loads``), so that the file and
    ``dvc exp show``'s copy of it give the same digest."""
    text = json.dumps(metrics, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def stage_record(
    previous: Mapping[str, Any] | None,
    timing: Mapping[str, Any],
    data: Mapping[str, Any] | None,
    digest: str | None,
    key: str | None = None,
) -> dict[str, Any]:
    """The ``reports/timing/<tag>.json`` of a stage run (format in the module docstring).

    Args:
        previous: The file as the last run left it (its ``made`` is carried on), or None.
        timing: The stage's wall-clock figures (the runner's summary ``timing``).
        data: What the stage ran on (``name``, ``root``, ``sequences``, ``frames``).
        digest: :func:`metrics_digest` of the metrics it wrote, None if it writes none.
        key: The key of the outputs it made (:mod:`dexflow.pipeline.validity`), None where
            unknown.
    """
    here = current(data)
    made = dict((previous or {}).get("made") or {})
    if digest is not None:
        made.pop(digest, None)  # re-inserted last: the most recent maker
        made[digest] = {k: here[k] for k in ("machine_id", "commit", "dirty")}
    kept = dict(list(made.items())[-MADE_KEPT:])
    return {**timing, "provenance": here, "metrics_digest": digest, "key": key, "made": kept}


def read_records(timing_dir: str | Path | None) -> dict[str, dict]:
    """Every stage's record in ``timing_dir`` (``reports/timing``) by tag; files without
    provenance (written before it was recorded) or unreadable are left out."""
    records: dict[str, dict] = {}
    if timing_dir is None or not Path(timing_dir).is_dir():
        return records
    for path in sorted(Path(timing_dir).glob("*.json")):
        try:
            record = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if isinstance(record, dict) and isinstance(record.get("provenance"), dict):
            records[path.stem] = record
    return records


def made_by(metrics: Any | None, record: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """Who made a stage's outputs: ``{"machine_id", "commit", "dirty"}``, or None if unknown.

    Args:
        metrics: The stage's metrics as parsed (None for a stage that writes none: then the
            record's last run is taken at its word).
        record: The stage's ``reports/timing`` record (:func:`read_records`), or None.
    """
    if not record:
        return None
    if metrics is None:
        last = record.get("provenance") or {}
        return {k: last.get(k) for k in ("machine_id", "commit", "dirty")}
    return (record.get("made") or {}).get(metrics_digest(metrics))


def stages_of(
    metrics_dir: str | Path, timing_dir: str | Path | None
) -> dict[str, dict[str, Any] | None]:
    """For every stage of a project (or sweep job), who made its current outputs
    (:func:`made_by`): the stages with a metrics file in ``metrics_dir`` (``reports/metrics``)
    and those with a record in ``timing_dir`` (``reports/timing``), ``report`` excepted (it
    writes no number)."""
    records = read_records(timing_dir)
    metrics = {}
    for path in sorted(Path(metrics_dir).glob("*.json")):
        try:
            metrics[path.stem] = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            metrics[path.stem] = {"unreadable": path.name}
    tags = sorted((set(metrics) | set(records)) - {"report"})
    return {tag: made_by(metrics.get(tag), records.get(tag)) for tag in tags}


def machine_facts(records: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """The facts of every machine the ``records`` (:func:`read_records`) last ran on, by id;
    this machine's always."""
    found = {machine_id(): machine()}
    for record in records.values():
        last = record.get("provenance") or {}
        if isinstance(last.get("machine_id"), str) and isinstance(last.get("machine"), dict):
            found.setdefault(last["machine_id"], last["machine"])
    return found


def machine_of(stages: Mapping[str, Mapping[str, Any] | None]) -> str | None:
    """The one machine id that made every stage, or None (no stage, one unknown, or several)."""
    ids = {(s or {}).get("machine_id") for s in stages.values()}
    if len(ids) != 1:
        return None
    (found,) = ids
    return found if isinstance(found, str) else None


def data_text(name: Any, sequences: Any = None, frames: Any = None) -> str:
    """``demo, 24 sequences, 2713 frames`` (the counts left out where unknown)."""
    parts = [str(name) if name not in (None, "") else UNKNOWN]
    if isinstance(sequences, (int, float)) and not isinstance(sequences, bool):
        parts.append(f"{int(sequences)} sequences")
    if isinstance(frames, (int, float)) and not isinstance(frames, bool):
        parts.append(f"{int(frames)} frames")
    return ", ".join(parts)


def _dirty_text(dirty: Any) -> str:
    return {True: "yes", False: "no"}.get(dirty, UNKNOWN)


def markdown(record: Mapping[str, Any] | None = None, data: str | None = None) -> list[str]:
    """The provenance block (module docstring): ``- commit: ...``, ``- machine: ...`` and, when
    ``data`` is given (:func:`data_text`), ``- data: ...``. ``record``: :func:`current`'s
    (default: this process)."""
    record = current() if record is None else record
    facts = record.get("machine") or {}
    lines = [
        f"- commit: {record.get('commit', UNKNOWN)} "
        f"(uncommitted changes: {_dirty_text(record.get('dirty'))})",
        f"- machine: {record.get('machine_id', UNKNOWN)} ({describe_machine(facts)})",
    ]
    if data is not None:
        lines.append(f"- data: {data}")
    return lines
