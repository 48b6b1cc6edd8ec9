"""A grasp carried as one body: the base's targets that move a held grasp with the human's
fingertips (stage track's grip schedules with the hold ``grasp``, :mod:`dexflow.sim.track`).

A human grasp carries the object as a rigid constellation of fingertips while the wrist turns
under it; a robot grasp held as formed at the lift, on a base that follows the wrist, misses
the fingertips by centimetres. :func:`grasp_carry` moves the base with the constellation
instead.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from dexflow.geometry import rigid_fit
from dexflow.hands.robot import base_transform
from dexflow.sim.replay_criteria import lift_frame

__all__ = ["grasp_carry"]


def _euler_near(rotations: np.ndarray, before: np.ndarray) -> np.ndarray:
    """(T, 3) intrinsic x-y-z Euler angles of ``rotations (T, 3, 3)`` (the base joints'
    convention, :func:`dexflow.hands.robot.base_transform`), each frame the one of the two
    equivalent solutions, shifted by whole turns, nearest the frame before (``before (3,)``
    for the first): the base's hinge targets move the short way, never through a turn."""
    raw = Rotation.from_matrix(rotations).as_euler("XYZ")
    other = np.stack([raw[:, 0] + np.pi, np.pi - raw[:, 1], raw[:, 2] + np.pi], axis=1)
    out = np.empty_like(raw)
    previous = np.asarray(before, dtype=float)
    for t in range(len(raw)):  # sequential: each frame's choice depends on the last
        options = [
            c + 2 * np.pi * np.round((previous - c) / (2 * np.pi)) for c in (raw[t], other[t])
        ]
        previous = min(options, key=lambda c: float(np.abs(c - previous).sum()))
        out[t] = previous
    return out


def _continuous_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """(T, 3) rotation vectors of the same rotations, each the equivalent one (angle less a whole
    turn about the same axis) nearest the frame before: continuous through half a turn, where
    the shortest one flips (a carried object may be turned over), so it can be interpolated
    and smoothed."""
    out = np.array(rotvec, dtype=float)
    for t in range(1, len(out)):  # sequential: each frame's choice depends on the last
        angle = np.linalg.norm(out[t])
        if angle < 1e-9:
            continue
        axis = out[t] / angle
        turns = np.round((axis @ out[t - 1] - angle) / (2 * np.pi))
        out[t] = axis * (angle + 2 * np.pi * turns)
    return out


def _smooth_keeping_ends(x: np.ndarray, sigma: float) -> np.ndarray:
    """``x (T, D)`` smoothed over time by a Gaussian of ``sigma`` frames, each end extended by
    its point reflection (``2 x[0] - x[k]``): the ends keep their values and a steady motion
    stays as it is, where padding with the end value would lag it."""
    pad = min(int(np.ceil(4 * sigma)), len(x) - 1)
    if sigma <= 0 or pad < 1:
        return np.array(x, dtype=float)
    extended = np.concatenate(
        [2 * x[0] - x[pad:0:-1], x, 2 * x[-1] - x[-2 : -pad - 2 : -1]], axis=0
    )
    return gaussian_filter1d(extended, sigma, axis=0, mode="nearest")[pad : pad + len(x)]


def grasp_carry(
    base: np.ndarray,
    tips: np.ndarray,
    poses: np.ndarray,
    window: tuple[int, int, int],
    smooth_frames: float,
) -> np.ndarray:
    """(T, 6) the base's targets of a grasp carried as one body: from the lift to the window's
    end, the base at the lift moved by the human fingertips' rigid motion since then; ``base
    (T, 6)`` elsewhere.

    A human grasp carries the object nearly as a rigid constellation (on 28 real DexYCB
    captures, Shadow's scale, the five fingertips keep their shape at the lift to 8 mm during
    the carry: the residual of the fit below), while the wrist turns under it and the recorded
    object pose slides against it: fingers held as they are at the lift on a base that
    follows the wrist miss the fingertips by 41 mm during the carry, on a base moved with the
    constellation by 10 mm (refine: 5 mm). The motion of each observed
    frame ``t`` is the least-squares rigid transform ``M(t)`` taking the fingertips at the
    lift to those at ``t`` (:func:`dexflow.geometry.rigid_fit`; the first observed carry frame
    stands in for an unobserved lift); unobserved frames take the motion of the nearest
    observed ones (linear between, held at the ends), and the motion is smoothed by a Gaussian
    of ``smooth_frames`` frames, its ends kept (the fit of five jittering points turns by
    hundredths of a radian per frame, more where a finger moves; the servos are fed the
    targets' velocity). The base then is
    ``M(t) B(lift)``, ``M(t)`` a turn about the fingertips' centre at the lift and a shift.

    Args:
        base: (T, 6) the base's targets (translation, x-y-z Euler angles unwrapped).
        tips: (T, K, 3) the human fingertips, NaN where not observed.
        poses: (T, 4, 4) the recorded object poses (for the lift, :func:`lift_frame`).
        window: ``(start, first_contact, end)``.
    """
    out = np.array(base, dtype=float)
    lift, end = lift_frame(poses, window), window[2]
    frames = np.arange(lift, end + 1)
    observed = frames[np.isfinite(tips[frames]).all(axis=(1, 2))]
    if len(frames) < 2 or len(observed) == 0:
        return out
    reference = tips[observed[0]]
    middle = reference.mean(axis=0)  # turns are about the fingertips' centre, not the origin
    motion = rigid_fit(reference, tips[observed])  # (n, 4, 4)
    rotvec = _continuous_rotvec(Rotation.from_matrix(motion[:, :3, :3]).as_rotvec())
    shift = tips[observed].mean(axis=1) - middle
    steps = np.concatenate([rotvec, shift], axis=1)  # (n, 6)
    steps = np.stack([np.interp(frames, observed, steps[:, i]) for i in range(6)], axis=1)
    steps[0] = 0.0  # the lift itself: where the grasp is formed
    steps = _smooth_keeping_ends(steps, smooth_frames)
    rot = Rotation.from_rotvec(steps[:, :3]).as_matrix()  # (n, 3, 3)
    lifted = base_transform(torch.as_tensor(out[lift : lift + 1])).numpy()[0]
    turned = rot @ lifted[:3, :3]
    out[frames, :3] = rot @ (lifted[:3, 3] - middle) + middle + steps[:, 3:]
    out[frames, 3:6] = _euler_near(turned, out[lift, 3:6])
    return out
