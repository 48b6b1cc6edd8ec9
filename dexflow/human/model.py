"""An anatomical human hand model: 20 joint angles -> the 21 MANO-order keypoints.

The model is a kinematic skeleton with adult bone lengths, not a mesh. It exists so that dexflow
can generate realistic demonstrations without licensed MANO files. The frame is the canonical
wrist frame of a right hand (:func:`dexflow.human.keypoints.wrist_frame`): origin at the wrist,
z from the wrist to the middle MCP, y towards the index MCP (orthogonalised against z), and
x = y × z, out of the palm. Every finger flexes towards +x.

Joint angles, radians, in :data:`JOINT_NAMES` order (per finger: abduction or the thumb's
carpometacarpal pair, then flexion from the palm outwards). Each finger segment is a capsule
(:attr:`HandShape.radii`) so that the skin, not only the bone axis, can touch an object.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.geometry import transform_points
from dexflow.human.keypoints import FINGER_KEYPOINTS, FINGERS, NUM_KEYPOINTS

__all__ = ["JOINT_NAMES", "HandShape", "finger_capsules", "forward_keypoints"]

JOINT_NAMES = (
    "thumb_cmc_flex",
    "thumb_cmc_abd",
    "thumb_mcp",
    "thumb_ip",
    *(f"{f}_{j}" for f in FINGERS[1:] for j in ("abd", "mcp", "pip", "dip")),
)


def _default_bases() -> dict[str, np.ndarray]:
    return {
        "thumb": np.array([0.012, 0.022, 0.028]),
        "index": np.array([0.0, 0.024, 0.086]),
        "middle": np.array([0.0, 0.0, 0.090]),
        "ring": np.array([0.003, -0.019, 0.084]),
        "little": np.array([0.008, -0.036, 0.075]),
    }


def _default_bones() -> dict[str, tuple[float, float, float]]:
    # Thumb: metacarpal, proximal, distal; fingers: proximal, middle, distal phalanx (to the
    # end of the fingertip). Adult averages, metres.
    return {
        "thumb": (0.046, 0.033, 0.029),
        "index": (0.042, 0.025, 0.022),
        "middle": (0.046, 0.028, 0.023),
        "ring": (0.043, 0.027, 0.022),
        "little": (0.034, 0.020, 0.020),
    }


@dataclass(frozen=True)
class HandShape:
    """Bone geometry of one (right) hand, in metres, in the canonical wrist frame.

    Attributes:
        bases: Per finger, the first keypoint (thumb CMC or finger MCP) relative to the wrist.
        bones: Per finger, the lengths of its three segments, palm outwards.
        spread: Per finger, the resting splay about the palm normal (rad, + towards the thumb).
        radii: Capsule radius of the three segments of every finger (skin thickness).
        scale: Uniform size factor (1.0 = average adult).
    """

    bases: dict[str, np.ndarray] = field(default_factory=_default_bases)
    bones: dict[str, tuple[float, float, float]] = field(default_factory=_default_bones)
    spread: dict[str, float] = field(
        default_factory=lambda: {"index": 0.10, "middle": 0.0, "ring": -0.09, "little": -0.20}
    )
    radii: tuple[float, float, float] = (0.010, 0.009, 0.008)
    scale: float = 1.0


def _thumb_base_rotation() -> np.ndarray:
    """Rest frame of the thumb metacarpal: z along the bone, x across the palm, y palmar."""
    z = np.array([0.20, 0.55, 0.80])
    z /= np.linalg.norm(z)
    x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=-1)


# Opposition: abducting the thumb also pronates it, turning its flexion towards the palm.
_THUMB_PRONATION_PER_ABDUCTION = 0.9


_THUMB_BASE = _thumb_base_rotation()


def forward_keypoints(
    angles: np.ndarray, wrist_pose: np.ndarray | None = None, shape: HandShape | None = None
) -> np.ndarray:
    """Keypoints of the hand for a batch of joint angles.

    Args:
        angles: (..., 20) joint angles in :data:`JOINT_NAMES` order, radians.
        wrist_pose: (..., 4, 4) wrist-to-world transforms; identity if None.
        shape: Bone geometry; the average adult if None.

    Returns:
        (..., 21, 3) keypoints in MANO order, metres.
    """
    shape = shape or HandShape()
    angles = np.asarray(angles, dtype=np.float64)
    batch = angles.shape[:-1]
    kp = np.zeros((*batch, NUM_KEYPOINTS, 3))
    for i, finger in enumerate(FINGERS):
        a = angles[..., 4 * i : 4 * i + 4]
        # Intrinsic Euler angles (upper-case axes): the product Ra Rb ... of elementary rotations.
        if finger == "thumb":  # flexion (y), abduction (-x) and the pronation it brings (z)
            pronation = _THUMB_PRONATION_PER_ABDUCTION * a[..., 1]
            euler = np.stack([a[..., 0], -a[..., 1], pronation], axis=-1)
            rot = _THUMB_BASE @ Rotation.from_euler("YXZ", euler).as_matrix()
        else:  # splay about x, then MCP flexion about the new y
            euler = np.stack([-(shape.spread[finger] + a[..., 0]), a[..., 1]], axis=-1)
            rot = Rotation.from_euler("XY", euler).as_matrix()
        flex = (a[..., 2], a[..., 3])
        chain = FINGER_KEYPOINTS[finger]
        pos = np.broadcast_to(shape.bases[finger] * shape.scale, (*batch, 3))
        kp[..., chain[0], :] = pos
        for j, length in enumerate(shape.bones[finger]):
            if j > 0:
                rot = rot @ Rotation.from_euler("Y", flex[j - 1][..., None]).as_matrix()
            pos = pos + rot[..., :, 2] * (length * shape.scale)
            kp[..., chain[j + 1], :] = pos
    if wrist_pose is not None:
        wrist_pose = np.asarray(wrist_pose, dtype=np.float64)
        kp = transform_points(wrist_pose, kp)
    return kp


def finger_capsules(
    keypoints: np.ndarray, shape: HandShape | None = None, samples_per_segment: int = 6
) -> tuple[np.ndarray, np.ndarray]:
    """Points along every finger segment's axis with the skin radius there.

    Args:
        keypoints: (..., 21, 3) keypoints.
        shape: Gives the capsule radii and scale.
        samples_per_segment: Points per segment, both ends included.

    Returns:
        points (..., 5, P, 3) and radii (P,) with P = 3 * samples_per_segment: the skin of
        finger f is every point within ``radii`` of ``points[..., f, :, :]``.
    """
    shape = shape or HandShape()
    kp = np.asarray(keypoints, dtype=np.float64)
    t = np.linspace(0.0, 1.0, samples_per_segment)
    points = []
    for finger in FINGERS:
        chain = FINGER_KEYPOINTS[finger]
        segs = [
            kp[..., chain[j], None, :] * (1 - t[:, None])
            + kp[..., chain[j + 1], None, :] * t[:, None]
            for j in range(3)
        ]
        points.append(np.concatenate(segs, axis=-2))
    radii = np.repeat(np.asarray(shape.radii) * shape.scale, samples_per_segment)
    return np.stack(points, axis=-3), radii
