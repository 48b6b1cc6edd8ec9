"""``dexflow exp``: the headline metrics of every experiment side by side, in a terminal.

One row per experiment (:func:`dexflow.tools.experiments.collect_dvc`, ``collect_multirun``):
its name, its commit, the parameters that differ between the experiments, then
:data:`HEADLINE_METRICS`, labelled as the ablation report labels them
(:func:`dexflow.tools.ablation.metric_label`).
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import dataclass

from dexflow.errors import ConfigError
from dexflow.tools.ablation import metric_label
from dexflow.tools.experiments import Experiment, swept_factors

__all__ = ["HEADLINE_METRICS", "HeadlineTable", "format_table", "headline_table"]

# What `dexflow exp` shows of every experiment: the refined trajectories' simulation success
# (SSR), penetration (PD), contact distance (CD), fingertip error and smoothness (RMS joint
# acceleration), their replay success, and the retargeting speed (multirun jobs record it).
HEADLINE_METRICS = (
    "refine.ssr",
    "refine.pd_mm",
    "refine.cd_mm",
    "refine.fingertip_error_mm",
    "refine.rms_acc",
    "replay_refine.success_rate",
    "timing.retarget_dexflow.frames_per_second",
)


@dataclass
class HeadlineTable:
    """The table of ``dexflow exp``.

    Attributes:
        columns: The key of each column: ``experiment``, ``rev``, the differing parameters,
            then the metrics.
        header: Two rows: the label of each column, then the unit and ↑/↓ of each metric.
        rows: One per experiment: strings for its name, commit and parameters, then a float
            (None where missing) per metric.
        metrics: The metric keys (the last ``len(metrics)`` columns).
        notes: ``name: why`` for each experiment without metrics (failed, queued).
    """

    columns: list[str]
    header: list[list[str]]
    rows: list[list]
    metrics: list[str]
    notes: list[str]


def headline_table(
    experiments: list[Experiment], metrics: list[str] | None = None
) -> HeadlineTable:
    """One row per experiment: its name, its commit, the parameters that differ between the
    experiments (one column per factor, as the ablation report groups them: ``hand.name`` for
    every ``hand.*`` key a hand choice changes), then one column per metric.

    Args:
        experiments: From :func:`~dexflow.tools.experiments.collect_dvc` and/or ``collect_multirun``.
        metrics: Flat metric keys; default: those of :data:`HEADLINE_METRICS` any experiment has.

    Raises:
        ConfigError: a metric of ``metrics`` that no experiment has, with the closest keys.
    """
    known = sorted({k for e in experiments for k in e.metrics})
    if metrics is None:
        metrics = [m for m in HEADLINE_METRICS if m in known]
    for m in metrics:
        if m not in known:
            close = difflib.get_close_matches(m, known, n=3, cutoff=0.5)
            hint = f"did you mean {', '.join(close)}? " if close else ""
            raise ConfigError(
                f"metric {m!r}: no experiment has it; {hint}`dexflow exp --all` lists every "
                "metric by its key"
            )
    factors = [f.name for f in swept_factors(experiments, skip=("hydra.",))]
    labels = [metric_label(m) for m in metrics]
    header = [
        ["experiment", "rev", *factors, *(label for label, _, _ in labels)],
        ["", "", *("" for _ in factors),
         *(f"{unit} {'↑' if up else '↓'}".strip() for _, unit, up in labels)],
    ]  # fmt: skip
    rows, notes = [], []
    for e in experiments:
        rev = "" if e.rev in (None, e.name) else e.rev if e.rev == "workspace" else e.rev[:7]
        params = [_plain(e.params.get(f)) for f in factors]
        rows.append([e.name, rev, *params, *(e.metrics.get(m) for m in metrics)])
        if e.error or not e.metrics:
            notes.append(f"{e.name}: {e.error or 'no metrics'}")
    return HeadlineTable(["experiment", "rev", *factors, *metrics], header, rows, metrics, notes)


def _plain(value) -> str:
    """A parameter as the command line writes it (``allegro``, ``0.5``, ``[1, 2]``)."""
    return "—" if value is None else value if isinstance(value, str) else json.dumps(value)


def format_table(header: list[list[str]], rows: list[list[object]], width: int = 24) -> str:
    """Aligned columns: text left, numbers right (3 significant digits, ``—`` for none); a text
    cell longer than ``width`` ends in ``…``."""

    def text(value) -> str:
        if value is None or (isinstance(value, float) and not math.isfinite(value)):
            return "—"
        if isinstance(value, float):
            return _number(value)
        value = str(value)
        return value if len(value) <= width else value[: width - 1] + "…"

    cells = [[text(v) for v in row] for row in rows]
    numeric = [
        all(isinstance(r[i], (float, type(None))) for r in rows) for i in range(len(header[0]))
    ]
    sizes = [max(len(line[i]) for line in [*header, *cells]) for i in range(len(header[0]))]
    lines = []
    for line in [*header, *cells]:
        parts = [
            c.rjust(n) if right else c.ljust(n)
            for c, n, right in zip(line, sizes, numeric, strict=True)
        ]
        lines.append("  ".join(parts).rstrip())
    return "\n".join(lines)


def _number(value: float) -> str:
    magnitude = abs(value)
    if magnitude >= 100:
        return f"{value:.0f}"
    if magnitude >= 10:
        return f"{value:.1f}"
    return f"{value:.2f}" if magnitude >= 0.1 or value == 0 else f"{value:.3f}"
