"""Stand-ins for YCB objects: meshes of the real objects' sizes and shapes, built from primitives.

Sizes are the bounding-box extents of the YCB-Video models (DexYCB). Every mesh is returned in
its resting pose on a table: z up, the bounding box centred on the origin. Like real scans,
some stand-ins are deliberately left with holes (``watertight=False`` in :data:`STANDINS`), and
all are refined to a few thousand faces.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

__all__ = ["STANDINS", "Standin", "build_standin"]

_MAX_EDGE = 0.012


def _cylinder(radius: float, height: float, center=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=48)
    mesh.apply_translation(center)
    return mesh


def _box(extents, center=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(center)
    return mesh


def _rounded_box(extents, radius: float) -> trimesh.Trimesh:
    half = np.asarray(extents) / 2 - radius
    ball = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    return trimesh.convex.convex_hull(np.concatenate([ball.vertices + c for c in corners]))


def _master_chef_can() -> trimesh.Trimesh:
    return _cylinder(0.0512, 0.1401)


def _cracker_box() -> trimesh.Trimesh:
    return _box((0.164, 0.0717, 0.2135))


def _sugar_box() -> trimesh.Trimesh:
    return _box((0.094, 0.0495, 0.176))


def _tomato_soup_can() -> trimesh.Trimesh:
    return _cylinder(0.0339, 0.102)


def _mustard_bottle() -> trimesh.Trimesh:
    body = _cylinder(0.5, 0.160, center=(0.0, 0.0, -0.0157))
    body.apply_scale((0.0972, 0.0666, 1.0))
    cap = _cylinder(0.0150, 0.0320, center=(0.0, 0.0, 0.0797))
    return body.union(cap)


def _potted_meat_can() -> trimesh.Trimesh:
    return _rounded_box((0.1021, 0.0603, 0.0836), radius=0.010)


def _banana() -> trimesh.Trimesh:
    """A curved, tapered tube along half a circle, scaled to the banana's extents."""
    arc_radius, n_ring, n_side = 0.071, 48, 20
    t = np.linspace(0.0, 1.0, n_ring)
    angle = np.pi * t
    centre = np.stack([-arc_radius * np.cos(angle), arc_radius * np.sin(angle), 0 * t], axis=-1)
    tangent = np.stack([np.sin(angle), np.cos(angle), 0 * t], axis=-1)
    normal = np.stack([np.cos(angle), -np.sin(angle), 0 * t], axis=-1)
    binormal = np.cross(tangent, normal)
    radius = 0.01835 * (0.25 + 0.75 * np.sin(np.pi * t) ** 0.5)
    phi = np.linspace(0.0, 2 * np.pi, n_side, endpoint=False)
    ring = (
        np.cos(phi)[None, :, None] * normal[:, None]
        + np.sin(phi)[None, :, None] * binormal[:, None]
    )
    vertices = (centre[:, None] + radius[:, None, None] * ring).reshape(-1, 3)
    faces = []
    for i in range(n_ring - 1):
        for j in range(n_side):
            a, b = i * n_side + j, i * n_side + (j + 1) % n_side
            c, d = a + n_side, b + n_side
            faces += [[a, c, b], [b, c, d]]
    caps = [len(vertices), len(vertices) + 1]
    vertices = np.vstack([vertices, centre[0], centre[-1]])
    last = (n_ring - 1) * n_side
    for j in range(n_side):
        faces.append([caps[0], j, (j + 1) % n_side])
        faces.append([caps[1], last + (j + 1) % n_side, last + j])
    mesh = trimesh.Trimesh(vertices, np.array(faces), process=True)
    mesh.fix_normals()
    mesh.apply_scale(np.array([0.1784, 0.1089, 0.0367]) / mesh.extents)
    return mesh


def _bleach_cleanser() -> trimesh.Trimesh:
    body = _rounded_box((0.1024, 0.0677, 0.2506), radius=0.012)
    recess = _box((0.040, 0.080, 0.060), center=(0.040, 0.0, 0.080))
    return body.difference(recess)


def _bowl() -> trimesh.Trimesh:
    """An open spherical cap: rim 161 mm across, 55 mm deep, 4 mm wall."""
    depth, rim_radius, wall = 0.055, 0.0807, 0.004
    sphere_radius = (rim_radius**2 + depth**2) / (2 * depth)
    centre = (0.0, 0.0, sphere_radius - depth)
    outer = trimesh.creation.icosphere(subdivisions=4, radius=sphere_radius)
    inner = trimesh.creation.icosphere(subdivisions=4, radius=sphere_radius - wall)
    outer.apply_translation(centre)
    inner.apply_translation(centre)
    below_rim = _box((0.4, 0.4, 0.2), center=(0.0, 0.0, -0.1))
    return outer.difference(inner).intersection(below_rim)


def _mug() -> trimesh.Trimesh:
    """An open cylinder (81.4 mm across, 93.1 mm tall) with a ring handle: 117 mm overall."""
    radius, height = 0.0407, 0.0931
    body = _cylinder(radius, height)
    cavity = _cylinder(radius - 0.004, height, center=(0.0, 0.0, 0.006))
    handle = trimesh.creation.torus(major_radius=0.026, minor_radius=0.0062, major_sections=48)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation((radius + 0.0356 - 0.026 - 0.0062, 0.0, 0.0))
    return body.union(handle).difference(cavity)


def _large_clamp() -> trimesh.Trimesh:
    """A U-shaped clamp body: a 120 mm back bar and two 171 mm arms, 39.2 mm thick."""
    thick = 0.0392
    back = _box((0.026, 0.120, thick), center=(-0.0726, 0.0, 0.0))
    arm_a = _box((0.1713, 0.022, thick), center=(0.0, 0.049, 0.0))
    arm_b = _box((0.1713, 0.022, thick), center=(0.0, -0.049, 0.0))
    return back.union(arm_a).union(arm_b)


def _foam_brick() -> trimesh.Trimesh:
    return _box((0.0778, 0.0526, 0.0511))


@dataclass(frozen=True)
class Standin:
    """One YCB stand-in: its id, real extents (mm, largest first) and how to build it."""

    name: str
    extents_mm: tuple[float, float, float]
    build: Callable[[], trimesh.Trimesh]
    grasps: tuple[str, ...]
    watertight: bool = True
    symmetry_axis: tuple[float, float, float] | None = (
        None  # shape symmetric about it (object frame)
    )


STANDINS: dict[str, Standin] = {
    s.name: s
    for s in (
        Standin(
            "002_master_chef_can",
            (140.1, 102.4, 102.3),
            _master_chef_can,
            ("power", "tripod", "lateral"),
            watertight=False,
            symmetry_axis=(0.0, 0.0, 1.0),
        ),
        Standin(
            "003_cracker_box", (213.5, 164.0, 71.7), _cracker_box, ("power", "pinch", "lateral")
        ),
        Standin("004_sugar_box", (176.0, 94.0, 49.5), _sugar_box, ("power", "pinch", "tripod")),
        Standin(
            "005_tomato_soup_can",
            (102.0, 67.9, 67.8),
            _tomato_soup_can,
            ("power", "tripod", "pinch"),
            symmetry_axis=(0.0, 0.0, 1.0),
        ),
        Standin(
            "006_mustard_bottle",
            (191.4, 97.2, 66.6),
            _mustard_bottle,
            ("power", "tripod", "lateral"),
        ),
        Standin(
            "010_potted_meat_can",
            (102.1, 83.6, 60.3),
            _potted_meat_can,
            ("power", "pinch", "tripod"),
        ),
        Standin("011_banana", (178.4, 108.9, 36.7), _banana, ("power", "pinch", "tripod")),
        Standin(
            "021_bleach_cleanser",
            (250.6, 102.4, 67.7),
            _bleach_cleanser,
            ("power", "lateral", "tripod"),
        ),
        Standin(
            "024_bowl",
            (161.4, 161.1, 55.0),
            _bowl,
            # lateral second: the bowl's rim is the stand-in a lateral grasp holds best, and the
            # default demo (2 sequences per object) then has every grasp type
            ("pinch", "lateral", "tripod"),
            watertight=False,
            symmetry_axis=(0.0, 0.0, 1.0),
        ),
        Standin(
            "025_mug", (117.0, 93.1, 81.4), _mug, ("power", "pinch", "tripod"), watertight=False
        ),
        Standin(
            "051_large_clamp", (171.3, 120.0, 39.2), _large_clamp, ("pinch", "lateral", "power")
        ),
        Standin("061_foam_brick", (77.8, 52.6, 51.1), _foam_brick, ("power", "pinch", "tripod")),
    )
}


def _punch_holes(
    mesh: trimesh.Trimesh, rng: np.random.Generator, count: int = 3
) -> trimesh.Trimesh:
    """Remove a few small patches of faces, the way a scan misses the parts a camera cannot see."""
    keep = np.ones(len(mesh.faces), dtype=bool)
    centers = mesh.triangles_center
    bottom = centers[:, 2] < mesh.bounds[0, 2] + 0.02 * (mesh.bounds[1, 2] - mesh.bounds[0, 2])
    candidates = np.flatnonzero(bottom) if bottom.sum() > count else np.arange(len(mesh.faces))
    for idx in rng.choice(candidates, size=count, replace=False):
        keep &= np.linalg.norm(centers - centers[idx], axis=-1) > 0.008
    return trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=True)


def build_standin(name: str, seed: int = 0) -> trimesh.Trimesh:
    """Build the stand-in mesh ``name`` (a key of :data:`STANDINS`), in metres.

    The mesh is refined so no edge is longer than 12 mm, centred on its bounding box, and, for
    stand-ins marked not watertight, given small holes chosen by ``seed``.
    """
    spec = STANDINS[name]
    mesh = spec.build()
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, _MAX_EDGE)
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    if not spec.watertight:
        mesh = _punch_holes(mesh, np.random.default_rng(seed))
    return mesh
