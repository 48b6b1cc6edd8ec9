"""Stage report: the paper-style summary of one pipeline run, generated from its metrics.

- :func:`write_summary` -> ``reports/summary.md`` (+ PNG figures): the paper's Table II/III layout
  (baseline vs DexFlow vs DexFlow + refinement) beside the published numbers, each rate and mean
  over sequences with its 95 % interval (:mod:`dexflow.stats`), contact quality, and a
  per-object breakdown.

The comparison of experiments (``reports/sweep.md``) is :mod:`dexflow.tools.experiments`.

It opens with their provenance (:mod:`dexflow.pipeline.provenance`): the commit and machine they were
written on, the data, and the machine(s) the numbers were made on.

**One file** (about 820 lines): the summary is one document: each section is a function of its own, in the
order the summary shows them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from dexflow import stats
from dexflow.io.layout import Layout
from dexflow.params import PipelineParams
from dexflow.pipeline import provenance
from dexflow.pipeline.runner import StageSpec

__all__ = [
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
}
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
TABLE_II = ("ssr", "ssr_paper", "ssr_bench", "spd_mm", "pd_mm", "cd_mm", "cd_contact_mm", "fvr")
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
    layout: Layout, data_name: str | None = None, out_md: str | Path | None = None
) -> Path:
    """:func:`write_summary` on a project's files (``layout``): what the ``report`` stage and
    ``dexflow report summary`` write (``out_md`` defaults to ``reports/summary.md``)."""
    return write_summary(
        layout.stage_metrics_dir, layout.metrics_table, layout.plots,
        out_md or layout.summary_report, layout.figures, data_name=data_name,
        stage_summary=layout.metrics.summary,
        replay_dirs={m: layout.replay(m).root for m in METHOD_LABELS},
        timing_dir=layout.reports / "timing",
    )  # fmt: skip


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
) -> Path:
    """Write ``summary.md`` and its figures from the metrics stage's outputs.

    The report opens with its provenance (:mod:`dexflow.pipeline.provenance`): the commit and machine
    it is written on, the data, and the machines and commits the stages behind its numbers ran
    on (they may have run earlier, elsewhere: DVC restores outputs from its cache), flagged
    when they differ. Rates and means over sequences are given with their 95 % intervals
    (:mod:`dexflow.stats`) in *Spread over sequences*. Same inputs, machine and commit: the same
    bytes.

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
    lines = [
        "# dexflow summary",
        "",
        "Generated by the `report` stage from `reports/metrics/` and `data/metrics/`; do not edit.",
        f"Data: **{data}**. Hand: **{hand}**. Sequences: {_sequence_counts(metrics)}. "
        "Definitions: README, *Metrics*.",
        "",
        *_provenance_section(metrics, table, data, metrics_dir, timing_dir),
        *_dropped_section(metrics, accounts),
        "## Grasp quality (paper Table II layout)",
        "",
        *_method_table(metrics, TABLE_II, paper=True),
        "",
        "Paper rows: DexFlow on DexYCB with ShadowHand, as published, only beside the numbers "
        "computed with the paper's definitions: SSR by its gravity protocol, PD, SPD and CD as "
        "BODex defines them (CD: every finger, capped at 1 cm). The paper does not state the "
        "units of PD, SPD and CD: they are shown as printed, dexflow's in mm. *SSR every test*, "
        "the headline, counts a sequence only where one frame passes both tests (the paper's "
        "and DexGraspBench's) in every engine run: the conservative SSR. *CD in contact* and "
        "the *violation rate* are dexflow's own measures. Not comparable, so not shown: "
        + PAPER_NOT_COMPARABLE
        + ". "
        + _data_caveat(demo, data)
        + " The 95 % interval of each value: *Spread over sequences*.",
        "",
        *_spread_section(table, stage),
        f"## Simulation ({_engines_title(stage)}: the paper's gravity test and DexGraspBench's "
        "push, six directions each)",
        "",
        *_simulation_table(stage),
        "",
        *_engines_section(stage),
        "Each tested frame closes the fingers once and runs two independent tests from that "
        "grasp: *the paper's* (the object's weight along each of six axis directions for 100 "
        "control steps; held if the object still touches the hand at the end of each) and "
        "*DexGraspBench's* (a push of about the object's weight along each direction; held if "
        "it moves less than 5 cm and turns less than 15°). *The two tests agree*: the share of "
        "tested frames both hold or both drop, the check that neither SSR is an artefact of "
        "its protocol. A tested frame counts only if it starts with the hand at most "
        "`simulate.penetration_tol_m` inside the object (links wedged inside an object hold it "
        "without a grasp); the SSRs without that rule are measured only with "
        "`simulate.test_over_tolerance: true` (by default the frames over the tolerance, which "
        "cannot count, are not tested: their deep overlaps are the engine's slowest steps). "
        "Starting penetration is the deepest point of the hand's collision geometry (every "
        "shape, forearm and palm included) inside the object's mesh (signed distance, the "
        "definition of PD); the overlap with the convex parts the physics uses "
        "(which bulge beyond a scanned mesh by millimetres) is shown beside it. Why frames "
        "fail: *lost while the fingers closed* counts the tested frames whose object moved or "
        "turned past the DexGraspBench thresholds before any push (MuJoCo; pybullet holds it "
        "then), and *imbalance* is how one-sided the pushes into the object are, 0 when they "
        "cancel, 1 when all press the same way; *contact imbalance* is the same measure of the "
        "contacts stage contact found at those frames (the fingers the grasp was retargeted and "
        "refined towards, where the human touched): near 1, those contacts are one-sided and "
        "copying them cannot enclose the object (`dexflow/sim/protocol.py`).",
        "",
        *_replay_section(stage, replay_dirs or {}, figures_dir, rel),
        "## Motion quality (paper Table III layout)",
        "",
        *_method_table(metrics, TABLE_III, paper=False),
        "",
        "*Fingertip error vs surface tips*: against the human fingertips pushed out to the "
        "object's surface where they lie inside it (annotation error puts them millimetres "
        "inside on real captures, so a hand that does not penetrate cannot reach them); the "
        "raw error beside it. The paper's Table III numbers are not comparable (above). "
        "*Keypoint Chamfer* (in `metrics.json`, not shown) equals the keypoint error wherever "
        "no keypoint is nearer another's human keypoint than its own.",
        "",
        "## Contact detection",
        "",
        *_contact_rows(stage.get("contact", {}), metrics),
    ]
    note = stage.get("contact", {}).get("inference_note")
    lines += ["", note] if note else []
    lines += ["", "## Per object", ""]
    lines += _per_object(table)
    lines += ["", "## Figures", ""]
    for name, caption in _figures(metrics, table, Path(plots_dir), figures_dir):
        lines += [f"![{caption}]({rel / name})", ""]
    from dexflow.io.atomic import atomic_path

    with atomic_path(out_md) as tmp:
        tmp.write_text("\n".join(lines).rstrip() + "\n")
    return out_md


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


def _replay_section(stage: dict, dirs: dict, figures_dir: Path, rel: Path) -> list[str]:
    """Stage replay per method (its metrics), and the object's position error over time."""
    found = {m: stage[f"replay_{m}"] for m in METHOD_LABELS if stage.get(f"replay_{m}")}
    if not found:
        return []
    lines = [
        "## Replay (object free under gravity: SPIDER's success and carried)",
        "",
        "| | scored | not scored | success (%) | SPIDER (%) | carried (%) | position error (cm) | "
        "rotation error (rad) | held (% of grasp) | lost (%) | left behind (cm) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m, r in found.items():
        cells = [
            str(r.get("num_scored", r.get("num_replayed", 0))), _not_scored(r),
            cell(r.get("success_rate"), 1),
            cell(r.get("spider_success_rate"), 1), cell(r.get("carried_rate"), 1),
            cell(100 * r.get("position_error_mean_m", math.nan), 1),
            cell(r.get("rotation_error_mean_rad")), cell(100 * r.get("held_fraction", math.nan), 0),
            cell(r.get("lost_rate"), 0), cell(100 * r.get("static_error_mean_m", math.nan), 1),
        ]  # fmt: skip
        lines.append(f"| {METHOD_LABELS[m]} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "The trajectory played back in MuJoCo from `replay.lead_frames` before the first contact "
        "to the release (the recorded object leaves the recorded hand: `replay."
        "release_distance_m`) or else the last contact: base along q through force-limited "
        "servos, fingers by position control, the object free under gravity on a table "
        "(`dexflow/stages/replay.py`). Only the part where the human holds the object is scored. "
        "*Not scored*: sequences the replay cannot reproduce, left out of every rate and error "
        "(*no support*: the recorded object is not resting before the grasp; *free fall*: it "
        "falls freely while it would be scored; *no contact*). *SPIDER*: mean object error "
        "below `replay.max_position_error_m` and `replay.max_rotation_error_rad` (10 cm, "
        "0.5 rad). *Carried*: final position error below `replay.max_position_error_m` and "
        "below `replay.carried_fraction` of the recorded object's net displacement (where an "
        "object left behind ends). *Success*: both. Errors are means over the grasp. "
        "*Held*: the share of the grasp before the "
        "object is first `replay.lost_position_m` or `lost_rotation_rad` off its recorded pose "
        "(*lost*). *Left behind*: the "
        "mean error of an object that never moves; where it is below the threshold, SPIDER's "
        "criterion alone does not tell carrying from leaving the object where it was.",
        "",
    ]
    figure = _replay_figure(dirs, figures_dir)
    if figure:
        lines += [f"![Object position error over time, per method]({rel / figure})", ""]
    return lines


def _not_scored(replay: dict) -> str:
    """The replay's not-scored count with its reasons, e.g. ``2 (1 no support, 1 free fall)``."""
    total = int(replay.get("num_not_scored", 0))
    reasons = [(int(replay.get(f"num_not_scored_{k}", 0)), k.replace("_", " "))
               for k in ("no_contact", "no_support", "free_fall")]  # fmt: skip
    named = ", ".join(f"{n} {why}" for n, why in reasons if n)
    return f"{total} ({named})" if named else str(total)


def _replay_figure(dirs: dict, figures_dir: Path) -> str | None:
    """Mean (over sequences) object position error against time since the first contact."""
    from dexflow.io.artifacts import read_replay

    curves = {}
    for m, root in dirs.items():
        summary = _read_json(Path(root) / "summary.json")
        runs = []
        for name, entry in sorted(summary.get("sequences", {}).items()):
            if entry.get("status") != "ok" or not entry.get("replayed"):
                continue
            rows = read_replay(Path(root) / "sequences" / f"{name}.npz").rows
            runs.append(rows["position_error_m"][rows["frame"] >= entry["first_contact"]])
        if runs:
            longest = max(len(r) for r in runs)
            padded = np.full((len(runs), longest), np.nan)
            for i, r in enumerate(runs):
                padded[i, : len(r)] = r
            curves[m] = np.nanmean(padded, axis=0)
    if not curves:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.5))
    colors = dict(zip(METHOD_LABELS, ["#999999", "#4c72b0", "#55a868"], strict=True))
    for m, curve in curves.items():
        ax.plot(np.arange(len(curve)), 100 * curve, label=METHOD_LABELS[m], color=colors[m])
    ax.set_xlabel("frames since the first contact")
    ax.set_ylabel("object position error (cm)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, figures_dir / "summary_replay.png")
    plt.close("all")
    return "summary_replay.png"


def _read_json(path: str | Path | None) -> dict:
    if path is None or not Path(path).is_file():
        return {}
    return json.loads(Path(path).read_text())


def _provenance_section(
    metrics: dict, table, data: str, metrics_dir: Path, timing_dir: str | Path | None
) -> list[str]:
    """Where the report was written (commit, machine), on which data, and where the stages
    behind its numbers ran, flagged when they differ (:mod:`dexflow.pipeline.provenance`)."""
    frames = metrics.get("num_frames")
    if frames is None and len(table) and "frames" in table.columns:
        frames = int(table[table["method"] == table["method"].iloc[0]]["frames"].sum())
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


def _spread_section(table, stage: dict) -> list[str]:
    """Each rate and mean over sequences with its 95 % interval (:mod:`dexflow.stats`): the
    columns of ``sequences.csv``, the simulate stage's SSRs that are not in it (without the
    penetration rule, per engine), the replay stage's rates."""
    rows: list[tuple[str, dict[str, stats.Interval | None], int]] = []
    for key, (digits, rate) in SPREAD_COLUMNS.items():
        if key not in getattr(table, "columns", ()):
            continue
        cells = {}
        for m in METHOD_LABELS:
            values = table.loc[table["method"] == m, key].to_numpy(dtype=float)
            found = stats.sequence_interval(values, rate=rate, lower=0.0)  # none is negative
            cells[m] = found if len(values) else None
        rows.append((METRICS[key][0], cells, digits))
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
                 for m in METHOD_LABELS}  # fmt: skip
        if any(cells.values()):
            rows.append((label, cells, 1))
    replayed = {m: stage.get(f"replay_{m}") or {} for m in METHOD_LABELS}
    for key, label in REPLAY_RATES.items():
        cells = {m: stats.rate_of_sequences(r.get(key), r.get("num_scored", r.get("num_replayed")))
                 for m, r in replayed.items()}  # fmt: skip
        if any(cells.values()):
            rows.append((label, cells, 1))
    if not rows:
        return []
    lines = [
        "## Spread over sequences (95 % intervals)",
        "",
        "Each cell: value [low, high], the 95 % interval over the sequences (`dexflow/stats.py`): "
        "Wilson's score interval for a rate of sequences (each sequence held or not), Student's "
        "t for a mean over sequences. The values are means over the per-sequence rows of "
        "`data/metrics/sequences.csv` (the tables' aggregates, but for a pooled or maximal one) "
        "and the simulate and replay stages' rates over the sequences they counted. Velocity KL "
        "pools the speeds of all sequences, and the shares of frames in *Simulation* pool "
        "frames: they have no per-sequence value here, so no interval.",
        "",
        "| | " + " | ".join(METHOD_LABELS) + " | sequences | interval |",
        "|---" * (len(METHOD_LABELS) + 3) + "|",
    ]
    for label, cells, digits in rows:
        found = [c for c in cells.values() if c is not None]
        counts = [str(c.n) for c in found]
        n = counts[0] if len(set(counts)) == 1 else ", ".join(counts)
        kinds = ", ".join(sorted({"Wilson" if c.method == "wilson" else "t" for c in found}))
        texts = ["—" if c is None else c.text(digits) for c in cells.values()]
        lines.append(f"| {label} | " + " | ".join(texts) + f" | {n} | {kinds} |")
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


def _method_table(metrics: dict, keys, paper: bool) -> list[str]:
    head = "| method | " + " | ".join(METRICS[k][0] for k in keys) + " |"
    lines = [head, "|---" * (len(keys) + 1) + "|"]
    for method, label in METHOD_LABELS.items():
        cells = [cell(metrics.get(f"{method}.{k}"), 3 if k == "fvr" else 2) for k in keys]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if paper:
        for method, label in (("baseline", "paper: DexRetarget"), ("refine", "paper: DexFlow")):
            published = PAPER[method]
            cells = []
            for k in keys:
                cells.append(str(published[k]) if k in published else "")
            lines.append(f"| *{label}* | " + " | ".join(cells) + " |")
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


def _simulation_table(stage: dict) -> list[str]:
    """SSR under both criteria, with and without the penetration rule, and the starting
    penetration of the tested frames, from ``reports/metrics/simulate_<method>.json``."""
    lines = [
        "| method | SSR every test % | SSR paper protocol % | SSR DexGraspBench % | the two "
        "tests agree (% of frames) | frames tested | starting penetration mm (mean) | frames "
        "over the tolerance % | on the convex parts: mm (mean) | lost while the fingers closed % "
        "| imbalance (mean) | contact imbalance (mean) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for method, label in METHOD_LABELS.items():
        sim = stage.get(f"simulate_{method}")
        if not sim:
            lines.append(f"| {label} |" + " — |" * 11)
            continue
        cells = [cell(sim.get(k)) for k in ("ssr", "ssr_paper", "ssr_bench")]
        cells.append(cell(_criteria_agreement(sim), 0))
        cells += [str(sim.get("frames_evaluated", "—")), cell(sim.get("penetration_mean_mm"))]
        cells.append(cell(100 * sim["over_tolerance"], 0) if "over_tolerance" in sim else "—")
        cells.append(cell(sim.get("parts_penetration_mean_mm")))
        lost = sim.get("lost_closing")
        cells.append("—" if lost is None else cell(100 * lost, 0))
        cells.append(cell(sim.get("imbalance_mean")))
        cells.append(cell(sim.get("contact_imbalance_mean")))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def _criteria_agreement(sim: dict) -> float | None:
    """The share (%) of tested frames on which the paper's test and DexGraspBench's agree."""
    counts = [
        sim.get(k) for k in ("criteria_agree_hold", "criteria_agree_drop", "criteria_disagree")
    ]
    if None in counts or not sum(counts):
        return None
    return 100.0 * (counts[0] + counts[1]) / sum(counts)


def _per_object(table) -> list[str]:
    if not len(table):
        return ["(no sequences)"]
    keys = ("ssr", "pd_mm", "cd_mm", "keypoint_error_mm")
    grouped = table.groupby(["object", "method"])[list(keys)].mean()
    head = "| object | n | " + " | ".join(
        f"{METRICS[k][0].split(' ')[0]} {m}" for k in keys for m in METHOD_LABELS
    )
    lines = [head + " |", "|---" * (2 + len(keys) * len(METHOD_LABELS)) + "|"]
    counts = table[table["method"] == "refine"].groupby("object").size()
    for obj in sorted(table["object"].unique()):
        cells = []
        for k in keys:
            for m in METHOD_LABELS:
                value = grouped[k].get((obj, m), float("nan"))
                cells.append(cell(float(value), 1 if k == "ssr" else 2))
        lines.append(f"| {obj} | {int(counts.get(obj, 0))} | " + " | ".join(cells) + " |")
    return lines


def _figures(metrics: dict, table, plots_dir: Path, figures_dir: Path) -> list[tuple[str, str]]:
    import pandas as pd

    plt = pyplot()
    out = []
    keys = [k for k in (*TABLE_II, *TABLE_III) if any(f"{m}.{k}" in metrics for m in METHOD_LABELS)]
    fig, axes = plt.subplots(2, (len(keys) + 1) // 2, figsize=(3 * ((len(keys) + 1) // 2), 6))
    for ax, key in zip(np.ravel(axes), keys, strict=False):
        values = [metrics.get(f"{m}.{key}", np.nan) for m in METHOD_LABELS]
        ax.bar(range(3), values, color=["#999999", "#4c72b0", "#55a868"])
        ax.set_xticks(range(3), ["baseline", "retarget", "refine"], fontsize=8)
        ax.set_title(METRICS[key][0], fontsize=9)
    for ax in np.ravel(axes)[len(keys) :]:
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, figures_dir / "summary_methods.png")
    out.append(("summary_methods.png", "Every metric per method"))

    if len(table):
        fig, ax = plt.subplots(figsize=(10, 4))
        pivot = table.pivot_table(index="object", columns="method", values="pd_mm")
        pivot = pivot[[m for m in METHOD_LABELS if m in pivot.columns]]
        pivot.plot.bar(ax=ax, color=["#999999", "#4c72b0", "#55a868"], rot=45, fontsize=8)
        ax.set_ylabel("penetration depth (mm)")
        fig.tight_layout()
        save_figure(fig, figures_dir / "summary_objects_pd.png")
        out.append(("summary_objects_pd.png", "Penetration depth per object and method"))

    error, pen = plots_dir / "keypoint_error.csv", plots_dir / "penetration.csv"
    if error.is_file() and pen.is_file():
        error, pen = pd.read_csv(error), pd.read_csv(pen)
        example = sorted(error["sequence"].unique())[0]
        fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
        for ax, frame, label in ((axes[0], error, "keypoint error (mm)"),
                                 (axes[1], pen, "penetration (mm)")):  # fmt: skip
            rows = frame[frame["sequence"] == example]
            for m, color in zip(METHOD_LABELS, ["#999999", "#4c72b0", "#55a868"], strict=True):
                ax.plot(rows["time_s"], rows[m], label=m, color=color)
            ax.set_ylabel(label)
        axes[0].legend(fontsize=8)
        axes[1].set_xlabel(f"time (s), sequence {example}")
        fig.tight_layout()
        save_figure(fig, figures_dir / "summary_timeline.png")
        out.append(("summary_timeline.png", f"Keypoint error and penetration over {example}"))
    plt.close("all")
    return out


def run_report(params: PipelineParams, layout: Layout) -> dict:
    """Stage runner: :func:`write_project_summary` for the data ``params.data`` names."""
    out = write_project_summary(layout, data_name=params.data.name)
    return {"stage": "report", "summary": str(out)}


STAGE = StageSpec(
    name="report",
    run=run_report,
    metric_keys=(),  # a report, not a measurement
    describe=lambda s: f"wrote {s['summary']}",
)
