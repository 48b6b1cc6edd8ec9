"""Rigid transforms applied to batches of points: one definition for every stage."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "pose_from_vector",
    "pose_vector",
    "rigid_fit",
    "rotate_vectors",
    "transform_points",
    "world_to_object",
]


def transform_points(transform, points):
    """Apply rigid transforms to batches of points: ``R p + t``.

    Works on numpy arrays and on torch tensors alike; with tensors, gradients flow to both
    arguments.

    Args:
        transform: (..., 4, 4) transforms from the points' frame to the target frame.
        points: (..., N, 3) points; the leading dimensions broadcast against ``transform``'s,
            e.g. ``(T, 4, 4)`` with ``(T, N, 3)``, or ``(4, 4)`` with ``(N, 3)``.

    Returns:
        (..., N, 3) points in the target frame, the type of ``points``.
    """
    return points @ transform[..., :3, :3].mT + transform[..., None, :3, 3]


def rotate_vectors(transform, vectors):
    """Apply the rotation of rigid transforms to batches of vectors (normals): ``R v``.

    Args:
        transform: (..., 4, 4) transforms (only the rotation block is used).
        vectors: (..., N, 3) vectors, numpy arrays or torch tensors (differentiable).

    Returns:
        (..., N, 3) rotated vectors.
    """
    return vectors @ transform[..., :3, :3].mT


def world_to_object(points: np.ndarray, obj_pose: np.ndarray) -> np.ndarray:
    """Map world points into the object's frame, batched over frames.

    The inverse is the general matrix inverse, not the rigid ``(R^T, -R^T t)``: the two agree
    only to the orthonormality of ``R``, and a sequence's poses are accepted with up to
    ``1e-4`` of error there (float32 annotations), so the rigid inverse would shift points.

    Args:
        points: (T, N, 3) world points.
        obj_pose: (T, 4, 4) object poses (object mesh -> world).

    Returns:
        (T, N, 3) the points in object-mesh coordinates.
    """
    return transform_points(np.linalg.inv(np.asarray(obj_pose)), points)


def pose_vector(pose: np.ndarray) -> np.ndarray:
    """(T, 7) ``[x, y, z, qw, qx, qy, qz]`` (qw >= 0) of rigid transforms ``pose (T, 4, 4)``."""
    quat = Rotation.from_matrix(pose[:, :3, :3]).as_quat(canonical=True, scalar_first=True)
    return np.concatenate([pose[:, :3, 3], quat], axis=1)


def pose_from_vector(vector: np.ndarray) -> np.ndarray:
    """(T, 4, 4) rigid transforms of ``vector (T, 7)`` = ``[x, y, z, qw, qx, qy, qz]``."""
    vector = np.asarray(vector, dtype=np.float64)
    pose = np.repeat(np.eye(4)[None], len(vector), axis=0)
    pose[:, :3, :3] = Rotation.from_quat(vector[:, 3:], scalar_first=True).as_matrix()
    pose[:, :3, 3] = vector[:, :3]
    return pose


def rigid_fit(source: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(T, 4, 4) the rigid transforms that best map the points ``source (K, 3)`` onto each
    ``targets[t] (K, 3)`` (least squares: Kabsch's method, reflections excluded)."""
    source = np.asarray(source, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.float64)
    a = source - source.mean(axis=0)
    b_mean = targets.mean(axis=1)  # (T, 3)
    cov = np.einsum("ki,tkj->tij", a, targets - b_mean[:, None])  # (T, 3, 3)
    u, _, vt = np.linalg.svd(cov)
    sign = np.sign(np.linalg.det(np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)))
    flip = np.ones((len(cov), 3))
    flip[:, 2] = sign
    rot = np.swapaxes(vt, 1, 2) @ (flip[:, :, None] * np.swapaxes(u, 1, 2))
    out = np.repeat(np.eye(4)[None], len(cov), axis=0)
    out[:, :3, :3] = rot
    out[:, :3, 3] = b_mean - rot @ source.mean(axis=0)
    return out
