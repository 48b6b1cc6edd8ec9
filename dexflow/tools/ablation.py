"""Ablation suites: the paper's questions, each answered by named experiments against the default.

``dexflow report ablation --suite paper`` runs the default configuration and every experiment of
``conf/experiment/`` that a question of the suite names, one pipeline run per experiment in its
own directory (``multirun/<report name>/<experiment>/``, the machinery of ``dexflow.tools.sweep``: a
stage whose params an experiment leaves unchanged is reused, not rerun), then writes one table
per question. Running it again reuses every experiment that finished with the same composed
params and the same dexflow code (a digest of the package's files); an interrupted or failed
one, or one run with other code, is run again. ``--no-run`` only writes the report (the
experiments not run yet are listed as queued).

How a difference is read. Every experiment runs on the same sequences as the default, so each
metric is compared sequence by sequence: Δ is the mean over sequences of (experiment − default)
and ± the half-width of its 95 % confidence interval (Student's t over the paired sequences).
A Δ inside its ± (the interval contains 0) is within the spread across sequences: the report
says so instead of calling it an effect. The intervals are per comparison: with dozens of them
in a suite, one or two "resolved" differences are expected by chance alone (no multiplicity
correction), and sequences of the same object are not fully independent, so the intervals are,
if anything, optimistic. Values are means over sequences of the per-sequence metrics that stage metrics
writes (``data/metrics/sequences.csv``; definitions in :mod:`dexflow.stages.metrics`), so a pooled
aggregate of ``reports/metrics/metrics.json`` (velocity KL pools the speeds, ``pd_max_mm`` is a
maximum) can differ from the mean shown here. Aggregates that exist only pooled (contact
precision, recall and flicker; retarget speed) are shown without a spread.

Which runs are compared. Two machines can give different numbers for the same parameters (a
library version, the CPU), so only runs of one machine are compared: every stage of the default
and of the experiment must have been made on the same machine, as their ``reports/timing``
records say (:mod:`dexflow.pipeline.provenance`). The suite reruns here whatever this machine did not
make (the project's outputs committed from elsewhere included); the report states the machine,
and lists any experiment it cannot compare with the reason.

**One file** (about 600 lines): the suite's questions, the paired comparison that answers them and the
runner that makes the experiments are one report's parts, each a few functions.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dexflow import stats
from dexflow.errors import ConfigError
from dexflow.io.atomic import atomic_path, save_json
from dexflow.io.layout import Layout
from dexflow.pipeline import provenance
from dexflow.tools.sweep import STATUS_FILE, UNFINISHED

__all__ = [
    "METRIC_LABELS",
    "SUITES",
    "SUITE_OVERRIDES",
    "Comparison",
    "ExperimentResult",
    "Question",
    "compare",
    "load_result",
    "metric_label",
    "run_suite",
    "suite_command",
    "suite_experiments",
    "write_suite_report",
]
log = logging.getLogger(__name__)

DEFAULT = "default"  # the experiment without overrides: what every other one is compared to
CONFIDENCE = stats.CONFIDENCE


@dataclass(frozen=True)
class Question:
    """One question of a suite: which experiments answer it, for which methods, by which metrics.

    Attributes:
        key: Short name (CSV, anchors).
        title: The question as a reader asks it.
        experiments: Names of ``conf/experiment/*.yaml``, each compared to the default.
        methods: Methods of ``sequences.csv`` (``baseline``, ``retarget``, ``refine``).
        metrics: Per-sequence columns of ``sequences.csv`` (at most six: tables stay readable).
        pooled: Flat keys of ``reports/metrics``/``reports/timing`` (``contact.precision``,
            ``timing.retarget_dexflow.frames_per_second``) shown beside, without a spread.
    """

    key: str
    title: str
    experiments: tuple[str, ...]
    methods: tuple[str, ...]
    metrics: tuple[str, ...]
    pooled: tuple[str, ...] = ()


SUITES: dict[str, tuple[Question, ...]] = {
    "paper": (
        Question(
            "temporal",
            "What do the temporal terms buy?",
            ("no_temporal",),
            ("retarget", "refine"),
            ("keypoint_error_mm", "fingertip_error_mm", "rms_acc", "velocity_kl"),
        ),
        Question(
            "global_search",
            "What does the global search buy?",
            ("global_search_off", "global_search_every_frame"),
            ("retarget", "refine"),
            ("keypoint_error_mm", "fingertip_error_mm", "rms_acc", "pd_mm"),
            ("timing.retarget_dexflow.frames_per_second",),
        ),
        Question(
            "contact_smoothing",
            "What does contact smoothing buy?",
            ("no_contact_smoothing",),
            ("refine",),
            ("cd_mm", "pd_mm", "fingertip_error_mm", "rms_acc", "ssr"),
            ("contact.flicker_final", "contact.precision", "contact.recall"),
        ),
        Question(
            "refine_energies",
            "What does each refinement energy buy?",
            (
                "refine_no_dis",
                "refine_no_pen",
                "refine_no_align",
                "refine_no_spen",
                "refine_no_joints",
            ),
            ("refine",),
            ("pd_mm", "pd_max_mm", "cd_mm", "spd_mm", "fingertip_error_mm", "ssr"),
        ),
        Question(
            "hands",
            "How do the hands compare?",
            ("allegro",),
            ("baseline", "retarget", "refine"),
            ("keypoint_error_mm", "rms_acc", "pd_mm", "cd_mm", "ssr"),
        ),
    ),
    # Stage track (every experiment with track=on: SUITE_OVERRIDES): what each part of the
    # search buys in replay success, at what cost in fingertip error, penetration and time.
    "track": (
        Question(
            "track_parts",
            "What does each part of the tracking search buy?",
            (
                "track_no_prior",
                "track_no_tip_term",
                "track_few_samples",
                "track_short_horizon",
                "track_one_schedule",
                "track_no_hold",
                "track_grasp_carry",
                "track_no_mpc",
                "track_no_contact_guidance",
                "track_no_object_guidance",
            ),
            ("track",),
            ("fingertip_error_mm", "pd_mm", "pd_own_object_mm", "rms_acc"),
            (
                "replay_track.success_rate",
                "replay_track.carried_rate",
                "replay_track.position_error_mean_m",
                "track_refine.feasible_rate",
                "timing.track_refine.cpu_seconds_per_70_frames",
            ),
        ),
    ),
}
# Hydra overrides a suite's every experiment (its default too) runs with.
SUITE_OVERRIDES: dict[str, tuple[str, ...]] = {"track": ("track=on",)}

# metric -> (label, unit, higher is better); also the labels of `dexflow exp`
# (:func:`metric_label`)
METRIC_LABELS = {
    "keypoint_error_mm": ("keypoint error", "mm", False),
    "fingertip_error_mm": ("fingertip error", "mm", False),
    "fingertip_error_surface_mm": ("fingertip error vs surface tips", "mm", False),
    "time_aligned_cd_mm": ("time-aligned CD", "mm", False),
    "velocity_kl": ("velocity KL", "", False),
    "rms_acc": ("RMS acc", "rad/s²", False),
    "pd_mm": ("PD", "mm", False),
    "pd_max_mm": ("PD max", "mm", False),
    "pd_own_object_mm": ("PD own object", "mm", False),
    "cd_mm": ("CD", "mm", False),
    "cd_contact_mm": ("CD in contact", "mm", False),
    "spd_mm": ("SPD", "mm", False),
    "fvr": ("FVR", "", False),
    "ssr": ("SSR", "%", True),
    "ssr_paper": ("SSR paper protocol", "%", True),
    "ssr_bench": ("SSR DexGraspBench", "%", True),
    "contact.flicker_final": ("contact flicker", "/finger/s", False),
    "contact.precision": ("contact precision", "", True),
    "contact.recall": ("contact recall", "", True),
    "timing.retarget_dexflow.frames_per_second": ("retarget speed", "frames/s", True),
    "success_rate": ("replay success", "%", True),
    "carried_rate": ("replay carried", "%", True),
    "position_error_mean_m": ("replay object error", "m", False),
    "feasible_rate": ("feasible", "%", True),
    "cpu_seconds_per_70_frames": ("track cost", "CPU s / 70 frames", False),
}


def metric_label(metric: str) -> tuple[str, str, bool]:
    """(label, unit, higher is better) of a metric: a key of :data:`METRIC_LABELS`, else a flat
    key of ``reports/metrics`` by its last part (``refine.pd_mm`` as ``pd_mm``); an unknown
    metric is labelled by its key."""
    if metric in METRIC_LABELS:
        return METRIC_LABELS[metric]
    return METRIC_LABELS.get(metric.rpartition(".")[2], (metric, "", False))


def suite_experiments(suite: str) -> list[str]:
    """The default, then every experiment the suite's questions name, in order, once each."""
    if suite not in SUITES:
        raise KeyError(f"unknown ablation suite {suite!r}; known: {', '.join(sorted(SUITES))}")
    names = [e for q in SUITES[suite] for e in q.experiments]
    return [DEFAULT, *dict.fromkeys(names)]


@dataclass
class ExperimentResult:
    """What one experiment's directory holds.

    Attributes:
        status: ``complete``, ``failed`` or ``queued`` (not run yet, or still running).
        error: Why it failed (the stage and its last line).
        rows: The per-sequence rows of ``sequences.csv`` (strings as read).
        pooled: Flat numbers of ``reports/metrics/*.json`` (``contact.precision``) and
            ``reports/timing/*.json`` (``timing.<stage>.frames_per_second``).
        stages: Per stage who made its outputs (:func:`dexflow.pipeline.provenance.stages_of`:
            machine, commit; None where not recorded).
    """

    name: str
    status: str
    error: str | None = None
    rows: list[dict[str, str]] = field(default_factory=list)
    pooled: dict[str, float] = field(default_factory=dict)
    stages: dict[str, dict | None] = field(default_factory=dict)

    @property
    def machine(self) -> str | None:
        """The machine id that made every stage's outputs (None: not recorded, or several)."""
        return provenance.machine_of(self.stages)


def _numbers(tree, prefix: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_numbers(value, f"{prefix}{key}."))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[prefix + key] = float(value)
    return out


def load_result(job: Path, name: str | None = None) -> ExperimentResult:
    """Read an experiment directory (``sweep_status.json``, ``data/metrics/sequences.csv``,
    ``reports/metrics``, ``reports/timing``); a missing directory or status is ``queued``."""
    job = Path(job)
    name = name or job.name
    try:
        status = json.loads((job / STATUS_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return ExperimentResult(name, "queued")
    if status.get("status") != "ok":
        stage, error = status.get("stage"), status.get("error")
        if error == UNFINISHED:  # running now, or killed: the next run of the suite runs it
            return ExperimentResult(name, "queued", f"stage {stage} running or interrupted")
        return ExperimentResult(name, "failed", f"stage {stage}: {error}")
    layout = Layout(root=job)
    try:
        with layout.metrics_table.open(newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        return ExperimentResult(name, "failed", f"no per-sequence metrics ({exc.strerror})")
    pooled: dict[str, float] = {}
    for folder, prefix in (
        (layout.reports / "metrics", ""),
        (layout.reports / "timing", "timing."),
    ):
        for path in sorted(folder.glob("*.json")):
            stem = "" if path.stem == "metrics" else f"{path.stem}."
            content = json.loads(path.read_text(encoding="utf-8"))
            if prefix:  # the speeds, not where the stage ran
                content = {k: v for k, v in content.items() if k not in _RECORD_KEYS}
            pooled.update(_numbers(content, prefix + stem))
    stages = provenance.stages_of(layout.reports / "metrics", layout.reports / "timing")
    return ExperimentResult(name, "complete", None, rows, pooled, stages)


# The keys of a reports/timing record that say where the stage ran (dexflow.pipeline.provenance).
_RECORD_KEYS = ("provenance", "metrics_digest", "made")


@dataclass(frozen=True)
class Comparison:
    """One metric of one method, experiment against default, over the paired sequences.

    Attributes:
        n: Sequences with a finite value in both.
        default, value: Means over those sequences.
        delta: Mean of the per-sequence differences (experiment − default).
        half_width: Half-width of the 95 % confidence interval of ``delta`` (NaN for n < 2).
    """

    n: int
    default: float
    value: float
    delta: float
    half_width: float

    @property
    def resolved(self) -> bool:
        """The difference is larger than the spread across sequences (the interval excludes 0)."""
        return math.isfinite(self.half_width) and abs(self.delta) > self.half_width


def _column(rows: list[dict[str, str]], method: str, metric: str) -> dict[str, float]:
    out = {}
    for row in rows:
        if row.get("method") != method:
            continue
        try:
            value = float(row.get(metric, "nan"))
        except ValueError:
            continue
        if math.isfinite(value):
            out[row["sequence"]] = value
    return out


def compare(default: ExperimentResult, other: ExperimentResult, method: str, metric: str):
    """The paired comparison of ``metric`` for ``method``, or None without common sequences.
    The interval is :func:`dexflow.stats.mean_interval`'s of the per-sequence differences."""
    a, b = _column(default.rows, method, metric), _column(other.rows, method, metric)
    common = sorted(set(a) & set(b))
    if not common:
        return None
    x = np.array([a[s] for s in common])
    y = np.array([b[s] for s in common])
    diff = stats.mean_interval(y - x, CONFIDENCE)
    half = (diff.high - diff.low) / 2  # NaN for one sequence
    return Comparison(len(common), float(x.mean()), float(y.mean()), diff.value, half)


def _fmt(value: float) -> str:
    if not math.isfinite(value):
        return "—"
    magnitude = abs(value)
    digits = 1 if magnitude >= 10 else 2 if magnitude >= 0.1 else 3
    return f"{value:.{digits}f}"


def _signed(value: float) -> str:
    return "—" if not math.isfinite(value) else ("+" if value >= 0 else "−") + _fmt(abs(value))


def _label(metric: str) -> str:
    label, unit, higher = metric_label(metric)
    return f"{label}{' ' + unit if unit else ''} {'↑' if higher else '↓'}"


def _cell(c: Comparison | None) -> str:
    if c is None:
        return "—"
    spread = f" ± {_fmt(c.half_width)}" if math.isfinite(c.half_width) else ""
    text = f"{_fmt(c.value)} ({_signed(c.delta)}{spread})"
    return f"**{text}**" if c.resolved else text


def _finding(experiment: str, method: str, comparisons: dict[str, Comparison]) -> str:
    """One sentence: the resolved differences (better / worse), those within the spread, and
    the metrics no sequence changed."""
    clear, unclear, same = [], [], []
    for metric, c in comparisons.items():
        label, unit, higher = metric_label(metric)
        unit = f" {unit}" if unit else ""
        spread = f"{_signed(c.delta)} ± {_fmt(c.half_width)}"
        if c.delta == 0 and not c.half_width > 0:  # every paired difference is 0
            same.append(label)
        elif c.resolved:
            better = (c.delta > 0) == higher
            clear.append(
                f"{label} {_fmt(c.default)} → {_fmt(c.value)}{unit} "
                f"({'better' if better else 'worse'}, {spread})"
            )
        else:
            unclear.append(f"{label} ({spread}{unit})")
    n = max((c.n for c in comparisons.values()), default=0)
    text = f"`{experiment}` ({method}, {n} sequences): "
    text += "; ".join(clear) if clear else "no difference larger than the spread"
    if unclear:
        text += "; within the spread across sequences: " + ", ".join(unclear)
    if same:
        text += "; unchanged in every sequence: " + ", ".join(same)
    return text + "."


def write_suite_report(
    suite: str,
    results: dict[str, ExperimentResult],
    out_md: str | Path,
    command: str,
    data: str,
) -> Path:
    """Write the suite's report (one section per question) and the CSV of every comparison
    beside it (``<out>.csv``).

    Only runs of one machine are compared: an experiment is compared to the default only where
    every stage of both was made on the same machine (:attr:`ExperimentResult.machine`); one
    made elsewhere, or without a record of where, is listed as not compared, and with the
    default's machine unknown nothing is. :func:`run_suite` reruns what this machine did not
    make, so that its reports compare everything.

    Args:
        results: By experiment name; those missing are reported as queued.
        command: The command that made the report (quoted in it).
        data: What the experiments ran on (quoted in it).
    """
    out_md = Path(out_md)
    names = suite_experiments(suite)
    results = {n: results.get(n) or ExperimentResult(n, "queued") for n in names}
    default = results[DEFAULT]
    lines = [
        f"# dexflow ablations: the {suite} suite",
        "",
        f"Generated by `{command}` on {data}.",
        "",
        "Written by:",
        "",
        *provenance.markdown(None, data),
        "",
        _machine_statement(default),
        "",
        "Each experiment (`conf/experiment/<name>.yaml`) ran the whole pipeline and is compared "
        "to the default sequence by sequence. A cell reads *value (Δ ± ci)*: the mean over "
        "the sequences both have, the mean per-sequence difference to the default and the "
        f"half-width of its {CONFIDENCE:.0%} confidence interval (Student's t over the "
        "sequences); the default's row is its mean over all of its sequences. **Bold**: the "
        "interval excludes 0; otherwise the difference is within the spread across sequences. "
        "Each interval stands alone: among the dozens here, one or two bold cells are expected "
        "by chance. ↑ higher is better, ↓ lower. Every comparison is in "
        f"[`{out_md.with_suffix('.csv').name}`]({out_md.with_suffix('.csv').name}).",
        "",
    ]
    csv_rows: list[dict] = []
    for q in SUITES[suite]:
        lines += [f"## {q.title}", ""]
        lines += _question_section(q, default, results, csv_rows)
    lines += [
        "## Experiments",
        "",
        "| experiment | status | sequences | note | machine |",
        "|---|---|---|---|---|",
    ]
    for name in names:
        r = results[name]
        count = len({row["sequence"] for row in r.rows}) if r.rows else "—"
        note = (r.error or "").replace("|", "/").replace("\n", " ")
        if r.status == "queued":
            note = (r.error or "not run yet") + " (rerun the command to run it)"
        elif r.status == "complete" and name != DEFAULT and not _same_machine(default, r):
            note = _not_compared(default, r)
        machine = "—" if r.status != "complete" else r.machine or "not recorded"
        lines.append(f"| `{name}` | {r.status} | {count} | {note} | {machine} |")
    with atomic_path(out_md) as tmp:
        tmp.write_text("\n".join(lines).rstrip() + "\n", encoding="utf-8")
    columns = ["question", "experiment", "method", "metric", "sequences", "default", "value",
               "delta", "half_width", "resolved"]  # fmt: skip
    with atomic_path(out_md.with_suffix(".csv")) as tmp, tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(csv_rows)
    return out_md


def _same_machine(default: ExperimentResult, other: ExperimentResult) -> bool:
    """Both complete and every stage of both made on one recorded machine."""
    return (
        default.status == other.status == "complete"
        and default.machine is not None
        and other.machine == default.machine
    )


def _not_compared(default: ExperimentResult, other: ExperimentResult) -> str:
    """Why a complete experiment is not compared to the default (a table note)."""
    if default.machine is None:
        return "not compared: the default's machine is not recorded"
    where = f"made on machine {other.machine}" if other.machine else "not recorded where made"
    return f"not compared: {where}, the default on {default.machine}; rerun it here"


def _machine_statement(default: ExperimentResult) -> str:
    """Which machine the comparisons are made on, or why there are none."""
    if default.status != "complete":
        return "No comparison: the default has not finished."
    if default.machine is None:
        return (
            "**No comparison: the default's machine is not recorded** (no `reports/timing` "
            "record matches its metrics, or its stages ran on several machines): a difference "
            "to it could be the machine's. Rerun the suite on this machine."
        )
    here = " (this machine)" if default.machine == provenance.machine_id() else ""
    return (
        f"Same machine: the default and every experiment compared to it ran, every stage, on "
        f"machine {default.machine}{here}. An experiment made elsewhere, or without a record "
        "of where, is not compared (see *Experiments*)."
    )


def _question_section(q: Question, default, results, csv_rows: list[dict]) -> list[str]:
    if default.status != "complete":
        return [f"No numbers: the default is {default.status} ({default.error or 'not run'}).", ""]
    if default.machine is None:
        return ["No numbers: the default's machine is not recorded (see above).", ""]
    multi = len(q.methods) > 1
    head = ["experiment", *(["method"] if multi else []), *(_label(m) for m in q.metrics)]
    lines = [] if multi else [f"Method: {q.methods[0]}.", ""]
    lines += ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    findings, missing = [], []
    for method in q.methods:
        base = [_fmt(np.mean(list(_column(default.rows, method, m).values()) or [np.nan]))
                for m in q.metrics]  # fmt: skip
        lines.append(
            "| " + " | ".join([f"`{DEFAULT}`", *([method] if multi else []), *base]) + " |"
        )
        for name in q.experiments:
            r = results[name]
            if r.status != "complete":
                missing.append(f"`{name}` ({r.status})")
                continue
            if not _same_machine(default, r):
                missing.append(f"`{name}` (made on another machine, or not recorded where)")
                continue
            comparisons = {m: compare(default, r, method, m) for m in q.metrics}
            cells = [_cell(comparisons[m]) for m in q.metrics]
            lines.append(
                "| " + " | ".join([f"`{name}`", *([method] if multi else []), *cells]) + " |"
            )
            found = {m: c for m, c in comparisons.items() if c is not None}
            if found:
                findings.append(_finding(name, method, found))
            for m, c in found.items():
                csv_rows.append({"question": q.key, "experiment": name, "method": method,
                                 "metric": m, "sequences": c.n, "default": c.default,
                                 "value": c.value, "delta": c.delta, "half_width": c.half_width,
                                 "resolved": c.resolved})  # fmt: skip
    lines.append("")
    if q.pooled:
        lines += _pooled_table(q, default, results)
    lines += ["**Findings.** " + (" ".join(findings) if findings else "No experiment finished.")]
    if missing:
        lines += ["", "Not in the table: " + ", ".join(dict.fromkeys(missing)) + "."]
    return [*lines, ""]


def _pooled_table(q: Question, default: ExperimentResult, results) -> list[str]:
    """The question's pooled aggregates (no per-sequence value, so no spread)."""
    done = [default, *(results[n] for n in q.experiments if _same_machine(default, results[n]))]
    lines = [
        "Pooled over all sequences (no per-sequence value, so no spread):",
        "",
        "| experiment | " + " | ".join(_label(k) for k in q.pooled) + " |",
        "|---" * (len(q.pooled) + 1) + "|",
    ]
    for r in done:
        cells = [_fmt(r.pooled.get(k, float("nan"))) for k in q.pooled]
        lines.append(f"| `{r.name}` | " + " | ".join(cells) + " |")
    return [*lines, ""]


def run_suite(
    suite: str,
    project: str | Path,
    jobs_dir: str | Path,
    overrides: list[str] | None = None,
    run: bool = True,
) -> dict[str, ExperimentResult]:
    """Run (or resume) every experiment of ``suite`` and return their results.

    The default runs first, in ``jobs_dir/default``, reusing the project's outputs where its
    params match the project's ``params.yaml`` (the demo after ``dvc repro``) and this machine
    made them (the project's ``reports/timing`` says so; outputs made elsewhere, e.g. committed
    from another machine, are made again here). Every other experiment runs in
    ``jobs_dir/<name>`` reusing the default's outputs where its params leave a stage unchanged
    (``refine_no_pen`` reruns refine and what follows it). A stage an experiment's directory
    already holds, made on this machine with the key the stage has now (its command, params
    and the bytes of its deps: :mod:`dexflow.pipeline.validity`), is kept, so a resumed suite
    runs only what is missing or changed. So every experiment and the default it is compared to
    come from this machine.

    Args:
        project: The project root (``conf/``, ``stages/``, ``dvc.yaml``, ``params.yaml``).
        overrides: Hydra overrides for every experiment (``data=custom``, ``data.root=...``),
            after the suite's own (:data:`SUITE_OVERRIDES`: ``track=on`` for suite track).
        run: False: only read what the directories hold.
    """
    from omegaconf import OmegaConf

    from dexflow.config import compose_params
    from dexflow.tools.sweep import run_job

    project, jobs_dir = Path(project).resolve(), Path(jobs_dir).resolve()
    names = suite_experiments(suite)
    overrides = [*SUITE_OVERRIDES.get(suite, ()), *(overrides or [])]
    machine = provenance.machine_id()
    results: dict[str, ExperimentResult] = {}
    for i, name in enumerate(names, 1):
        job = jobs_dir / name
        if run:
            extra = [] if name == DEFAULT else [f"experiment={name}"]
            job.mkdir(parents=True, exist_ok=True)
            try:
                composed = compose_params(
                    [*(overrides or []), *extra], job / "params.composed.yaml"
                )
            except ConfigError as exc:  # this experiment cannot run; the others still do
                failed = {"status": "failed", "stage": "params", "error": str(exc)}
                save_json(job / STATUS_FILE, failed)  # as run_job records a rejected config
                results[name] = load_result(job, name)
                log.error("[%d/%d] %s: %s", i, len(names), name, exc)
                continue
            base = project if name == DEFAULT else jobs_dir / DEFAULT
            log.info("[%d/%d] %s: in %s", i, len(names), name, job)
            handler = logging.FileHandler(job / "sweep.log", mode="w", encoding="utf-8")
            logging.getLogger("dexflow").addHandler(handler)
            try:
                run_job(OmegaConf.load(composed), base, job, machine=machine)
            finally:
                logging.getLogger("dexflow").removeHandler(handler)
                handler.close()
            if name == DEFAULT:  # the others reuse its outputs: it needs the pipeline file
                link = job / "dvc.yaml"
                if not link.exists():
                    link.symlink_to(project / "dvc.yaml")
        results[name] = load_result(job, name)
        log.info("[%d/%d] %s: %s", i, len(names), name, results[name].status)
    return results


def suite_command(suite: str, overrides: list[str], out: str | Path, default_out: Path) -> str:
    """The command line that reproduces a suite report (quoted in it)."""
    parts = ["dexflow", "report", "ablation", "--suite", suite]
    for o in overrides:
        parts += ["--set", o]
    if Path(out) != default_out:
        parts += ["--out", str(out)]
    return shlex.join(parts)
