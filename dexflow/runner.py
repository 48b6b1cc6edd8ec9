"""The one skeleton every stage script runs: params in, stage run, metrics and timing out.

A stage module declares a :class:`StageSpec` (its name, its runner, the summary keys that are
its DVC metrics, a one-line description); its script in ``stages/`` is then just::

    from dexflow.refine import STAGE
    from dexflow.runner import stage_main

    sys.exit(stage_main(STAGE, sys.argv[1:]))

:func:`stage_main` loads and validates ``params.yaml``, builds the project's
:class:`~dexflow.io.layout.Layout`, calls the runner (which maps over the sequences with
:class:`dexflow.resume.StageOutput`: resume, progress bar, one failed sequence never stops the
rest), writes ``reports/metrics/<tag>.json`` (deterministic) and ``reports/timing/<tag>.json``
(wall clock), logs one line and every dropped sequence with its reason, and returns the exit
code:

- 0: the stage completed and at least one sequence went through (the others were dropped for
  bad input, each listed in ``summary.json`` under ``dropped``);
- 1: no sequence went through, or an item failed for a reason other than its input (a full disk,
  memory, a killed worker: :class:`~dexflow.errors.IncompleteStageError`). Nothing is written
  then, so DVC caches nothing, and the next ``dvc repro`` resumes and retries those items;
- 2: the configuration or the input as a whole is unusable (``params.yaml``, no sequences
  under ``data.root``); the one-line message names the key or the folder.

Runners return their summary (what ``summary.json`` holds) with the wall-clock figures under the
key ``timing``, which is never written into the stage's outputs (DVC hashes those).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from dexflow.config import load_params
from dexflow.errors import DexflowError, IncompleteStageError
from dexflow.io.atomic import save_json
from dexflow.io.layout import Layout
from dexflow.params import PipelineParams

__all__ = ["StageSpec", "run_stage", "stage_main"]

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
    """Run a stage and write its metrics and timing files; returns the summary (timing
    included)."""
    summary = spec.run(params, layout, *args)
    tag = spec.tag(tuple(args))
    keys = spec.metric_keys
    if keys is None:
        keys = [k for k in summary if k not in _PER_ITEM_KEYS]
    elif keys:
        keys = [*keys, *(k for k in _DROPPED_COUNTS if k not in keys)]
    if keys:
        save_json(layout.stage_metrics(tag), {k: summary[k] for k in keys if k in summary})
    if summary.get("timing"):
        save_json(layout.timing(tag), summary["timing"])
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


# Per-item entries of a summary (summary.json holds them; the DVC metrics do not), and the
# counts every stage that maps over sequences adds to its metrics.
_PER_ITEM_KEYS = ("sequences", "timing", "dropped", "warnings", "objects")
_DROPPED_COUNTS = ("num_input_sequences", "num_dropped")


def _sequence_entries(summary: dict) -> dict[str, dict]:
    """Per sequence its entry, for stages that map over sequences (others have none)."""
    entries = summary.get("sequences")
    return entries if isinstance(entries, dict) else {}


def stage_main(spec: StageSpec, args: list[str] | None = None) -> int:
    """A stage script's ``main``: see the module docstring for the exit codes. An unexpected
    exception (a bug) still ends in a traceback."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    label = "@".join([spec.name, *(args or ())])
    try:
        params = load_params("params.yaml")
        summary = run_stage(spec, params, Layout.of(params.data.root), tuple(args or ()))
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
