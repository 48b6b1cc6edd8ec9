"""Left hands: mirror a sequence and its object to a right hand (x -> -x), and back.

Mirroring is the reflection ``M = diag(-1, 1, 1)`` of the world. Keypoints become ``M p``; the
object mesh becomes ``M v`` (faces re-wound to keep normals outwards) and its pose
``M T M``, which is again a rigid transform. Everything relative (contacts, distances) is kept.
Results on the mirrored data map back with the same reflection (:func:`unmirror_points`,
:func:`unmirror_transforms`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import trimesh

from dexflow.io.sequence import Sequence

__all__ = ["MIRROR", "mirror_mesh", "mirror_sequence", "unmirror_points", "unmirror_transforms"]

MIRROR = np.diag([-1.0, 1.0, 1.0])


def mirror_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The reflected mesh, faces re-wound so that normals still point outwards."""
    return trimesh.Trimesh(mesh.vertices * [-1.0, 1.0, 1.0], mesh.faces[:, ::-1], process=False)


def _mirror_transforms(transforms: np.ndarray) -> np.ndarray:
    m4 = np.eye(4)
    m4[:3, :3] = MIRROR
    return m4 @ np.asarray(transforms, dtype=np.float64) @ m4


def mirror_sequence(seq: Sequence, mirrored_mesh: str) -> Sequence:
    """Mirror a left-hand sequence to a right one.

    Args:
        seq: A sequence with ``side == 'left'``.
        mirrored_mesh: Path (relative to the data root) of the mirrored mesh written beside it.

    Returns:
        The sequence with ``side='left'`` kept, ``mirrored=True``, keypoints and object mirrored.
    """
    extras = dict(seq.extras)
    if "gt_keypoints" in extras:
        extras["gt_keypoints"] = np.asarray(extras["gt_keypoints"]) @ MIRROR
    return replace(
        seq,
        keypoints=np.asarray(seq.keypoints, dtype=np.float64) @ MIRROR,
        obj_pose=_mirror_transforms(seq.obj_pose),
        obj_mesh=mirrored_mesh,
        mirrored=True,
        extras=extras,
    )


def unmirror_points(points: np.ndarray) -> np.ndarray:
    """Map points (..., 3) computed on mirrored data back to the original (left-hand) world."""
    return np.asarray(points) @ MIRROR


def unmirror_transforms(transforms: np.ndarray) -> np.ndarray:
    """Map rigid transforms (..., 4, 4) computed on mirrored data back to the original world."""
    return _mirror_transforms(transforms)
