"""Trajectory measures shared by stages and reports: smoothness and speed-distribution distance."""

from __future__ import annotations

import numpy as np

__all__ = ["fingertip_speeds", "rms_acceleration", "velocity_kl"]


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
