"""``dexflow bench real``: the pipeline on a subset of real captures, with the refined motion and
the grasp-test breakdown that explain its numbers."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from dexflow.io.layout import Layout, StageDir
from dexflow.params import SimulateParams
from dexflow.tools.bench.pipeline import machine_line, pipeline_stages, publish, subset_root
from dexflow.tools.tip_motion import NEAR_M

REAL_COLUMNS = (
    ("fingertip_error_mm", "fingertip error mm", "{:.1f}"),
    ("fingertip_error_surface_mm", "vs surface tips mm", "{:.1f}"),
    ("rms_acc", "RMS acc rad/s²", "{:.2f}"),
    ("pd_mm", "PD mean mm", "{:.2f}"),
    ("pd_max_mm", "PD max mm", "{:.1f}"),
    ("pd_own_object_mm", "PD own object mm", "{:.2f}"),
    ("cd_mm", "CD mm", "{:.2f}"),
    ("ssr", "SSR %", "{:.1f}"),
    ("ssr_paper", "SSR paper %", "{:.1f}"),
    ("ssr_bench", "SSR bench %", "{:.1f}"),
)


def _real_engines(results: dict[str, dict]) -> list[str]:
    """Per hand, method and engine the SSRs and the frames perturbations overturn, the per-frame
    agreement of the paper's test and DexGraspBench's, and with two engines theirs (empty
    with one engine and no perturbations)."""
    sims = [(h, m, s) for h, r in results.items() for m, s in r.get("simulate", {}).items()]
    engines = sorted({e for *_, s in sims for e in str(s.get("engines", "")).split(",") if e})
    if not sims or (len(engines) < 2 and not any(s.get("perturbations") for *_, s in sims)):
        return []
    lines = [
        "| hand | method | engine | SSR paper % | SSR bench % | frames flipped by perturbations % |",
        "|---|---|---|---|---|---|",
    ]
    for hand, method, sim in sims:
        for engine in str(sim.get("engines", "")).split(","):
            cells = [sim.get(f"{k}_{engine}", float("nan")) for k in ("ssr_paper", "ssr_bench")]
            cells.append(100 * sim.get(f"flipped_{engine}", float("nan")))
            text = " | ".join(f"{c:.1f}" for c in cells)
            lines.append(f"| {hand} | {method} | {engine} | {text} |")
    pairs = [("criteria_", f"the paper's test and DexGraspBench's ({engines[0]})")]
    if len(engines) > 1:
        pairs.append(("", f"{engines[0]} and {engines[1]} (the paper's test)"))
    for prefix, what in pairs:
        lines += ["", f"Per-frame agreement of {what}:", "",
                  "| hand | method | frames | both hold | both drop | disagree |",
                  "|---|---|---|---|---|---|"]  # fmt: skip
        for hand, method, sim in sims:
            keys = (f"{prefix}agree_hold", f"{prefix}agree_drop", f"{prefix}disagree")
            counts = [int(sim.get(k, 0)) for k in keys]
            lines.append(
                f"| {hand} | {method} | {sum(counts)} | " + " | ".join(map(str, counts)) + " |"
            )
    return lines


def _replay_lines(results: dict[str, dict], names: dict[str, str]) -> list[str]:
    """Stage replay per hand and method (success: SPIDER's thresholds and carried), and stage
    track's cost where it ran; none without replays."""
    rows = []
    for hand, r in results.items():
        for method, label in names.items():
            s = r.get("replay", {}).get(f"replay@{method}")
            if s:
                rows.append(
                    f"| {hand} | {label} | {s['num_scored']} | {s['success_rate']:.1f} | "
                    f"{s['spider_success_rate']:.1f} | {s['carried_rate']:.1f} | "
                    f"{s['lost_rate']:.0f} | {100 * s['position_error_mean_m']:.1f} | "
                    f"{s['rotation_error_mean_rad']:.2f} | {s['ceiling_success_rate']:.1f} | "
                    f"{s['unstable_rest_rate']:.0f} |"
                )
    if not rows:
        return []
    lines = [
        "Replay (the object free under gravity; `dexflow/stages/replay.py`):",
        "",
        "| hand | method | scored | success % | SPIDER % | carried % | lost % | object error cm "
        "| rad | rigid ceiling % | unstable rest % |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "- *Rigid ceiling*: the success an object welded to the hand's base from the recorded "
        "lift would have; *unstable rest*: objects that, left alone at their recorded pose on "
        "the replay's table, are lost before the lift (`dexflow/stages/replay.py`).",
    ]
    for hand, r in results.items():
        track = r.get("replay", {}).get("track@refine")
        if track:
            timing = track.get("timing", {})
            lines.append(
                f"- {hand}, stage track: {track['num_tracked']} tracked, feasible "
                f"{track['feasible_rate']:.1f} %; {timing.get('cpu_seconds_per_70_frames', 0):.1f} "
                "CPU s per 70 frames of the replay window (one core); grip drift "
                f"{1000 * track.get('grip_drift_mean_m', float('nan')):.1f} mm (the human's "
                "fingertips slide that far over the recorded object while it is carried: a "
                "grasp that holds it and moves it as recorded misses them by at least that much)."
            )
    return lines


def bench_real(
    root: str,
    hands: list[str] | None = None,
    workers: int = 2,
    sequences: int = 0,
    work: str | None = None,
    out: str | None = "reports/real.md",
    overrides: list[str] | None = None,
    skip: list[str] | None = None,
) -> dict[str, dict]:
    """The whole pipeline (no demo stage) on a converted dataset, per hand, with its metrics.

    ``root`` holds canonical sequences (``dexflow convert``). For every hand the stages run in
    ``work/<hand>`` (a temporary directory by default) with the project's ``conf/`` defaults
    plus ``overrides`` (Hydra syntax, e.g. ``simulate=both``), and the metrics stage's aggregates
    are tabulated per method: the numbers of docs/results.md. ``sequences > 0``
    takes that many evenly spaced sequences. ``skip`` leaves out the stages whose names start
    with one of its entries (e.g. ``simulate``: the grasp tests, most of the time on many
    sequences; the metrics then have no SSR).

    After the metrics' table the report says why targets are missed: per method how the grasp
    test's frames fail (:func:`grasp_breakdown`) and where refinement moved the fingertips
    (:func:`refine_motion`).

    Returns:
        Per hand: ``metrics`` (the metrics stage's aggregates), ``simulate`` (per trajectory
        label, the simulate stage's summary), ``grasps`` (per label, :func:`grasp_breakdown`),
        ``motion`` (:func:`refine_motion`), ``seconds`` per stage, ``sequences``, ``frames``
        and ``retarget_s_per_sequence`` (CPU seconds of retarget@dexflow per sequence:
        wall-clock time x workers / sequences).
    """
    import shutil
    import tempfile

    from dexflow.config import compose_params, load_params

    source = Path(root).resolve()  # stages run in the work folder: no relative paths
    if not StageDir(source).sequences_dir.is_dir():
        raise FileNotFoundError(f"{source}: no sequences/ folder (convert a dataset first)")
    base = Path(work).resolve() if work else Path(tempfile.mkdtemp(prefix="dexflow-real-"))
    data_root = subset_root(source, sequences, base / "subset")
    results: dict[str, dict] = {}
    for hand in hands or ["shadow", "allegro"]:
        folder = base / hand
        folder.mkdir(parents=True, exist_ok=True)
        run = "sequential" if workers <= 1 else "local"
        fixed = [f"hand={hand}", "data=custom", f"data.root={data_root}", f"run={run}"]
        params = load_params(compose_params([*fixed, *(overrides or [])], folder / "params.yaml"))
        params = dataclasses.replace(params, run=dataclasses.replace(params.run, n_jobs=workers))
        seconds, summary, frames, simulated, replayed = {}, {}, 0, {}, {}
        layout = Layout.of(data_root, root=folder)
        for name, fn in pipeline_stages(params, layout):
            if name == "demo" or any(name.startswith(prefix) for prefix in skip or ()):
                continue
            start = time.perf_counter()
            summary = fn()
            seconds[name] = time.perf_counter() - start
            if name == "retarget@dexflow":
                frames, count = int(summary["num_frames"]), int(summary["num_sequences"])
            if name.startswith(("replay@", "track@")):
                replayed[name] = {k: v for k, v in summary.items() if k != "sequences"}
            if name.startswith("simulate@"):
                simulated[name.partition("@")[2]] = {
                    k: v for k, v in summary.items() if k not in ("sequences", "timing")
                }
        results[hand] = {
            "metrics": {k: v for k, v in summary.items() if k != "sequences"},
            "simulate": simulated,
            "replay": replayed,
            "motion": refine_motion(params, layout),
            "grasps": {m: grasp_breakdown(layout.simulate(m), params.simulate) for m in simulated},
            "seconds": seconds,
            "sequences": count,
            "frames": frames,
            "retarget_s_per_sequence": seconds["retarget@dexflow"] * workers / max(count, 1),
        }
    if not work:
        shutil.rmtree(base, ignore_errors=True)
    text = _real_table(results, source, sequences, workers, overrides or [])
    publish(text, out)
    return results


def refine_motion(params, layout: Layout) -> dict[str, float]:
    """:func:`dexflow.tools.tip_motion.summarize_motion` of retargeted -> refined over every
    sequence that both stages wrote (stage outputs in ``layout``)."""
    from dexflow.hands.files import staged_spec
    from dexflow.hands.robot import cached_hand
    from dexflow.io.artifacts import ObjectAssets, read_trajectory
    from dexflow.io.sequence import load_sequence
    from dexflow.tools.tip_motion import fingertip_motion, summarize_motion

    hand = cached_hand(staged_spec(params.hand, layout.hand_files.root), None)
    aligned, parts = layout.scale_align, []
    for path in layout.retarget("dexflow").sequence_files():
        refined = layout.refine.sequence(path)
        if not refined.is_file():
            continue  # failed in refine: reported there
        seq = load_sequence(aligned.sequence(path), aligned.root)
        retargeted = read_trajectory(path, hand.joint_names, frames=seq.num_frames)
        parts.append(fingertip_motion(
            hand, retargeted.q, read_trajectory(refined, hand.joint_names, seq.num_frames).q,
            retargeted["keypoints_human"], retargeted["observed"].astype(bool), seq.obj_pose,
            ObjectAssets(aligned.object_of(seq.obj_mesh)).sdf(),
        ))  # fmt: skip
    return summarize_motion(parts)


def grasp_breakdown(out: StageDir, params: SimulateParams | None = None) -> dict[str, float]:
    """Which frames a method's grasp test counts, and how the tested ones fail.

    From stage simulate's rows in ``out`` (its first engine; robust DexGraspBench criterion):
    ``tested`` and ``skipped`` frames (skipped: over the penetration tolerance, not tested),
    ``held`` (tested frames that hold), ``opposed`` (tested frames where the thumb and another
    finger touch the object at the start) and ``opposed_held`` (both 0, and ``thumb`` False,
    for a hand without a finger named ``thumb``); over the tested frames that fail, the median
    ``displacement_mm`` and ``rotation_deg`` under the first push (the test stops at the first
    failing direction) and ``lost_closing``, how many of them had already moved or turned
    beyond the criterion's thresholds (``params``: ``max_displacement_m``,
    ``max_rotation_deg``) while the fingers closed, before any push (0 for an engine that
    holds the object then); the median ``imbalance`` of the pushes
    (:func:`dexflow.sim.protocol.imbalance`: 0 opposed, 1 one-sided) of the held frames
    (``imbalance_held``) and of the failed ones (``imbalance_failed``), and likewise that of
    stage contact's contacts at those frames (``contact_imbalance_held``,
    ``contact_imbalance_failed``: :func:`dexflow.sim.protocol.contact_imbalance`).
    """
    import json

    from dexflow.io.artifacts import read_simulation
    from dexflow.sim.protocol import lost_while_closing

    p = params or SimulateParams()
    summary = json.loads(out.summary.read_text())
    counts = dict.fromkeys(("tested", "held", "opposed", "opposed_held", "lost_closing"), 0)
    displacement, rotation, thumb = [], [], True
    balance: dict[bool, list[float]] = {True: [], False: []}
    target: dict[bool, list[float]] = {True: [], False: []}
    for path in out.sequence_files():
        result = read_simulation(path)
        rows, engine = result.rows, result.engines[0]
        held = rows[f"{engine}.bench"].astype(bool)
        touching = rows[f"{engine}.touching"].astype(bool)
        thumb = thumb and "thumb" in result.fingers
        opposed = np.zeros(len(held), dtype=bool)
        if "thumb" in result.fingers:
            opposed = touching[:, result.fingers.index("thumb")] & (touching.sum(1) >= 2)
        closing = lost_while_closing(
            rows[f"{engine}.closing_displacement_m"], rows[f"{engine}.closing_rotation_deg"], p
        )
        counts["tested"] += len(held)
        counts["held"] += int(held.sum())
        counts["opposed"] += int(opposed.sum())
        counts["opposed_held"] += int((opposed & held).sum())
        counts["lost_closing"] += int((closing & ~held).sum())
        displacement += list(rows[f"{engine}.displacement_m"][~held, 0])
        rotation += list(rows[f"{engine}.rotation_deg"][~held, 0])
        for kept in (True, False):
            balance[kept] += list(rows[f"{engine}.imbalance"][held == kept])
            target[kept] += list(rows["contact_imbalance"][held == kept])
    failed = np.array(displacement, dtype=float)
    return {
        **counts,
        "skipped": int(summary.get("frames_skipped", 0)),
        "thumb": thumb,
        "displacement_mm": 1000 * float(np.nanmedian(failed)) if len(failed) else float("nan"),
        "rotation_deg": float(np.nanmedian(rotation)) if rotation else float("nan"),
        "imbalance_held": _median(balance[True]),
        "imbalance_failed": _median(balance[False]),
        "contact_imbalance_held": _median(target[True]),
        "contact_imbalance_failed": _median(target[False]),
    }


def _median(values: list[float]) -> float:
    """The median of the finite ``values`` (NaN when there are none)."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    return float(np.median(finite)) if len(finite) else float("nan")


def _grasp_lines(results: dict[str, dict]) -> list[str]:
    """The table of :func:`grasp_breakdown` per hand and method."""
    from dexflow.stages.report import cell as _cell

    rows = [(h, m, g) for h, r in results.items() for m, g in r.get("grasps", {}).items()]
    if not rows:
        return []
    lines = [
        "Which frames the grasp test counts and how they fail (robust DexGraspBench criterion, "
        "first engine; *opposed*: the thumb and another finger touch the object at the start; "
        "*lost while closing*: the object moved or turned past the criterion's thresholds "
        "while the fingers closed, before any push; *imbalance*: how one-sided the pushes into "
        "the object are, 0 when they cancel, 1 when all press the same way; *contact "
        "imbalance*: the same of the contacts stage contact found at the frame, those the grasp "
        "aims for, `dexflow/sim/protocol.py`):",
        "",
        "| hand | method | frames tested | skipped (over the penetration tolerance) | held "
        "| opposed | opposed and held | failed: median displacement mm / rotation ° "
        "under the first push | failed: lost while closing | median imbalance held / failed "
        "| median contact imbalance held / failed |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for hand, method, g in rows:
        opposed = f"{g['opposed']} | {g['opposed_held']}" if g["thumb"] else "— | —"
        lines.append(
            f"| {hand} | {method} | {g['tested']} | {g['skipped']} | {g['held']} | {opposed} "
            f"| {g['displacement_mm']:.0f} / {g['rotation_deg']:.0f} | {g['lost_closing']} "
            f"| {_cell(g['imbalance_held'])} / {_cell(g['imbalance_failed'])} "
            f"| {_cell(g['contact_imbalance_held'])} / {_cell(g['contact_imbalance_failed'])} |"
        )
    return lines


def _motion_lines(results: dict[str, dict]) -> list[str]:
    """The table of where refinement moved the fingertips (:mod:`dexflow.tools.tip_motion`)."""
    rows = [(hand, r["motion"]) for hand, r in results.items() if r.get("motion", {}).get("tips")]
    if not rows:
        return []
    lines = [
        "Where refinement moves the fingertips (retargeted -> refined, observed frames; "
        f"*near*: the human fingertip within {1000 * NEAR_M:.0f} mm of the object; "
        "definitions in `dexflow/tools/tip_motion.py`):",
        "",
        "| hand | human tips inside the object mm | near % | near: fingertip error mm "
        "| near: moved along the normal (outward) / across it mm | far: fingertip error mm "
        "| far: moved mm | palm moved mm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for hand, m in rows:
        lines.append(
            f"| {hand} | {m['tip_depth_mm']:.2f} | {100 * m['near_share']:.0f} "
            f"| {m['near_error_from_mm']:.1f} → {m['near_error_to_mm']:.1f} "
            f"| {m['normal_mm']:.1f} ({m['outward_mm']:+.1f}) / {m['tangential_mm']:.1f} "
            f"| {m['far_error_from_mm']:.1f} → {m['far_error_to_mm']:.1f} "
            f"| {m['far_moved_mm']:.1f} | {m['palm_mm']:.1f} |"
        )
    return lines


def _real_table(
    results: dict[str, dict], source, sequences: int, workers: int, overrides: list[str] = ()
) -> str:
    command = f"dexflow bench real {source}" + (f" --subset {sequences}" if sequences else "")
    command += "".join(f" --set {o}" for o in overrides)
    first = next(iter(results.values()), {})
    data = f"{first.get('sequences', '?')} sequences, {first.get('frames', '?')} frames"
    lines = [
        "# dexflow on real captures",
        "",
        f"`{command}`: the pipeline at the project's defaults, per hand, on the converted data "
        f"in `{source}` ({data}); metrics as defined in `dexflow/stages/metrics.py` (observed frames "
        "only for the errors).",
        "",
        machine_line(),
        "",
        "| hand | method | " + " | ".join(label for _, label, _ in REAL_COLUMNS) + " |",
        "|---" * (len(REAL_COLUMNS) + 2) + "|",
    ]
    names = {"baseline": "position baseline", "retarget": "DexFlow retarget",
             "refine": "DexFlow + refine", "track": "DexFlow + track"}  # fmt: skip
    for hand, r in results.items():
        for method, label in names.items():
            if method == "track" and not any(k.startswith("track.") for k in r["metrics"]):
                continue  # run without track=on
            cells = []
            for key, _, fmt in REAL_COLUMNS:
                value = r["metrics"].get(f"{method}.{key}", float("nan"))
                cells.append("—" if value is None or not np.isfinite(value) else fmt.format(value))
            lines.append(f"| {hand} | {label} | " + " | ".join(cells) + " |")
    lines += ["", *_replay_lines(results, names), ""]
    lines += ["", *_real_engines(results), ""]
    for table in (_grasp_lines(results), _motion_lines(results)):
        lines += [*table, ""] if table else []
    for hand, r in results.items():
        total = sum(r["seconds"].values())
        lines.append(
            f"- {hand}: {r['sequences']} sequences, {r['frames']} frames; retarget "
            f"{r['retarget_s_per_sequence']:.1f} CPU s per sequence; whole pipeline {total:.0f} s "
            f"with {workers} worker(s) ({r['frames'] / total:.1f} frames/s)."
        )
    return "\n".join(lines) + "\n"
