"""Stage report: the summary of one pipeline run that a researcher reads in two minutes,
generated from its metrics.

- :func:`write_summary` -> ``reports/summary.md`` (+ PNG figures, + CSV tables): a five-line
  *key results* box (n, the headline per method with its 95 % interval, the caveats; a sixth
  line, tracking against refinement, where stage track ran), the robot hand on the object
  (:func:`write_hand_figure`), a few sentences on signals that look contradictory, then the
  paper's Table II/III layout (baseline vs DexFlow vs DexFlow + refinement, and DexFlow +
  tracking where its inputs hold it: :func:`_methods`) beside the published numbers, each
  rate and mean over sequences with its 95 % interval (:mod:`dexflow.stats`), simulation,
  replay, contact quality, a per-object breakdown, figures, provenance and, last, the
  definitions of every column.
- Tables in the Markdown keep at most :data:`MAX_COLUMNS` columns; each full table goes to a CSV
  next to it (``summary_<table>.csv``, full precision), which the Markdown links.

The comparison of experiments (``reports/sweep.md``) is :mod:`dexflow.tools.experiments`.

The provenance (:mod:`dexflow.pipeline.provenance`) says the commit and machine the report was
written on, the data, and the machine(s) the numbers were made on.

**One file** (about 1400 lines): the summary is one document: each section is a function of its
own, in the order the summary shows them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from dexflow import stats
from dexflow.io.layout import CORE_TRAJECTORIES, Layout
from dexflow.params import PipelineParams
from dexflow.pipeline import provenance
from dexflow.pipeline.runner import StageSpec

__all__ = [
    "CORE_METHODS",
    "METHOD_LABELS",
    "METRICS",
    "PAPER",
    "STAGE",
    "cell",
    "pyplot",
    "run_report",
    "save_figure",
    "write_project_summary",
    "write_summary",
]

METHOD_LABELS = {
    "baseline": "position baseline (DexRetarget-style)",
    "retarget": "DexFlow retargeting",
    "refine": "DexFlow + refinement",
    "track": "DexFlow + tracking (physics)",
}
# The methods every summary shows (a stage that did not run: —); the others of METHOD_LABELS
# (track, stage track's with ``track=on``) only where the inputs hold them (:func:`_methods`).
CORE_METHODS = CORE_TRAJECTORIES
SHORT_LABELS = {
    "baseline": "baseline",
    "retarget": "DexFlow",
    "refine": "DexFlow + refinement",
    "track": "DexFlow + tracking",
}
COLORS = {"baseline": "#999999", "retarget": "#4c72b0", "refine": "#55a868", "track": "#c44e52"}
TRACK_SUMMARY = "track_refine"  # stage track@refine's reports/metrics/track_refine.json
# Published (DexFlow paper, DexYCB, ShadowHand), only where the paper's definition is the one
# dexflow computes (SSR by the paper's gravity protocol; PD, SPD and CD as BODex defines them),
# as printed: the paper does not state their units. Not here, because no number of dexflow's
# means the same: FVR (the paper does not define it), the time-aligned CD 0.008 / DexRetarget
# 0.016 and the RMS acceleration 0.073 / 0.080 (definitions and units not given), velocity KL
# 0.48 (bins and speeds not given). PAPER_NOT_COMPARABLE lists them for the report's note.
PAPER = {
    "baseline": {"ssr_paper": 5.35, "pd_mm": 84.4},
    "refine": {"ssr_paper": 40.32, "spd_mm": 0.37, "pd_mm": 8.5, "cd_mm": 0.77},
}
PAPER_NOT_COMPARABLE = (
    "FVR 0.41 (the paper does not define FVR; dexflow's `fvr` is its own), velocity KL 0.48, "
    "RMS acceleration 0.073 -> 0.080 after refinement and time-aligned CD 0.008 (DexRetarget "
    "0.016), whose definitions and units the paper does not give"
)
# Metric -> (label, higher is better)
METRICS = {
    "ssr": ("SSR every test % ↑", True),
    "ssr_paper": ("SSR paper protocol % ↑", True),
    "ssr_bench": ("SSR DexGraspBench % ↑", True),
    "spd_mm": ("SPD mm ↓", False),
    "pd_mm": ("PD mm ↓", False),
    "cd_mm": ("CD mm ↓", False),
    "cd_contact_mm": ("CD in contact mm (dexflow) ↓", False),
    "fvr": ("violation rate (dexflow's FVR) ↓", False),
    "velocity_kl": ("velocity KL ↓", False),
    "rms_acc": ("RMS acc rad/s² ↓", False),
    "time_aligned_cd_mm": ("keypoint Chamfer mm (dexflow) ↓", False),
    "keypoint_error_mm": ("keypoint error mm ↓", False),
    "fingertip_error_mm": ("fingertip error mm ↓", False),
    "fingertip_error_surface_mm": ("fingertip error vs surface tips mm ↓", False),
}
# the Markdown shows the first MAX_COLUMNS - 1 of a table's metrics, the CSV every one
TABLE_II = ("ssr", "ssr_paper", "ssr_bench", "spd_mm", "pd_mm", "cd_mm", "fvr", "cd_contact_mm")
TABLE_III = ("velocity_kl", "rms_acc", "keypoint_error_mm", "fingertip_error_mm",
             "fingertip_error_surface_mm")  # fmt: skip


def cell(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return f"{value:.{digits}f}"


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"svg.hashsalt": "dexflow", "figure.dpi": 100})
    return plt


def save_figure(fig, path: Path) -> None:
    from dexflow.io.atomic import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": None})
    fig.clf()


# ---------------------------------------------------------------------------------- summary


def write_project_summary(
    layout: Layout,
    data_name: str | None = None,
    out_md: str | Path | None = None,
    params: PipelineParams | None = None,
) -> Path:
    """:func:`write_summary` on a project's files (``layout``): what the ``report`` stage and
    ``dexflow report summary`` write (``out_md`` defaults to ``reports/summary.md``).

    With ``params`` (the run's), the summary also shows the robot hand on the object
    (:func:`write_hand_figure`) and names the replay's thresholds.
    """
    figures = layout.figures
    hand_figure = write_hand_figure(params, layout, figures) if params is not None else None
    return write_summary(
        layout.stage_metrics_dir, layout.metrics_table, layout.plots,
        out_md or layout.summary_report, figures, data_name=data_name,
        stage_summary=layout.metrics.summary,
        replay_dirs={m: layout.replay(m).root for m in METHOD_LABELS},
        timing_dir=layout.reports / "timing", hand_figure=hand_figure,
        replay_limits=None if params is None else {
            "position_m": params.replay.max_position_error_m,
            "rotation_rad": params.replay.max_rotation_error_rad},
    )  # fmt: skip


MAX_COLUMNS = 8  # the widest table the Markdown shows; the full tables go to CSV files
HAND_FIGURE = "summary_hand.png"


def write_summary(
    metrics_dir,
    sequences_csv,
    plots_dir,
    out_md,
    figures_dir,
    data_name: str | None = None,
    stage_summary: str | Path | None = None,
    replay_dirs: dict[str, str | Path] | None = None,
    timing_dir: str | Path | None = None,
    hand_figure: tuple[str, str] | None = None,
    replay_limits: dict[str, float] | None = None,
) -> Path:
    """Write ``summary.md``, its figures and its full tables (CSV) from the metrics stage's
    outputs.

    The summary opens with a five-line key-results box: n (sequences, frames, data, hand), the
    headline per method with its 95 % interval (:mod:`dexflow.stats`), the caveats (a sixth
    line, tracking against refinement, where stage track ran); then the hand figure
    (``hand_figure``) and one sentence for each pair of signals that look contradictory. Tables
    keep at most :data:`MAX_COLUMNS` columns; each full table is written next to ``out_md`` as
    ``summary_<table>.csv`` and linked. The provenance (:mod:`dexflow.pipeline.provenance`)
    says the commit and machine it is written on, the data, and the machines and commits the
    stages behind its numbers ran on (they may have run earlier, elsewhere: DVC restores
    outputs from its cache), flagged when they differ. The definitions of every column close
    it. Same inputs, machine and commit: the same bytes. The methods: :data:`CORE_METHODS`, and
    track wherever the inputs hold it (:func:`_methods`).

    Args:
        metrics_dir: ``reports/metrics`` (``metrics.json``, ``contact.json``, ...).
        sequences_csv: The metrics stage's per-sequence table.
        plots_dir: The per-frame CSVs (``keypoint_error.csv``, ``penetration.csv``).
        out_md: The Markdown file to write.
        figures_dir: Where the PNGs go (linked relative to ``out_md``).
        data_name: ``data.name`` of the run (``demo`` for the generated demo); None to tell the
            demo by its ground truth (contact precision/recall exist only there).
        stage_summary: The metrics stage's ``summary.json``: every sequence dropped on the way
            (by which stage, why) and the warnings, listed in the report.
        replay_dirs: Per method the replay stage's directory (``data/replay/<label>``): the
            object's error over time is plotted from its sequences (None or absent: no plot).
        timing_dir: ``reports/timing``: the stages' records of where they ran (None: not
            recorded).
        hand_figure: ``(file name in figures_dir, caption)`` of the robot-hand figure
            (:func:`write_hand_figure`); None: not shown.
        replay_limits: SPIDER's thresholds, ``position_m`` and ``rotation_rad`` (the replay
            params), named in the text; None: named by their keys only.
    """
    import pandas as pd

    metrics_dir, out_md, figures_dir = Path(metrics_dir), Path(out_md), Path(figures_dir)
    metrics = json.loads((metrics_dir / "metrics.json").read_text())
    stage = {
        p.stem: json.loads(p.read_text())
        for p in sorted(metrics_dir.glob("*.json"))
        if p.stem != "metrics"
    }
    table = pd.read_csv(sequences_csv)
    hand = ", ".join(sorted(table["hand"].unique())) if len(table) else "?"
    rel = figures_dir.relative_to(out_md.parent)
    demo = data_name == "demo" if data_name else "contact.precision" in metrics
    data = data_name or ("demo" if demo else "your sequences")
    accounts = _read_json(stage_summary)
    methods = _methods(metrics, stage, table)
    spread = _spread_rows(table, stage, methods)
    frames = _frame_count(metrics, table)

    def csv_of(name: str) -> Path:
        return out_md.with_name(f"summary_{name}.csv")

    lines = [
        "# dexflow summary",
        "",
        *_key_results(metrics, stage, spread, data, hand, frames, demo, methods),
        "",
    ]
    if hand_figure:
        name, caption = hand_figure
        lines += [f"![The robot hand on the object]({rel / name})", "", f"*{caption}.*", ""]
    lines += [
        "Generated by the `report` stage from `reports/metrics/` and `data/metrics/`; do not edit.",
        f"Data: **{data}**. Hand: **{hand}**. Sequences: {_sequence_counts(metrics)}. "
        "Definitions: *Definitions* at the end, and README, *Metrics*.",
        "",
        *_readings(metrics, stage, replay_limits),
        *_dropped_section(metrics, accounts),
        "## Grasp quality (paper Table II layout)",
        "",
        *_method_table(metrics, TABLE_II, csv_of("grasp"), methods, paper=True),
        "- Paper rows: DexFlow on DexYCB with ShadowHand, as published, only where the paper's "
        "definition is dexflow's; units as printed (the paper states none), dexflow's in mm.",
        "- " + _data_caveat(demo, data),
        "- The 95 % interval of each value: *Spread over sequences*; each column: *Definitions*.",
        "",
        *_spread_section(spread, methods, csv_of("spread")),
        f"## Simulation ({_engines_title(stage)}: the paper's gravity test and DexGraspBench's "
        "push, six directions each)",
        "",
        *_simulation_table(stage, methods, csv_of("simulation")),
        "",
        *_engines_section(stage),
        *_replay_section(
            stage,
            {m: d for m, d in (replay_dirs or {}).items() if m in methods},
            figures_dir,
            rel,
            csv_of("replay"),
        ),
        "## Motion quality (paper Table III layout)",
        "",
        *_method_table(metrics, TABLE_III, csv_of("motion"), methods, paper=False),
        "- The paper's Table III numbers are not comparable (*Definitions*, *Grasp quality*).",
        "",
        "## Contact detection",
        "",
        *_contact_rows(stage.get("contact", {}), metrics),
        "",
        "## Per object",
        "",
        *_per_object(table, methods, csv_of("objects")),
        "",
        "## Figures",
        "",
    ]
    figures = _figures(metrics, table, spread, Path(plots_dir), figures_dir, methods)
    for name, caption in figures:
        lines += [f"![{caption}]({rel / name})", ""]
    lines += [
        *_provenance_section(metrics, frames, data, metrics_dir, timing_dir),
        *_definitions(stage, replay_limits, methods),
    ]
    from dexflow.io.atomic import atomic_path

    with atomic_path(out_md) as tmp:
        tmp.write_text("\n".join(lines).rstrip() + "\n")
    return out_md


def _methods(metrics: dict, stage: dict, table) -> tuple[str, ...]:
    """The methods the summary shows: :data:`CORE_METHODS` always, then each other method of
    :data:`METHOD_LABELS` (track) that the inputs hold: rows of ``sequences.csv``, aggregates
    of ``metrics.json`` (``<method>.<metric>``), a simulate or replay summary (and for track,
    stage track's summary)."""
    held = set(table["method"]) if len(table) else set()

    def present(m: str) -> bool:
        return (
            m in held
            or any(k.startswith(f"{m}.") for k in metrics)
            or any(f"{s}_{m}" in stage for s in ("simulate", "replay"))
            or (m == "track" and TRACK_SUMMARY in stage)
        )

    return CORE_METHODS + tuple(m for m in METHOD_LABELS if m not in CORE_METHODS and present(m))


def _frame_count(metrics: dict, table) -> int | None:
    """The frames of the data: ``num_frames`` of the metrics, else summed over the table."""
    frames = metrics.get("num_frames")
    if frames is None and len(table) and "frames" in table.columns:
        frames = int(table[table["method"] == table["method"].iloc[0]]["frames"].sum())
    return frames


def _csv_link(path: Path) -> str:
    return f"Full table: [{path.name}]({path.name})."


def _write_csv(path: Path, header: list[str], rows: list[list]) -> None:
    """A full table as CSV (floats at full precision, empty for a missing value), atomically."""
    import csv
    import io

    from dexflow.io.atomic import atomic_path

    def text(value) -> str:
        if value is None or (isinstance(value, float) and not math.isfinite(value)):
            return ""
        return repr(float(value)) if isinstance(value, (float, np.floating)) else str(value)

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows([text(v) for v in row] for row in rows)
    with atomic_path(path) as tmp:
        tmp.write_text(buffer.getvalue())


def _markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    if len(header) > MAX_COLUMNS:  # a bug of this module, not of the data
        raise AssertionError(f"a table of {len(header)} columns; at most {MAX_COLUMNS} fit")
    return [
        "| " + " | ".join(header) + " |",
        "|---" * len(header) + "|",
        *("| " + " | ".join(r) + " |" for r in rows),
    ]


# ------------------------------------------------------------------------- key results


def _interval_text(interval: stats.Interval | None, digits: int) -> str:
    return "—" if interval is None else interval.text(digits)


def _headline(spread: dict, key: str, methods) -> str | None:
    """``baseline v [l, h] · DexFlow ... · + refinement ...`` of a spread row (each of
    ``methods``), then how refinement compares with the baseline (intervals apart or not); None
    if absent."""
    if key not in spread:
        return None
    _, cells, digits = spread[key]
    text = " · ".join(f"{SHORT_LABELS[m]} {_interval_text(cells.get(m), digits)}" for m in methods)
    verdict = _verdict(cells.get("refine"), cells.get("baseline"), "refinement", "the baseline")
    return f"{text} ({verdict})" if verdict else text


def _verdict(new, old, new_name: str, old_name: str) -> str | None:
    """Whether the interval ``new`` lies above or below ``old`` (``refinement above the
    baseline, intervals apart``) or overlaps it; None where either has no interval."""
    if (
        new is None
        or old is None
        or not all(math.isfinite(x) for x in (new.low, new.high, old.low, old.high))
    ):
        return None
    if new.low > old.high:
        return f"{new_name} above {old_name}, intervals apart"
    if new.high < old.low:
        return f"{new_name} below {old_name}, intervals apart"
    return f"{new_name} vs {old_name.removeprefix('the ')}: intervals overlap, not resolved"


def _key_results(
    metrics: dict,
    stage: dict,
    spread: dict,
    data: str,
    hand: str,
    frames,
    demo: bool,
    methods=CORE_METHODS,
) -> list[str]:
    """The five-line box: n; SSR, penetration and keypoint error, replay success per method
    (``methods``) with their 95 % intervals; with track among ``methods``, a sixth line:
    tracking's replay success against refinement's (:func:`_tracking_line`); the caveats.
    Every number from the inputs."""
    sequences = metrics.get("num_input_sequences", metrics.get("num_sequences", "?"))
    dropped = metrics.get("num_dropped", 0)
    through = f" ({sequences - dropped} through every stage)" if dropped else ""
    frames_text = f", {frames} frames" if frames is not None else ""
    lines = [
        f"> **Key results.** n = {sequences} sequences{through}{frames_text}; data **{data}**; "
        f"hand **{hand}**. Per method: value [95 % interval] over the sequences."
    ]
    grasp = _headline(spread, "ssr", methods)
    lines.append(
        "> - **Grasp held in simulation** (SSR every test, % of sequences ↑): "
        + (grasp or "not measured")
    )
    pd = _headline(spread, "pd_mm", methods)
    keypoint = _headline(spread, "keypoint_error_mm", methods)
    lines.append(
        f"> - **Penetration** (PD, mm ↓): {pd or 'not measured'}; **keypoint error** (mm ↓): "
        f"{keypoint or 'not measured'}"
    )
    replay = _headline(spread, "success_rate", methods)
    lines.append(
        "> - **Replay success** (object carried along its recorded path, % of sequences ↑): "
        + (replay or "not replayed")
    )
    if "track" in methods:
        lines.append(_tracking_line(stage, spread))
    caveats = [_data_caveat(demo, data).rstrip(".")]
    spider = _spider_left_behind(stage)
    if spider:
        caveats.append(
            f"replay's SPIDER rate counts objects the hand lost ({spider['label']}: "
            f"{spider['spider']:.0f} % pass it, {spider['lost']:.0f} % lost): read *success*"
        )
    caveats.append("intervals treat sequences as independent (sequences of one object are not)")
    lines.append("> - **Caveats**: " + "; ".join(caveats) + ".")
    return lines


def _tracking_line(stage: dict, spread: dict) -> str:
    """The key-results line of stage track: the tracked trajectories' replay success against
    the refined ones' (intervals apart or not), and the share of tracked sequences whose
    tracked trajectory is feasible (``track_refine.json``)."""
    success = spread.get("success_rate")
    if success is None or (success[1].get("track") is None and success[1].get("refine") is None):
        text = "not replayed"
    else:
        _, cells, digits = success
        text = " vs ".join(
            f"{SHORT_LABELS[m]} {_interval_text(cells.get(m), digits)}" for m in ("track", "refine")
        )
        verdict = _verdict(cells.get("track"), cells.get("refine"), "tracking", "refinement")
        text += f" ({verdict})" if verdict else ""
    tracked = stage.get(TRACK_SUMMARY) or {}
    if tracked.get("num_tracked") is not None:
        text += (
            f"; feasible (its replay succeeds) {cell(tracked.get('feasible_rate'), 1)} % of the "
            f"{tracked['num_tracked']} tracked sequences"
        )
    return (
        "> - **Tracking** (physics in the loop, stage track; replay success, % of sequences ↑): "
        + text
    )


def _spider_left_behind(stage: dict) -> dict | None:
    """The method whose SPIDER rate exceeds its *success* most while most of its objects are
    lost: its label, SPIDER and lost rates and left-behind error; None if none does."""
    found = []
    for m in METHOD_LABELS:
        r = stage.get(f"replay_{m}") or {}
        spider, lost = r.get("spider_success_rate"), r.get("lost_rate")
        if spider is None or lost is None or lost < 50:
            continue
        gap = spider - (r.get("success_rate") or 0.0)
        if gap > 0:
            found.append((gap, METHOD_LABELS[m], spider, lost, r.get("static_error_mean_m")))
    if not found:
        return None
    _, label, spider, lost, static = max(found, key=lambda f: f[0])
    return {"label": label, "spider": spider, "lost": lost, "static_m": static}


CEILING_NOTE_BELOW = 50.0  # % of sequences: a rigid ceiling lower than this gets a note


def _replay_limits_notes(replay: dict) -> list[str]:
    """Notes on what bounds the replay's success regardless of the grip (refine's replay): a
    rigid ceiling below :data:`CEILING_NOTE_BELOW` %, and objects that do not rest as recorded;
    none where neither holds."""
    notes = []
    ceiling, rotation = (
        replay.get("ceiling_success_rate"),
        replay.get("ceiling_rotation_error_mean_rad"),
    )
    if ceiling is not None and rotation is not None and ceiling < CEILING_NOTE_BELOW:
        notes.append(
            f"- **Replay, {METHOD_LABELS['refine']}: rigid ceiling {ceiling:.0f} %.** An object "
            "welded to the hand from the recorded lift would follow its recording in only "
            f"{ceiling:.0f} % of the sequences (mean rotation error {rotation:.2f} rad): the "
            "recorded object turns relative to the hand (or its annotation spins, or its "
            "rotations are misread: `dexflow convert` checks them), so no grip on this hand "
            "path can succeed more often."
        )
    unstable = replay.get("unstable_rest_rate")
    if unstable:
        drift = _scaled(replay.get("rest_drift_mean_m"), 100)
        notes.append(
            f"- **{unstable:.0f} % of the objects do not rest as recorded.** Left alone on the "
            "replay's table at their recorded pose, they are lost before the recorded lift "
            f"(mean drift {cell(drift, 1)} cm): the object topples whatever the hand does."
        )
    return notes


def _readings(metrics: dict, stage: dict, limits: dict | None) -> list[str]:
    """One sentence for each pair of signals that look contradictory in this run (only those
    that do)."""
    notes = []
    spider = _spider_left_behind(stage)
    if spider:
        left = (
            f" an object the hand leaves on the table is on average "
            f"{100 * spider['static_m']:.1f} cm from its recorded path,"
            if spider["static_m"] is not None
            else ""
        )
        limit = (
            f"{100 * limits['position_m']:.0f} cm" if limits else "`replay.max_position_error_m`"
        )
        notes.append(
            f"- **Replay, {spider['label']}: SPIDER {spider['spider']:.0f} % beside "
            f"{spider['lost']:.0f} % lost.** SPIDER's criterion is the object's *mean* error "
            "over the grasp below "
            f"{limit}:{left} so it passes objects the hand dropped or never lifted; *success* "
            "also requires the object carried to where the recording ends."
        )
    notes += _replay_limits_notes(stage.get("replay_refine") or {})
    kl = {m: metrics.get(f"{m}.velocity_kl") for m in ("baseline", "retarget")}
    acc = {m: metrics.get(f"{m}.rms_acc") for m in ("baseline", "retarget")}
    if all(v is not None for v in (*kl.values(), *acc.values())) and (
        kl["retarget"] > kl["baseline"] and acc["retarget"] < acc["baseline"]
    ):
        ratio = kl["retarget"] / kl["baseline"] if kl["baseline"] > 0 else math.inf
        notes.append(
            f"- **Velocity KL: DexFlow {kl['retarget']:.2f}, {ratio:.0f}x the baseline's "
            f"{kl['baseline']:.2f}.** It compares the robot's fingertip speeds with the human's: "
            "the per-frame baseline reproduces them frame by frame, at the cost of jittering "
            f"joints (RMS acceleration {acc['baseline']:.1f} vs {acc['retarget']:.2f} rad/s²), "
            "while DexFlow's temporal terms smooth them: a higher KL here is the smoothing, not "
            "worse motion."
        )
    pd = {m: metrics.get(f"{m}.pd_mm") for m in ("retarget", "refine")}
    kp = {m: metrics.get(f"{m}.keypoint_error_mm") for m in ("retarget", "refine")}
    if all(v is not None for v in (*pd.values(), *kp.values())) and (
        pd["refine"] < pd["retarget"] and kp["refine"] > kp["retarget"]
    ):
        notes.append(
            f"- **Refinement: penetration {pd['retarget']:.2f} -> {pd['refine']:.2f} mm, "
            f"keypoint error {kp['retarget']:.2f} -> {kp['refine']:.2f} mm.** It moves the "
            "fingers out of the object, away from the human keypoints that lie inside it: the "
            "trade the refinement makes."
        )
    if not notes:
        return []
    return ["## Reading the numbers", "", *notes, ""]


def _contact_rows(contact: dict, metrics: dict) -> list[str]:
    """Contact flicker the paper's way (a single threshold on the baseline retargeting against
    DexFlow's dual threshold and inference on its own), then what each part removes on the
    same trajectory, and precision/recall where the data has ground truth (stage contact's
    ``contact.json``, definitions in :mod:`dexflow.stages.contact`)."""

    def percent(key: str) -> str:
        value = contact.get(key)
        return "—" if value is None else cell(100 * value, 0) + " %"

    lines = [
        "| state changes per finger per second, or the share removed | value | paper |",
        "|---|---|---|",
        f"| single threshold on the baseline retargeting | "
        f"{cell(contact.get('flicker_baseline_threshold'))} | |",
        f"| DexFlow: dual threshold and inference on its retargeting | "
        f"{cell(contact.get('flicker_dexflow'))} | |",
        f"| removed, DexFlow vs the baseline (the paper's comparison) | "
        f"{percent('flicker_reduction_vs_baseline')} | 68 % |",
        f"| removed by the dual threshold vs a single one (same trajectory) | "
        f"{percent('changes_removed_vs_threshold')} | |",
        f"| removed by the inference after the dual threshold (same trajectory) | "
        f"{percent('changes_removed_by_inference')} | |",
    ]
    for key in ("precision", "recall"):
        if f"contact.{key}" in metrics:
            lines.append(f"| {key} vs ground truth (demo) | {cell(metrics[f'contact.{key}'])} | |")
    return lines


def _replay_section(
    stage: dict, dirs: dict, figures_dir: Path, rel: Path, csv_path: Path | None = None
) -> list[str]:
    """Stage replay per method (its metrics; the full table to ``csv_path``), and the object's
    position error over time."""
    found = {m: stage[f"replay_{m}"] for m in METHOD_LABELS if stage.get(f"replay_{m}")}
    if not found:
        return []
    columns = [  # (header, value of a replay summary, digits; None: text)
        ("scored", lambda r: r.get("num_scored", r.get("num_replayed", 0)), None),
        ("not scored", _not_scored, None),
        ("success (%)", lambda r: r.get("success_rate"), 1),
        ("SPIDER (%)", lambda r: r.get("spider_success_rate"), 1),
        ("carried (%)", lambda r: r.get("carried_rate"), 1),
        ("rigid ceiling (%)", lambda r: r.get("ceiling_success_rate"), 1),
        ("position error (cm)", lambda r: _scaled(r.get("position_error_mean_m"), 100), 1),
        ("lost (%)", lambda r: r.get("lost_rate"), 0),
        ("rotation error (rad)", lambda r: r.get("rotation_error_mean_rad"), 2),
        ("held (% of grasp)", lambda r: _scaled(r.get("held_fraction"), 100), 0),
        ("left behind (cm)", lambda r: _scaled(r.get("static_error_mean_m"), 100), 1),
        ("unstable rest (%)", lambda r: r.get("unstable_rest_rate"), 0),
    ]
    shown = MAX_COLUMNS - 1
    rows_md, rows_csv = [], []
    for m, r in found.items():
        values = [get(r) for _, get, _ in columns]
        rows_csv.append([METHOD_LABELS[m], *values])
        rows_md.append([METHOD_LABELS[m]] + [
            str(v) if digits is None else cell(v, digits)
            for v, (_, _, digits) in zip(values[:shown], columns[:shown], strict=True)
        ])  # fmt: skip
    lines = [
        "## Replay (object free under gravity: SPIDER's success and carried)",
        "",
        *_markdown_table(["method", *(h for h, _, _ in columns[:shown])], rows_md),
        "",
    ]
    if csv_path is not None:
        _write_csv(csv_path, ["method", *(h for h, _, _ in columns)], rows_csv)
        lines += [
            "- " + _csv_link(csv_path) + " Also: lost, rotation error, held, left behind "
            "(cm, where an object that never moves ends up), unstable rest.",
        ]
    lines += [
        "- *Success* = *SPIDER* (mean error small) and *carried* (final error small); "
        "*Definitions*, *Replay*.",
        *_tracking_bullet(stage.get(TRACK_SUMMARY)),
        "",
    ]
    figure = _replay_figure(dirs, figures_dir)
    if figure:
        name, caption = figure
        lines += [f"![{caption}]({rel / name})", ""]
    return lines


def _tracking_bullet(tracked: dict | None) -> list[str]:
    """Stage track's own summary (``track_refine.json``) as one bullet; none without it."""
    if not tracked:
        return []
    position = _scaled(tracked.get("position_error_mean_m"), 100)
    final = _scaled(tracked.get("position_error_final_m"), 100)
    return [
        f"- *{METHOD_LABELS['track']}* (stage track, `track=on`): "
        f"{tracked.get('num_tracked', 0)} sequences tracked, *feasible* (the tracked "
        f"trajectory's replay succeeds) {cell(tracked.get('feasible_rate'), 1)} % of them; "
        f"object error {cell(position, 1)} cm (final {cell(final, 1)} cm), "
        f"{cell(tracked.get('rotation_error_mean_rad'))} rad; lost "
        f"{cell(tracked.get('lost_rate'), 0)} %; grip drift "
        f"{cell(_scaled(tracked.get('grip_drift_mean_m'), 1000), 1)} mm (the human's fingertips "
        "slide that far over the recorded object while it is carried: a grasp that holds it and "
        "moves it as recorded misses them by at least that much; "
        f"`reports/metrics/{TRACK_SUMMARY}.json`)."
    ]


def _scaled(value, factor: float):
    return None if value is None else factor * value


def _not_scored(replay: dict) -> str:
    """The replay's not-scored count with its reasons, e.g. ``2 (1 no support, 1 free fall)``."""
    total = int(replay.get("num_not_scored", 0))
    reasons = [(int(replay.get(f"num_not_scored_{k}", 0)), k.replace("_", " "))
               for k in ("no_contact", "no_support", "free_fall")]  # fmt: skip
    named = ", ".join(f"{n} {why}" for n, why in reasons if n)
    return f"{total} ({named})" if named else str(total)


def _replay_figure(dirs: dict, figures_dir: Path) -> tuple[str, str] | None:
    """The mean over the replayed sequences of the object's position error against the frames
    since each one's first contact, with its 95 % interval (Student's t over the sequences
    at each frame), drawn while at least half of them last (they differ in length)."""
    from dexflow.io.artifacts import read_replay

    curves, counts = {}, {}
    for m, root in dirs.items():
        summary = _read_json(Path(root) / "summary.json")
        runs = []
        for name, entry in sorted(summary.get("sequences", {}).items()):
            if entry.get("status") != "ok" or not entry.get("replayed"):
                continue
            rows = read_replay(Path(root) / "sequences" / f"{name}.npz").rows
            runs.append(rows["position_error_m"][rows["frame"] >= entry["first_contact"]])
        if runs:
            lengths = sorted(len(r) for r in runs)
            shown = lengths[(len(runs) - 1) // 2]  # frames that at least half the runs reach
            padded = np.full((len(runs), shown), np.nan)
            for i, r in enumerate(runs):
                padded[i, : min(len(r), shown)] = r[:shown]
            intervals = [stats.mean_interval(100 * padded[:, t], lower=0.0) for t in range(shown)]
            curves[m] = np.array([(c.value, c.low, c.high) for c in intervals])
            counts[m] = len(runs)
    if not curves:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.8))
    for m, curve in curves.items():
        frames = np.arange(len(curve))
        n = counts[m]
        ax.plot(frames, curve[:, 0], label=f"{METHOD_LABELS[m]} (n = {n})", color=COLORS[m])
        ax.fill_between(frames, curve[:, 1], curve[:, 2], color=COLORS[m], alpha=0.2, lw=0)
    ax.set_xlabel("frames since the sequence's first contact")
    ax.set_ylabel("object position error (cm)")
    sizes = sorted(set(counts.values()))
    ax.set_title(
        f"Replay: object position error, mean over the {'/'.join(map(str, sizes))} replayed "
        "sequences per method\n(band: 95 % interval over them; drawn while at least half of "
        "them last)",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, figures_dir / "summary_replay.png")
    plt.close("all")
    caption = (
        "Replay: the object's position error from each sequence's first contact, mean over the "
        "replayed sequences of each method with its 95 % interval"
    )
    return "summary_replay.png", caption


def _read_json(path: str | Path | None) -> dict:
    if path is None or not Path(path).is_file():
        return {}
    return json.loads(Path(path).read_text())


def _provenance_section(
    metrics: dict, frames, data: str, metrics_dir: Path, timing_dir: str | Path | None
) -> list[str]:
    """Where the report was written (commit, machine), on which data, and where the stages
    behind its numbers ran, flagged when they differ (:mod:`dexflow.pipeline.provenance`)."""
    sequences = metrics.get("num_input_sequences", metrics.get("num_sequences"))
    here = provenance.current()
    lines = [
        "## Provenance",
        "",
        "Written by:",
        "",
        *provenance.markdown(here, provenance.data_text(data, sequences, frames)),
        "",
        *_stages_provenance(metrics_dir, timing_dir, here),
        "",
    ]
    return lines


def _stages_provenance(metrics_dir: Path, timing_dir, here: dict) -> list[str]:
    """Where the stages whose metrics the report shows ran: one line when one machine and one
    commit made them all, else a table per stage, with a warning when several machines (or an
    unknown one) made them. Several commits alone are how DVC works (it reruns only the stages
    whose inputs changed), stated without a warning."""
    made = provenance.stages_of(metrics_dir, timing_dir)
    known = {tag: m for tag, m in made.items() if m}
    unknown = sorted(tag for tag, m in made.items() if not m)
    facts = provenance.machine_facts(provenance.read_records(timing_dir))
    machines = sorted({str(m.get("machine_id")) for m in known.values()})
    commits = {(m.get("commit"), m.get("dirty")) for m in known.values()}
    why_unknown = (
        "no `reports/timing` record matches the metrics they hold: restored from git or the DVC "
        "cache, made elsewhere, or run before dexflow recorded it"
    )
    if not made:
        return ["The stages: none found in `reports/metrics`."]
    if not known:
        return [
            f"**The stages: machine and commit not recorded for any of the {len(made)}** "
            f"({why_unknown}); rerun them here (`dvc repro --force`) to know where the numbers "
            "come from."
        ]
    if len(machines) == 1 and len(commits) == 1 and not unknown:
        ((commit, dirty),) = commits
        lines = [
            f"The stages: all {len(made)} ran on machine {machines[0]}, at commit {commit} "
            f"(uncommitted changes: {_yes_no(dirty)})."
        ]
        if machines[0] != here["machine_id"]:
            lines += ["", f"- machine {machines[0]}: {_machine_text(facts, machines[0])}"]
        return lines
    if len(machines) > 1 or unknown:
        head = (
            f"**The stages ran on {len(machines)} machine(s)"
            + (f", and {len(unknown)} did not record where ({why_unknown})" if unknown else "")
            + "**: numbers made on different machines may differ for that reason alone; rerun "
            "them here (`dvc repro --force`) before comparing them."
        )
    else:
        head = (
            f"The stages ran on machine {machines[0]}, at {len(commits)} commits (DVC reruns only "
            "the stages whose inputs changed):"
        )
    lines = [
        head,
        "",
        "| stage | machine | commit | uncommitted changes |",
        "|---|---|---|---|",
    ]
    for tag, m in made.items():
        if m:
            commit = str(m.get("commit") or provenance.UNKNOWN)[:12]
            cells = [str(m.get("machine_id")), commit, _yes_no(m.get("dirty"))]
        else:
            cells = ["not recorded", "—", "—"]
        lines.append(f"| {tag} | " + " | ".join(cells) + " |")
    lines.append("")
    lines += [f"- machine {m}: {_machine_text(facts, m)}" for m in machines]
    return lines


def _machine_text(facts: dict, machine: str) -> str:
    if machine in facts:
        return provenance.describe_machine(facts[machine])
    return "no description recorded"


def _yes_no(flag) -> str:
    return {True: "yes", False: "no"}.get(flag, provenance.UNKNOWN)


# Per-sequence columns of sequences.csv given with their interval: key -> (digits, rate).
SPREAD_COLUMNS = {
    "ssr": (1, True), "ssr_paper": (1, True), "ssr_bench": (1, True), "spd_mm": (2, False),
    "pd_mm": (2, False), "cd_mm": (2, False), "fvr": (3, False), "rms_acc": (2, False),
    "keypoint_error_mm": (2, False), "fingertip_error_mm": (2, False),
    "fingertip_error_surface_mm": (2, False),
}  # fmt: skip
REPLAY_RATES = {
    "success_rate": "replay success %",
    "spider_success_rate": "replay SPIDER %",
    "carried_rate": "replay carried %",
    "lost_rate": "replay lost %",
}


def _spread_rows(table, stage: dict, methods=CORE_METHODS) -> dict[str, tuple[str, dict, int]]:
    """Each rate and mean over sequences with its 95 % interval (:mod:`dexflow.stats`), by key:
    ``(label, {method: Interval or None}, digits)`` for each of ``methods``. The columns of
    ``sequences.csv``, the simulate stage's SSRs that are not in it (without the penetration
    rule, per engine), the replay stage's rates."""
    rows: dict[str, tuple[str, dict[str, stats.Interval | None], int]] = {}
    for key, (digits, rate) in SPREAD_COLUMNS.items():
        if key not in getattr(table, "columns", ()):
            continue
        cells = {}
        for m in methods:
            values = table.loc[table["method"] == m, key].to_numpy(dtype=float)
            found = stats.sequence_interval(values, rate=rate, lower=0.0)  # none is negative
            cells[m] = found if len(values) else None
        rows[key] = (METRICS[key][0], cells, digits)
    simulated = _simulated(stage)
    engines = _engines(stage)
    keys = {"ssr_raw": "SSR every test without the rule %",
            "ssr_paper_raw": "SSR paper protocol without the rule %",
            "ssr_bench_raw": "SSR DexGraspBench without the rule %"}  # fmt: skip
    if len(engines) > 1:
        for engine in engines:
            keys |= {f"ssr_paper_{engine}": f"SSR paper protocol % ({engine})",
                     f"ssr_bench_{engine}": f"SSR DexGraspBench % ({engine})"}  # fmt: skip
    for key, label in keys.items():
        cells = {m: stats.rate_of_sequences(simulated.get(m, {}).get(key),
                                            simulated.get(m, {}).get("num_ok"))
                 for m in methods}  # fmt: skip
        if any(cells.values()):
            rows[key] = (label, cells, 1)
    replayed = {m: stage.get(f"replay_{m}") or {} for m in methods}
    for key, label in REPLAY_RATES.items():
        cells = {m: stats.rate_of_sequences(r.get(key), r.get("num_scored", r.get("num_replayed")))
                 for m, r in replayed.items()}  # fmt: skip
        if any(cells.values()):
            rows[key] = (label, cells, 1)
    return rows


def _spread_section(rows: dict, methods=CORE_METHODS, csv_path: Path | None = None) -> list[str]:
    """:func:`_spread_rows` as a table, a column per method (the bounds, unrounded, to
    ``csv_path``)."""
    if not rows:
        return []
    lines = [
        "## Spread over sequences (95 % intervals)",
        "",
        "- Each cell: value [low, high], the 95 % interval over the sequences: Wilson's for a "
        "rate of sequences, Student's t for a mean (*Definitions*, *Intervals*).",
        "- Pooled values (velocity KL, shares of frames) have no per-sequence value: no interval.",
    ]
    if csv_path is not None:
        lines.append("- " + _csv_link(csv_path))
    lines += [
        "",
        "| | " + " | ".join(methods) + " | sequences | interval |",
        "|---" * (len(methods) + 3) + "|",
    ]
    full = []
    for label, cells, digits in rows.values():
        found = [c for c in cells.values() if c is not None]
        counts = [str(c.n) for c in found]
        n = counts[0] if len(set(counts)) == 1 else ", ".join(counts)
        kinds = ", ".join(sorted({"Wilson" if c.method == "wilson" else "t" for c in found}))
        texts = ["—" if cells.get(m) is None else cells[m].text(digits) for m in methods]
        lines.append(f"| {label} | " + " | ".join(texts) + f" | {n} | {kinds} |")
        for m, c in cells.items():
            if c is not None:
                full.append([label, m, c.value, c.low, c.high, c.n, c.method])
    if csv_path is not None:
        _write_csv(csv_path, ["metric", "method", "value", "low", "high", "n", "interval"], full)
    return [*lines, ""]


def _sequence_counts(metrics: dict) -> str:
    """How many sequences the data held, went through every stage, were dropped."""
    if "num_input_sequences" not in metrics:  # metrics from before the stages counted drops
        return f"{metrics.get('num_sequences', 0)} ({metrics.get('num_failed', 0)} failed)"
    total, dropped = metrics["num_input_sequences"], metrics.get("num_dropped", 0)
    text = f"{total} in the data, {total - dropped} through every stage"
    return text + (f", **{dropped} dropped** (see *Dropped sequences*)" if dropped else "")


def _markdown_cell(text) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _dropped_section(metrics: dict, accounts: dict) -> list[str]:
    """Every sequence a stage dropped, with the stage and the reason; then the warnings."""
    dropped, warnings = accounts.get("dropped", {}), accounts.get("warnings", {})
    lines: list[str] = []
    if dropped or metrics.get("num_dropped"):
        total = metrics.get("num_input_sequences", accounts.get("num_input_sequences", "?"))
        lines += [
            "## Dropped sequences",
            "",
            f"{len(dropped) or metrics.get('num_dropped')} of {total} input sequences are not "
            "(or not wholly) in the tables below: the stage named dropped each for a fault of "
            "its input. Fix the input and run `dvc repro` again.",
            "",
            "| sequence | stage | reason |",
            "|---|---|---|",
            *(f"| {name} | {_markdown_cell(info.get('stage', '?'))} | "
              f"{_markdown_cell(info.get('error', '?'))} |"
              for name, info in sorted(dropped.items())),
            "",
        ]  # fmt: skip
    if warnings:
        lines += [
            "## Warnings",
            "",
            "| sequence | warning |",
            "|---|---|",
            *(f"| {name} | {_markdown_cell(note)} |"
              for name, notes in sorted(warnings.items()) for note in notes),
            "",
        ]  # fmt: skip
    return lines


def _data_caveat(demo: bool, data: str) -> str:
    """What the paper rows can be compared with, on this run's data."""
    if demo:
        return (
            "On the demo data the grasps are synthetic, so only the comparison between rows of "
            "this run is meaningful."
        )
    return (
        f"This run's data is `{data}`, not the paper's DexYCB test split: compare the rows of "
        "this run with each other first, and with the paper's only where the data and the hand "
        "match."
    )


def _method_table(
    metrics: dict, keys, csv_path: Path | None, methods=CORE_METHODS, paper: bool = False
) -> list[str]:
    """``methods`` by metrics (``keys``), with the paper's rows where ``paper``; the Markdown
    shows the first :data:`MAX_COLUMNS` - 1 metrics, ``csv_path`` gets them all."""
    shown = list(keys)[: MAX_COLUMNS - 1]
    rows_csv, rows_md = [], []
    for method in methods:
        label = METHOD_LABELS[method]
        values = [metrics.get(f"{method}.{k}") for k in keys]
        rows_csv.append([label, *values])
        rows_md.append([label] + [cell(v, 3 if k == "fvr" else 2)
                                  for v, k in zip(values[: len(shown)], shown, strict=True)])  # fmt: skip
    if paper:
        for method, label in (("baseline", "paper: DexRetarget"), ("refine", "paper: DexFlow")):
            published = PAPER[method]
            rows_csv.append([label, *(published.get(k) for k in keys)])
            shown_published = (str(published[k]) if k in published else "" for k in shown)
            rows_md.append([f"*{label}*", *shown_published])
    lines = _markdown_table(["method", *(METRICS[k][0] for k in shown)], rows_md)
    if csv_path is not None:
        _write_csv(csv_path, ["method", *(METRICS[k][0] for k in keys)], rows_csv)
        hidden = [METRICS[k][0] for k in keys if k not in shown]
        also = f" Also: {', '.join(hidden)}." if hidden else ""
        lines += ["", "- " + _csv_link(csv_path) + also]
    return lines


def _simulated(stage: dict) -> dict[str, dict]:
    return {m: stage[f"simulate_{m}"] for m in METHOD_LABELS if stage.get(f"simulate_{m}")}


def _engines(stage: dict) -> list[str]:
    """The engines of the simulate stages (``engines``: comma-separated, the first the SSR's)."""
    found = next((s["engines"] for s in _simulated(stage).values() if s.get("engines")), None)
    return found.split(",") if found else ["pybullet"]


def _engines_title(stage: dict) -> str:
    engines = _engines(stage)
    return " and ".join(engines) + (" (SSR: held in both)" if len(engines) > 1 else "")


def _engines_section(stage: dict) -> list[str]:
    """Per engine SSR and the share of frames whose single trial a perturbation overturns;
    with two engines, their per-frame agreement (the paper's criterion)."""
    simulated = _simulated(stage)
    engines = _engines(stage)
    trials = max((s.get("perturbations", 0) for s in simulated.values()), default=0)
    if len(engines) < 2 and not trials:
        return []
    lines = [
        "### Engines and robustness",
        "",
        f"Every tested frame ran in {', '.join(engines)}; a frame succeeds only if it succeeds in "
        f"the nominal trial and in each of {trials} perturbed trials (`simulate.perturbations`: "
        "the object moved and turned a little, the friction scaled). *Flipped*: frames whose "
        "nominal result the perturbations overturn.",
        "",
        "| method | engine | SSR paper protocol % | SSR DexGraspBench % | frames flipped % |",
        "|---|---|---|---|---|",
    ]
    for method, sim in simulated.items():
        for engine in engines:
            cells = [cell(sim.get(f"{k}_{engine}")) for k in ("ssr_paper", "ssr_bench")]
            flipped = sim.get(f"flipped_{engine}")
            cells.append("—" if flipped is None else cell(100 * flipped, 1))
            lines.append(f"| {METHOD_LABELS[method]} | {engine} | " + " | ".join(cells) + " |")
    if len(engines) > 1:
        lines += [
            "",
            f"Per-frame agreement of {engines[0]} and {engines[1]} (the paper's criterion, the "
            "one both engines run with the same protocol):",
            "",
            "| method | frames | both hold | both drop | disagree |",
            "|---|---|---|---|---|",
        ]
        for method, sim in simulated.items():
            counts = [int(sim.get(k, 0)) for k in ("agree_hold", "agree_drop", "disagree")]
            lines.append(
                f"| {METHOD_LABELS[method]} | {sum(counts)} | "
                + " | ".join(map(str, counts))
                + " |"
            )
    return [*lines, ""]


SIMULATION_COLUMNS = (  # (header, value of a simulate summary, digits), the shown ones first
    ("SSR every test %", lambda sim: sim.get("ssr"), 2),
    ("SSR paper protocol %", lambda sim: sim.get("ssr_paper"), 2),
    ("SSR DexGraspBench %", lambda sim: sim.get("ssr_bench"), 2),
    ("frames tested", lambda sim: sim.get("frames_evaluated"), None),
    ("starting penetration mm (mean)", lambda sim: sim.get("penetration_mean_mm"), 2),
    ("lost while the fingers closed %", lambda sim: _scaled(sim.get("lost_closing"), 100), 0),
    ("imbalance (mean)", lambda sim: sim.get("imbalance_mean"), 2),
    ("the two tests agree (% of frames)", lambda sim: _criteria_agreement(sim), 0),
    ("frames over the tolerance %", lambda sim: _scaled(sim.get("over_tolerance"), 100), 0),
    ("on the convex parts: mm (mean)", lambda sim: sim.get("parts_penetration_mean_mm"), 2),
    ("contact imbalance (mean)", lambda sim: sim.get("contact_imbalance_mean"), 2),
)


def _simulation_table(stage: dict, methods=CORE_METHODS, csv_path: Path | None = None) -> list[str]:
    """SSR under both criteria, the frames tested and why frames fail, per method of
    ``methods``, from ``reports/metrics/simulate_<method>.json``; every column (the starting penetration with
    and without the convex parts, the tests' agreement) to ``csv_path``."""
    shown = MAX_COLUMNS - 1
    rows_md, rows_csv = [], []
    for method in methods:
        label = METHOD_LABELS[method]
        sim = stage.get(f"simulate_{method}")
        values = [get(sim) if sim else None for _, get, _ in SIMULATION_COLUMNS]
        rows_csv.append([label, *values])
        rows_md.append([label] + [
            "—" if v is None else str(v) if digits is None else cell(v, digits)
            for v, (_, _, digits) in zip(values[:shown], SIMULATION_COLUMNS[:shown], strict=True)
        ])  # fmt: skip
    lines = _markdown_table(["method", *(h for h, _, _ in SIMULATION_COLUMNS[:shown])], rows_md)
    lines += [
        "",
        "- A frame counts only if the hand starts at most `simulate.penetration_tol_m` inside "
        "the object; *lost while the fingers closed* and *imbalance* say why frames fail "
        "(*Definitions*, *Simulation*).",
    ]
    if csv_path is not None:
        _write_csv(csv_path, ["method", *(h for h, _, _ in SIMULATION_COLUMNS)], rows_csv)
        hidden = ", ".join(h for h, _, _ in SIMULATION_COLUMNS[shown:])
        lines.append("- " + _csv_link(csv_path) + f" Also: {hidden}.")
    return lines


def _criteria_agreement(sim: dict) -> float | None:
    """The share (%) of tested frames on which the paper's test and DexGraspBench's agree."""
    counts = [
        sim.get(k) for k in ("criteria_agree_hold", "criteria_agree_drop", "criteria_disagree")
    ]
    if None in counts or not sum(counts):
        return None
    return 100.0 * (counts[0] + counts[1]) / sum(counts)


def _per_object(table, methods=CORE_METHODS, csv_path: Path | None = None) -> list[str]:
    """Per object: the refined SSR and, for PD, CD and keypoint error, baseline -> refine
    (means over the object's sequences); every method's (``methods``) to ``csv_path``."""
    if not len(table):
        return ["(no sequences)"]
    keys = [k for k in ("ssr", "pd_mm", "cd_mm", "keypoint_error_mm") if k in table.columns]
    grouped = table.groupby(["object", "method"])[keys].mean()
    counts = table[table["method"] == "refine"].groupby("object").size()

    def mean(obj: str, key: str, method: str) -> float:
        return float(grouped[key].get((obj, method), float("nan")))

    short = {k: METRICS[k][0].rsplit(" ", 1)[0] for k in keys}  # without the arrow
    header = ["object", "n"] + [
        f"{short[k]}, refine" if k == "ssr" else f"{short[k]}: baseline -> refine" for k in keys
    ]
    rows_md, rows_csv = [], []
    for obj in sorted(table["object"].unique()):
        cells = []
        for k in keys:
            if k == "ssr":
                cells.append(cell(mean(obj, k, "refine"), 1))
            else:
                cells.append(f"{cell(mean(obj, k, 'baseline'))} -> {cell(mean(obj, k, 'refine'))}")
        rows_md.append([obj, str(int(counts.get(obj, 0))), *cells])
        rows_csv.append([obj, int(counts.get(obj, 0))]
                        + [mean(obj, k, m) for k in keys for m in methods])  # fmt: skip
    lines = _markdown_table(header, rows_md)
    if csv_path is not None:
        _write_csv(csv_path, ["object", "n"] + [f"{METRICS[k][0]} {m}" for k in keys
                                                 for m in methods], rows_csv)  # fmt: skip
        lines += ["", "- " + _csv_link(csv_path) + " Also: every method, DexFlow retargeting's "
                  "included."]  # fmt: skip
    return lines


def _figures(
    metrics: dict,
    table,
    spread: dict,
    plots_dir: Path,
    figures_dir: Path,
    methods=CORE_METHODS,
) -> list[tuple[str, str]]:
    """Each metric per method of ``methods`` (bars: the aggregate; whiskers: its 95 % interval
    where it has one), PD per object (whiskers: the range of its sequences), and one sequence
    over time."""
    import pandas as pd

    plt = pyplot()
    out = []
    keys = [k for k in (*TABLE_II, *TABLE_III) if any(f"{m}.{k}" in metrics for m in methods)]
    columns = (len(keys) + 1) // 2
    n = metrics.get("num_sequences", metrics.get("num_input_sequences"))
    fig, axes = plt.subplots(2, columns, figsize=(3 * columns, 6.4), squeeze=False)
    for ax, key in zip(np.ravel(axes), keys, strict=False):
        values = np.array([metrics.get(f"{m}.{key}", np.nan) for m in methods], float)
        intervals = spread.get(key, (None, {}, 0))[1]
        low = [intervals[m].low if intervals.get(m) else np.nan for m in methods]
        high = [intervals[m].high if intervals.get(m) else np.nan for m in methods]
        has = np.isfinite(low) & np.isfinite(high)
        ax.bar(range(len(methods)), values, color=[COLORS[m] for m in methods])
        if has.any():
            centre = np.array([intervals[m].value if intervals.get(m) else np.nan
                               for m in methods])  # fmt: skip
            ax.errorbar(np.flatnonzero(has), centre[has],
                        yerr=[centre[has] - np.asarray(low)[has], np.asarray(high)[has] - centre[has]],
                        fmt="none", ecolor="k", capsize=3, lw=1)  # fmt: skip
        ax.set_xticks(range(len(methods)), list(methods), fontsize=8)
        suffix = "" if has.any() else "\n(no interval: pooled or not per sequence)"
        ax.set_title(METRICS[key][0] + suffix, fontsize=9)
    for ax in np.ravel(axes)[len(keys) :]:
        ax.axis("off")
    fig.suptitle(f"Every metric per method, n = {n} sequences (whiskers: 95 % interval over them)",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    save_figure(fig, figures_dir / "summary_methods.png")
    out.append(("summary_methods.png", "Every metric per method, with 95 % intervals"))

    if len(table):
        fig, ax = plt.subplots(figsize=(10, 4.4))
        grouped = table.groupby(["object", "method"])["pd_mm"]
        mean, low, high = (grouped.agg(f).unstack("method") for f in ("mean", "min", "max"))
        drawn = [m for m in methods if m in mean.columns]
        objects = list(mean.index)
        width = 0.8 / len(drawn)
        for i, m in enumerate(drawn):
            x = np.arange(len(objects)) + (i - (len(drawn) - 1) / 2) * width
            ax.bar(x, mean[m], width, color=COLORS[m], label=m)
            ax.errorbar(x, mean[m], yerr=[mean[m] - low[m], high[m] - mean[m]], fmt="none",
                        ecolor="k", capsize=2, lw=0.8)  # fmt: skip
        counts = table[table["method"] == drawn[-1]].groupby("object").size()
        ax.set_xticks(range(len(objects)),
                      [f"{o} (n = {counts.get(o, 0)})" for o in objects], rotation=45,
                      ha="right", fontsize=8)  # fmt: skip
        ax.set_ylabel("penetration depth (mm)")
        ax.set_title("Penetration depth per object and method: mean over the object's sequences "
                     "(whiskers: their range)", fontsize=9)  # fmt: skip
        ax.legend(fontsize=8)
        fig.tight_layout()
        save_figure(fig, figures_dir / "summary_objects_pd.png")
        out.append(("summary_objects_pd.png", "Penetration depth per object and method"))

    error, pen = plots_dir / "keypoint_error.csv", plots_dir / "penetration.csv"
    if error.is_file() and pen.is_file():
        error, pen = pd.read_csv(error), pd.read_csv(pen)
        example = sorted(error["sequence"].unique())[0]
        fig, axes = plt.subplots(2, 1, figsize=(8, 5.2), sharex=True)
        for ax, frame, label in ((axes[0], error, "keypoint error (mm)"),
                                 (axes[1], pen, "penetration (mm)")):  # fmt: skip
            rows = frame[frame["sequence"] == example]
            for m in (m for m in methods if m in rows.columns):
                ax.plot(rows["time_s"], rows[m], label=m, color=COLORS[m])
            ax.set_ylabel(label)
        axes[0].legend(fontsize=8)
        axes[0].set_title(f"One sequence (n = 1, not a mean): {example}, per frame", fontsize=9)
        axes[1].set_xlabel("time (s)")
        fig.tight_layout()
        save_figure(fig, figures_dir / "summary_timeline.png")
        out.append(("summary_timeline.png", f"Keypoint error and penetration over {example}"))
    plt.close("all")
    return out


def write_hand_figure(
    params: PipelineParams, layout: Layout, figures_dir: Path, frames: int = 4
) -> tuple[str, str] | None:
    """The robot hand of the refined trajectory on the object at ``frames`` frames of the
    first sequence (by name; the one *summary_timeline.png* shows), to
    ``figures_dir/summary_hand.png``.

    The hand's collision meshes are posed by forward kinematics at the refined ``q``
    (``data/refine``), the hand loaded from stage hand's copy (``data/hand``); the object mesh
    of the scaled scene (``data/scale_align``) at its recorded pose. The frames: the replay's
    start, first contact, middle of the grasp and last contact (``data/replay/refine``), else
    evenly spaced over the sequence.

    Returns:
        ``(file name, caption)``; None when no sequence was refined.
    """
    from dexflow import plots
    from dexflow.geometry import transform_points
    from dexflow.io.artifacts import read_trajectory
    from dexflow.io.sequence import load_sequence
    from dexflow.objects.mesh import load_mesh
    from dexflow.pipeline.labelled import labelled_hand

    names = sorted(layout.refine.names())
    if not names:
        return None
    name = names[0]
    hand = labelled_hand(params, layout)
    aligned = layout.scale_align
    seq = load_sequence(aligned.sequence(name), data_root=aligned.root)
    q = read_trajectory(layout.refine.sequence(name), hand.joint_names, seq.num_frames).q
    entry = _read_json(layout.replay("refine").summary).get("sequences", {}).get(name, {})
    chosen = _hand_frames(entry, seq.num_frames, frames)
    mesh = load_mesh(aligned.root / seq.obj_mesh)
    picked = np.array([f for f, _ in chosen])
    objects = [transform_points(seq.obj_pose[f], mesh.vertices) for f in picked]
    fingers = hand.keypoints(q[picked]).detach().cpu().numpy()  # (K, N, 3)
    # looking across the hand's approach (object to fingers, horizontal), from above
    approach = (fingers.mean(axis=1) - np.mean(objects, axis=1)).mean(axis=0)
    azim = float(np.degrees(np.arctan2(approach[1], approach[0]))) - 90.0
    plots.plot_hand_on_object(
        plots.posed_hand_triangles(hand, q[picked]),
        [v[mesh.faces] for v in objects],
        [np.concatenate([v, f]) for v, f in zip(objects, fingers, strict=True)],
        [f"frame {f}: {why}" for f, why in chosen],
        figures_dir / HAND_FIGURE,
        f"{hand.spec.name} hand, refined trajectory, on {seq.obj_name}: "
        f"{name} (n = 1 sequence, {len(picked)} frames)",
        elev=25.0,
        azim=round(azim, 1),
    )
    caption = (
        f"The robot hand ({hand.spec.name}, its collision meshes posed by forward kinematics at "
        f"the refined q) on the object at its recorded pose, sequence {name}, frames "
        + ", ".join(f"{f} ({why})" for f, why in chosen)
    )
    return HAND_FIGURE, caption


def _hand_frames(entry: dict, num_frames: int, count: int) -> list[tuple[int, str]]:
    """``count`` frames to draw with what each shows: the replay's start, first contact, middle
    of the grasp and last contact where the replay recorded them, else evenly spaced."""
    first, last = entry.get("first_contact", -1), entry.get("last_contact", -1)
    if count == 4 and 0 <= first <= last < num_frames:
        start = min(max(0, entry.get("start", first)), first)
        found = {start: "approach", first: "human first touches", (first + last) // 2: "mid-grasp",
                 last: "human last touches"}  # fmt: skip
        if len(found) == 4:
            return sorted(found.items())
    spaced = np.linspace(0, num_frames - 1, count).round().astype(int)
    return [
        (int(f), f"{i + 1} of {count}, evenly spaced") for i, f in enumerate(dict.fromkeys(spaced))
    ]


def _definitions(stage: dict, limits: dict | None, methods=CORE_METHODS) -> list[str]:
    """What every column means, as bullets under the section they belong to (tracking's only
    with track among ``methods``)."""
    spider = (
        f" ({100 * limits['position_m']:.0f} cm, {limits['rotation_rad']:g} rad in this run)"
        if limits
        else ""
    )
    lines = [
        "## Definitions",
        "",
        "### Grasp quality",
        "",
        "- *Paper rows*: DexFlow on DexYCB with ShadowHand, as published, only beside the numbers "
        "computed with the paper's definitions: SSR by its gravity protocol, PD, SPD and CD as "
        "BODex defines them (CD: every finger, capped at 1 cm).",
        "- The paper does not state the units of PD, SPD and CD: they are shown as printed, "
        "dexflow's in mm.",
        "- *SSR every test*, the headline: a sequence counts only where one frame passes both "
        "tests (the paper's and DexGraspBench's) in every engine run: the conservative SSR.",
        "- *CD in contact* and the *violation rate* are dexflow's own measures.",
        "- Not comparable, so not shown: " + PAPER_NOT_COMPARABLE + ".",
        "",
        "### Intervals",
        "",
        "- value [low, high]: the 95 % interval over the sequences (`dexflow/stats.py`): "
        "Wilson's score interval for a rate of sequences (each sequence held or not), "
        "Student's t for a mean over sequences.",
        "- The values are means over the per-sequence rows of `data/metrics/sequences.csv` (the "
        "tables' aggregates, but for a pooled or maximal one) and the simulate and replay "
        "stages' rates over the sequences they counted.",
        "- Velocity KL pools the speeds of all sequences, and the shares of frames in "
        "*Simulation* pool frames: they have no per-sequence value here, so no interval.",
        "- Sequences are treated as independent; those of one object are not fully so, which "
        "makes the intervals, if anything, too narrow.",
        "",
        "### Simulation",
        "",
        "- Each tested frame closes the fingers once and runs two independent tests from that "
        "grasp: *the paper's* (the object's weight along each of six axis directions for 100 "
        "control steps; held if the object still touches the hand at the end of each) and "
        "*DexGraspBench's* (a push of about the object's weight along each direction; held if "
        "it moves less than 5 cm and turns less than 15°).",
        "- *The two tests agree*: the share of tested frames both hold or both drop, the check "
        "that neither SSR is an artefact of its protocol.",
        "- A tested frame counts only if it starts with the hand at most "
        "`simulate.penetration_tol_m` inside the object (links wedged inside an object hold it "
        "without a grasp).",
        "- The SSRs without that rule are measured only with `simulate.test_over_tolerance: "
        "true` (by default the frames over the tolerance, which cannot count, are not tested: "
        "their deep overlaps are the engine's slowest steps).",
        "- *Starting penetration*: the deepest point of the hand's collision geometry (every "
        "shape, forearm and palm included) inside the object's mesh (signed distance, the "
        "definition of PD).",
        "- *On the convex parts*: the overlap with the convex parts the physics uses (which "
        "bulge beyond a scanned mesh by millimetres).",
        "- *Lost while the fingers closed*: the tested frames whose object moved or turned past "
        "the DexGraspBench thresholds before any push (MuJoCo; pybullet holds it then).",
        "- *Imbalance*: how one-sided the pushes into the object are, 0 when they cancel, 1 "
        "when all press the same way.",
        "- *Contact imbalance*: the same measure of the contacts stage contact found at those "
        "frames (the fingers the grasp was retargeted and refined towards, where the human "
        "touched): near 1, those contacts are one-sided and copying them cannot enclose the "
        "object (`dexflow/sim/protocol.py`).",
        "",
        "### Replay",
        "",
        "- The trajectory played back in MuJoCo from `replay.lead_frames` before the first "
        "contact to the release (the recorded object leaves the recorded hand: "
        "`replay.release_distance_m`) or else the last contact: base along q through "
        "force-limited servos, fingers by position control, the object free under gravity on "
        "a table (`dexflow/stages/replay.py`).",
        "- Only the part where the human holds the object is scored.",
        "- *Not scored*: sequences the replay cannot reproduce, left out of every rate and "
        "error (*no support*: the recorded object is not resting before the grasp; *free "
        "fall*: it falls freely while it would be scored; *no contact*).",
        "- *SPIDER*: mean object error below `replay.max_position_error_m` and "
        f"`replay.max_rotation_error_rad`{spider}.",
        "- *Carried*: final position error below `replay.max_position_error_m` and below "
        "`replay.carried_fraction` of the recorded object's net displacement (where an object "
        "left behind ends).",
        "- *Success*: both. Errors are means over the grasp.",
        "- *Held*: the share of the grasp before the object is first `replay.lost_position_m` "
        "or `lost_rotation_rad` off its recorded pose (*lost*).",
        "- *Left behind*: the mean error of an object that never moves; where it is below the "
        "threshold, SPIDER's criterion alone does not tell carrying from leaving the object "
        "where it was.",
        "- *Rigid ceiling*: the success an object welded to the hand's base from the recorded "
        "lift would have (no physics): no grip does better along that base path.",
        "- *Unstable rest*: the share of sequences whose object, left alone on the replay's "
        "table at its recorded pose, is *lost* before the recorded lift (it rests on an edge: "
        "the annotation or the table's frame is tilted, or its rotations are misread).",
        *(
            [
                f"- *{METHOD_LABELS['track']}*: stage track's trajectories, searched in the "
                "replay's own scene for the position targets under which the object follows its "
                "recorded path (`dexflow/stages/track.py`); the replay replays their targets. "
                "*Feasible*: a tracked trajectory whose replay succeeds, as a share of the "
                "tracked sequences (those the replay scores).",
            ]
            if "track" in methods
            else []
        ),
        "",
        "### Motion quality",
        "",
        "- *Fingertip error vs surface tips*: against the human fingertips pushed out to the "
        "object's surface where they lie inside it (annotation error puts them millimetres "
        "inside on real captures, so a hand that does not penetrate cannot reach them); the "
        "raw error beside it.",
        "- *Keypoint Chamfer* (in `metrics.json`, not shown) equals the keypoint error "
        "wherever no keypoint is nearer another's human keypoint than its own.",
    ]
    note = stage.get("contact", {}).get("inference_note")
    if note:
        lines += ["", "### Contact inference", "", f"- {note}"]
    return [*lines, ""]


def run_report(params: PipelineParams, layout: Layout) -> dict:
    """Stage runner: :func:`write_project_summary` for the data ``params.data`` names."""
    out = write_project_summary(layout, data_name=params.data.name, params=params)
    return {"stage": "report", "summary": str(out)}


STAGE = StageSpec(
    name="report",
    run=run_report,
    metric_keys=(),  # a report, not a measurement
    describe=lambda s: f"wrote {s['summary']}",
)
