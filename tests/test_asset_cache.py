"""The object asset cache: convex parts decomposed once per mesh and settings, scale-equivariant,
exactly what CoACD returned, and off when asked."""

from __future__ import annotations

import numpy as np
import trimesh

from dexflow.objects import convex
from dexflow.objects.convex import CACHE_ENV, cached_convex_decomposition, convex_decomposition

SETTINGS = {"threshold": 0.2, "max_hulls": 4, "preprocess_resolution": 20, "mcts_iterations": 20,
            "mcts_max_depth": 2, "mcts_nodes": 10, "seed": 0}  # fmt: skip


def _mesh() -> trimesh.Trimesh:  # an L: two convex parts at least
    a = trimesh.creation.box(extents=(0.06, 0.02, 0.02))
    b = trimesh.creation.box(extents=(0.02, 0.06, 0.02))
    b.apply_translation((0.02, 0.02, 0.0))
    return trimesh.boolean.union([a, b], engine="manifold")


def _counting(monkeypatch) -> list[int]:
    calls: list[int] = []
    original = convex._coacd_parts

    def counted(mesh, **settings):
        calls.append(len(mesh.faces))
        return original(mesh, **settings)

    monkeypatch.setattr(convex, "_coacd_parts", counted)
    return calls


def _vertices(parts) -> np.ndarray:
    return np.concatenate([p.vertices for p in parts])


def test_the_second_request_reads_the_parts_back_without_decomposing(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    calls = _counting(monkeypatch)
    first = cached_convex_decomposition(_mesh(), **SETTINGS)
    again = cached_convex_decomposition(_mesh(), **SETTINGS)
    assert len(calls) == 1 and len(list((tmp_path / "cache" / "convex").glob("*.npz"))) == 1
    assert len(first) >= 2 and np.array_equal(_vertices(first), _vertices(again))
    fresh = convex_decomposition(_mesh(), **SETTINGS)  # uncached: CoACD again (call 2)
    assert np.array_equal(_vertices(first), _vertices(fresh))  # exactly what CoACD returns
    cached_convex_decomposition(_mesh(), **{**SETTINGS, "seed": 1})  # other settings: computed
    moved = _mesh()
    moved.apply_translation((0.001, 0, 0))
    cached_convex_decomposition(moved, **SETTINGS)  # another mesh: computed
    assert len(calls) == 4


def test_parts_of_a_scaled_mesh_are_the_scaled_parts(tmp_path, monkeypatch):
    """What lets one cache entry serve every hand's scale (stage scale_align scales the parts)."""
    monkeypatch.setenv(CACHE_ENV, "off")
    mesh = _mesh()
    big = mesh.copy()
    big.apply_scale(1.7)
    parts = convex_decomposition(mesh, **SETTINGS)
    for part in parts:
        part.apply_scale(1.7)
    assert np.allclose(
        _vertices(parts), _vertices(convex_decomposition(big, **SETTINGS)), atol=1e-12
    )


def test_the_cache_can_be_turned_off_or_be_unwritable(tmp_path, monkeypatch, caplog):
    calls = _counting(monkeypatch)
    monkeypatch.setenv(CACHE_ENV, "off")
    cached_convex_decomposition(_mesh(), **SETTINGS)
    cached_convex_decomposition(_mesh(), **SETTINGS)
    assert len(calls) == 2
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(CACHE_ENV, str(blocker))
    assert len(cached_convex_decomposition(_mesh(), **SETTINGS)) >= 2  # parts still returned
    assert "not written" in caplog.text


def test_a_damaged_entry_is_decomposed_again_and_replaced(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    calls = _counting(monkeypatch)
    first = cached_convex_decomposition(_mesh(), **SETTINGS)
    (entry,) = (tmp_path / "cache" / "convex").glob("*.npz")
    entry.write_bytes(entry.read_bytes()[:100])  # cut short (a full disk, a killed copy)
    again = cached_convex_decomposition(_mesh(), **SETTINGS)
    assert len(calls) == 2 and "unreadable" in caplog.text
    assert np.array_equal(_vertices(first), _vertices(again))
    cached_convex_decomposition(_mesh(), **SETTINGS)
    assert len(calls) == 2  # replaced by a good entry


def test_coacd_uses_every_core_inside_a_one_thread_worker_with_the_same_parts(monkeypatch):
    """A pool worker is limited to one OpenMP thread; CoACD is given one per core, and its parts
    do not depend on that."""
    import os

    import coacd
    from threadpoolctl import threadpool_info, threadpool_limits

    cores = os.cpu_count()
    seen: list[int] = []
    original = coacd.run_coacd

    def recorded(*args, **kwargs):
        seen.append(max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "openmp"))
        return original(*args, **kwargs)

    monkeypatch.setattr(coacd, "run_coacd", recorded)
    with threadpool_limits(limits=1, user_api="openmp"):  # what joblib gives a worker
        parts = convex_decomposition(_mesh(), **SETTINGS)
        monkeypatch.setattr(os, "cpu_count", lambda: 1)  # one thread, as a worker had before
        single = convex_decomposition(_mesh(), **SETTINGS)
    assert seen == [cores, 1]
    np.testing.assert_array_equal(_vertices(parts), _vertices(single))
