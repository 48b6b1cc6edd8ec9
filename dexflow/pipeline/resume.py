"""Resumable stage outputs: a rerun keeps what an interrupted run with the same inputs completed.

A stage's output directory holds, while the stage runs, two kinds of bookkeeping:

- ``.stage.json``: the stage's label (with its method) and the key of its outputs
  (:mod:`dexflow.pipeline.validity`: its command, params and the bytes of every dep), the one
  key by which every runner decides whether outputs are still valid.
- ``.done/<group>/<name>.json``: one record per completed item, written after its outputs: the
  value the item returned (its summary entry).

On start, a directory with another fingerprint (or none) is emptied: a changed param, command
or input (any byte of any dep) starts the stage afresh, as DVC would. One with the same
fingerprint is kept and swept: every file that is not an output of an item with a record goes
(half-written temporary files, outputs without a record, the old summary). An item with a
record is not run again (the key says its inputs are the ones it was made from); its recorded
value is reused, so the summary is the one an uninterrupted run writes. When the stage
finishes, :meth:`StageOutput.finish`
writes ``summary.json`` and removes the bookkeeping, so a completed output directory holds
exactly the stage's outputs (what DVC hashes: no timestamps, no absolute paths) and a later run
starts from scratch. Items that failed leave no record and are retried.

Failures are of two kinds (:mod:`dexflow.pipeline.parallel`). An item whose input is bad
(:class:`~dexflow.errors.DexflowError`) is *dropped*: listed in ``summary.json`` with its reason,
the others complete. An item that failed for another reason (a full disk, memory, a killed
worker) makes :meth:`StageOutput.finish` raise :class:`IncompleteStageError` instead of writing
the summary: the stage exits non-zero, DVC caches nothing, and the bookkeeping stays, so the next
``dvc repro`` resumes and retries just those items.

Every summary also accounts for the sequences dropped before the stage: ``finish`` adds
``dropped`` (per sequence the first stage that dropped it and why, from the input stages'
summaries and this one's), ``num_input_sequences`` (the sequences of the data root that reached
the first stage) and ``num_dropped``, and ``warnings`` (per sequence, the ``warning`` of any
stage's entry), so the last stage's summary lists every sequence the pipeline lost.

Example (a stage runner)::

    stage = StageOutput(out_root, "contact", {"hand": params.hand, "contact": params.contact},
                        inputs=(retarget_root, aligned_root))
    files = stage.start()
    results = stage.map(one, files, params.run)
    ...
    stage.finish(summary)
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dexflow.errors import IncompleteStageError
from dexflow.io.atomic import atomic_path, save_json
from dexflow.io.layout import StageDir, stray_files
from dexflow.pipeline import validity
from dexflow.pipeline.parallel import ItemResult, map_items

if TYPE_CHECKING:
    from dexflow.params import RunParams

__all__ = [
    "DONE_DIR",
    "STAGE_FILE",
    "IncompleteStageError",
    "StageOutput",
    "Tally",
]

STAGE_FILE = ".stage.json"
DONE_DIR = ".done"
_MISSING = "-"
log = logging.getLogger(__name__)


def _files_size(paths: Iterable[Path]) -> int:
    return sum(p.stat().st_size for p in paths if p.is_file())


def _plain(obj: Any) -> Any:
    """Params (dataclasses, mappings, sequences, scalars) as plain JSON values."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        obj = dataclasses.asdict(obj)
    if isinstance(obj, Mapping):
        return {str(key): _plain(value) for key, value in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(value) for value in obj]
    return obj


def _dumps(obj: Any) -> str:
    """Canonical JSON text (sorted keys; non-JSON scalars as their str)."""
    return json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n"


def _stem(item: Path) -> str:
    return Path(item).stem


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "item"):  # numpy scalars
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


@dataclasses.dataclass
class _Recorded:
    """``func`` followed by the item's done-record (pickled to workers with it)."""

    func: Callable[[Any], Any]
    name: Callable[[Any], str]
    record_dir: Path

    def __call__(self, item: Any) -> Any:
        value = self.func(item)
        key = self.name(item)
        try:
            text = json.dumps({"value": value}, default=_json_default, indent=1)
        except (TypeError, ValueError) as exc:  # the item stands; only resuming it is lost
            log.warning("%s: no done-record (%s); a rerun recomputes it", key, exc)
            return value
        with atomic_path(self.record_dir / f"{key}.json") as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")
        return value


class StageOutput:
    """The output directory of one stage run, resumable after an interruption.

    Args:
        out_root: The stage's output directory.
        stage: Label of the stage and its method (``"retarget dexflow"``); also the default
            progress-bar label.
        params: Every params section that determines the outputs, e.g.
            ``{"hand": params.hand, "refine": params.refine}`` (dataclasses or plain values).
        inputs: The input stage directories; sequences are listed from the first. An item
            named ``<name>`` reads ``<root>/sequences/<name>.npz`` of each (those are hashed per
            item) and may read anything else below them (hashed once, into the fingerprint).
    """

    def __init__(
        self,
        out_root: StageDir | str | Path,
        stage: str,
        params: Mapping[str, Any],
        inputs: Iterable[StageDir | str | Path],
    ) -> None:
        self.out = _stage_dir(out_root)
        self.out_root = self.out.root
        self.stage = stage
        self.input_dirs = [_stage_dir(p) for p in inputs]
        self.inputs = [d.root for d in self.input_dirs]
        self.params = _plain(dict(params))
        self.retry: dict[str, str] = {}  # items that failed for a reason other than their input

    def fingerprint(self) -> dict:
        """What ``.stage.json`` holds: the stage's label and the key of its outputs
        (:mod:`dexflow.pipeline.validity`): the one the stage runner computed from the registry
        (:data:`~dexflow.pipeline.validity.RUNNING_KEY`), else one of this stage's params, the
        dexflow package and its inputs' bytes. Deterministic: no paths, no times."""
        running = validity.RUNNING_KEY.get()
        if running is None:
            deps = {"dexflow": validity.path_digest(validity.CHECKOUT / "dexflow")}
            deps |= {f"input {i}": validity.path_digest(r) for i, r in enumerate(self.inputs)}
            running = validity.key(self.stage, self.params, deps)
        return {"stage": self.stage, "key": running}

    def start(self) -> list[Path]:
        """List the sequence files of the first input; empty the output directory unless it
        holds an interrupted run with the same fingerprint.

        Raises:
            NoSequencesError: the first input holds no ``sequences/*.npz`` (hidden files are
                not sequences).
        """
        files = self.input_dirs[0].sequence_files()
        fingerprint = _dumps(self.fingerprint())
        marker = self.out_root / STAGE_FILE
        try:
            resumed = marker.read_text(encoding="utf-8") == fingerprint
        except OSError:
            resumed = False
        if resumed:
            for entry in self.out_root.iterdir():  # old summary, temporaries
                if entry.is_file() and entry.name != STAGE_FILE:
                    entry.unlink()
            log.info("%s: resuming the interrupted run in %s", self.stage, self.out_root)
        else:
            if self.out_root.exists():
                shutil.rmtree(self.out_root)
            self.out_root.mkdir(parents=True)
            with atomic_path(marker) as tmp:
                tmp.write_text(fingerprint, encoding="utf-8")
        (self.out_root / "sequences").mkdir(exist_ok=True)
        return files

    def map(
        self,
        func: Callable[[Any], dict],
        items: Iterable[Any],
        run: int | RunParams,
        desc: str | None = None,
        *,
        group: str = "sequences",
        name: Callable[[Any], str] = _stem,
        inputs: Callable[[Any], list[Path]] | None = None,
    ) -> list[ItemResult]:
        """:func:`dexflow.pipeline.parallel.map_items`, skipping the items an interrupted run completed.

        Args:
            func: Function of one item; writes the item's outputs (atomically) below
                ``out_root/<group>/`` as ``<name>.*`` files or a ``<name>/`` directory and
                returns its summary entry (JSON values).
            items: The items (by default sequence files).
            run: The ``run`` params or an int n_jobs.
            desc: Progress-bar label; the stage's label by default.
            group: Subdirectory of the outputs (``sequences``, ``objects``).
            name: The item's name (by default the file's stem).
            inputs: The files an item reads (by default ``<root>/sequences/<name>.npz`` of
                every input root): their sizes order the work, largest first.

        Returns:
            One result per item, in input order; reused items carry their recorded value.
        """
        items = list(items)
        names = [name(item) for item in items]
        if inputs is None:
            files_of = [[d.sequence(n) for d in self.input_dirs] for n in names]
        else:
            files_of = [[Path(p) for p in inputs(item)] for item in items]
        record_dir = self.out_root / DONE_DIR / group
        done: dict[str, Any] = {}
        for key in names:
            try:
                record = json.loads((record_dir / f"{key}.json").read_text(encoding="utf-8"))
            except (OSError, ValueError):
                continue
            if isinstance(record, dict) and "value" in record:
                done[key] = record["value"]
        _sweep(self.out_root / group, record_dir, set(done))
        if done:
            log.info("%s: %d of %d %s already done", self.stage, len(done), len(items), group)
        # Largest inputs first (longest sequences, biggest meshes): the last item to finish is
        # then a short one, so workers idle less at the end. Results do not depend on the order.
        sizes = {n: _files_size(files) for n, files in zip(names, files_of, strict=True)}
        todo = sorted(
            (i for i, key in enumerate(names) if key not in done), key=lambda i: -sizes[names[i]]
        )
        computed = map_items(
            _Recorded(func, name, record_dir),
            [items[i] for i in todo],
            run,
            desc or self.stage,
        )
        by_index = dict(zip(todo, computed, strict=True))
        for result in computed:
            if result.retry:
                self.retry[name(result.item)] = result.error or "failed"
        return [
            ItemResult(item, value=done[key]) if key in done else by_index[i]
            for i, (item, key) in enumerate(zip(items, names, strict=True))
        ]

    def run(self, func: Callable[[Path], dict], files: list[Path], run: int | RunParams) -> Tally:
        """Map ``func`` over the sequence files (resuming) and tally the outcome: the part of
        every stage runner that is the same in all of them."""
        start = time.perf_counter()
        results = self.map(func, files, run)
        seconds = time.perf_counter() - start
        return Tally({r.item.stem: r.entry() for r in results}, seconds)

    def finish(self, summary: dict) -> None:
        """Add the dropped sequences to ``summary`` (in place), write ``summary.json``, then drop
        the bookkeeping: the run is complete.

        Raises:
            IncompleteStageError: an item failed for a reason other than its input; nothing is
                written and the bookkeeping stays, so that a rerun resumes.
        """
        if self.retry:
            raise IncompleteStageError(self.stage, self.retry)
        self._account(summary)
        save_json(self.out_root / "summary.json", summary)
        (self.out_root / STAGE_FILE).unlink(missing_ok=True)
        shutil.rmtree(self.out_root / DONE_DIR, ignore_errors=True)

    def _account(self, summary: dict) -> None:
        """``dropped``, ``num_input_sequences``, ``num_dropped`` and ``warnings`` of the
        summary: this stage's failures and those its inputs' summaries record."""
        own: dict[str, dict] = summary.get("sequences", {})
        dropped: dict[str, dict] = {}
        warnings: dict[str, list[str]] = {}
        names = set(own)
        for root in self.inputs:
            if not (root / "summary.json").exists():  # a data root: what no stage reads
                folder = StageDir(root).sequences_dir
                for path, why in stray_files(folder).items():
                    name = path.relative_to(folder).as_posix()
                    dropped.setdefault(name, {"stage": "data", "error": f"{path}: {why}"})
                    names.add(name)
            before = _read_summary(root / "summary.json")
            for name, info in before.get("dropped", {}).items():
                dropped.setdefault(name, info)
            for name, entry in before.get("sequences", {}).items():
                if entry.get("status") != "ok":  # a summary written before ``dropped`` existed
                    info = {"stage": before.get("stage", root.name), "error": entry.get("error")}
                    dropped.setdefault(name, info)
            for name, notes in before.get("warnings", {}).items():
                warnings.setdefault(name, [])
                warnings[name] += [n for n in notes if n not in warnings[name]]
            names |= set(before.get("sequences", {})) | set(before.get("dropped", {}))
        for name, entry in own.items():
            if entry.get("status") != "ok":
                dropped.setdefault(name, {"stage": self.stage, "error": entry.get("error")})
            if entry.get("warning"):
                note = f"{self.stage}: {entry['warning']}"
                if note not in warnings.setdefault(name, []):
                    warnings[name].append(note)
        summary["num_input_sequences"] = len(names)
        summary["num_dropped"] = len(dropped)
        summary["dropped"] = dict(sorted(dropped.items()))
        summary["warnings"] = dict(sorted(warnings.items()))


def _read_summary(path: Path) -> dict:
    """An input stage's ``summary.json`` (empty if it has none: a data root)."""
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return summary if isinstance(summary, dict) else {}


def _stage_dir(path: StageDir | str | Path) -> StageDir:
    return path if isinstance(path, StageDir) else StageDir(Path(path))


@dataclass
class Tally:
    """What a stage's map over sequences gave.

    Attributes:
        sequences: Per sequence name its summary entry: ``status`` (``ok`` or ``failed``), the
            item's statistics or ``error``.
        seconds: Wall-clock seconds of the map (reused items take none).
    """

    sequences: dict[str, dict]
    seconds: float

    @property
    def ok(self) -> list[dict]:
        """The entries of the sequences that succeeded, in name order."""
        return [e for _, e in sorted(self.sequences.items()) if e["status"] == "ok"]

    def counts(self, stage: str, frames_key: str = "frames") -> dict:
        """The summary fields every stage has: its name, sequences in/ok/failed, frames."""
        ok = self.ok
        return {
            "stage": stage,
            "num_sequences": len(self.sequences),
            "num_ok": len(ok),
            "num_failed": len(self.sequences) - len(ok),
            "num_frames": int(sum(e.get(frames_key, 0) for e in ok)),
        }

    def mean(self, key: str, default: float = float("nan")) -> float:
        """Mean of a per-sequence statistic over the sequences that succeeded."""
        values = [e[key] for e in self.ok]
        return float(np.mean(values)) if values else default


def _sweep(out_dir: Path, record_dir: Path, keep: set[str]) -> None:
    """Remove outputs and records of every item not in ``keep`` (and temporary files)."""
    for directory, named in ((out_dir, _output_name), (record_dir, _stem)):
        if not directory.is_dir():
            continue
        for entry in directory.iterdir():
            if named(entry) in keep and not entry.name.startswith("."):
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()


def _output_name(entry: Path) -> str:
    """The item an output belongs to: a ``<name>/`` directory or a ``<name>.<ext>`` file."""
    return entry.name if entry.is_dir() else entry.stem
