"""Stage simulate (paper §IV-B): does a frame's grasp hold the object in a physics engine?

Engines (``simulate.engines``, conf group ``simulate=default|pybullet|both``): MuJoCo
(:class:`dexflow.sim.mujoco_world.MujocoGraspWorld`, the default), which runs both the paper's
gravity test and DexGraspBench's published push test (so that ``ssr_bench`` compares with
BODex and DexGraspBench), and pybullet with the paper's protocol below (:class:`GraspWorld`).
The paper's criterion (``contact``) means the same in both engines: the object's weight along
each of the six axis directions for ``control_steps * control_dt_s`` seconds, held if it still
touches the hand at the end. Every engine tests the same frames. With one engine its result is
the stage's SSR; with two, the headline SSR is the conservative one: a frame counts only if it
is held in **every** engine (``success_contact`` of a sequence, ``ssr`` of the stage; each
engine's own is kept under ``engines`` and ``ssr_<engine>``), and the summary counts the frames
on which the engines agree by the paper's criterion (``agree_hold``: both hold, ``agree_drop``:
both drop) or not (``disagree``): two independent implementations of one protocol, whose
agreement is the check that neither number is an artefact of one engine.

Robust success (``simulate.perturbations``): each frame is tested nominally and in ``count``
perturbed trials (object moved by up to ``position_m`` and turned by up to ``rotation_deg``,
friction scaled within ``1 ± friction_rel``; the same trials in every engine, seeded by the
frame); a criterion holds for the frame only if it holds in every trial, so that a grasp that
holds only on float noise (or on a lucky millimetre) is not counted. The nominal results are
kept (``*_single``) and the share of frames whose nominal success the perturbations overturn is
reported (``flipped``). With two engines a sequence's evaluation stops only once both engines
have succeeded, so the per-frame statistics (frames evaluated, ``flipped``, penetration) of an
engine depend on the engine set; the SSRs do not.

pybullet, headless (DIRECT): :mod:`dexflow.sim.pybullet_world`.

Protocol for one frame ``t`` (the paper's, after DexGraspNet):

1. Hand at ``q_t``, object at its pose ``T_t``, everything at rest. The **starting penetration**
   is the depth of the deepest point of the hand's collision geometry (every shape, forearm
   and palm included: :func:`dexflow.hands.robot.measurement_hand`) inside the object's mesh
   (:func:`dexflow.measures.penetration_depth` on the signed distance grid of stage
   scale_align: the same definition as metrics' PD). The convex parts the physics uses bulge
   beyond a scanned mesh by millimetres, so their overlap with the hand (``parts_penetration_m``,
   reported as a diagnostic) would reject flush grasps on a scan.
2. Every link closer to the object than ``contact_margin_m`` is **pushed** along the contact
   normal into the object by its gap plus ``push_m``: the joint change comes from one damped
   least-squares step on the stacked Jacobian of the links' contact points (fingers only; tied
   joints follow their leaders; limits hold). That configuration is the position-control target.
3. For each of the six axis directions ``±x, ±y, ±z`` in turn, from the same start: a force
   ``m g d`` (``g = gravity``) acts on the object's centre of mass (the hand is not pulled: a real
   controller compensates its own weight) for ``control_steps`` steps of ``control_dt_s``,
   each ``substeps`` physics steps. With ``early_exit``, a test ends once the object has been
   dropped (farther than ``drop_distance_m`` from the hand and displaced by more than
   ``max_displacement_m``: under a constant force it does not come back), and a frame's remaining
   directions are skipped once both criteria have failed (their entries stay NaN).
4. Per test: **held** if the object touches the hand at the end (closer than 1 mm);
   **displacement** of its centre of mass and **rotation** angle from the start.

Criteria, per frame, both reported:

- ``contact`` (paper): held in all six tests;
- ``bench`` (DexGraspBench): displacement < ``max_displacement_m`` and rotation
  < ``max_rotation_deg`` in all six tests.

A frame counts as a success only when it starts with the hand at most ``penetration_tol_m``
inside the object, both on the object's mesh (the starting penetration above, the definition of
PD) and in the geometry the engines simulate (the convex parts: the deepest overlap any engine
finds, ``-gap``): a link wedged inside the object "holds" it without a real grasp, and the
physics wedges against the parts, which bulge beyond a scanned mesh by millimetres (measured on
83 DexYCB captures with ShadowHand: refine's tested frames start 0.97 mm into the mesh on
average but 3.4 mm into the parts; the rule on the mesh alone counted 60 % of sequences, at
most 17-25 % of which hold from a frame that is not wedged in the physics). Frames over either
tolerance cannot count, and their deep overlap makes every physics step dearer (measured on the
demo: 30 µs per MuJoCo step for a frame within the tolerance, 200-600 µs for a palm 7 mm
inside), so by default they are not tested (``skipped``; ``over_tolerance_parts`` counts those
within it on the mesh but not on the parts); their starting penetration is still measured and
reported. With ``test_over_tolerance`` they are tested too and the uncounted result is kept
(``*_raw``, ``ssr_raw``) so that reports can show what the tolerance removes; otherwise those
are null. The counted SSRs are the same either way: a frame's result does not depend on the
frames tested before it (below). A sequence succeeds (per criterion) if any evaluated frame at
or after its first contact (stage contact) succeeds; frames are taken every ``stride`` frames
and, with ``early_stop``, evaluation stops at the first frame that passes every test. SSR = the
percentage of sequences that succeed.

Deterministic: every test starts from a freshly built world state with the same calls, so a
frame's result does not depend on the frames tested before it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dexflow.hands.robot import measurement_hand
from dexflow.io.artifacts import (
    ENGINE_KEYS,
    SIMULATION_KEYS,
    ObjectAssets,
    SimulationResult,
    write_simulation,
)
from dexflow.io.layout import Layout
from dexflow.measures import hand_object_depths
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import PipelineParams, SimulateParams
from dexflow.pipeline.labelled import labelled_hand, labelled_output, load_labelled
from dexflow.pipeline.runner import StageSpec
from dexflow.sim.protocol import (
    DIRECTIONS,
    contact_imbalance,
    lost_while_closing,
    perturbations,
)
from dexflow.sim.world import GraspWorld, grasp_world

__all__ = [
    "DIRECTIONS",
    "STAGE",
    "GraspWorld",
    "run_simulate",
    "simulate_sequence",
]


logger = logging.getLogger(__name__)


def simulate_sequence(
    worlds: Mapping[str, GraspWorld] | GraspWorld,
    q: np.ndarray,
    poses: np.ndarray,
    first_contact: int,
    sdf: SignedDistanceGrid,
    contact_map: Mapping[str, np.ndarray] | None = None,
) -> tuple[dict[str, np.ndarray], dict]:
    """Evaluate the frames of one trajectory from its first contact on, in every engine.

    Each frame is tested in every engine of ``worlds`` (the same frames in all), nominally and
    under ``simulate.perturbations.count`` perturbed copies (the object moved and turned a
    little, the friction scaled; the same copies in every engine). A trial's criteria are the
    engine's (``test_frame``); a frame's are robust: met in the nominal trial and in every
    perturbed one (``*_single``: the nominal trial alone).

    Args:
        worlds: Per engine name (``pybullet``, ``mujoco``) a world whose object is this
            sequence's; the first engine's result is the sequence's. A single world stands for
            ``{world.engine: world}``.
        q: (T, dof) hand trajectory.
        poses: (T, 4, 4) object poses.
        first_contact: First frame with a finger in contact (-1: none, nothing is evaluated).
        sdf: The object mesh's signed distance grid (stage scale_align's ``sdf.npz``): the
            starting penetration of the penetration rule is measured on it.
        contact_map: Stage contact's map of this trajectory (``ContactResult.contact_map``):
            each evaluated frame's ``contact_imbalance`` comes from it
            (:func:`dexflow.sim.protocol.contact_imbalance`; NaN without a map).

    Returns:
        Per evaluated frame arrays (``frame``, ``penetration_m`` on the mesh,
        ``contact_imbalance``, and per engine
        ``<engine>.<key>`` for :data:`~dexflow.io.artifacts.ENGINE_KEYS`) and the sequence's
        result: the first engine's successes at the top level, every engine's under
        ``engines``, and with two engines the frames on which they agree (``agree_hold``,
        ``agree_drop``) or not (``disagree``) by the DexGraspBench criterion.
    """
    if not isinstance(worlds, Mapping):
        worlds = {worlds.engine: worlds}
    engines = list(worlds)
    p, hand = worlds[engines[0]].params, worlds[engines[0]].hand
    frames = [] if first_contact < 0 else list(range(first_contact, len(q), p.stride))
    if p.max_frames > 0:
        frames = frames[: p.max_frames]
    q, poses = np.asarray(q, dtype=float), np.asarray(poses, dtype=float)
    depth = np.zeros(len(q))
    if frames:  # in chunks of frames: memory bounded on long captures
        measured = measurement_hand(hand)  # every collision shape, forearm and palm included
        depth[frames] = hand_object_depths(measured, q[frames], poses[frames], sdf)[0]
    balance = np.full(len(frames), np.nan)
    if contact_map is not None:
        balance = contact_imbalance(contact_map, np.array(frames, dtype=int))
    rows: list[dict] = []
    found = {e: dict.fromkeys(("contact", "bench", "contact_raw", "bench_raw")) for e in engines}
    # per criterion, and for the headline ("all": every criterion), held in every engine
    every = dict.fromkeys(k + raw for k in (*_CRITERIA, "all") for raw in ("", "_raw"))
    considered = []  # frames reached before the early stop, tested or not
    wedged = 0  # of them, within the tolerance on the mesh but not on the convex parts
    for t, target in zip(frames, balance, strict=True):
        row: dict = {"frame": t, "penetration_m": float(depth[t])}
        row["contact_imbalance"] = float(target)
        within = row["penetration_m"] <= p.penetration_tol_m
        if within:  # and in the geometry the engines simulate (the convex parts)
            start = max(0.0, -min(w.gap(q[t], poses[t]) for w in worlds.values()))
            within = start <= p.penetration_tol_m
            wedged += not within
        considered.append(t)
        if not (within or p.test_over_tolerance):
            continue  # cannot count; a deep overlap costs the engine the most per step
        trials = perturbations(p.perturbations, t)
        for engine, world in worlds.items():
            nominal = world.test_frame(q[t], poses[t])
            robust = {k: bool(nominal[k]) for k in _CRITERIA}
            for perturbation in trials:
                if not any(robust.values()):
                    break  # every criterion has failed: more trials cannot change the frame
                trial = world.test_frame(q[t], poses[t], perturbation)
                robust = {k: robust[k] and bool(trial[k]) for k in _CRITERIA}
            row |= {f"{engine}.{k}": v for k, v in nominal.items() if k not in _CRITERIA}
            hit = found[engine]
            for key in _CRITERIA:
                row[f"{engine}.{key}_single"] = bool(nominal[key])
                row[f"{engine}.{key}"] = robust[key]
                if robust[key] and hit[f"{key}_raw"] is None:
                    hit[f"{key}_raw"] = t
                if robust[key] and within and hit[key] is None:
                    hit[key] = t
        held = {k: all(row[f"{e}.{k}"] for e in engines) for k in _CRITERIA}
        held["all"] = all(held.values())
        for key, value in held.items():
            if value and every[f"{key}_raw"] is None:
                every[f"{key}_raw"] = t
            if value and within and every[key] is None:
                every[key] = t
        rows.append(row)
        # a headline success is a success of every criterion in every engine: nothing to find
        done = every["all"] is not None
        if p.early_stop and done:
            break
    arrays = _rows_to_arrays(rows, engines, len(hand.spec.fingers))
    pen = depth[considered]
    result = {
        "frames": len(q),
        "first_contact": int(first_contact),
        "evaluated": len(rows),
        "skipped": len(considered) - len(rows),
        "over_tolerance_parts": wedged,
        "penetration_mean_mm": float(pen.mean() * 1000) if len(pen) else 0.0,
        "over_tolerance": float((pen > p.penetration_tol_m).mean()) if len(pen) else 0.0,
        "contact_imbalance_sum": float(np.nansum(arrays["contact_imbalance"])),
        "contact_imbalance_frames": int(np.isfinite(arrays["contact_imbalance"]).sum()),
        "engines": {e: _engine_result(arrays, e, found[e], p) for e in engines},
    }
    result |= result["engines"][engines[0]]
    raw = p.test_over_tolerance  # else the frames over the tolerance were not tested
    for key, name in (
        ("contact", "success_contact"),
        ("bench", "success_bench"),
        ("all", "success"),
    ):
        result[name] = every[key] is not None
        result[f"{name}_raw"] = (every[f"{key}_raw"] is not None) if raw else None
    result["success_frame"] = -1 if every["all"] is None else int(every["all"])
    first = engines[0]  # the two criteria of one engine: independent tests of the same grasp
    a, b = arrays[f"{first}.contact"], arrays[f"{first}.bench"]
    result["criteria_agree_hold"] = int(np.count_nonzero(a & b))
    result["criteria_agree_drop"] = int(np.count_nonzero(~a & ~b))
    result["criteria_disagree"] = int(np.count_nonzero(a != b))
    if len(engines) > 1:  # two engines: their per-frame agreement on the paper's criterion
        a, b = (arrays[f"{e}.contact"] for e in engines[:2])
        result["agree_hold"] = int(np.count_nonzero(a & b))
        result["agree_drop"] = int(np.count_nonzero(~a & ~b))
        result["disagree"] = int(np.count_nonzero(a != b))
    return arrays, result


_CRITERIA = ("contact", "bench")


def _engine_result(arrays: dict, engine: str, hit: dict, p: SimulateParams) -> dict:
    """One engine's result for a sequence (successes, flips, overlap with the convex parts)."""
    parts = arrays[f"{engine}.parts_penetration_m"]
    flipped = np.zeros(len(parts), dtype=bool)
    for key in _CRITERIA:
        flipped |= arrays[f"{engine}.{key}_single"] != arrays[f"{engine}.{key}"]
    raw = p.test_over_tolerance  # else the frames over the tolerance were not tested
    closing = arrays[f"{engine}.closing_displacement_m"]
    lost = lost_while_closing(closing, arrays[f"{engine}.closing_rotation_deg"], p)
    balance = arrays[f"{engine}.imbalance"]
    balance = balance[np.isfinite(balance)]
    return {
        "success_contact": hit["contact"] is not None,
        "success_bench": hit["bench"] is not None,
        "success_contact_raw": (hit["contact_raw"] is not None) if raw else None,
        "success_bench_raw": (hit["bench_raw"] is not None) if raw else None,
        "success_frame": -1 if hit["contact"] is None else int(hit["contact"]),
        "flipped_frames": int(flipped.sum()),
        "parts_penetration_mean_mm": float(parts.mean() * 1000) if len(parts) else 0.0,
        "parts_over_tolerance": float((parts > p.penetration_tol_m).mean()) if len(parts) else 0.0,
        # None: this engine's test holds the object while the fingers close (pybullet)
        "lost_closing_frames": None if np.isnan(closing).any() else int(lost.sum()),
        "imbalance_sum": float(balance.sum()),
        "imbalance_frames": len(balance),
    }


def _rows_to_arrays(rows: list[dict], engines: list[str], fingers: int) -> dict[str, np.ndarray]:
    """Stack the per-frame rows into the arrays of a simulation result (empty ones shaped)."""
    width = {"touching": fingers} | dict.fromkeys(
        ("held", "displacement_m", "rotation_deg", "tested"), 6
    )
    flags = ("contact", "bench", "contact_single", "bench_single")
    arrays = {}
    for key in [*SIMULATION_KEYS, *(f"{e}.{k}" for e in engines for k in ENGINE_KEYS)]:
        base = key.partition(".")[2] or key
        if rows:
            arrays[key] = np.array([r[key] for r in rows])
        else:
            arrays[key] = np.zeros((0, width[base]) if base in width else 0)
        if base in flags:
            arrays[key] = arrays[key].astype(bool)
    return arrays


def run_simulate(params: PipelineParams, layout: Layout, label: str) -> dict:
    """Stage runner: the six-direction test on every trajectory labelled ``label``.

    Args:
        params: Pipeline params (``hand``, ``simulate``, ``run``).
        layout: The project's paths; the trajectories are ``layout.trajectory(label)``.
        label: One of :data:`~dexflow.io.layout.TRAJECTORIES` (baseline, retarget, refine).

    Returns:
        The summary (also written to the stage's ``summary.json``), with the wall-clock speed
        under ``timing`` (returned, not written there).
    """
    out, aligned = layout.simulate(label), layout.scale_align
    stage = labelled_output("simulate", params, layout, label, out)
    files = stage.start()
    sp = params.simulate
    if files:  # a hand the engines cannot load fails the stage once (exit 2), not every sequence
        for engine in sp.engines:
            grasp_world(engine, labelled_hand(params, layout), sp)

    def one(path: Path) -> dict:
        hand, seq, q, found = load_labelled(params, layout, path)
        worlds = {engine: grasp_world(engine, hand, sp) for engine in sp.engines}
        assets = ObjectAssets(aligned.object_of(seq.obj_mesh))
        for world in worlds.values():
            world.set_object(assets.paths.convex)
        start = time.perf_counter()
        rows, result = simulate_sequence(
            worlds, q, seq.obj_pose, found.first_contact, assets.sdf(), found.contact_map
        )
        result["seconds"] = time.perf_counter() - start
        fingers = list(hand.spec.fingers)
        write_simulation(out.sequence(path), SimulationResult(rows, fingers, list(sp.engines)))
        return result

    tally = stage.run(one, files, params.run)
    ok = tally.ok
    seconds = sum(s.pop("seconds") for s in ok)
    evaluated = sum(s["evaluated"] for s in ok)

    summary = {
        **tally.counts("simulate"),
        "method": label,
        "engines": ",".join(sp.engines),
        "perturbations": sp.perturbations.count,
        "frames_evaluated": evaluated,
        "frames_skipped": int(sum(s["skipped"] for s in ok)),
        "frames_over_tolerance_parts": int(sum(s["over_tolerance_parts"] for s in ok)),
        "penetration_mean_mm": tally.mean("penetration_mean_mm"),
        "over_tolerance": tally.mean("over_tolerance", 0.0),
        "contact_imbalance_mean": _ratio(
            sum(s["contact_imbalance_sum"] for s in ok),
            sum(s["contact_imbalance_frames"] for s in ok),
        ),
    }
    for i, engine in enumerate(sp.engines):
        stats = _engine_summary([s["engines"][engine] for s in ok], evaluated)
        if i == 0:
            summary |= stats
        summary |= {f"{k}_{engine}": v for k, v in stats.items()}

    def percent(key: str) -> float | None:
        values = [s[key] for s in ok]
        if None in values:
            return None  # not measured (frames over the tolerance untested)
        return float(100 * np.mean(values)) if ok else float("nan")

    # across engines: the paper's criterion, DexGraspBench's, and the headline (every test)
    for key, name in (("ssr", "success"), ("ssr_paper", "success_contact"),
                      ("ssr_bench", "success_bench")):  # fmt: skip
        summary[key], summary[f"{key}_raw"] = percent(name), percent(f"{name}_raw")
    for key in ("criteria_agree_hold", "criteria_agree_drop", "criteria_disagree"):
        summary[key] = int(sum(s[key] for s in ok))
    if len(sp.engines) > 1:
        for key in ("agree_hold", "agree_drop", "disagree"):
            summary[key] = int(sum(s[key] for s in ok))
    summary["sequences"] = dict(sorted(tally.sequences.items()))
    stage.finish(summary)
    speed = evaluated / seconds if seconds else 0.0
    return {**summary, "timing": {"frames_per_second_one_core": speed}}


def _engine_summary(entries: list[dict], evaluated: int) -> dict:
    """One engine's aggregates over the sequences the stage processed (SSRs in %; ``flipped``:
    the share of evaluated frames whose nominal trial and robust result differ;
    ``lost_closing``: the share whose object moved or turned past the DexGraspBench thresholds
    while the fingers closed, before any push, None for an engine that holds it then;
    ``imbalance_mean``: the mean :func:`dexflow.sim.protocol.imbalance` of the frames with a
    contact)."""

    def percent(key: str) -> float | None:
        values = [e[key] for e in entries]
        if any(v is None for v in values):
            return None  # not measured (frames over the tolerance untested)
        return float(100 * np.mean(values)) if entries else float("nan")

    def mean(key: str) -> float:
        return float(np.mean([e[key] for e in entries])) if entries else float("nan")

    flipped = sum(e["flipped_frames"] for e in entries)
    lost = [e["lost_closing_frames"] for e in entries]
    balanced = sum(e["imbalance_frames"] for e in entries)
    return {
        "ssr_paper": percent("success_contact"),
        "ssr_bench": percent("success_bench"),
        "ssr_paper_raw": percent("success_contact_raw"),
        "ssr_bench_raw": percent("success_bench_raw"),
        "parts_penetration_mean_mm": mean("parts_penetration_mean_mm"),
        "parts_over_tolerance": mean("parts_over_tolerance"),
        "flipped": flipped / evaluated if evaluated else 0.0,
        "lost_closing": (None if None in lost else (sum(lost) / evaluated if evaluated else 0.0)),
        "imbalance_mean": _ratio(sum(e["imbalance_sum"] for e in entries), balanced),
    }


def _ratio(total: float, count: int) -> float:
    """``total / count``, NaN when ``count`` is 0 (a mean over no frames)."""
    return total / count if count else float("nan")


STAGE = StageSpec(
    name="simulate",
    run=run_simulate,
    metric_keys=None,  # every aggregate: the first engine's, each engine's (``<key>_<engine>``)
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences; SSR {s['ssr']:.1f} % (every test), "
        f"{s['ssr_paper']:.1f} % (the paper's gravity test), {s['ssr_bench']:.1f} % "
        f"(DexGraspBench); the two agree on {_agreement(s):.0f} % of the frames; without the "
        "penetration tolerance "
        + ("not tested" if s["ssr_raw"] is None else
           f"{s['ssr_raw']:.1f} % / {s['ssr_paper_raw']:.1f} % / {s['ssr_bench_raw']:.1f} %")
        + f"; {s['frames_evaluated']} frames tested ({s['frames_skipped']} over the tolerance "
        "skipped), "
        f"mean starting penetration {s['penetration_mean_mm']:.2f} mm; "
        f"{s['timing']['frames_per_second_one_core']:.2f} frames/s per core"
    ),
)  # fmt: skip


def _agreement(summary: dict) -> float:
    """The share (%) of tested frames on which the first engine's two criteria agree."""
    agree = summary["criteria_agree_hold"] + summary["criteria_agree_drop"]
    total = agree + summary["criteria_disagree"]
    return 100.0 * agree / total if total else float("nan")
