"""Convex decomposition of object meshes for physics simulation (CoACD)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from dexflow.io.atomic import atomic_path

__all__ = ["convex_decomposition", "read_convex_obj", "write_convex_obj"]


def convex_decomposition(
    mesh: trimesh.Trimesh,
    threshold: float = 0.1,
    max_hulls: int = 16,
    preprocess_resolution: int = 30,
    mcts_iterations: int = 60,
    mcts_max_depth: int = 2,
    mcts_nodes: int = 10,
    seed: int = 0,
) -> list[trimesh.Trimesh]:
    """Split ``mesh`` into convex parts with CoACD (Wei et al. 2022); deterministic for a seed.

    Non-watertight meshes are first made manifold by CoACD's own preprocessing.

    Returns:
        Convex meshes whose union approximates ``mesh``.
    """
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(
        coacd.Mesh(
            np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32)
        ),
        threshold=threshold,
        max_convex_hull=max_hulls,
        preprocess_resolution=preprocess_resolution,
        mcts_iterations=mcts_iterations,
        mcts_max_depth=mcts_max_depth,
        mcts_nodes=mcts_nodes,
        seed=seed,
    )
    return [trimesh.Trimesh(v, f, process=True) for v, f in parts]


def write_convex_obj(path: str | Path, parts: list[trimesh.Trimesh]) -> None:
    """Write convex parts as one OBJ, one ``o`` group per part (pybullet reads it as a compound)."""
    lines, offset = [], 1
    for i, part in enumerate(parts):
        lines.append(f"o part_{i:03d}")
        lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in part.vertices]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in part.faces]
        offset += len(part.vertices)
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def read_convex_obj(path: str | Path) -> list[np.ndarray]:
    """The vertices (V, 3) of every part of an OBJ written by :func:`write_convex_obj` (or any
    OBJ with one ``o``/``g`` group per convex part; a file without groups is one part).

    Raises:
        ValueError: the file holds no vertices.
    """
    parts: list[list[list[float]]] = []
    current: list[list[float]] | None = None
    for line in Path(path).read_text().splitlines():
        tag, _, rest = line.partition(" ")
        if tag in ("o", "g"):
            current = None
        elif tag == "v":
            if current is None:
                current = []
                parts.append(current)
            current.append([float(x) for x in rest.split()[:3]])
    out = [np.asarray(vertices, dtype=float) for vertices in parts if vertices]
    if not out:
        raise ValueError(f"{path}: no vertices (expected one group of vertices per convex part)")
    return out
