"""Signed distance to an object surface, robust to meshes that are not watertight.

Sign convention: negative inside the object, positive outside and on the surface, metres.

Inside/outside comes from the generalised winding number (Jacobson et al. 2013): a point is
inside where the winding number exceeds 0.5. For a closed mesh that is exact; for a scanned mesh
with holes the winding number degrades gracefully, so a hole does not flip the sign of a whole
region the way ray parity or pseudo-normals do. The magnitude is the exact distance to the
nearest triangle. Both come from libigl.

For the batched, repeated queries of later stages the field is sampled once on a regular grid
(:class:`SignedDistanceGrid`) and interpolated trilinearly.

The winding number is the grid's largest cost (about 4x the distances), so the grid's signs are
found coarse to fine (:func:`_grid_winding`): a node whose distance to the surface exceeds the
diagonal of the coarser grid's cell around it has no surface anywhere in that cell; if the
cell's corners all wind clearly (by more than :data:`_SURE`) on one side of 0.5, the node takes
their side. Only the nodes near the surface, or in a cell whose corners disagree or are not
clear, are evaluated. For a closed mesh that is exact (the winding number is 0 or 1 off the
surface). For a mesh with holes the winding number is continuous away from the surface, and a
cell without surface whose corners all lie clearly on one side of 0.5 could only hide the other
side in a pocket smaller than the cell, which the field of a hole (smooth over the hole's size)
does not have; the test suite checks the signs equal the full evaluation on closed and holed
meshes.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import igl
import numpy as np
import trimesh

from dexflow.io.atomic import save_npz

__all__ = ["SignedDistanceGrid", "signed_distance", "winding_number"]

_CHUNK = 200_000


def _mesh_arrays(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    return vertices, faces


def winding_number(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Generalised winding number of ``mesh`` at ``points (N, 3)``; about 1 inside, 0 outside."""
    vertices, faces = _mesh_arrays(mesh)
    return _winding(vertices, faces, np.asarray(points, dtype=np.float64).reshape(-1, 3))


def _chunks(points: np.ndarray):
    for start in range(0, len(points), _CHUNK):
        yield np.ascontiguousarray(points[start : start + _CHUNK])


def _nodes(axes: list[np.ndarray]) -> np.ndarray:
    """(N, 3) grid nodes of three coordinate axes, C order (the first axis slowest)."""
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _unsigned_distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Exact distance from ``points (N, 3)`` to the nearest triangle."""
    squared = [igl.point_mesh_squared_distance(c, vertices, faces)[0] for c in _chunks(points)]
    return np.sqrt(np.concatenate(squared)) if squared else np.zeros(0)


_DIRECT_NODES = 4096  # grids this small are evaluated node by node
# A point this close to the surface is on it, and its signed distance is +distance. The winding
# number there is 0.5 only up to rounding, and libigl's threads round it differently from run to
# run: 9,191 to 9,193 of the 9,244 grid nodes on a box's faces (which lie on grid planes when
# the padding is a whole number of spacings) came out inside, so the grid's bytes, and the
# stages' results after it, changed between two runs of the same input.
_ON_SURFACE_M = 1e-9
_SURE = 0.25  # a cell's corners decide its nodes when all wind this far on one side of 0.5


def _grid_winding(
    vertices: np.ndarray, faces: np.ndarray, axes: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The distance to the surface and the winding number at each node of the grid ``axes``
    (uniform, equal spacing), the winding number coarse to fine (module docstring): a node
    whose coarse cell has no surface and whose corners all wind further than :data:`_SURE`
    from 0.5 on one side takes their mean; the others are evaluated. Arrays of the grid's
    shape: (winding, distance)."""
    shape = tuple(len(a) for a in axes)
    nodes = _nodes(axes)
    distance = _unsigned_distance(vertices, faces, nodes).reshape(shape)
    if distance.size <= _DIRECT_NODES or min(shape) < 3:
        return _winding(vertices, faces, nodes).reshape(shape), distance
    spacing = float(axes[0][1] - axes[0][0])
    # every second node, one more where needed so that the coarse cells cover the whole grid
    coarse_axes = [a[0] + 2 * spacing * np.arange((len(a) - 1) // 2 + 2) for a in axes]
    coarse = _grid_winding(vertices, faces, coarse_axes)[0]
    i, j, k = np.meshgrid(*[np.arange(n) // 2 for n in shape], indexing="ij")  # cell per node
    corners = np.stack(
        [coarse[i + a, j + b, k + c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], axis=-1
    )
    low, high = corners.min(axis=-1), corners.max(axis=-1)
    sure = (high < 0.5 - _SURE) | (low > 0.5 + _SURE)
    todo = ~(sure & (distance > 2 * spacing * np.sqrt(3.0)))  # else: no surface in the cell
    winding = corners.mean(axis=-1)
    if todo.any():
        winding[todo] = _winding(vertices, faces, nodes.reshape(*shape, 3)[todo])
    return winding, distance


def _winding(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    out = [igl.winding_number(vertices, faces, chunk) for chunk in _chunks(points)]
    return np.concatenate(out) if out else np.zeros(0)


def signed_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Exact signed distance from ``points (..., 3)`` to ``mesh``; negative inside.

    Returns:
        (...,) distances in the units of the mesh.
    """
    points = np.asarray(points, dtype=np.float64)
    flat = np.ascontiguousarray(points.reshape(-1, 3))
    vertices, faces = _mesh_arrays(mesh)
    dist = _unsigned_distance(vertices, faces, flat)
    return _signed(_winding(vertices, faces, flat), dist).reshape(points.shape[:-1])


def _signed(winding: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Signed distance from the winding number and the unsigned distance: negative where the
    winding number exceeds 0.5, except on the surface (within :data:`_ON_SURFACE_M`), where
    the winding number's rounding decides nothing."""
    return np.where((winding > 0.5) & (distance > _ON_SURFACE_M), -distance, distance)


@dataclass
class SignedDistanceGrid:
    """A signed distance field sampled on a regular grid, queried by trilinear interpolation.

    Attributes:
        origin: (3,) position of grid node (0, 0, 0), metres.
        spacing: Distance between neighbouring nodes, metres.
        values: (nx, ny, nz) signed distances at the nodes.
    """

    origin: np.ndarray
    spacing: float
    values: np.ndarray

    @classmethod
    def from_mesh(
        cls, mesh: trimesh.Trimesh, spacing: float = 0.002, padding: float = 0.03
    ) -> SignedDistanceGrid:
        """Sample :func:`signed_distance` of ``mesh`` on a grid covering its bounds + padding."""
        lo = mesh.bounds[0] - padding
        hi = mesh.bounds[1] + padding
        counts = np.ceil((hi - lo) / spacing).astype(int) + 1
        axes = [lo[i] + spacing * np.arange(counts[i]) for i in range(3)]
        winding, distance = _grid_winding(*_mesh_arrays(mesh), axes)
        values = _signed(winding, distance)
        return cls(
            origin=lo.astype(np.float64), spacing=float(spacing), values=values.astype(np.float32)
        )

    @property
    def upper(self) -> np.ndarray:
        """(3,) position of the last grid node."""
        return self.origin + self.spacing * (np.array(self.values.shape) - 1)

    def query(self, points: np.ndarray, with_gradient: bool = False):
        """Signed distance (and its gradient) at ``points (..., 3)``.

        Outside the grid the value at the nearest grid point plus the distance to the grid box
        is returned, which never underestimates how far outside the object a point is.

        Returns:
            (...,) distances, and with ``with_gradient`` also (..., 3) gradients (outward
            normals near the surface).
        """
        points = np.asarray(points, dtype=np.float64)
        shape = points.shape[:-1]
        flat = points.reshape(-1, 3)
        clamped = np.clip(flat, self.origin, self.upper)
        outside = np.linalg.norm(flat - clamped, axis=-1)
        rel = (clamped - self.origin) / self.spacing
        dims = np.array(self.values.shape)
        base = np.clip(np.floor(rel).astype(np.int64), 0, dims - 2)
        frac = rel - base
        # the eight corners of each point's cell as offsets into the flat grid: one index
        # computation and eight np.take (several times faster than 3-D fancy indexing)
        _, ny, nz = self.values.shape
        flat_values = self.values.reshape(-1)
        first = base @ np.array([ny * nz, nz, 1], dtype=np.int64)
        c = np.empty((len(first), 8))
        for n, (di, dj, dk) in enumerate(itertools.product((0, 1), repeat=3)):
            c[:, n] = np.take(flat_values, first + (di * ny * nz + dj * nz + dk))
        c = c.reshape(-1, 2, 2, 2)
        fx, fy, fz = frac[:, 0, None, None], frac[:, 1, None], frac[:, 2]
        cx = c[:, 0] * (1 - fx) + c[:, 1] * fx
        cxy = cx[:, 0] * (1 - fy) + cx[:, 1] * fy
        dist = cxy[:, 0] * (1 - fz) + cxy[:, 1] * fz + outside
        if not with_gradient:
            return dist.reshape(shape)
        gx = (c[:, 1] - c[:, 0]) / self.spacing
        gx = gx[:, 0] * (1 - fy) + gx[:, 1] * fy
        gx = gx[:, 0] * (1 - fz) + gx[:, 1] * fz
        gy = (cx[:, 1] - cx[:, 0]) / self.spacing
        gy = gy[:, 0] * (1 - fz) + gy[:, 1] * fz
        gz = (cxy[:, 1] - cxy[:, 0]) / self.spacing
        grad = np.stack([gx, gy, gz], axis=-1)
        away = outside > 0
        if away.any():
            grad[away] = (flat[away] - clamped[away]) / outside[away, None]
        return dist.reshape(shape), grad.reshape((*shape, 3))

    def save(self, path: str | Path) -> None:
        save_npz(
            path, {"origin": self.origin, "spacing": np.array(self.spacing), "values": self.values}
        )

    @classmethod
    def load(cls, path: str | Path) -> SignedDistanceGrid:
        with np.load(path) as data:
            return cls(data["origin"], float(data["spacing"]), data["values"])
