"""The embedded demo: deterministic, valid, and realistic in the ways the issue lists."""

from __future__ import annotations

import numpy as np
import pytest

from dexflow.data.demo import generate_demo
from dexflow.data.ycb_standins import STANDINS, build_standin
from dexflow.human.cleaning import detect_bad_frames
from dexflow.human.keypoints import FINGERTIPS
from dexflow.human.model import HandShape, finger_capsules
from dexflow.io.sequence import load_sequence
from dexflow.objects.sdf import SignedDistanceGrid, signed_distance
from dexflow.params import DemoConfig

SMALL = dict(objects=["061_foam_brick"], sequences_per_object=2, min_frames=60, max_frames=70)
NO_TEMPLATE = dict(template_start_probability=0.0, template_end_probability=0.0)


def _files(root):
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_same_seed_gives_identical_files(tmp_path):
    cfg = DemoConfig(seed=3, **SMALL)
    generate_demo(cfg, tmp_path / "a")
    generate_demo(cfg, tmp_path / "b", 2)
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert sorted(a) == sorted(b) and len(a) == 4  # mesh, 2 sequences, index.json
    assert all(a[k] == b[k] for k in a)
    generate_demo(DemoConfig(seed=4, **SMALL), tmp_path / "c")
    c = _files(tmp_path / "c")
    assert any(a[k] != c.get(k) for k in a if k.startswith("sequences/"))


def test_stand_ins_have_real_sizes():
    for name, spec in STANDINS.items():
        mesh = build_standin(name)
        extents = np.sort(mesh.extents)[::-1] * 1000
        np.testing.assert_allclose(extents, spec.extents_mm, rtol=0.02, err_msg=name)
        assert len(mesh.faces) >= 500, name
        assert mesh.is_watertight == spec.watertight, name


def _skin_distance(seq, keypoints, mesh_path):
    from dexflow.objects.mesh import load_mesh

    sdf = SignedDistanceGrid.from_mesh(load_mesh(mesh_path), spacing=0.002)
    inv = np.linalg.inv(seq.obj_pose)
    kp_obj = np.einsum("tij,tkj->tki", inv[:, :3, :3], keypoints) + inv[:, None, :3, 3]
    skin, radii = finger_capsules(kp_obj, HandShape(scale=float(seq.extras["hand_scale"])))
    return (sdf.query(skin) - radii).min(axis=-1)


@pytest.mark.parametrize(
    ("mode", "lo", "hi"), [("inside", -0.0105, -0.0025), ("hover", 0.0, 0.0115)]
)
def test_annotation_error_puts_contacts_inside_or_hovering(tmp_path, mode, lo, hi):
    cfg = DemoConfig(
        seed=1,
        objects=["005_tomato_soup_can"],
        sequences_per_object=1,
        noise_std_m=0.0,
        dropout_bursts=0.0,
        tracking_loss_probability=0.0,
        **NO_TEMPLATE,
        hold_penetration_probability=0.0,  # only the per-finger annotation error here
        tip_inside_probability=0.0,
        inside_fraction=1.0 if mode == "inside" else 0.0,
        hover_fraction=1.0 if mode == "hover" else 0.0,
    )
    generate_demo(cfg, tmp_path)
    path = next((tmp_path / "sequences").glob("*.npz"))
    seq = load_sequence(path, data_root=tmp_path)
    gt = seq.gt_contact
    assert gt.any(axis=0).sum() >= 2  # thumb and at least one finger touch
    recorded = _skin_distance(seq, seq.keypoints, tmp_path / seq.obj_mesh)
    clean = _skin_distance(seq, seq.extras["gt_keypoints"], tmp_path / seq.obj_mesh)
    assert (clean[gt] <= cfg.contact_tolerance_m + 1e-3).all()  # the truth touches
    held = recorded[gt]
    assert lo <= np.median(held) <= hi, (mode, np.median(held))


def test_tracker_artefacts_are_present_and_marked(tmp_path):
    cfg = DemoConfig(
        seed=2,
        objects=["061_foam_brick"],
        sequences_per_object=1,
        dropout_bursts=3.0,
        tracking_loss_probability=1.0,
        **NO_TEMPLATE,  # template runs: test_template_runs_at_the_start_and_end_like_dexycb
    )
    generate_demo(cfg, tmp_path)
    seq = load_sequence(next((tmp_path / "sequences").glob("*.npz")), data_root=tmp_path)
    dropped = ~seq.valid
    assert dropped.any() and np.isnan(seq.keypoints[dropped]).all()
    assert np.isfinite(seq.keypoints[~dropped]).all()
    lost = seq.extras["gt_tracking_lost"]
    assert 2 <= lost.sum() <= 5 and seq.valid[lost].all()
    jump = np.linalg.norm(seq.keypoints[lost, 0] - seq.extras["gt_keypoints"][lost, 0], axis=-1)
    assert (jump >= 0.19).all()  # "teleported" tens of centimetres
    ok = ~dropped & ~lost
    noise = np.linalg.norm(seq.keypoints[ok] - seq.extras["gt_keypoints"][ok], axis=-1)
    assert 0.001 < np.median(noise) < 0.02  # a tracker's few millimetres, plus annotation error


def test_template_runs_at_the_start_and_end_like_dexycb(tmp_path):
    cfg = DemoConfig(seed=5, **SMALL, template_start_probability=1.0, template_end_probability=1.0)
    generate_demo(cfg, tmp_path)
    for path in sorted((tmp_path / "sequences").glob("*.npz")):
        seq = load_sequence(path, data_root=tmp_path)
        template, lost = seq.extras["gt_template"], seq.extras["gt_tracking_lost"]
        n = seq.num_frames
        starts = np.flatnonzero(np.diff(np.r_[0, template.astype(int)]) == 1)
        assert list(starts) in ([0], [0, n - template[::-1].argmin()]), starts
        assert template[0] and template[-1] and template.sum() < n / 2
        assert seq.valid[template].all() and lost[template].all()  # valid, as uncleaned
        frames = seq.keypoints[template]
        np.testing.assert_array_equal(frames, np.repeat(frames[:1], len(frames), axis=0))
        away = np.linalg.norm(frames[:, 0] - seq.extras["gt_keypoints"][template, 0], axis=-1)
        assert (away > 0.45).all() and (away < 1.0).all()
        # The cleaner finds every lost frame (template runs and teleports) and no real one.
        observed, found = detect_bad_frames(seq.keypoints, seq.valid, 0.08, fps=seq.fps)
        np.testing.assert_array_equal(found, lost)
        np.testing.assert_array_equal(observed, seq.valid & ~lost)


def _held_tip_and_wrist_distance(seq, mesh, keypoints):
    held = seq.gt_contact.sum(axis=1) >= 2
    held &= ~seq.extras["gt_tracking_lost"] & seq.valid
    inv = np.linalg.inv(seq.obj_pose[held])
    points = keypoints[held][:, [0, *FINGERTIPS]]
    local = np.einsum("tij,tkj->tki", inv[:, :3, :3], points) + inv[:, None, :3, 3]
    dist = signed_distance(mesh, local.reshape(-1, 3)).reshape(len(local), -1)
    return dist[:, 1:].min(axis=1), dist[:, 0]


def test_annotated_hand_penetrates_the_object_while_holding(tmp_path):
    from dexflow.objects.mesh import load_mesh

    common = dict(
        seed=1, objects=["005_tomato_soup_can"], sequences_per_object=1, **NO_TEMPLATE,
        tracking_loss_probability=0.0, dropout_bursts=0.0, hold_penetration_wobble_m=0.0,
    )  # fmt: skip
    tips = DemoConfig(
        **common, hold_penetration_probability=0.0, tip_inside_probability=1.0,
        tip_depth_mean_m=1.0, tip_depth_max_m=0.006,  # D = 6 mm
    )  # fmt: skip
    palm = DemoConfig(
        **common, hold_penetration_probability=1.0, hold_penetration_m=(0.008, 0.008),
        tip_inside_probability=0.0,
    )  # fmt: skip
    for name, cfg in (("tips", tips), ("palm", palm)):
        generate_demo(cfg, tmp_path / name)
    seqs = {
        name: load_sequence(next((tmp_path / name / "sequences").glob("*.npz")))
        for name in ("tips", "palm")
    }
    mesh = load_mesh(tmp_path / "tips" / seqs["tips"].obj_mesh)
    seq = seqs["tips"]
    tip, _ = _held_tip_and_wrist_distance(seq, mesh, seq.keypoints)
    clean_tip, _ = _held_tip_and_wrist_distance(seq, mesh, seq.extras["gt_keypoints"])
    assert np.median(clean_tip) > 0.0  # the truth touches with the skin, tips outside
    assert np.median(tip) < -0.003  # the annotation: the deepest fingertip 6 mm inside
    seq = seqs["palm"]
    _, wrist = _held_tip_and_wrist_distance(seq, mesh, seq.keypoints)
    _, clean_wrist = _held_tip_and_wrist_distance(seq, mesh, seq.extras["gt_keypoints"])
    assert 0.004 < np.median(clean_wrist - wrist) < 0.012  # the whole hand 8 mm deeper


def test_default_demo_penetrates_like_dexycb(tmp_path):
    from dexflow.objects.mesh import load_mesh

    objects = ["005_tomato_soup_can", "025_mug", "006_mustard_bottle", "024_bowl"]
    generate_demo(DemoConfig(seed=0, objects=objects, sequences_per_object=2), tmp_path, 2)
    deepest = []
    for path in sorted((tmp_path / "sequences").glob("*.npz")):
        seq = load_sequence(path, data_root=tmp_path)
        tip, _ = _held_tip_and_wrist_distance(
            seq, load_mesh(tmp_path / seq.obj_mesh), seq.keypoints
        )
        deepest.append(np.maximum(-tip, 0.0))
    deepest = np.concatenate(deepest)
    assert 0.001 < np.median(deepest) < 0.008, np.median(deepest)  # DexYCB: ~4 mm
    assert 0.1 < (deepest > 0.01).mean() < 0.45, (deepest > 0.01).mean()  # DexYCB: ~28 %


def test_the_default_demo_has_every_grasp_type(tmp_path):
    """Each object's sequences cycle through its listed grasp types; the default demo's 2 per
    object still list every type, and the lateral grasp (the bowl's second) is synthesised,
    not replaced by a fallback."""
    from dexflow.data.grasps import GRASP_TYPES
    from dexflow.data.ycb_standins import STANDINS

    per_object = DemoConfig().sequences_per_object
    assert per_object == 2
    listed = {g for s in STANDINS.values() for g in s.grasps[:per_object]}
    assert listed == set(GRASP_TYPES)
    generate_demo(
        DemoConfig(seed=0, objects=["024_bowl"], sequences_per_object=per_object), tmp_path
    )
    names = sorted(p.stem for p in (tmp_path / "sequences").glob("*.npz"))
    assert names == ["024_bowl__00_pinch", "024_bowl__01_lateral"]


def _can(tmp_path, **quirks):
    cfg = DemoConfig(
        seed=6, objects=["005_tomato_soup_can"], sequences_per_object=1, **NO_TEMPLATE, **quirks
    )
    generate_demo(cfg, tmp_path)
    return load_sequence(next((tmp_path / "sequences").glob("*.npz")), data_root=tmp_path)


def test_tilted_rests_and_spinning_annotations_like_dexycb(tmp_path):
    """With both quirks on, the can's recorded scene is tilted 15-40 degrees (its axis off the
    vertical at rest, so it stands on its rim's edge) and its annotation turns about its axis
    while held, by up to spin_rad, its surface where it was: the hand's distances to it are
    those of the same sequence without the quirks, which is that sequence turned."""
    plain = _can(tmp_path / "plain", rest_tilt_probability=0.0, spin_probability=0.0)
    odd = _can(tmp_path / "odd", rest_tilt_probability=1.0, spin_probability=1.0)
    upright = plain.obj_pose[0, :3, 2] @ [0.0, 0.0, 1.0]
    tilt = np.degrees(np.arccos(np.clip(odd.obj_pose[0, :3, 2] @ [0.0, 0.0, 1.0], -1, 1)))
    assert upright == pytest.approx(1.0) and 15.0 - 1e-6 <= tilt <= 40.0 + 1e-6
    scene = odd.obj_pose[0] @ np.linalg.inv(plain.obj_pose[0])  # the tilt (no spin at rest)
    turned = np.linalg.inv(plain.obj_pose) @ np.linalg.inv(scene) @ odd.obj_pose  # the spin
    axis = turned[:, :3, 2]  # the can's axis does not move: the spin is about it
    np.testing.assert_allclose(axis, np.tile([0.0, 0.0, 1.0], (len(axis), 1)), atol=1e-9)
    spin = np.abs(np.arctan2(turned[:, 1, 0], turned[:, 0, 0]))
    assert spin[0] < 1e-9 and 1.0 - 1e-6 <= spin.max() <= 2.5 + 1e-6
    mesh = tmp_path / "odd" / odd.obj_mesh
    before = _skin_distance(plain, plain.keypoints, mesh)
    after = _skin_distance(odd, odd.keypoints, mesh)
    ok = np.isfinite(before) & np.isfinite(after)
    near = ok & (np.abs(before) < 0.02)  # inside the SDF's grid (3 cm of padding)
    assert near.sum() > 100
    np.testing.assert_allclose(after[near], before[near], atol=1e-3)
