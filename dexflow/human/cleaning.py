"""Finding frames of a capture that carry no usable hand observation.

Real captures have dropouts (no hand, NaN or a ``valid = False`` flag) and tracking loss that
the tracker reports as valid: a default hand pose far away for a few frames, so the wrist
"teleports" tens of centimetres and back. DexYCB leaves unannotated frames at the MANO template
hand, ~0.8 m from the real one, most often in a run at the START of a sequence (up to 25
frames), sometimes at its end. Both are found here, once, for adapters (which mask them on
conversion) and for retargeting (which bridges them).

Tracking loss is found by continuity, not by distance from a running reference (which a run at
the start would become):

1. the tracked frames are cut into *segments* wherever the wrist moves implausibly far between
   consecutive tracked frames ``a < b``:
   ``||w_b - w_a|| > jump_threshold_m + max_wrist_speed_mps * (b - a - 1) / fps``
   (a dropout gap between them allows the distance the wrist can travel meanwhile);
2. segments are linked in time order into *groups*: a segment joins the group whose last frame
   it plausibly continues by the same rule (the nearest one where several do), or starts a new
   group;
3. the group with the most frames is the hand; every other group is tracking loss.

So a lost run anywhere (start, middle, end) and of any length shorter than the real hand's is
found, and a real frame is only masked if the real hand itself jumps by more than the threshold.
A wrist-to-middle-MCP length 30 % off the hand's median marks single odd frames as well.
"""

from __future__ import annotations

import numpy as np

from dexflow.human.keypoints import MIDDLE_MCP, WRIST

__all__ = ["MAX_WRIST_SPEED_MPS", "detect_bad_frames", "nearest_index"]

# Fastest wrist motion assumed across a dropout gap (hand-object manipulation; the fastest real
# DexYCB frame-to-frame wrist step is ~1.9 m/s, sustained motion is far slower).
MAX_WRIST_SPEED_MPS = 2.0
_SIZE_TOLERANCE = 0.3


def _segment_starts(wrist: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """Start indices of runs of ``wrist (N, 3)`` without a step over ``threshold (N - 1,)``."""
    step = np.linalg.norm(np.diff(wrist, axis=0), axis=-1)
    return np.concatenate([[0], np.flatnonzero(step > threshold) + 1])


def detect_bad_frames(
    keypoints: np.ndarray,
    valid: np.ndarray | None,
    jump_threshold_m: float,
    *,
    fps: float = 30.0,
    max_wrist_speed_mps: float = MAX_WRIST_SPEED_MPS,
) -> tuple[np.ndarray, np.ndarray]:
    """Frames to leave unfitted.

    Args:
        keypoints: (T, 21, 3) keypoints (NaN allowed).
        valid: (T,) tracker validity, or None for all frames.
        jump_threshold_m: Largest plausible wrist displacement between consecutive frames;
            farther means the hand was lost (or found again).
        fps: Frame rate, Hz (converts dropout gaps to time).
        max_wrist_speed_mps: Wrist speed allowed across a dropout gap, m/s.

    Returns:
        observed (T,): tracked, finite and not lost; lost (T,): tracking loss reported as valid
        (frames outside the largest continuous group, see the module docstring, or with a
        wrist-to-middle-MCP length 30 % off the hand's median).

    Raises:
        ValueError: If ``keypoints`` is not (T, 21, 3) or ``valid`` is not (T,).
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.ndim != 3 or kp.shape[1:] != (21, 3):
        raise ValueError(f"keypoints: expected (T, 21, 3), found {kp.shape}")
    tracked = np.isfinite(kp).all(axis=(1, 2))
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (len(kp),):
            raise ValueError(f"valid: expected ({len(kp)},), found {valid.shape}")
        tracked &= valid
    lost = np.zeros(len(kp), dtype=bool)
    idx = np.flatnonzero(tracked)
    if len(idx) < 2:
        return tracked, lost
    wrist = kp[idx, WRIST]
    per_gap_frame = max_wrist_speed_mps / fps
    starts = _segment_starts(wrist, jump_threshold_m + per_gap_frame * (np.diff(idx) - 1))
    ends = np.append(starts[1:], len(idx)) - 1

    group_of = np.empty(len(starts), dtype=int)
    last_end: list[int] = []  # per group, the index (into idx) of its last frame
    for s, (start, end) in enumerate(zip(starts, ends, strict=True)):
        tails = np.asarray(last_end, dtype=int)
        if len(tails):
            dist = np.linalg.norm(wrist[start] - wrist[tails], axis=-1)
            allowed = jump_threshold_m + per_gap_frame * (idx[start] - idx[tails] - 1)
            fits = dist <= allowed
        if len(tails) and fits.any():
            g = int(np.flatnonzero(fits)[np.argmin(dist[fits])])
            last_end[g] = int(end)
        else:
            g = len(last_end)
            last_end.append(int(end))
        group_of[s] = g
    group_frames = np.bincount(group_of, weights=ends - starts + 1)
    hand = np.repeat(group_of == int(np.argmax(group_frames)), ends - starts + 1)

    size = np.linalg.norm(kp[idx, MIDDLE_MCP] - kp[idx, WRIST], axis=-1)
    odd = np.abs(size / np.median(size[hand]) - 1.0) > _SIZE_TOLERANCE
    lost[idx[~hand | odd]] = True
    return tracked & ~lost, lost


def nearest_index(idx: np.ndarray, n: int) -> np.ndarray:
    """(n,) for every frame 0..n-1 the nearest of the sorted frames ``idx`` (the earlier one
    on a tie), in O(n log len(idx)) memory-light steps (a frames x frames table would take
    0.3 GB at 6,000 frames)."""
    frames = np.arange(n)
    after = np.clip(np.searchsorted(idx, frames), 0, len(idx) - 1)
    before = np.clip(after - 1, 0, len(idx) - 1)
    left, right = idx[before], idx[after]
    return np.where(np.abs(frames - left) <= np.abs(right - frames), left, right)
