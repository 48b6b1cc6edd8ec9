"""Stage scale_align: similarity scaling, fingertip offsets, object precomputation, bad files."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from dexflow.io.layout import Layout
from dexflow.io.sequence import load_sequence, save_sequence
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import PipelineParams
from dexflow.stages.scale_align import run_scale_align, scale_sequence

from .conftest import make_sequence


def test_scaling_is_a_similarity_about_the_origin(sequence):
    out = scale_sequence(sequence, 1.5, dict.fromkeys(["thumb", "index"], 0.0))
    np.testing.assert_allclose(out.keypoints, sequence.keypoints * 1.5)
    np.testing.assert_allclose(out.obj_pose[:, :3, 3], sequence.obj_pose[:, :3, 3] * 1.5)
    np.testing.assert_array_equal(out.obj_pose[:, :3, :3], sequence.obj_pose[:, :3, :3])
    assert float(out.extras["scale"]) == 1.5


def test_fingertip_offset_moves_the_tip_along_the_distal_bone(sequence):
    out = scale_sequence(sequence, 1.0, {"index": 0.01, "thumb": -0.005})
    for tip, dip, offset in ((8, 7, 0.01), (4, 3, -0.005)):
        before = np.linalg.norm(sequence.keypoints[:, tip] - sequence.keypoints[:, dip], axis=-1)
        after = np.linalg.norm(out.keypoints[:, tip] - out.keypoints[:, dip], axis=-1)
        np.testing.assert_allclose(after - before, offset, atol=1e-12)
    np.testing.assert_array_equal(out.keypoints[:, 12], sequence.keypoints[:, 12])


def _params(**run) -> PipelineParams:
    params = PipelineParams()
    params.hand.scale = 1.2
    params.scale_align.sdf_spacing_m = 0.004
    params.scale_align.surface_samples = 256
    params.run.backend = run.get("backend", "sequential")
    params.run.n_jobs = run.get("n_jobs", 1)
    return params


def test_stage_precomputes_each_object_once_and_reports_bad_sequences(data_root):
    seqs = data_root / "sequences"
    save_sequence(seqs / "good_a.npz", make_sequence(12), data_root=data_root)
    save_sequence(seqs / "good_b.npz", make_sequence(15), data_root=data_root)
    bad = make_sequence(10)
    arrays = bad.to_arrays()
    arrays["keypoints"] = arrays["keypoints"] * 1000  # millimetres
    np.savez(seqs / "in_mm.npz", **arrays)
    (seqs / "broken.npz").write_bytes(b"garbage")
    save_sequence(seqs / "no_mesh.npz", replace(make_sequence(10), obj_mesh="meshes/gone.obj"))

    layout = Layout.of(data_root, root=data_root / "project")
    summary = run_scale_align(_params(), layout)
    out = layout.scale_align.root

    assert summary["num_ok"] == 2 and summary["num_failed"] == 3
    status = summary["sequences"]
    assert "millimetres" in status["in_mm"]["error"]
    assert "broken" in status and status["broken"]["status"] == "failed"
    assert "gone.obj" in status["no_mesh"]["error"]
    assert json.loads((out / "summary.json").read_text()) == summary

    ok_objects = [k for k, v in summary["objects"].items() if v["status"] == "ok"]
    assert len(ok_objects) == 1  # both good sequences share one precomputed box
    obj_dir = out / "objects" / ok_objects[0]
    mesh = trimesh.load(obj_dir / "mesh.obj", force="mesh")
    np.testing.assert_allclose(np.sort(mesh.extents), np.sort([0.06, 0.04, 0.08]) * 1.2, atol=1e-6)
    surface = np.load(obj_dir / "surface.npz")
    sdf = SignedDistanceGrid.load(obj_dir / "sdf.npz")
    assert np.abs(sdf.query(surface["points"])).max() < 0.004
    outward = sdf.query(surface["points"] + 0.004 * surface["normals"])
    assert (outward > 0).all()  # normals point out of the object
    convex = trimesh.load(obj_dir / "convex.obj", force="mesh")
    assert convex.volume == pytest.approx(mesh.volume, rel=0.1)

    aligned = load_sequence(out / "sequences" / "good_a.npz", data_root=out)
    np.testing.assert_allclose(aligned.keypoints, make_sequence(12).keypoints * 1.2)
    assert aligned.obj_mesh == f"objects/{ok_objects[0]}/mesh.obj"


def test_backends_give_identical_outputs(data_root):
    for i in range(3):
        save_sequence(
            data_root / "sequences" / f"s{i}.npz", make_sequence(10 + i), data_root=data_root
        )
    seq, par = Layout.of(data_root, data_root / "seq"), Layout.of(data_root, data_root / "par")
    run_scale_align(_params(), seq)
    run_scale_align(_params(backend="local", n_jobs=2), par)
    seq_out, par_out = seq.scale_align.root, par.scale_align.root
    files = sorted(p.relative_to(seq_out) for p in seq_out.rglob("*") if p.is_file())
    assert files
    for rel in files:
        assert (seq_out / rel).read_bytes() == (par_out / rel).read_bytes(), rel
