"""Loading object meshes with errors that say what is wrong and where.

An object mesh comes from a dataset or a user's scan, so :func:`load_mesh` checks that it can be
an object before any stage computes a signed distance field on it. In this order it refuses
(:class:`~dexflow.errors.MeshError`, naming the file and what was found):

- a file that is missing, unreadable or holds no triangles;
- a vertex that is NaN or infinite (trimesh would silently drop it and the faces using it);
- fewer than :data:`MIN_FACES` triangles (a tetrahedron is the smallest closed surface);
- a largest extent over :data:`MAX_OBJECT_EXTENT_M` (millimetres), or of zero;
- a flat mesh: thinner along its thinnest principal axis than :data:`FLAT_FRACTION` of its
  extent along the widest (a sheet, a single polygon), or whose triangles cover less than a
  square of that fraction of its extent (all of them degenerate). Such a mesh encloses no
  volume, so its inside (the sign of its distance field) means nothing.

An inside-out mesh (faces wound so that their normals point into the object) is not refused but
flipped, with a warning (logged, and kept in ``mesh.metadata[MESH_WARNING]`` for the stage
summary): its signed distance would otherwise call the object's inside outside, and every
penetration would read 0 mm. See :func:`_orientation` for how it is told.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from dexflow.errors import MeshError

__all__ = [
    "FLAT_FRACTION",
    "INSIDE_OUT_FRACTION",
    "MAX_OBJECT_EXTENT_M",
    "MESH_WARNING",
    "MIN_FACES",
    "load_mesh",
    "write_obj",
]

log = logging.getLogger(__name__)

# Hand-held objects are smaller than this; a larger mesh is almost always in millimetres.
MAX_OBJECT_EXTENT_M = 2.0
# The fewest triangles of a surface enclosing a volume (a tetrahedron).
MIN_FACES = 4
# A mesh thinner than this fraction of its width is flat (a credit card is 0.009 of its width).
FLAT_FRACTION = 1e-3
# A mesh is inside out where its signed volume is below -this fraction of its unsigned volume.
INSIDE_OUT_FRACTION = 0.05
# Key of ``Trimesh.metadata`` holding the warning of a mesh load_mesh repaired (flipped).
MESH_WARNING = "dexflow_warning"


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Read a triangle mesh (OBJ, PLY, STL, GLB, ...) in metres, checked to be an object.

    Returns:
        The mesh as ``trimesh.load(path, force="mesh", process=True)`` reads it; faces flipped
        if it was inside out (then ``mesh.metadata[MESH_WARNING]`` says so).

    Raises:
        MeshError: the file is missing or unreadable, has no triangles or fewer than
            :data:`MIN_FACES`, holds non-finite vertices, is so large it must be in
            millimetres, or is flat (see the module docstring).
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    mesh = _read(path)
    _check_size(mesh, path)
    _check_not_flat(mesh, path)
    return _outward(mesh, path)


def _read(path: Path) -> trimesh.Trimesh:
    """The processed mesh, after checking the file's own vertices are finite.

    trimesh's processing drops non-finite vertices with their faces, so a NaN vertex would
    become a silent hole: the file is read once unprocessed to see them. The mesh returned is
    read as it always was (``process=True``), so a valid file gives the same mesh.
    """
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
        if isinstance(mesh, trimesh.Trimesh) and len(mesh.faces):
            raw = trimesh.load(path, force="mesh", process=False)
        else:
            raw = mesh
    except Exception as exc:  # trimesh raises many types for broken files
        raise MeshError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError(f"{path}: expected a triangle mesh, found no triangles")
    vertices = np.asarray(raw.vertices, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if len(bad) or not np.isfinite(mesh.vertices).all():
        first = f" (first: vertex {bad[0]} = {vertices[bad[0]].tolist()})" if len(bad) else ""
        raise MeshError(
            f"{path}: {max(len(bad), 1)} of {len(vertices)} vertices are NaN or inf{first}; "
            "an object mesh needs finite coordinates"
        )
    return mesh


def _check_size(mesh: trimesh.Trimesh, path: Path) -> None:
    """Refuse fewer than :data:`MIN_FACES` triangles, millimetres, and a zero extent."""
    if len(mesh.faces) < MIN_FACES:
        raise MeshError(
            f"{path}: {len(mesh.faces)} triangle(s); an object's surface needs at least "
            f"{MIN_FACES} (a tetrahedron)"
        )
    extent = float(mesh.extents.max())
    if extent > MAX_OBJECT_EXTENT_M:
        raise MeshError(
            f"{path}: largest extent {extent:.4g} > {MAX_OBJECT_EXTENT_M} m; expected metres "
            "(a mesh in millimetres must be scaled by 0.001)"
        )
    if extent <= 0:
        raise MeshError(f"{path}: degenerate mesh (zero extent)")


def _check_not_flat(mesh: trimesh.Trimesh, path: Path) -> None:
    """Refuse a mesh without volume: flat along a principal axis, or of (nearly) zero area.

    The principal axes are the eigenvectors of the used vertices' covariance; the extents along
    them do not depend on how the mesh is posed (a sheet tilted in the box's diagonal has a
    thick bounding box but a zero principal extent).
    """
    points = mesh.vertices[np.unique(mesh.faces)]
    centred = points - points.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)
    along = centred @ axes
    extents = along.max(axis=0) - along.min(axis=0)
    thin, wide = float(extents.min()), float(extents.max())
    if thin < FLAT_FRACTION * wide:
        raise MeshError(
            f"{path}: flat mesh: {thin * 1000:.3g} mm thick along its thinnest principal axis "
            f"and {wide * 1000:.3g} mm wide (less than {FLAT_FRACTION:g} of it); an object mesh "
            "must enclose a volume"
        )
    area = float(mesh.area)
    if area < (FLAT_FRACTION * wide) ** 2:
        raise MeshError(
            f"{path}: degenerate mesh: its {len(mesh.faces)} triangles cover {area:.3g} m² "
            f"(a {wide * 1000:.3g} mm wide object needs at least {(FLAT_FRACTION * wide) ** 2:.3g})"
        )


def _orientation(mesh: trimesh.Trimesh) -> float:
    """Signed over unsigned volume of the mesh, in [-1, 1]: positive for outward faces.

    The signed volume is the sum over triangles (a, b, c) of the tetrahedron volumes
    ``det(a - o, b - o, c - o) / 6`` about a point ``o`` (the bounding box's centre). For a
    closed mesh with outward normals it is the enclosed volume, whatever ``o``; an inside-out
    one gives its negative. Scans are not closed, but a hole of area A at distance d from ``o``
    changes the sum by at most A d / 3, small next to the volume for the small holes of a scan,
    so the sign still tells. Divided by the unsigned volume (the sum of the tetrahedra's
    absolute volumes), it is 1 for a closed convex mesh, less for concave meshes and thin
    shells, whose walls' two sides nearly cancel (the demo's bowl and mug, open shells with
    holes, give 0.13 and 0.16), and near 0 for a mesh whose faces are wound inconsistently.
    """
    tetrahedra = mesh.triangles - mesh.bounds.mean(axis=0)
    six_volumes = np.einsum(
        "ij,ij->i", tetrahedra[:, 0], np.cross(tetrahedra[:, 1], tetrahedra[:, 2])
    )
    unsigned = float(np.abs(six_volumes).sum())
    return float(six_volumes.sum()) / unsigned if unsigned > 0 else 0.0


def _outward(mesh: trimesh.Trimesh, path: Path) -> trimesh.Trimesh:
    """``mesh`` with its faces flipped if it is clearly inside out (:func:`_orientation`
    below ``-INSIDE_OUT_FRACTION``); ambiguous meshes (near 0) are left as they are."""
    orientation = _orientation(mesh)
    if orientation >= -INSIDE_OUT_FRACTION:
        return mesh
    mesh.invert()
    note = (
        f"the mesh was inside out (signed volume {orientation:.2f} of its unsigned volume: "
        "its normals pointed into the object); its faces were flipped"
    )
    log.warning("%s: %s", path, note)
    mesh.metadata[MESH_WARNING] = note
    return mesh


def write_obj(path: str | Path, mesh: trimesh.Trimesh) -> None:
    """Write ``mesh`` as OBJ atomically, without normals (deterministic bytes)."""
    from dexflow.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(trimesh.exchange.obj.export_obj(mesh, include_normals=False))
