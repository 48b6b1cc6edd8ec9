"""Stage contact (paper §III-C, Algorithm 1): which robot fingers touch the object, and where.

Per frame and finger, ``d_f(t)`` is the smallest signed distance from the finger's contact
candidates (hand surface points on the finger's ``links`` in the hand config) to the object
surface, from the object's signed distance grid (negative inside).

1. **Dual threshold with hysteresis**: in contact below ``dis_min``, out of contact above
   ``dis_max``, otherwise the previous state (first frame: out).
2. **Frame-to-frame inference**: ``C_t = I((C_{t-1} + C_{t+1}) / 2 + α v_f Δt > τ_c)``, with
   ``Δt = 1 / fps`` of the sequence. With the paper's constants it flips a frame only when both
   neighbours disagree with it: a one-frame spike (0 1 0) is removed and a one-frame gap (1 0 1)
   is filled. Applied literally at the edges of a contact (0 1 1) it would also shorten every
   contact by a frame at each end; dexflow applies it only where both neighbours agree.
3. **Guard** (three-step protocol) on filling a gap: (a) the finger's path over the 5 frames
   around it is continuous: a cubic polynomial fitted to the other four frames predicts the
   frame within ``spline_tolerance_m``; (b) contact is likely: ``P_c = σ(β1 (a_tol -
   ||ä_finger - ä_object||))`` > 0.5, i.e. the finger accelerates with the object (dexflow's
   reading of ``σ(β1 (T̈ - T̈_obj))``, which compares the two accelerations); (c) the finger is
   slower than ``v_max`` relative to the object.

The contact map keeps, per frame and finger in contact, up to ``map_points`` hand points closest
to the surface with their nearest object surface points and outward normals, all in the object
frame (what refinement's E_dis and E_align need).

**Flicker** is state changes per finger per second (:func:`dexflow.measures.state_flicker`). The
paper's 68 % compares conventional detection on a conventional retargeting with DexFlow's on its
own, so the summary holds three detections: ``threshold`` (a single threshold, in contact below
``dis_min``), ``raw`` (hysteresis) and ``final`` (after inference); the first also on the
baseline retargeting (trajectory ``baseline``, retarget method ``position``).

**What the inference can change.** With ``x = α v_f Δt``, a frame between two contact frames
gets ``I(1 + x > τ_c)`` and one between two frames out of contact ``I(x > τ_c)``; for
``x <= τ_c < 1 + x`` (the paper's constants: x = 0.016 at 30 fps, τ_c = 0.7) it changes exactly
the *one-frame runs*, states whose two neighbours agree with each other and not with it. The
hysteresis leaves one only where the distance crosses the whole band in one frame: a one-frame
contact at ``t`` needs ``d(t) < dis_min`` and ``d(t+1) > dis_max``, a one-frame gap
``d(t) > dis_max`` and ``d(t+1) < dis_min``. So on hysteresis states the inference acts only
where a finger moves more than ``dis_max - dis_min`` (5.8 mm, 0.17 m/s at 30 fps) along the
surface normal between two frames. Filling a one-frame gap also needs the guard, and there
``d(t-1) <= dis_max < d(t)`` and ``d(t+1) < dis_min`` make the distance's second difference
exceed the band: an acceleration above ``(dis_max - dis_min) fps²`` (5.2 m/s² at 30 fps), more
than the likelihood test's ``a_tol`` (5 m/s²) allows the finger relative to the object. The
summary counts the band crossings (``band_jumps``), the one-frame runs, the states the inference
removed and filled, and says all this in ``inference_note``.

**One file** (about 580 lines): stage contact's math is one state machine: the dual thresholds, the frame-
to-frame smoothing and the inference read and write the same per-finger states, in the notation of
the paper's equations; apart, each part would be read without the others it depends on.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from dexflow.geometry import transform_points, world_to_object
from dexflow.hands.files import staged_spec
from dexflow.hands.robot import RobotHand, cached_hand
from dexflow.io.artifacts import ContactResult, ObjectAssets, read_trajectory, write_contact
from dexflow.io.layout import Layout, StageDir
from dexflow.io.sequence import load_sequence
from dexflow.measures import (
    contact_counts,
    flicker_reduction,
    frame_chunks,
    hand_object_depths,
    precision_recall,
    state_flicker,
)
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import ContactParams, PipelineParams
from dexflow.pipeline.resume import StageOutput
from dexflow.pipeline.runner import StageSpec

__all__ = [
    "STAGE",
    "band_jumps",
    "contact_states",
    "contact_summary",
    "finger_distances",
    "hysteresis",
    "infer_frames",
    "inference_reach",
    "one_frame_runs",
    "run_contact",
    "state_changes",
]


def hysteresis(distance: np.ndarray, dis_min: float, dis_max: float) -> np.ndarray:
    """Dual-threshold states (T, F) from distances (T, F): on below dis_min, off above dis_max."""
    distance = np.asarray(distance)
    state = np.zeros(distance.shape, dtype=bool)
    current = np.zeros(distance.shape[1:], dtype=bool)
    for t in range(len(distance)):  # a scan over time: each state depends on the previous one
        current = np.where(
            distance[t] < dis_min, True, np.where(distance[t] > dis_max, False, current)
        )
        state[t] = current
    return state


def infer_frames(
    state: np.ndarray, fps: float, params: ContactParams, allow_fill: np.ndarray | None = None
) -> np.ndarray:
    """Frame-to-frame inference on (T, F) states; ``allow_fill`` (T, F) guards gap filling."""
    state = np.asarray(state, dtype=bool)
    out = state.copy()
    if len(state) < 3:
        return out
    prev, nxt = state[:-2].astype(float), state[2:].astype(float)
    rule = (prev + nxt) / 2 + params.alpha * params.finger_speed_mps / fps > params.tau_c
    agree = state[:-2] == state[2:]  # both neighbours say the same thing
    middle = state[1:-1]
    fill = agree & rule & ~middle
    remove = agree & ~rule & middle
    if allow_fill is not None:
        fill &= allow_fill[1:-1]
    out[1:-1] = np.where(fill, True, np.where(remove, False, middle))
    return out


def _guard(
    points: np.ndarray, obj_pos: np.ndarray, fps: float, params: ContactParams
) -> np.ndarray:
    """(T, F) True where filling a gap passes the three-step protocol.

    Args:
        points: (T, F, 3) a representative point per finger (its closest candidate), world.
        obj_pos: (T, 3) object position, world.
    """
    n_frames = len(points)
    ok = np.zeros(points.shape[:2], dtype=bool)
    if n_frames < 5:
        return ok
    offsets = np.array([-2, -1, 1, 2])
    basis = np.vander(offsets, 4, increasing=True)  # cubic through the four neighbours
    predict = np.linalg.lstsq(basis, np.eye(4), rcond=None)[0][0]  # value at offset 0
    centre = np.arange(2, n_frames - 2)
    neighbours = points[centre[:, None] + offsets]  # (T-4, 4, F, 3)
    fitted = np.einsum("k,tkfc->tfc", predict, neighbours)
    continuous = np.linalg.norm(fitted - points[centre], axis=-1) < params.spline_tolerance_m
    dt = 1.0 / fps
    acc = (points[centre + 1] - 2 * points[centre] + points[centre - 1]) / dt**2
    acc_obj = (obj_pos[centre + 1] - 2 * obj_pos[centre] + obj_pos[centre - 1]) / dt**2
    gap = np.linalg.norm(acc - acc_obj[:, None], axis=-1)
    likely = 1 / (1 + np.exp(-params.beta1 * (params.accel_tolerance_mps2 - gap))) > 0.5
    rel_vel = (points[centre + 1] - points[centre - 1]) - (
        obj_pos[centre + 1] - obj_pos[centre - 1]
    )[:, None]
    slow = np.linalg.norm(rel_vel, axis=-1) / (2 * dt) < params.v_max_mps
    ok[centre] = continuous & likely & slow
    return ok


def finger_distances(
    hand: RobotHand, q: np.ndarray, obj_pose: np.ndarray, sdf: SignedDistanceGrid
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance of every hand surface point to the object, batched over frames.

    Returns:
        per-finger minimum (T, F), all point distances (T, N), points in the object frame
        (T, N, 3).
    """
    with torch.no_grad():
        points, _ = hand.surface(torch.as_tensor(q, dtype=hand.dtype), normals=False)
    points = points.numpy()
    local = world_to_object(points, obj_pose)
    dist = sdf.query(local)
    per_finger = np.stack(
        [np.where(m, dist, np.inf).min(axis=1) for m in hand.finger_point_masks.values()], axis=1
    )
    return per_finger, dist, local


def contact_states(distance, fps, params: ContactParams, guard: np.ndarray | None = None):
    """Raw (hysteresis) and final (inferred) states (T, F)."""
    raw = hysteresis(distance, params.dis_min_m, params.dis_max_m)
    final = (
        infer_frames(raw, fps, params, guard if params.guard else None) if params.smoothing else raw
    )
    return raw, final


def state_changes(state: np.ndarray) -> np.ndarray:
    """Number of state changes per finger (F,)."""
    return np.abs(np.diff(np.asarray(state, dtype=int), axis=0)).sum(axis=0)


def one_frame_runs(state: np.ndarray) -> np.ndarray:
    """(T, F) True at the states of (T, F) states whose two neighbours agree with each other and
    not with them: one-frame contacts and one-frame gaps, the states frame-to-frame inference
    changes (with ``α v_f Δt <= τ_c < 1 + α v_f Δt``). The first and last frames are False."""
    state = np.asarray(state, dtype=bool)
    alone = np.zeros(state.shape, dtype=bool)
    alone[1:-1] = (state[:-2] == state[2:]) & (state[1:-1] != state[:-2])
    return alone


def band_jumps(distance: np.ndarray, dis_min: float, dis_max: float) -> np.ndarray:
    """(T - 1, F) True at the steps between consecutive frames of (T, F) distances that cross
    the whole hysteresis band: from below ``dis_min`` to above ``dis_max`` or back.

    Every one-frame run of :func:`hysteresis` states ends with one (a one-frame contact at
    ``t`` has ``d(t) < dis_min`` and ``d(t + 1) > dis_max``; a gap the reverse), so finger by
    finger ``one_frame_runs(hysteresis(d, ...)).sum(0) <= band_jumps(d, ...).sum(0)``.
    """
    distance = np.asarray(distance)
    before, after = distance[:-1], distance[1:]
    up = (before < dis_min) & (after > dis_max)
    down = (before > dis_max) & (after < dis_min)
    return up | down


def inference_reach(params: ContactParams, fps: float) -> str:
    """One sentence: which states frame-to-frame inference can change at ``fps``, derived from
    the constants (``x = α v_f Δt``: between two contact frames the rule gives ``1 + x > τ_c``,
    between two frames out of contact ``x > τ_c``)."""
    if not params.smoothing:
        return "Frame-to-frame inference is off (contact.smoothing false): final = hysteresis."
    x = params.alpha * params.finger_speed_mps / fps
    rule = f"α v_f Δt = {x:.3f} at {fps:g} fps, τ_c = {params.tau_c:g}"
    keeps_inside, sets_outside = 1 + x > params.tau_c, x > params.tau_c
    if keeps_inside and not sets_outside:
        band = params.dis_max_m - params.dis_min_m
        fill = " where the guard allows" if params.guard else ""
        return (
            f"Frame-to-frame inference ({rule}) changes only one-frame runs, states whose two "
            f"neighbours agree with each other and not with them: it removes a one-frame contact "
            f"(α v_f Δt <= τ_c) and fills a one-frame gap (1 + α v_f Δt > τ_c){fill}. Hysteresis "
            f"leaves such a run only where a finger's distance crosses the whole band "
            f"dis_max - dis_min = {1000 * band:.1f} mm between two frames (faster than "
            f"{band * fps:.2f} m/s along the surface normal): entering contact needs d < "
            f"{1000 * params.dis_min_m:g} mm, leaving it d > {1000 * params.dis_max_m:g} mm."
            + _guard_reach(params, fps)
        )
    inside = [] if keeps_inside else ["removes every contact frame between two contact frames"]
    outside = ["sets contact between two frames out of contact"] if sets_outside else []
    return (
        f"Frame-to-frame inference ({rule}) {' and '.join(inside + outside)}: at these "
        "constants it changes states inside runs, not only one-frame runs."
    )


def _guard_reach(params: ContactParams, fps: float) -> str:
    """The guard's acceleration test against a one-frame gap: ``d(t - 1) <= dis_max < d(t)`` and
    ``d(t + 1) < dis_min``, so the distance's second difference is below ``-(dis_max -
    dis_min)``, an acceleration of more than ``(dis_max - dis_min) fps²``."""
    least = (params.dis_max_m - params.dis_min_m) * fps**2
    if not params.guard or least <= params.accel_tolerance_mps2:
        return ""
    return (
        f" The guard refuses a fill where the finger accelerates more than a_tol = "
        f"{params.accel_tolerance_mps2:g} m/s² relative to the object, and the distance at a "
        f"one-frame gap has a second difference above (dis_max - dis_min) fps² = {least:.1f} m/s²."
    )


def _first_change(raw: np.ndarray, final: np.ndarray, fingers: list[str]) -> dict | None:
    """The first (frame, then finger) state the inference changed, with the states of the two
    frames either side, or None."""
    changed = np.argwhere(raw != final)
    if not len(changed):
        return None
    t, f = (int(i) for i in changed[0])
    window = slice(max(t - 2, 0), t + 3)
    return {
        "finger": fingers[f],
        "frame": t,
        "frames": [window.start, min(window.stop, len(raw)) - 1],
        "raw": "".join("1" if v else "0" for v in raw[window, f]),
        "final": "".join("1" if v else "0" for v in final[window, f]),
    }


def _empty_contact_map() -> dict[str, np.ndarray]:
    empty = np.zeros((0, 3))
    return {
        "map_frame": np.zeros(0, int),
        "map_finger": np.zeros(0, int),
        "map_hand_index": np.zeros(0, int),
        "map_hand_point": empty,
        "map_object_point": empty,
        "map_object_normal": empty,
    }


def _contact_map(local, dist, final, masks, surface_tree, surface_normals, k):
    rows = []
    for f, mask in enumerate(masks):
        idx = np.flatnonzero(mask)
        for t in np.flatnonzero(final[:, f]):
            order = idx[np.argsort(dist[t, idx])[:k]]
            rows.append((t, f, order))
    if not rows:
        return _empty_contact_map()
    frame = np.concatenate([np.full(len(o), t) for t, _, o in rows])
    finger = np.concatenate([np.full(len(o), f) for _, f, o in rows])
    index = np.concatenate([o for *_, o in rows])
    hand_points = local[frame, index]
    _, nearest = surface_tree.query(hand_points)
    return {
        "map_frame": frame,
        "map_finger": finger,
        "map_hand_index": index,
        "map_hand_point": hand_points,
        "map_object_point": surface_tree.data[nearest],
        "map_object_normal": surface_normals[nearest],
    }


def contact_sequence(
    hand: RobotHand,
    trajectory_file: Path,
    aligned: StageDir,
    params: ContactParams,
    baseline_file: Path | None = None,
) -> tuple[ContactResult, dict]:
    """Everything for one sequence: the result to save and statistics.

    Args:
        trajectory_file: The DexFlow retargeting (``data/retarget/dexflow/sequences/<name>``).
        baseline_file: The baseline retargeting of the same sequence; when given (and present),
            the statistics add single-threshold detection on it (``*_baseline_threshold``).
    """
    seq = load_sequence(aligned.sequence(trajectory_file), data_root=aligned.root)
    q = read_trajectory(trajectory_file, hand.joint_names, frames=seq.num_frames).q
    assets = ObjectAssets(aligned.object_of(seq.obj_mesh))
    sdf = assets.sdf()
    points, normals = assets.surface()
    tree = cKDTree(points)
    masks = list(hand.finger_point_masks.values())
    # Two passes over chunks of frames, so that memory is bounded by a chunk: the per-finger
    # distances and closest points first (the states need every frame), then the contact map.
    distance = np.zeros((len(q), len(masks)))
    closest = np.zeros((len(q), len(masks), 3))
    chunks, last = frame_chunks(len(q)), None
    for frames in chunks:
        distance[frames], dist, local = finger_distances(hand, q[frames], seq.obj_pose[frames], sdf)
        rows = np.arange(len(local))[:, None]
        nearest = np.stack([np.where(m, dist, np.inf).argmin(axis=1) for m in masks], axis=1)
        closest[frames] = local[rows, nearest]
        last = (frames, dist, local)  # the map reuses it (a short sequence's only chunk)
    world = transform_points(seq.obj_pose, closest)
    guard = _guard(world, seq.obj_pose[:, :3, 3], seq.fps, params)
    raw, final = contact_states(distance, seq.fps, params, guard)
    parts = []
    for frames in chunks:
        if not final[frames].any():
            continue
        if last is not None and frames == last[0]:
            _, dist, local = last
        else:
            _, dist, local = finger_distances(hand, q[frames], seq.obj_pose[frames], sdf)
        part = _contact_map(local, dist, final[frames], masks, tree, normals, params.map_points)
        part["map_frame"] = part["map_frame"] + frames.start
        parts.append(part)
    contact_map = _empty_contact_map()
    if parts:  # by finger, then frame: the same map whatever the chunks
        joined = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        order = np.argsort(joined["map_finger"], kind="stable")
        contact_map = {k: v[order] for k, v in joined.items()}
    result = ContactResult(
        distance_m=distance,
        raw=raw,
        final=final,
        fingers=list(hand.spec.fingers),
        fps=seq.fps,
        contact_map=contact_map,
    )
    threshold = distance < params.dis_min_m  # a single threshold, for comparison
    alone = one_frame_runs(raw)
    stats = {
        "frames": len(q),
        "fps": float(seq.fps),
        "fingers": int(final.shape[1]),
        "changes_threshold": int(state_changes(threshold).sum()),
        "changes_raw": int(state_changes(raw).sum()),
        "changes_final": int(state_changes(final).sum()),
        "flicker_threshold": state_flicker(threshold, seq.fps),
        "flicker_raw": state_flicker(raw, seq.fps),
        "flicker_final": state_flicker(final, seq.fps),
        "one_frame_runs_threshold": int(one_frame_runs(threshold).sum()),
        "one_frame_runs_raw": int(alone.sum()),
        "one_frame_gaps_raw": int((alone & ~raw).sum()),
        "band_jumps": int(band_jumps(distance, params.dis_min_m, params.dis_max_m).sum()),
        "inference_changed": int(np.count_nonzero(raw != final)),
        "inference_removed": int(np.count_nonzero(raw & ~final)),
        "inference_filled": int(np.count_nonzero(~raw & final)),
        "inference_first_change": _first_change(raw, final, list(hand.spec.fingers)),
        "contact_fraction": float(final.mean()),
    }
    if baseline_file is not None and baseline_file.is_file():
        q_base = read_trajectory(baseline_file, hand.joint_names, frames=seq.num_frames).q
        _, distance_base = hand_object_depths(hand, q_base, seq.obj_pose, sdf)
        threshold_base = distance_base < params.dis_min_m
        stats["changes_baseline_threshold"] = int(state_changes(threshold_base).sum())
        stats["flicker_baseline_threshold"] = state_flicker(threshold_base, seq.fps)
    if seq.gt_contact is not None:
        from dexflow.human.keypoints import FINGERS

        cols = [FINGERS.index(f) for f in hand.spec.fingers]
        truth = seq.gt_contact[:, cols]
        stats["raw_vs_truth"] = contact_counts(raw, truth)
        stats["final_vs_truth"] = contact_counts(final, truth)
    return result, stats


def _mean(entries: list[dict], key: str, default: float = float("nan")) -> float:
    values = [e[key] for e in entries]
    return float(np.mean(values)) if values else default


def _example(name: str, change: Mapping) -> str:
    first, last = change["frames"]
    return (
        f"{name}, finger {change['finger']}, frames {first}-{last}: hysteresis "
        f"{change['raw']} -> inference {change['final']}"
    )


# Per-sequence counts the summary adds up.
_COUNTS = (
    "one_frame_runs_threshold",
    "one_frame_runs_raw",
    "one_frame_gaps_raw",
    "band_jumps",
    "inference_changed",
    "inference_removed",
    "inference_filled",
)


def contact_summary(entries: Mapping[str, dict], params: ContactParams) -> dict:
    """The stage's figures from the per-sequence entries of :func:`contact_sequence` (those
    with ``status`` ``ok``). Flicker is state changes per finger per second, a mean over
    sequences; shares are fractions (0.33 is 33 %); counts are sums over sequences.

    The paper's comparison (its 68 %), over the ``num_compared`` sequences that have a baseline
    trajectory:

    - ``flicker_baseline_threshold``: a single threshold (``dis_min``) on the baseline
      retargeting (retarget method ``position``).
    - ``flicker_dexflow``: hysteresis and inference on the DexFlow retargeting.
    - ``flicker_reduction_vs_baseline``: ``1 - flicker_dexflow / flicker_baseline_threshold``
      (:func:`~dexflow.measures.flicker_reduction`; NaN, written null, without a baseline).

    On the DexFlow retargeting, every sequence:

    - ``flicker_threshold``, ``flicker_raw``, ``flicker_final``: single threshold, hysteresis,
      after inference.
    - ``changes_removed_by_inference``: share of the hysteresis state changes the inference
      removes; ``changes_removed_vs_threshold``: share of the single threshold's state changes
      that hysteresis and inference together remove.
    - ``one_frame_runs_threshold``, ``one_frame_runs_raw`` (of which ``one_frame_gaps_raw`` are
      gaps): the states the inference can change (:func:`one_frame_runs`); ``band_jumps``:
      finger steps crossing the whole hysteresis band (:func:`band_jumps`).
    - ``inference_changed`` (``inference_removed`` contact states, ``inference_filled`` gaps)
      and ``inference_changed_share`` of all states (frames x fingers).
    - ``inference_example``: the first state the inference changed (sequences by name), with
      the hysteresis and final states of the frames around it; absent if none.
    - ``inference_note``: the sentence of :func:`inference_reach` and these counts.
    """
    named = [(n, e) for n, e in sorted(entries.items()) if e.get("status") == "ok"]
    ok = [e for _, e in named]
    single, raw, final = (sum(e[f"changes_{k}"] for e in ok) for k in ("threshold", "raw", "final"))
    compared = [e for e in ok if "flicker_baseline_threshold" in e]
    flicker_baseline = _mean(compared, "flicker_baseline_threshold")
    flicker_dexflow = _mean(compared, "flicker_final")
    states = sum(e["frames"] * e["fingers"] for e in ok)
    steps = sum((e["frames"] - 1) * e["fingers"] for e in ok)
    changed = sum(e["inference_changed"] for e in ok)
    examples = [_example(n, e["inference_first_change"]) for n, e in named
                if e["inference_first_change"]]  # fmt: skip
    summary = {
        "num_compared": len(compared),
        "changes_baseline_threshold": sum(e["changes_baseline_threshold"] for e in compared),
        "flicker_baseline_threshold": flicker_baseline,
        "flicker_dexflow": flicker_dexflow,
        "flicker_reduction_vs_baseline": flicker_reduction(flicker_baseline, flicker_dexflow),
        "changes_threshold": single,
        "changes_raw": raw,
        "changes_final": final,
        "changes_removed_by_inference": (raw - final) / raw if raw else 0.0,
        "changes_removed_vs_threshold": (single - final) / single if single else 0.0,
        "flicker_threshold": _mean(ok, "flicker_threshold", 0.0),
        "flicker_raw": _mean(ok, "flicker_raw", 0.0),
        "flicker_final": _mean(ok, "flicker_final", 0.0),
        **{key: sum(e[key] for e in ok) for key in _COUNTS},
        "inference_changed_share": changed / states if states else 0.0,
    }
    if examples:
        summary["inference_example"] = examples[0]
    if ok:
        runs, gaps = summary["one_frame_runs_raw"], summary["one_frame_gaps_raw"]
        rates = sorted({e["fps"] for e in ok})
        lowest = (
            ""
            if len(rates) == 1
            else f" (Frame rates {rates[0]:g} to {rates[-1]:g} fps: the figures are the lowest's.)"
        )
        summary["inference_note"] = (
            f"{inference_reach(params, rates[0])}{lowest} In these {len(ok)} sequences "
            f"{summary['band_jumps']} of {steps} finger steps crossed the whole band (every "
            f"one-frame run ends with one, and so may a longer run); the hysteresis states hold "
            f"{runs} one-frame runs where a single threshold at dis_min on the same trajectory "
            f"holds {summary['one_frame_runs_threshold']}; the inference removed "
            f"{summary['inference_removed']} of the {runs - gaps} one-frame contacts and filled "
            f"{summary['inference_filled']} of the {gaps} one-frame gaps, {changed} of {states} "
            "states "
            f"({100 * summary['inference_changed_share']:.2g} %)"
            + (f"; e.g. {examples[0]}." if examples else ".")
        )
    truth = [e for e in ok if "raw_vs_truth" in e]
    for which in ("raw_vs_truth", "final_vs_truth"):
        if truth:
            counts = {k: sum(e[which][k] for e in truth) for k in ("tp", "fp", "fn")}
            summary[which] = precision_recall(**counts)
    return summary


def run_contact(params: PipelineParams, layout: Layout) -> dict:
    """Stage runner over every retargeted sequence (``layout.retarget("dexflow")``), with the
    baseline's (``layout.trajectory("baseline")``) for the paper's flicker comparison."""
    source, aligned, out = layout.retarget("dexflow"), layout.scale_align, layout.contact
    baseline = layout.trajectory("baseline")
    stage = StageOutput(
        out,
        "contact",
        {"hand": params.hand, "contact": params.contact},
        inputs=(source, aligned, layout.hand_files, baseline),
    )
    files = stage.start()
    spec = staged_spec(params.hand, layout.hand_files.root)

    def one(path: Path) -> dict:
        torch.set_num_threads(1)
        hand = cached_hand(spec, None)
        result, stats = contact_sequence(
            hand, path, aligned, params.contact, baseline.sequence(path)
        )
        write_contact(out.sequence(path), result)
        return stats

    tally = stage.run(one, files, params.run)
    summary = {**tally.counts("contact"), **contact_summary(tally.sequences, params.contact)}
    summary["sequences"] = dict(sorted(tally.sequences.items()))
    stage.finish(summary)
    frames, seconds = summary["num_frames"], tally.seconds
    return {**summary, "timing": {"frames_per_second": frames / seconds if seconds else 0.0}}


STAGE = StageSpec(
    name="contact",
    run=run_contact,
    metric_keys=("num_sequences", "num_ok", "num_failed", "num_frames", "num_compared",
                 "flicker_baseline_threshold", "flicker_dexflow", "flicker_reduction_vs_baseline",
                 "flicker_threshold", "flicker_raw", "flicker_final",
                 "changes_removed_by_inference", "changes_removed_vs_threshold",
                 *_COUNTS, "inference_changed_share", "inference_example",
                 "inference_note", "raw_vs_truth", "final_vs_truth"),
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences; contact flicker (changes per finger per "
        f"second): baseline + single threshold {s['flicker_baseline_threshold']:.2f} -> DexFlow "
        f"{s['flicker_dexflow']:.2f}, {100 * s['flicker_reduction_vs_baseline']:.0f} % fewer "
        f"(paper: 68 %); on DexFlow's trajectory single threshold {s['flicker_threshold']:.2f}, "
        f"hysteresis {s['flicker_raw']:.2f}, inference {s['flicker_final']:.2f} "
        f"({s['inference_changed']} states changed); F1 "
        f"{s.get('raw_vs_truth', {}).get('f1', float('nan')):.3f} -> "
        f"{s.get('final_vs_truth', {}).get('f1', float('nan')):.3f}"
    ),
)  # fmt: skip
