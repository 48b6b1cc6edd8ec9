"""Human hand keypoint conventions: the MANO 21-joint order and the canonical wrist frame."""

from __future__ import annotations

import numpy as np

__all__ = [
    "FINGERS",
    "FINGERTIPS",
    "FINGER_KEYPOINTS",
    "INDEX_MCP",
    "KEYPOINT_NAMES",
    "MIDDLE_MCP",
    "NUM_KEYPOINTS",
    "WRIST",
    "wrist_frame",
]

NUM_KEYPOINTS = 21
FINGERS = ("thumb", "index", "middle", "ring", "little")
# Per finger, its four keypoints from the palm outwards (MCP, PIP, DIP, tip; for the thumb the
# first is the carpometacarpal joint, as in MANO).
FINGER_KEYPOINTS = {finger: tuple(range(1 + 4 * i, 5 + 4 * i)) for i, finger in enumerate(FINGERS)}
FINGERTIPS = tuple(chain[-1] for chain in FINGER_KEYPOINTS.values())
WRIST = 0
INDEX_MCP = FINGER_KEYPOINTS["index"][0]
MIDDLE_MCP = FINGER_KEYPOINTS["middle"][0]
KEYPOINT_NAMES = (
    "wrist",
    *(f"{finger}_{part}" for finger in FINGERS for part in ("mcp", "pip", "dip", "tip")),
)


def wrist_frame(keypoints: np.ndarray) -> np.ndarray:
    """Canonical wrist frame of a right hand, batched.

    Origin at the wrist, z from the wrist to the middle MCP, y towards the index MCP
    (orthogonalised against z), x = y × z, which points out of the palm.

    Args:
        keypoints: (..., 21, 3) keypoints.

    Returns:
        (..., 4, 4) transforms from the wrist frame to the keypoints' frame.
    """
    kp = np.asarray(keypoints, dtype=np.float64)
    origin = kp[..., WRIST, :]
    z = kp[..., MIDDLE_MCP, :] - origin
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    y = kp[..., INDEX_MCP, :] - origin
    y = y - (y * z).sum(-1, keepdims=True) * z
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    x = np.cross(y, z)
    frame = np.zeros((*kp.shape[:-2], 4, 4))
    frame[..., :3, 0] = x
    frame[..., :3, 1] = y
    frame[..., :3, 2] = z
    frame[..., :3, 3] = origin
    frame[..., 3, 3] = 1.0
    return frame
