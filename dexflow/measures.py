"""Measures shared by stages and reports: hand-object and self-penetration, smoothness, speeds.

Each measure has one definition here; stage modules (simulate, metrics, ...) import it from this
leaf module and never from each other.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from scipy.spatial import ConvexHull

from dexflow.geometry import world_to_object

if TYPE_CHECKING:
    from dexflow.hands.robot import RobotHand
    from dexflow.objects.sdf import SignedDistanceGrid

__all__ = [
    "CD_CAP_M",
    "FRAME_CHUNK",
    "SelfCollision",
    "capped_contact_distance",
    "chamfer_per_frame",
    "contact_counts",
    "contact_distance",
    "finger_minimum",
    "fingertip_speeds",
    "fingertips",
    "finite_mean",
    "flicker_reduction",
    "frame_chunks",
    "grip_drift",
    "hand_object_depths",
    "penetration_depth",
    "precision_recall",
    "rms_acceleration",
    "self_collision",
    "state_flicker",
    "surface_distances",
    "velocity_kl",
]


# Frames per batch where per-frame work on the hand's surface points (about 2,000 points, tens of
# kB per frame for each intermediate array) would otherwise make memory grow with the length of
# a sequence: a 10-minute capture is 18,000 frames.
FRAME_CHUNK = 256


def frame_chunks(num_frames: int, size: int = FRAME_CHUNK) -> list[slice]:
    """Consecutive slices of at most ``size`` frames covering ``range(num_frames)``."""
    return [slice(a, min(a + size, num_frames)) for a in range(0, num_frames, size)]


def finger_minimum(distances: np.ndarray, masks) -> np.ndarray:
    """(T, N) point distances -> (T, F) smallest distance of each finger's points (``masks``)."""
    return np.stack([np.where(m, distances, np.inf).min(axis=1) for m in masks], axis=1)


def hand_object_depths(
    hand: RobotHand, q: np.ndarray, obj_pose: np.ndarray, sdf: SignedDistanceGrid
) -> tuple[np.ndarray, np.ndarray]:
    """Penetration depth (T,) (:func:`penetration_depth`) and each finger's smallest signed
    distance (T, F) (fingers in the hand config's order), over :func:`frame_chunks`."""
    masks = list(hand.finger_point_masks.values())
    depth, per_finger = np.zeros(len(q)), np.zeros((len(q), len(masks)))
    for frames in frame_chunks(len(q)):
        distances, _ = surface_distances(hand, q[frames], obj_pose[frames], sdf)
        depth[frames] = penetration_depth(distances)
        per_finger[frames] = finger_minimum(distances, masks)
    return depth, per_finger


def surface_distances(
    hand: RobotHand, q: np.ndarray, obj_pose: np.ndarray, sdf: SignedDistanceGrid
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances of the hand's surface points to the object mesh, batched over frames.

    The points are :meth:`RobotHand.surface`: samples on the hand's collision geometry (every
    link not in the hand config's ``surface_exclude``). The distance is the object's mesh signed
    distance grid (winding-number sign, :mod:`dexflow.objects.sdf`), not its convex parts.

    Args:
        hand: The robot hand.
        q: (T, dof) configurations.
        obj_pose: (T, 4, 4) object poses (object mesh -> world).
        sdf: The object's signed distance grid, in object coordinates.

    Returns:
        Distances (T, N) in metres (negative inside the object) and world points (T, N, 3).
    """
    with torch.no_grad():
        points, _ = hand.surface(torch.as_tensor(q, dtype=hand.dtype), normals=False)
    points = points.cpu().numpy()
    return sdf.query(world_to_object(points, obj_pose)), points


def penetration_depth(distances: np.ndarray) -> np.ndarray:
    """Per frame the depth (m, >= 0) of the deepest point: ``max(0, -min_n d)``; (T, N) -> (T,)."""
    return np.clip(-distances.min(axis=1), 0.0, None)


def rms_acceleration(q: np.ndarray, fps: float) -> float:
    """Root-mean-square joint acceleration, rad/s² (central second differences).

    Args:
        q: (T, J) joint angles (pass only the joints to measure, e.g. without the base).
        fps: Frame rate.
    """
    q = np.asarray(q, dtype=np.float64)
    if len(q) < 3:
        return float("nan")
    acc = np.diff(q, n=2, axis=0) * fps**2
    return float(np.sqrt(np.mean(acc**2)))


def fingertips(hand: RobotHand, q: np.ndarray) -> np.ndarray:
    """(..., F, 3) the world positions of the fingertips (``hand.fingertip_keypoints``, the
    keypoints matched to the human's, as the fingertip error measures them) at ``q (..., dof)``,
    by the hand's forward kinematics."""
    q = np.asarray(q)
    with torch.no_grad():
        points = hand.keypoints(
            torch.as_tensor(q.reshape(-1, q.shape[-1]), dtype=hand.dtype, device=hand.device)
        )
    tips = points[:, hand.fingertip_keypoints].cpu().numpy()
    return tips.reshape(*q.shape[:-1], *tips.shape[1:])


def fingertip_speeds(tips: np.ndarray, fps: float, mask: np.ndarray | None = None) -> np.ndarray:
    """Speeds (m/s) of fingertips between consecutive frames where both frames are in ``mask``.

    Args:
        tips: (T, F, 3) fingertip positions.
        fps: Frame rate.
        mask: (T,) frames to use; all if None.

    Returns:
        1-D array of speeds of every fingertip over every usable frame pair.
    """
    tips = np.asarray(tips, dtype=np.float64)
    speed = np.linalg.norm(np.diff(tips, axis=0), axis=-1) * fps  # (T-1, F)
    ok = np.ones(len(speed), dtype=bool) if mask is None else mask[1:] & mask[:-1]
    speed = speed[ok]
    return speed[np.isfinite(speed)].reshape(-1)


def grip_drift(tips: np.ndarray, obj_pose: np.ndarray, iterations: int = 50) -> float:
    """How far fingertips slide over an object across frames: per fingertip, the mean distance
    (m) of its positions in the object's frame from their geometric median, averaged over the
    fingertips (NaN for fewer than 2 frames).

    A grasp whose fingertips stay put on the object can match such recorded fingertips no
    closer than this while it moves the object exactly as recorded: for robot fingertips ``c``
    fixed in the object's frame, the recorded pose ``T_t``, the simulated one ``S_t`` and the
    recorded tips ``h_t``, ``|T_t c - h_t| <= |S_t c - h_t| + |T_t c - S_t c|`` (fingertip error
    plus the object's displacement at the fingertips), and the geometric median is the ``c``
    that minimises the mean of the left side.

    Args:
        tips: (T, F, 3) fingertip positions in the world.
        obj_pose: (T, 4, 4) object poses.
        iterations: Weiszfeld iterations of the geometric median (converged to well below a
            micrometre for spreads of centimetres).
    """
    local = world_to_object(np.asarray(tips, dtype=np.float64), obj_pose)  # (T, F, 3)
    if len(local) < 2:
        return float("nan")
    median = local.mean(axis=0)
    for _ in range(iterations):  # Weiszfeld: weights 1 / distance, all fingertips at once
        weight = 1.0 / np.maximum(np.linalg.norm(local - median, axis=-1), 1e-9)  # (T, F)
        median = (weight[..., None] * local).sum(axis=0) / weight.sum(axis=0)[:, None]
    return float(np.linalg.norm(local - median, axis=-1).mean())


def velocity_kl(
    reference: np.ndarray, other: np.ndarray, bins: int = 30, eps: float = 1e-6
) -> float:
    """KL divergence KL(P_reference || P_other) of two speed histograms on shared bins.

    Bins span 0 to the 99th percentile of both samples pooled; each histogram gets ``eps``
    added to every bin before normalising, so empty bins do not make it infinite. Identical
    samples give 0.
    """
    reference, other = np.asarray(reference), np.asarray(other)
    if len(reference) == 0 or len(other) == 0:
        return float("nan")
    top = np.percentile(np.concatenate([reference, other]), 99) or 1.0
    edges = np.linspace(0.0, top, bins + 1)
    p = np.histogram(np.clip(reference, 0, top), edges)[0] + eps
    r = np.histogram(np.clip(other, 0, top), edges)[0] + eps
    p, r = p / p.sum(), r / r.sum()
    return float(np.sum(p * np.log(p / r)))


def contact_distance(per_finger: np.ndarray, contact: np.ndarray) -> np.ndarray:
    """Per frame the mean over fingers in contact of their distance clipped at 0 (NaN if none).

    Args:
        per_finger: (T, F) each finger's smallest signed distance to the object.
        contact: (T, F) contact states.

    Returns:
        (T,) contact distance in the unit of ``per_finger``.
    """
    contact = np.asarray(contact, dtype=bool)
    clipped = np.where(contact, np.clip(per_finger, 0.0, None), 0.0)
    count = contact.sum(axis=1)
    return np.where(count > 0, clipped.sum(axis=1) / np.maximum(count, 1), np.nan)


CD_CAP_M = 0.01  # BODex / DexGraspBench: a finger farther than 1 cm counts as 1 cm


def capped_contact_distance(per_finger: np.ndarray, grasp: np.ndarray) -> np.ndarray:
    """BODex's contact distance (DexGraspBench's ``contact_dist``), per frame of a grasp.

    Every finger of the hand counts, touching or not: its smallest signed distance to the
    object, clipped to ``[0, CD_CAP_M]`` (inside counts as 0, farther than 1 cm as 1 cm), then
    the mean over the fingers. A grasp whose fingers all rest on the surface scores 0; a finger
    that misses the object adds ``CD_CAP_M / F``. BODex evaluates one static grasp; a sequence's
    grasp frames are those where stage contact finds any finger in contact (``grasp``), and the
    other frames are NaN.

    Args:
        per_finger: (T, F) each finger's smallest signed distance to the object (m).
        grasp: (T,) the frames that are a grasp.

    Returns:
        (T,) contact distance (m), NaN outside the grasp.
    """
    capped = np.clip(per_finger, 0.0, CD_CAP_M).mean(axis=1)
    return np.where(np.asarray(grasp, dtype=bool), capped, np.nan)


def state_flicker(states: np.ndarray, fps: float) -> float:
    """State changes per finger per second of (T, F) boolean states.

    The changes are counted between consecutive frames, so the time they happen in is the
    ``T - 1`` frame intervals, ``(T - 1) / fps`` seconds; 0 for fewer than two frames.
    """
    states = np.asarray(states, dtype=bool)
    if len(states) < 2:
        return 0.0
    changes = np.count_nonzero(states[1:] != states[:-1])
    return float(changes / states.shape[1] / ((len(states) - 1) / fps))


def flicker_reduction(before: float, after: float) -> float:
    """The share of the flicker ``before`` that ``after`` removes: ``1 - after / before``.

    Both are :func:`state_flicker` values (state changes per finger per second) of the same
    frames, fingers and sequences, so the share is also that of the state changes removed.
    Negative where ``after`` flickers more; NaN where ``before`` is 0 or either is NaN (nothing
    to remove: no share is defined).
    """
    if not before > 0 or not np.isfinite(after):
        return float("nan")
    return float(1.0 - after / before)


def contact_counts(predicted: np.ndarray, truth: np.ndarray) -> dict[str, int]:
    """True positives, false positives and false negatives of (T, F) contact states.

    Counts (not rates) so that sequences pool: :func:`precision_recall` of the summed counts
    is the precision and recall over all frames and fingers of all sequences.
    """
    predicted, truth = np.asarray(predicted, dtype=bool), np.asarray(truth, dtype=bool)
    return {
        "tp": int(np.count_nonzero(predicted & truth)),
        "fp": int(np.count_nonzero(predicted & ~truth)),
        "fn": int(np.count_nonzero(~predicted & truth)),
    }


def precision_recall(tp: int, fp: int, fn: int) -> dict[str, float]:
    """Precision, recall and F1 from counts (0 where a denominator is 0)."""
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"precision": precision, "recall": recall, "f1": f1}


def finite_mean(values) -> float:
    """Mean of the finite values (NaN where there is none): how every per-frame measure is
    averaged over frames, and every per-sequence one over sequences."""
    values = np.asarray(values, dtype=float).ravel()
    values = values[np.isfinite(values)]
    return float(values.mean()) if len(values) else float("nan")


def chamfer_per_frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Symmetric Chamfer distance per frame between point sets (T, A, 3) and (T, B, 3)."""
    d = np.linalg.norm(a[:, :, None] - b[:, None], axis=-1)  # (T, A, B)
    return 0.5 * (d.min(axis=2).mean(axis=1) + d.min(axis=1).mean(axis=1))


class SelfCollision:
    """Depth of hand surface points inside the collision shapes of non-adjacent links.

    Boxes, cylinders and meshes are treated as convex polytopes (their convex hull's planes:
    exact depth inside, which is all a penetration depth needs); spheres and capsules exactly.
    """

    def __init__(self, hand: RobotHand) -> None:
        self.hand = hand
        model = hand.model
        has_geometry = {g.link for g in model.geometries}

        def geometric_parent(link: str) -> str | None:
            parent = model.parents.get(link, (None, None))[0]
            while parent is not None and parent not in has_geometry:
                parent = model.parents.get(parent, (None, None))[0]
            return parent

        self.shapes = []  # (link, kind, data)
        for g in model.geometries:
            vertices = np.asarray(g.mesh.vertices)
            center = vertices.mean(axis=0)
            bound = (center, float(np.linalg.norm(vertices - center, axis=1).max()) + 1e-6)
            if g.kind in ("sphere", "capsule"):
                middle = g.transform[:3, 3]
                axis = g.transform[:3, 2] * (g.size[1] if g.kind == "capsule" else 0.0)
                data = (middle - axis, middle + axis, g.size[0])
                self.shapes.append((g.link, "capsule", data, bound))
            else:
                hull = ConvexHull(vertices)
                self.shapes.append((g.link, "polytope", hull.equations, bound))
        self.links = list(dict.fromkeys(shape[0] for shape in self.shapes))
        point_links = np.asarray(hand.surface_point_links)
        parents = {link: geometric_parent(link) for link in has_geometry}
        self.masks = []  # per shape: which surface points may penetrate it
        for link, *_ in self.shapes:
            adjacent = {link, parents.get(link)} | {k for k, p in parents.items() if p == link}
            self.masks.append(~np.isin(point_links, sorted(a for a in adjacent if a)))
        zero_chunk = self._chunk(hand.zero().numpy())
        for s in range(len(self.shapes)):  # pairs overlapping at the zero pose
            _, cols, depth = self._depths(zero_chunk, s, self.masks[s])
            inside = np.flatnonzero(self.masks[s])[cols[depth > 1e-6]]
            overlapping = sorted({point_links[i] for i in inside})
            self.masks[s] &= ~np.isin(point_links, overlapping)

    def _chunk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World surface points (T, N, 3) and the shapes' link transforms (T, L, 4, 4)."""
        with torch.no_grad():
            qt = torch.as_tensor(q, dtype=self.hand.dtype)
            points = self.hand.surface(qt, normals=False)[0].numpy()
            return points, self.hand.link_transforms(qt, self.links).numpy()

    def _depths(self, chunk: tuple[np.ndarray, np.ndarray], s: int, mask: np.ndarray):
        """The surface points in ``mask`` near shape ``s`` (within its bounding sphere) in
        each frame of ``chunk`` (:meth:`_chunk`): their frame rows (K,), their columns among
        the points of ``mask`` (K,) and their depth inside the shape (K,), 0 where outside.
        Sparse, so that a frame's deepest point costs only the points near each shape."""
        points, frames = chunk
        link, kind, data, (center, radius) = self.shapes[s]
        t = frames[:, self.links.index(link)]
        rot, pos = t[:, :3, :3], t[:, :3, 3]
        candidates = points[:, mask]  # (T, M, 3)
        center_world = rot @ center + pos  # (T, 3)
        near = np.sum((candidates - center_world[:, None]) ** 2, axis=-1) < radius**2  # cull
        rows, cols = np.nonzero(near)
        if len(rows) == 0:
            return rows, cols, np.zeros(0)
        # only the points near the shape go to its frame: x = Rᵀ (p - o)
        x = ((candidates[rows, cols] - pos[rows])[:, None, :] @ rot[rows])[:, 0]  # (K, 3)
        if kind == "capsule":
            a, b, r = data
            ab = b - a
            u = np.clip(((x - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
            depth = r - np.linalg.norm(x - (a + u[:, None] * ab), axis=-1)
        else:
            depth = -(x @ data[:, :3].T + data[:, 3]).max(axis=-1)
        return rows, cols, np.clip(depth, 0.0, None)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """(T,) self-penetration depth (m) of configurations ``q (T, dof)``."""
        q = np.asarray(q)
        out = np.zeros(len(q))
        for frames in frame_chunks(len(q)):  # memory bounded by a chunk, not the sequence
            chunk = self._chunk(q[frames])
            deepest = np.zeros(len(chunk[0]))
            for s, mask in enumerate(self.masks):
                rows, _, depth = self._depths(chunk, s, mask)
                np.maximum.at(deepest, rows, depth)
            out[frames] = deepest
        return out


_SELF: dict[int, SelfCollision] = {}


def self_collision(hand: RobotHand) -> SelfCollision:
    """One :class:`SelfCollision` per hand and process."""
    if id(hand) not in _SELF:
        _SELF[id(hand)] = SelfCollision(hand)
    return _SELF[id(hand)]
