"""Loading object meshes with errors that say what is wrong and where."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from dexflow.errors import MeshError

__all__ = ["MAX_OBJECT_EXTENT_M", "load_mesh", "write_obj"]

# Hand-held objects are smaller than this; a larger mesh is almost always in millimetres.
MAX_OBJECT_EXTENT_M = 2.0


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Read a triangle mesh (OBJ, PLY, STL, GLB, ...) in metres.

    Raises:
        MeshError: the file is missing or unreadable, has no triangles, holds non-finite
            vertices, or is so large it must be in millimetres.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for broken files
        raise MeshError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError(f"{path}: expected a triangle mesh, found no triangles")
    if not np.isfinite(mesh.vertices).all():
        raise MeshError(f"{path}: vertices contain NaN or inf")
    extent = float(mesh.extents.max())
    if extent > MAX_OBJECT_EXTENT_M:
        raise MeshError(
            f"{path}: largest extent {extent:.4g} > {MAX_OBJECT_EXTENT_M} m; expected metres "
            "(a mesh in millimetres must be scaled by 0.001)"
        )
    if extent <= 0:
        raise MeshError(f"{path}: degenerate mesh (zero extent)")
    return mesh


def write_obj(path: str | Path, mesh: trimesh.Trimesh) -> None:
    """Write ``mesh`` as OBJ atomically, without normals (deterministic bytes)."""
    from dexflow.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(trimesh.exchange.obj.export_obj(mesh, include_normals=False))
