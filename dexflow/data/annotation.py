"""How the demo's recordings differ from its clean synthesis where real annotations do (and,
switched on, where object rotations read by the wrong convention would).

Functions of a sequence's random generator and :class:`~dexflow.params.DemoConfig`, used by
:mod:`dexflow.data.demo` (whose docstring lists every artefact): the annotated hand too deep in
the object while holding it (:func:`hold_penetration`), fingertip keypoints inside it
(:func:`tip_penetration`), the whole scene recorded tilted (:func:`rest_tilt`) and symmetric
objects' annotations spinning about their axis (:func:`annotation_spin`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.human.keypoints import FINGER_KEYPOINTS, FINGERS

if TYPE_CHECKING:
    from dexflow.objects.sdf import SignedDistanceGrid
    from dexflow.params import DemoConfig

__all__ = ["annotation_spin", "hold_penetration", "rest_tilt", "rigid_motion", "tip_penetration"]


def rigid_motion(rotvec, translation, centre: np.ndarray | None = None) -> np.ndarray:
    """(4, 4) rotation by ``rotvec`` about ``centre`` (default the origin) followed by
    ``translation``."""
    centre = np.zeros(3) if centre is None else np.asarray(centre, dtype=float)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    out[:3, 3] = centre - out[:3, :3] @ centre + translation
    return out


def rest_tilt(rng: np.random.Generator, cfg: DemoConfig, rest: np.ndarray) -> np.ndarray:
    """(4, 4) the turn of the whole recorded scene about a horizontal axis through the resting
    object's origin (``rest``), ``rest_tilt_deg`` with ``rest_tilt_probability``, else the
    identity."""
    if rng.random() >= cfg.rest_tilt_probability:
        return np.eye(4)
    heading = rng.uniform(0.0, 2 * np.pi)
    angle = np.radians(rng.uniform(*cfg.rest_tilt_deg))
    axis = np.array([np.cos(heading), np.sin(heading), 0.0])
    return rigid_motion(axis * angle, np.zeros(3), rest[:3, 3])


def annotation_spin(
    rng: np.random.Generator,
    cfg: DemoConfig,
    symmetry_axis: tuple[float, float, float] | None,
    ramp: np.ndarray,
    t_hold: int,
) -> np.ndarray:
    """(T, 4, 4) object-frame turns about ``symmetry_axis``: 0 until the hold (``t_hold``), then
    growing with the grip's closure ``ramp`` (T,) from the hold on, to ``spin_rad`` by the end
    (kept once put down); identities without an axis or outside ``spin_probability``."""
    out = np.repeat(np.eye(4)[None], len(ramp), axis=0)
    if symmetry_axis is None or rng.random() >= cfg.spin_probability:
        return out
    total = rng.uniform(*cfg.spin_rad) * rng.choice([-1.0, 1.0])
    held = np.zeros(len(ramp))
    held[t_hold:] = np.cumsum(ramp[t_hold:] > 0)
    share = held / max(held.max(), 1.0)
    axis = np.asarray(symmetry_axis, dtype=float)
    out[:, :3, :3] = Rotation.from_rotvec(np.outer(total * share, axis)).as_matrix()
    return out


def hold_penetration(
    rng: np.random.Generator,
    cfg: DemoConfig,
    ramp: np.ndarray,
    times: np.ndarray,
    approach_world: np.ndarray,
) -> np.ndarray:
    """(T, 3) shift of the annotated hand into the object while it holds it (0 elsewhere).

    Args:
        rng: The sequence's generator.
        cfg: ``hold_penetration_*`` say how often and how far.
        ramp: (T,) finger closure ramp: 0 on the reach, 1 while holding, back to 0 on release.
        times: (T,) frame times, seconds.
        approach_world: (T, 3) unit approach direction (hand -> object) per frame, world.
    """
    if not rng.random() < cfg.hold_penetration_probability:
        return np.zeros((len(ramp), 3))
    depth = rng.uniform(*cfg.hold_penetration_m)
    period, phase = rng.uniform(0.8, 2.0), rng.uniform(0, 2 * np.pi)
    wobble = cfg.hold_penetration_wobble_m * np.sin(2 * np.pi * times / period + phase)
    return (np.maximum(depth + wobble, 0.0) * ramp)[:, None] * approach_world


def tip_penetration(
    rng: np.random.Generator,
    cfg: DemoConfig,
    keypoints: np.ndarray,
    obj_pose: np.ndarray,
    sdf: SignedDistanceGrid,
    ramp: np.ndarray,
    times: np.ndarray,
    fingers: list[int],
) -> np.ndarray:
    """(T, 21, 3) displacement that puts the fingertip keypoints of ``fingers`` inside the object.

    Of ``fingers``, those whose tip keypoint is within 15 mm of the surface while held take
    part. With probability ``tip_inside_probability`` one of them has its tip keypoint
    ``D ~ min(Exponential(tip_depth_mean_m), tip_depth_max_m)`` inside the surface while held
    (plus a slow wobble of ``hold_penetration_wobble_m``), the others a random fraction of D; the
    finger's PIP and DIP follow a third and two thirds of its tip's displacement, along the
    surface normal at the tip. Weighted by ``ramp**3``, so it grows as the fingers close and
    vanishes on release; only where the tip is within 3 cm of the surface.

    Args:
        rng: The sequence's generator.
        cfg: ``tip_*`` and ``hold_penetration_wobble_m`` say how often and how deep.
        keypoints: (T, 21, 3) annotated keypoints, world.
        obj_pose: (T, 4, 4) object-to-world.
        sdf: The object's signed distance.
        ramp: (T,) finger closure ramp, 0..1.
        times: (T,) frame times, seconds.
        fingers: Fingers (0 thumb .. 4 little) that press on the object.
    """
    out = np.zeros_like(keypoints)
    rot, trans = obj_pose[:, :3, :3], obj_pose[:, :3, 3]
    held = ramp >= 0.99

    def tip_distance(chains: np.ndarray, moved: np.ndarray):
        tips = (keypoints + moved)[:, chains[:, -1]] - trans[:, None]
        dist, grad = sdf.query(np.einsum("tji,tfj->tfi", rot, tips), with_gradient=True)
        normal = np.einsum("tij,tfj->tfi", rot, grad)
        return dist, normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-9)

    if not fingers or not held.any():
        return out
    chains = np.array([FINGER_KEYPOINTS[FINGERS[f]] for f in fingers])  # (F, 4)
    dist, _ = tip_distance(chains, out)
    chains = chains[np.median(dist[held], axis=0) < 0.015]
    if not len(chains) or not rng.random() < cfg.tip_inside_probability:
        return out
    deepest = min(rng.exponential(cfg.tip_depth_mean_m), cfg.tip_depth_max_m)
    depth = deepest * rng.uniform(0.0, 1.0, size=len(chains))
    depth[rng.integers(len(chains))] = deepest
    period, phase = rng.uniform(0.8, 2.0), rng.uniform(0, 2 * np.pi)
    wobble = cfg.hold_penetration_wobble_m * np.sin(2 * np.pi * times / period + phase)
    target = -(depth[None] + wobble[:, None])  # (T, F)
    for _ in range(3):  # the surface is curved: a few Newton steps along its normal
        dist, normal = tip_distance(chains, out)
        weight = np.where(dist < 0.03, ramp[:, None] ** 3, 0.0)
        step = ((target - dist) * weight)[..., None] * normal  # (T, F, 3) of the tip
        for share, column in zip((1 / 3, 2 / 3, 1.0), (1, 2, 3), strict=True):
            out[:, chains[:, column]] += share * step
    return out
