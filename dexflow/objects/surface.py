"""Surface samples with outward normals, the object representation of contact and refinement."""

from __future__ import annotations

import numpy as np
import trimesh

from dexflow.objects.sdf import SignedDistanceGrid

__all__ = ["sample_surface"]


def sample_surface(
    mesh: trimesh.Trimesh, count: int, sdf: SignedDistanceGrid, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``count`` points on ``mesh`` with unit normals pointing out of the object.

    Scanned meshes do not always wind their faces consistently, so each face normal is flipped
    where it disagrees with the gradient of the (winding-number) signed distance.

    Returns:
        points (count, 3) and normals (count, 3).
    """
    points, face_index = trimesh.sample.sample_surface(mesh, count, seed=seed)
    normals = np.asarray(mesh.face_normals[face_index], dtype=np.float64)
    probe = points + 0.5 * sdf.spacing * normals
    _, grad = sdf.query(probe, with_gradient=True)
    flip = (grad * normals).sum(axis=-1) < 0
    normals[flip] *= -1.0
    return np.asarray(points, dtype=np.float64), normals
