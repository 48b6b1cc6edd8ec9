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
"""

from __future__ import annotations

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
from dexflow.measures import contact_counts, frame_chunks, precision_recall, state_flicker
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import ContactParams, PipelineParams
from dexflow.resume import StageOutput
from dexflow.runner import StageSpec

__all__ = [
    "STAGE",
    "contact_states",
    "finger_distances",
    "hysteresis",
    "infer_frames",
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
    hand: RobotHand, trajectory_file: Path, aligned: StageDir, params: ContactParams
) -> tuple[ContactResult, dict]:
    """Everything for one sequence: the result to save and statistics."""
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
    stats = {
        "frames": len(q),
        "changes_threshold": int(state_changes(threshold).sum()),
        "changes_raw": int(state_changes(raw).sum()),
        "changes_final": int(state_changes(final).sum()),
        "flicker_raw": state_flicker(raw, seq.fps),
        "flicker_final": state_flicker(final, seq.fps),
        "contact_fraction": float(final.mean()),
    }
    if seq.gt_contact is not None:
        from dexflow.human.keypoints import FINGERS

        cols = [FINGERS.index(f) for f in hand.spec.fingers]
        truth = seq.gt_contact[:, cols]
        stats["raw_vs_truth"] = contact_counts(raw, truth)
        stats["final_vs_truth"] = contact_counts(final, truth)
    return result, stats


def run_contact(params: PipelineParams, layout: Layout) -> dict:
    """Stage runner over every retargeted sequence (``layout.retarget("dexflow")``)."""
    source, aligned, out = layout.retarget("dexflow"), layout.scale_align, layout.contact
    stage = StageOutput(
        out,
        "contact",
        {"hand": params.hand, "contact": params.contact},
        inputs=(source, aligned, layout.hand_files),
    )
    files = stage.start()
    spec = staged_spec(params.hand, layout.hand_files.root)

    def one(path: Path) -> dict:
        torch.set_num_threads(1)
        hand = cached_hand(spec, None)
        result, stats = contact_sequence(hand, path, aligned, params.contact)
        write_contact(out.sequence(path), result)
        return stats

    tally = stage.run(one, files, params.run)
    ok, seconds = tally.ok, tally.seconds
    single = sum(s["changes_threshold"] for s in ok)
    raw = sum(s["changes_raw"] for s in ok)
    final = sum(s["changes_final"] for s in ok)
    summary = {
        **tally.counts("contact"),
        "changes_raw": raw,
        "changes_final": final,
        "changes_threshold": single,
        "fluctuation_removed": (raw - final) / raw if raw else 0.0,
        "fluctuation_removed_vs_threshold": (single - final) / single if single else 0.0,
        "flicker_raw": tally.mean("flicker_raw", 0.0),
        "flicker_final": tally.mean("flicker_final", 0.0),
    }
    truth = [s for s in ok if "raw_vs_truth" in s]
    for which in ("raw_vs_truth", "final_vs_truth"):
        if truth:
            counts = {k: sum(s[which][k] for s in truth) for k in ("tp", "fp", "fn")}
            summary[which] = precision_recall(**counts)
    summary["sequences"] = dict(sorted(tally.sequences.items()))
    stage.finish(summary)
    frames = summary["num_frames"]
    return {**summary, "timing": {"frames_per_second": frames / seconds if seconds else 0.0}}


STAGE = StageSpec(
    name="contact",
    run=run_contact,
    metric_keys=("num_sequences", "num_ok", "num_failed", "num_frames", "fluctuation_removed",
                 "fluctuation_removed_vs_threshold", "flicker_raw", "flicker_final",
                 "raw_vs_truth", "final_vs_truth"),
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences; fluctuations removed: "
        f"{100 * s['fluctuation_removed']:.0f} % of raw (hysteresis) states, "
        f"{100 * s['fluctuation_removed_vs_threshold']:.0f} % of single-threshold states; "
        f"{s['flicker_raw']:.2f} -> {s['flicker_final']:.2f} changes per "
        f"finger per second; F1 {s.get('raw_vs_truth', {}).get('f1', float('nan')):.3f} -> "
        f"{s.get('final_vs_truth', {}).get('f1', float('nan')):.3f}"
    ),
)  # fmt: skip
