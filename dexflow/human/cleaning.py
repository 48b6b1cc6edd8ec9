"""Finding frames of a capture that carry no usable hand observation.

Real captures have dropouts (no hand, NaN or a ``valid = False`` flag) and tracking loss that
the tracker reports as valid: a default hand pose far away for a few frames, so the wrist
"teleports" tens of centimetres and back. Both are found here, once, for adapters (which mask
them on conversion) and for retargeting (which bridges them).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter

from dexflow.human.keypoints import MIDDLE_MCP, WRIST

__all__ = ["JUMP_WINDOW", "detect_bad_frames"]

JUMP_WINDOW = 15  # frames of the running median; bursts of up to 7 frames are outvoted
_SIZE_TOLERANCE = 0.3


def detect_bad_frames(
    keypoints: np.ndarray, valid: np.ndarray | None, jump_threshold_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Frames to leave unfitted.

    Args:
        keypoints: (T, 21, 3) keypoints (NaN allowed).
        valid: (T,) tracker validity, or None for all frames.
        jump_threshold_m: Wrist distance from its 15-frame running median (over tracked frames)
            beyond which a frame counts as tracking loss.

    Returns:
        observed (T,): tracked, finite and not lost; lost (T,): tracking loss reported as valid
        (a wrist jump, or a wrist-to-middle-MCP length 30 % off the sequence median).
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    tracked = np.isfinite(kp).all(axis=(1, 2))
    if valid is not None:
        tracked &= np.asarray(valid, dtype=bool)
    lost = np.zeros(len(kp), dtype=bool)
    idx = np.flatnonzero(tracked)
    if len(idx) >= 3:
        wrist = kp[idx, WRIST]
        reference = median_filter(wrist, size=(min(JUMP_WINDOW, len(idx) | 1), 1), mode="nearest")
        jump = np.linalg.norm(wrist - reference, axis=-1) > jump_threshold_m
        size = np.linalg.norm(kp[idx, MIDDLE_MCP] - kp[idx, WRIST], axis=-1)
        odd = np.abs(size / np.median(size) - 1.0) > _SIZE_TOLERANCE
        lost[idx[jump | odd]] = True
    return tracked & ~lost, lost
