"""The one skeleton every stage script runs: params in, stage run, metrics and timing out.

A stage module declares a :class:`StageSpec` (its name, its runner, the summary keys that are
its DVC metrics, a one-line description); its script in ``stages/`` is then just::

    from dexflow.stages.refine import STAGE
    from dexflow.pipeline.runner import stage_main

    sys.exit(stage_main(STAGE, sys.argv[1:]))

:func:`stage_main` loads and validates ``params.yaml``, builds the project's
:class:`~dexflow.io.layout.Layout`, calls the runner (which maps over the sequences with
:class:`dexflow.pipeline.resume.StageOutput`: resume, progress bar, one failed sequence never stops the
rest), writes ``reports/metrics/<tag>.json`` (deterministic) and ``reports/timing/<tag>.json``
(wall clock, and where the stage ran: commit, machine, data; :mod:`dexflow.pipeline.provenance`), logs
one line and every dropped sequence with its reason, and returns the exit code:

- 0: the stage completed and at least one sequence went through (the others were dropped for
  bad input, each listed in ``summary.json`` under ``dropped``);
- 1: no sequence went through, or an item failed for a reason other than its input (a full disk,
  memory, a killed worker: :class:`~dexflow.errors.IncompleteStageError`). Nothing is written
  then, so DVC caches nothing, and the next ``dvc repro`` resumes and retries those items;
- 1 also when another run of the same stage still goes on in this project (a ``dvc repro``
  started while an interrupted one's stage runs: :func:`stage_lock`); a stage whose ``dvc
  repro`` is killed stops with it (:func:`_stops_with_parent`), its workers too;
- 2: the configuration or the input as a whole is unusable (``params.yaml``, no sequences
  under ``data.root``); the one-line message names the key or the folder.

Runners return their summary (what ``summary.json`` holds) with the wall-clock figures under the
key ``timing``, which is never written into the stage's outputs (DVC hashes those).
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import fcntl
import hashlib
import json
import logging
import os
import select
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from dexflow.config import load_params
from dexflow.errors import DexflowError, IncompleteStageError
from dexflow.io.atomic import save_json
from dexflow.io.layout import Layout
from dexflow.params import PipelineParams
from dexflow.pipeline import provenance, validity
from dexflow.pipeline.registry import load_stages, pipeline_file

__all__ = ["StageBusyError", "StageSpec", "run_stage", "stage_lock", "stage_main"]

log = logging.getLogger("dexflow.stage")


@dataclass(frozen=True)
class StageSpec:
    """A pipeline stage as its script runs it.

    Attributes:
        name: The stage's name in ``dvc.yaml`` (without ``@item``).
        run: ``run(params, layout, *args) -> summary``; ``args`` are the script's arguments
            (the ``foreach`` item: retarget's method, simulate's trajectory label).
        metric_keys: Summary keys written to ``reports/metrics/<tag>.json`` (those present),
            with the input and dropped sequence counts of every stage that maps over sequences;
            None writes every key but the per-sequence ones and ``timing``; ``()`` writes no
            file.
        describe: One log line from the summary.
    """

    name: str
    run: Callable[..., dict]
    metric_keys: tuple[str, ...] | None
    describe: Callable[[dict], str]

    def tag(self, args: list[str] | tuple[str, ...] = ()) -> str:
        """``<name>`` or ``<name>_<item>``: the file name of its metrics and timing."""
        return "_".join([self.name, *args])


def run_stage(spec: StageSpec, params: PipelineParams, layout: Layout, args=()) -> dict:
    """Run a stage and write its metrics and timing files (the timing file records where it
    ran, every run); returns the summary (timing included)."""
    key = stage_key_of(spec.name, tuple(args), params, layout.root)
    running = validity.RUNNING_KEY.set(key)
    try:
        summary = spec.run(params, layout, *args)
    finally:
        validity.RUNNING_KEY.reset(running)
    tag = spec.tag(tuple(args))
    keys = spec.metric_keys
    if keys is None:
        keys = [k for k in summary if k not in _PER_ITEM_KEYS]
    elif keys:
        keys = [*keys, *(k for k in _DROPPED_COUNTS if k not in keys)]
    digest = None
    if keys:
        save_json(layout.stage_metrics(tag), {k: summary[k] for k in keys if k in summary})
        written = json.loads(layout.stage_metrics(tag).read_text(encoding="utf-8"))
        digest = provenance.metrics_digest(written)
    _record_timing(layout.timing(tag), summary, params, digest, key)
    label = "@".join([spec.name, *args])
    log.info("%s: %s", label, spec.describe(summary))
    own = {n: e for n, e in _sequence_entries(summary).items() if e.get("status") != "ok"}
    for name, entry in own.items():
        log.error("%s: %s dropped: %s", label, name, entry.get("error"))
    for name, entry in _sequence_entries(summary).items():
        if entry.get("warning"):
            log.warning("%s: %s: %s", label, name, entry["warning"])
    dropped = summary.get("dropped", own)
    if len(dropped) > len(own):
        log.warning(
            "%s: %d of %d input sequences were dropped before this stage (the summary.json of "
            "each stage lists them with the reason)",
            label, len(dropped) - len(own), summary.get("num_input_sequences", 0),
        )  # fmt: skip
    return summary


def stage_key_of(
    name: str, args: tuple[str, ...], params: PipelineParams, folder: Path
) -> str | None:
    """The key (:func:`dexflow.pipeline.validity.stage_key`) of stage ``name`` (its ``foreach``
    item in ``args``) of dexflow's ``dvc.yaml`` run in ``folder`` with ``params``; None where
    ``dvc.yaml`` has no such stage (a stage run outside the pipeline, e.g. the demo of a project
    whose data is its own)."""
    stages = load_stages(pipeline_file(), dataclasses.asdict(params))
    matching = [
        s for s in stages
        if s.name.partition("@")[0] == name and (not args or s.name.partition("@")[2] == args[0])
    ]  # fmt: skip
    if len(matching) != 1:
        return None
    return validity.stage_key(matching[0], dataclasses.asdict(params), folder)


def _record_timing(
    path: Path, summary: dict, params: PipelineParams, digest: str | None, key: str | None
) -> None:
    """Write the stage's ``reports/timing`` record: its speeds, where it ran (commit, machine,
    data; :func:`dexflow.pipeline.provenance.stage_record`) and the key of the outputs it made
    (:mod:`dexflow.pipeline.validity`)."""
    try:
        previous = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        previous = None
    previous = previous if isinstance(previous, dict) else None
    data = {
        "name": params.data.name,
        "root": params.data.root,
        "sequences": summary.get("num_input_sequences", summary.get("num_sequences")),
        "frames": summary.get("num_frames"),
    }
    timing = summary.get("timing") or {}
    save_json(path, provenance.stage_record(previous, timing, data, digest, key))


# Per-item entries of a summary (summary.json holds them; the DVC metrics do not), and the
# counts every stage that maps over sequences adds to its metrics.
_PER_ITEM_KEYS = ("sequences", "timing", "dropped", "warnings", "objects")
_DROPPED_COUNTS = ("num_input_sequences", "num_dropped")


def _sequence_entries(summary: dict) -> dict[str, dict]:
    """Per sequence its entry, for stages that map over sequences (others have none)."""
    entries = summary.get("sequences")
    return entries if isinstance(entries, dict) else {}


@contextlib.contextmanager
def _stops_with_parent() -> Iterator[None]:
    """While the stage runs, stop (SIGTERM) when the process that started it dies: a killed
    ``dvc repro`` leaves no stage running on as an orphan (Linux; elsewhere only the SIGTERM
    part). SIGTERM ends the stage the way Ctrl-C does: its worker processes are stopped and the
    finished items stay recorded for the next run. Both are undone afterwards.

    DVC starts a stage as ``/bin/sh -c <cmd>``, and the shell outlives a killed ``dvc repro``
    (it waits for its child). So the kernel's parent-death signal covers the direct parent only,
    and a thread watches the launcher above a ``sh -c`` parent (:func:`_launcher_pid`) through a
    pidfd, which cannot mistake a new process that reuses the pid for the launcher."""

    def interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    prctl = ctypes.CDLL(None).prctl if sys.platform.startswith("linux") else None
    if prctl is not None:
        prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    done = threading.Event()
    watcher = _watch_launcher(done)
    try:
        yield
    finally:
        done.set()
        if watcher is not None:
            watcher.join()
        if prctl is not None:
            prctl(_PR_SET_PDEATHSIG, 0, 0, 0, 0)
        signal.signal(signal.SIGTERM, previous)


_SHELLS = frozenset({"sh", "dash", "bash", "zsh", "ksh", "busybox"})


def _launcher_pid() -> int | None:
    """The pid of the process that launched this one through a shell's ``-c`` (DVC's
    ``/bin/sh -c``), or None when the parent is not such a shell or ``/proc`` cannot tell."""
    parent = os.getppid()
    try:
        argv = Path(f"/proc/{parent}/cmdline").read_bytes().split(b"\0")
        stat = Path(f"/proc/{parent}/stat").read_text()
    except OSError:
        return None
    if len(argv) < 2 or Path(argv[0].decode(errors="replace")).name not in _SHELLS:
        return None
    if argv[1] != b"-c":
        return None
    # Fields after the command name, which is in parentheses and may itself hold spaces.
    grandparent = int(stat[stat.rindex(")") + 2 :].split()[1])
    return grandparent if grandparent > 1 else None


def _watch_launcher(done: threading.Event) -> threading.Thread | None:
    """Start a thread that sends this process SIGTERM when the launcher above a ``sh -c``
    parent exits, until ``done`` is set; None where there is nothing to watch."""
    pid = _launcher_pid()
    if pid is None or not hasattr(os, "pidfd_open"):
        return None
    try:
        handle = os.pidfd_open(pid)
    except OSError:  # gone already, or a kernel without pidfds
        return None

    def watch() -> None:
        try:
            while not done.is_set():
                if select.select([handle], [], [], 0.5)[0]:
                    os.kill(os.getpid(), signal.SIGTERM)
                    return
        finally:
            os.close(handle)

    thread = threading.Thread(target=watch, name="dexflow-launcher-watch", daemon=True)
    thread.start()
    return thread


_PR_SET_PDEATHSIG = 1  # linux/prctl.h


@contextlib.contextmanager
def stage_lock(root: Path, label: str) -> Iterator[None]:
    """Hold the lock of stage ``label`` of the project at ``root`` while it runs.

    A second run of the same stage in the same project (a ``dvc repro`` started while an
    interrupted one's stage still runs) would write the same files at the same time; it stops
    at once instead. The lock is an ``flock`` on a file in the system's temporary folder, so
    the kernel releases it whenever the holder dies, however it dies.

    Raises:
        StageBusyError: another process holds it (its pid in the message).
    """
    key = hashlib.sha1(str(Path(root).resolve()).encode()).hexdigest()[:16]
    folder = Path(tempfile.gettempdir()) / "dexflow-locks"
    folder.mkdir(exist_ok=True)
    path = folder / f"{key}-{label.replace('@', '_')}.lock"
    with open(path, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "?"
            raise StageBusyError(
                f"{label}: another run of this stage is still going in {Path(root).resolve()} "
                f"(pid {holder}); wait for it to end or stop it, then run again"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


class StageBusyError(RuntimeError):
    """Another process runs the same stage of the same project."""


def stage_main(spec: StageSpec, args: list[str] | None = None) -> int:
    """A stage script's ``main``: see the module docstring for the exit codes. An unexpected
    exception (a bug) still ends in a traceback."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    label = "@".join([spec.name, *(args or ())])
    try:
        params = load_params("params.yaml")
        with _stops_with_parent(), stage_lock(Path.cwd(), label):
            summary = run_stage(spec, params, Layout.of(params.data.root), tuple(args or ()))
    except StageBusyError as exc:
        log.error("%s", exc)
        return 1
    except IncompleteStageError as exc:
        log.error("%s", exc)
        return 1
    except DexflowError as exc:
        log.error("%s: %s", label, exc)
        return 2
    if _sequence_entries(summary) and summary.get("num_ok", 0) == 0:
        log.error("%s: no sequence went through (each one's reason is listed above)", label)
        return 1
    return 0
