"""Convex decomposition of object meshes for physics simulation (CoACD), cached by content.

CoACD is the slowest part of preparing an object (seconds to tens of seconds a mesh) and its
result is scale-equivariant (the parts of a mesh scaled by s are its parts scaled by s, to
1e-17 m). :func:`cached_convex_decomposition` therefore keeps the parts of every unscaled mesh
in a cache keyed by the mesh's vertices and faces, CoACD's settings and version: a second hand
(another scale), a rerun after a code change or another data root holding the same mesh reads
them back instead of decomposing again. The cache is ``$DEXFLOW_CACHE`` (``off`` disables it),
else ``$XDG_CACHE_HOME/dexflow`` or ``~/.cache/dexflow``; deleting it only costs time.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np
import trimesh

from dexflow.io.atomic import atomic_path, save_npz

__all__ = [
    "CACHE_ENV",
    "asset_cache_dir",
    "cached_convex_decomposition",
    "convex_decomposition",
    "read_convex_obj",
    "write_convex_obj",
]
log = logging.getLogger(__name__)

CACHE_ENV = "DEXFLOW_CACHE"
# Part of every cache key: raise it when the parts stored for the same mesh and settings would
# change (a new way of calling CoACD), so that old entries are not read back.
_CACHE_VERSION = 1


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
    parts = _coacd_parts(
        mesh,
        threshold=threshold,
        max_hulls=max_hulls,
        preprocess_resolution=preprocess_resolution,
        mcts_iterations=mcts_iterations,
        mcts_max_depth=mcts_max_depth,
        mcts_nodes=mcts_nodes,
        seed=seed,
    )
    return [trimesh.Trimesh(v, f, process=True) for v, f in parts]


def _coacd_parts(
    mesh, threshold, max_hulls, preprocess_resolution, mcts_iterations, mcts_max_depth,
    mcts_nodes, seed,
) -> list[tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """CoACD's own (vertices, faces) per part, computed with an OpenMP thread per core.

    A worker of a process pool is limited to one OpenMP thread (joblib sets
    ``OMP_NUM_THREADS`` to cores / workers), but a stage's objects are few and uneven: one
    holed mesh can take 20 s while the other workers are done and idle. CoACD's tree search
    runs 1.4x faster on 2 threads than on 1; two decompositions at once on 2 cores with 2
    threads each are 10 % slower than with 1 each. The parts do not depend on the number of
    threads (the same vertices to the bit with 1 and 2).
    """
    import coacd
    from threadpoolctl import threadpool_limits

    coacd.set_log_level("error")
    with threadpool_limits(limits=os.cpu_count() or 1, user_api="openmp"):
        return coacd.run_coacd(
            coacd.Mesh(
                np.asarray(mesh.vertices, dtype=np.float64),
                np.asarray(mesh.faces, dtype=np.int32),
            ),
            threshold=threshold,
            max_convex_hull=max_hulls,
            preprocess_resolution=preprocess_resolution,
            mcts_iterations=mcts_iterations,
            mcts_max_depth=mcts_max_depth,
            mcts_nodes=mcts_nodes,
            seed=seed,
        )


def asset_cache_dir() -> Path | None:
    """Where object assets are cached (module docstring); None when ``$DEXFLOW_CACHE`` is
    ``off``, ``0``, ``none`` or empty."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        if value.strip().lower() in ("", "0", "off", "none"):
            return None
        return Path(value).expanduser().resolve()  # the same folder from every stage's cwd
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "dexflow"


def cached_convex_decomposition(mesh: trimesh.Trimesh, **settings) -> list[trimesh.Trimesh]:
    """:func:`convex_decomposition` of ``mesh`` with ``settings``, read from the asset cache
    when it holds them (exactly the parts CoACD returned), else computed and stored there.

    A cache that cannot be written (read-only, full) is skipped with a warning: the parts are
    still returned.
    """
    from importlib.metadata import PackageNotFoundError, version

    folder = asset_cache_dir()
    if folder is None:
        return convex_decomposition(mesh, **settings)
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    try:
        coacd_version = version("coacd")
    except PackageNotFoundError:
        coacd_version = "unknown"
    header = [vertices.shape, faces.shape, settings, coacd_version, _CACHE_VERSION]
    key = hashlib.sha256(json.dumps(header, sort_keys=True).encode())
    key.update(vertices.tobytes())
    key.update(faces.tobytes())
    path = folder / "convex" / f"{key.hexdigest()}.npz"
    try:
        with np.load(path) as stored:
            count = int(stored["count"])
            parts = [(stored[f"v{i}"], stored[f"f{i}"]) for i in range(count)]
        log.debug("convex parts of a %d-face mesh read from %s", len(faces), path)
        return [trimesh.Trimesh(v, f, process=True) for v, f in parts]
    except FileNotFoundError:
        pass  # not cached yet: compute and store
    except Exception as exc:  # a damaged entry (cut short, corrupt): computed and replaced
        log.warning("object asset cache %s unreadable (%s): decomposing again", path, exc)
    parts = _coacd_parts(mesh, **settings)
    arrays = {"count": np.array(len(parts))}
    for i, (v, f) in enumerate(parts):
        arrays[f"v{i}"], arrays[f"f{i}"] = np.asarray(v), np.asarray(f)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_npz(path, arrays)
    except OSError as exc:
        log.warning("object asset cache %s not written (%s): convex parts not cached", path, exc)
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
