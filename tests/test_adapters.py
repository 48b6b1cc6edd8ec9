"""Dataset adapters on small fake datasets in each layout: exact joints, poses, order, errors."""

from __future__ import annotations

import json
import pickle
from dataclasses import replace

import numpy as np
import pytest
import trimesh
import yaml
from scipy.spatial.transform import Rotation

from dexflow.data.adapters import HO3D_TO_DEXFLOW, ConvertOptions, DatasetLayoutError, convert
from dexflow.geometry import world_to_object
from dexflow.human.mano import FINGERTIP_VERTICES, MANO_TO_DEXFLOW, load_mano
from dexflow.human.model import forward_keypoints
from dexflow.io.mirror import MIRROR, unmirror_points, unmirror_transforms
from dexflow.io.sequence import load_sequence

T = 6


def _hand(n=T, offset=(0.0, 0.0, 0.0)):
    """Keypoints (n, 21, 3) of a hand closing slowly beside the origin (MANO order, metres)."""
    angles = np.linspace(0.0, 0.5, n)[:, None] * np.ones(20)
    wrist = np.repeat(np.eye(4)[None], n, axis=0)
    wrist[:, :3, :3] = Rotation.from_euler("y", -90, degrees=True).as_matrix()
    wrist[:, :3, 3] = np.array([0.0, -0.02, -0.09]) + offset
    return forward_keypoints(angles, wrist)


def _poses(n=T):
    pose = np.repeat(np.eye(4)[None], n, axis=0)
    pose[:, :3, :3] = Rotation.from_rotvec(np.linspace([0, 0, 0], [0, 0, 0.3], n)).as_matrix()
    pose[:, :3, 3] = np.linspace([0.0, 0.0, 0.0], [0.0, 0.0, 0.05], n)
    return pose


def _box(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(0.06, 0.04, 0.08)).export(path)


def _ho3d_order(kp):
    out = np.empty_like(kp)
    out[..., list(HO3D_TO_DEXFLOW), :] = kp
    return out


def _make_dexycb(root, side="right"):
    seq = root / "20200709-subject-01" / "20200709_141754"
    extr = np.hstack(
        [Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_matrix(), [[0.1], [0.2], [0.3]]]
    )
    extr = np.vstack([extr, [0, 0, 0, 1]])
    tag = np.eye(4)  # the table's tag in DexYCB's world: tilted, off its origin
    tag[:3, :3] = Rotation.from_euler("xyz", [0.4, 0.1, -0.7]).as_matrix()
    tag[:3, 3] = [0.05, -0.3, 0.6]
    extr = tag @ extr  # the camera in the tag's frame is the one the test expects
    (root / "calibration" / "extrinsics_20200702_151821").mkdir(parents=True)
    (root / "calibration" / "extrinsics_20200702_151821" / "extrinsics.yml").write_text(
        yaml.safe_dump(
            {
                "extrinsics": {
                    "836212060125": extr[:3].reshape(-1).tolist(),
                    "apriltag": tag[:3].reshape(-1).tolist(),
                }
            }
        )
    )
    seq.mkdir(parents=True)
    (seq / "meta.yml").write_text(
        yaml.safe_dump(
            {
                "serials": ["836212060125", "839512060362"],
                "num_frames": T,
                "ycb_ids": [1, 14],
                "ycb_grasp_ind": 1,
                "mano_sides": [side],
                "extrinsics": "20200702_151821",
            }
        )
    )
    cam = seq / "836212060125"
    cam.mkdir()
    hand, poses = _hand(), _poses()
    world_to_cam = np.linalg.inv(extr) @ tag  # the expected (tag) frame to the camera
    for t in range(T):
        joints = hand[t] @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
        if t == 2:
            joints = -np.ones((21, 3))  # DexYCB's "no hand in this frame"
        obj = (world_to_cam @ poses[t])[:3]
        np.savez(
            cam / f"labels_{t:06d}.npz",
            joint_3d=joints[None],
            pose_y=np.stack([np.eye(4)[:3], obj]),
        )
    _box(root / "models" / "025_mug" / "textured_simple.obj")
    return hand, poses


def _edit_extrinsics(root, change) -> None:
    path = root / "calibration" / "extrinsics_20200702_151821" / "extrinsics.yml"
    data = yaml.safe_load(path.read_text())
    change(data["extrinsics"])
    path.write_text(yaml.safe_dump(data))


def test_dexycb_without_a_table_tag_stays_in_its_calibration_frame(tmp_path):
    """Calibrations without ``apriltag`` keep DexYCB's world frame (z no vertical): the same
    sequence moved by the tag's transform."""
    _, poses = _make_dexycb(tmp_path / "src")
    path = tmp_path / "src" / "calibration" / "extrinsics_20200702_151821" / "extrinsics.yml"
    tag = np.vstack([np.reshape(yaml.safe_load(path.read_text())["extrinsics"]["apriltag"],
                                (3, 4)), [0, 0, 0, 1]])  # fmt: skip
    _edit_extrinsics(tmp_path / "src", lambda extr: extr.pop("apriltag"))
    assert convert("dexycb", tmp_path / "src", tmp_path / "out")["num_ok"] == 1
    (path,) = (tmp_path / "out" / "sequences").glob("*.npz")
    seq = load_sequence(path, data_root=tmp_path / "out")
    np.testing.assert_allclose(seq.obj_pose, tag @ poses, atol=1e-9)


@pytest.mark.parametrize("side", ["right", "left"])
def test_dexycb_uses_the_given_joints_in_world_frame(tmp_path, side):
    """In the frame of the table's tag (z up), from the camera's labels and the extrinsics."""
    hand, poses = _make_dexycb(tmp_path / "src", side)
    report = convert("dexycb", tmp_path / "src", tmp_path / "out")
    assert report["num_ok"] == 1, report
    seq = load_sequence(
        next((tmp_path / "out" / "sequences").glob("*.npz")), data_root=tmp_path / "out"
    )
    assert seq.obj_name == "025_mug" and seq.fps == 30.0 and seq.source == "dexycb"
    assert not seq.valid[2] and np.isnan(seq.keypoints[2]).all() and seq.valid.sum() == T - 1
    ok = seq.valid
    if side == "right":
        np.testing.assert_allclose(seq.keypoints[ok], hand[ok], atol=1e-9)
        np.testing.assert_allclose(seq.obj_pose, poses, atol=1e-9)
    else:  # mirrored to a right hand, with its object; and back again
        assert seq.mirrored and seq.side == "left"
        np.testing.assert_allclose(seq.keypoints[ok], hand[ok] @ MIRROR, atol=1e-9)
        np.testing.assert_allclose(unmirror_points(seq.keypoints[ok]), hand[ok], atol=1e-9)
        np.testing.assert_allclose(unmirror_transforms(seq.obj_pose), poses, atol=1e-9)
        mesh = trimesh.load(tmp_path / "out" / seq.obj_mesh, force="mesh")
        assert mesh.volume > 0  # re-wound faces: still a solid, not an inside-out mesh


def test_ho3d_reorders_joints_and_fills_missing_frames(tmp_path):
    hand, poses = _hand(), _poses()
    meta = tmp_path / "src" / "MC1" / "meta"
    meta.mkdir(parents=True)
    for t in range(T):
        if t == 3:
            continue  # a frame file missing altogether
        joints = None if t == 1 else _ho3d_order(hand[t])
        record = {
            "handJoints3D": joints,
            "objRot": Rotation.from_matrix(poses[t, :3, :3]).as_rotvec()[:, None],
            "objTrans": poses[t, :3, 3],
            "objName": "025_mug",
        }
        with open(meta / f"{t:04d}.pkl", "wb") as handle:
            pickle.dump(record, handle)
    _box(tmp_path / "src" / "models" / "025_mug" / "textured_simple.obj")
    assert convert("ho3d", tmp_path / "src", tmp_path / "out")["num_ok"] == 1
    seq = load_sequence(tmp_path / "out" / "sequences" / "ho3d_src_MC1.npz")
    assert seq.num_frames == T and list(np.flatnonzero(~seq.valid)) == [1, 3]
    np.testing.assert_allclose(seq.keypoints[seq.valid], hand[seq.valid], atol=1e-12)
    np.testing.assert_allclose(seq.obj_pose[[0, 2, 4]], poses[[0, 2, 4]], atol=1e-9)
    np.testing.assert_allclose(seq.obj_pose[3], poses[2], atol=1e-9)  # held from a neighbour


def test_grab_and_generic_layouts(tmp_path):
    hand, poses = _hand(), _poses()
    src = tmp_path / "grab"
    _box(src / "tools" / "box.ply")
    obj = {
        "params": {
            "transl": poses[:, :3, 3],
            "global_orient": Rotation.from_matrix(poses[:, :3, :3]).as_rotvec(),
        },
        "object_mesh": "tools/box.ply",
    }
    (src / "s1").mkdir()
    np.savez(
        src / "s1" / "box_lift.npz",
        framerate=np.array(120.0),
        object=np.array(obj, dtype=object),
        rhand=np.array({"joints": hand}, dtype=object),
        lhand=np.array({"joints": hand}, dtype=object),
    )
    assert convert("grab", src, tmp_path / "out")["num_ok"] == 1
    seq = load_sequence(tmp_path / "out" / "sequences" / "grab_s1_box_lift.npz")
    assert seq.fps == 120.0
    np.testing.assert_allclose(seq.keypoints, hand, atol=1e-12)
    np.testing.assert_allclose(seq.obj_pose, poses, atol=1e-9)

    gen = tmp_path / "gen"
    _box(gen / "box.obj")
    np.savez(
        gen / "a.npz",
        keypoints=hand * 1000,
        obj_pose=poses * [1, 1, 1, 1],
        obj_mesh="box.obj",
        fps=60.0,
        units="mm",
        keypoint_order="mano",
    )
    np.savez(
        gen / "a.npz",
        keypoints=hand * 1000,
        obj_rotvec=Rotation.from_matrix(poses[:, :3, :3]).as_rotvec(),
        obj_trans=poses[:, :3, 3] * 1000,
        obj_mesh="box.obj",
        fps=60.0,
        units="mm",
    )
    cols = {
        f"kp{i}_{c}": _ho3d_order(hand)[:, i, k] for i in range(21) for k, c in enumerate("xyz")
    }
    rv = Rotation.from_matrix(poses[:, :3, :3]).as_rotvec()
    cols |= {
        "obj_rx": rv[:, 0],
        "obj_ry": rv[:, 1],
        "obj_rz": rv[:, 2],
        "obj_tx": poses[:, 0, 3],
        "obj_ty": poses[:, 1, 3],
        "obj_tz": poses[:, 2, 3],
    }
    import pandas as pd

    table = pd.DataFrame(cols)
    table.loc[4, "kp0_x"] = np.nan  # an empty cell: no hand in frame 4
    table.to_csv(gen / "b.csv", index=False)
    (gen / "b.json").write_text(
        json.dumps({"obj_mesh": "box.obj", "fps": 30, "keypoint_order": "ho3d"})
    )
    report = convert("generic", gen, tmp_path / "gen_out")
    assert report["num_ok"] == 2, report
    a = load_sequence(tmp_path / "gen_out" / "sequences" / "generic_a.npz")
    b = load_sequence(tmp_path / "gen_out" / "sequences" / "generic_b.npz")
    np.testing.assert_allclose(a.keypoints, hand, atol=1e-12)  # millimetres converted
    np.testing.assert_allclose(a.obj_pose, poses, atol=1e-9)
    np.testing.assert_allclose(
        b.keypoints[b.valid], hand[b.valid], atol=1e-12
    )  # HO-3D order undone
    assert list(np.flatnonzero(~b.valid)) == [4]
    assert report["sequences"]["a"]["fingertip_to_surface_mm_median"] < 200


def test_tracking_loss_frames_are_masked_on_conversion(tmp_path):
    n = 30
    hand, poses = _hand(n), _poses(n)
    hand[12:15] = _hand(3, offset=(0.4, 0.3, 0.0))  # a default pose reported far away
    gen = tmp_path / "gen"
    _box(gen / "box.obj")
    np.savez(gen / "a.npz", keypoints=hand, obj_pose=poses, obj_mesh="box.obj", fps=30.0)
    report = convert("generic", gen, tmp_path / "out")
    assert report["sequences"]["a"]["tracking_lost_frames"] == 3
    seq = load_sequence(tmp_path / "out" / "sequences" / "generic_a.npz")
    assert list(np.flatnonzero(~seq.valid)) == [12, 13, 14]


def _write_ho3d(seq_dir, hand, poses, template=(), obj="025_mug", side="right"):
    """HO-3D-layout frames; ``template`` frames carry the MANO template hand, as DexYCB's do."""
    meta = seq_dir / "meta"
    meta.mkdir(parents=True)
    far = _hand(1, offset=(0.5, -0.5, 0.3))[0]  # the template's joints: present, 0.8 m away
    for t in range(len(hand)):
        is_template = t in template
        record = {
            "handJoints3D": _ho3d_order(far if is_template else hand[t]),
            "handPose": np.zeros(48) if is_template else np.full(48, 0.1),
            "handTrans": np.zeros(3) if is_template else hand[t, 0],
            "objRot": Rotation.from_matrix(poses[t, :3, :3]).as_rotvec(),
            "objTrans": poses[t, :3, 3],
            "objName": obj,
            "side": side,
        }
        with open(meta / f"{t:04d}.pkl", "wb") as handle:
            pickle.dump(record, handle)


def test_ho3d_template_frames_are_invalid_at_the_source_even_when_most_frames_are(tmp_path):
    n = 20
    hand, poses = _hand(n), _poses(n)
    template = [*range(11), 18, 19]  # more than half: continuity alone would keep these
    _write_ho3d(tmp_path / "src" / "20201002-subject-08" / "20201002_104719", hand, poses, template)
    _box(tmp_path / "models" / "025_mug" / "textured_simple.obj")
    options = ConvertOptions(models=str(tmp_path / "models"))
    report = convert("ho3d", tmp_path / "src" / "20201002-subject-08", tmp_path / "out", options)
    entry = report["sequences"]["20201002-subject-08_20201002_104719"]
    assert entry["template_frames"] == 13 and entry["missing_frames"] == 0, entry
    seq = load_sequence(
        tmp_path / "out" / "sequences" / "ho3d_20201002-subject-08_20201002_104719.npz"
    )
    assert list(np.flatnonzero(seq.valid)) == list(range(11, 18))
    assert np.isnan(seq.keypoints[template]).all()
    np.testing.assert_allclose(seq.keypoints[seq.valid], hand[seq.valid], atol=1e-12)


def test_dexycb_all_zero_mano_pose_marks_a_template_frame(tmp_path):
    _make_dexycb(tmp_path / "src")
    cam = tmp_path / "src" / "20200709-subject-01" / "20200709_141754" / "836212060125"
    for t in range(T):
        with np.load(cam / f"labels_{t:06d}.npz") as data:
            fields = dict(data)
        fields["pose_m"] = np.zeros((1, 51)) if t in (0, 1) else np.full((1, 51), 0.1)
        np.savez(cam / f"labels_{t:06d}.npz", **fields)
    report = convert("dexycb", tmp_path / "src", tmp_path / "out")
    entry = report["sequences"]["20200709-subject-01_20200709_141754"]
    assert (entry["template_frames"], entry["missing_frames"]) == (2, 1), entry
    seq = load_sequence(next((tmp_path / "out" / "sequences").glob("*.npz")))
    assert list(np.flatnonzero(~seq.valid)) == [0, 1, 2]


def _two_subjects(root):
    """Two subject folders of HO-3D-layout captures (one without its mesh) and the models."""
    hand, poses = _hand(), _poses()
    _write_ho3d(root / "captures" / "20201002-subject-08" / "20201002_104719", hand, poses)
    _write_ho3d(root / "captures" / "20201015-subject-09" / "20201015_142724", hand, poses)
    _write_ho3d(
        root / "captures" / "20201015-subject-09" / "20201015_150000", hand, poses, obj="011_banana"
    )
    _box(root / "models" / "025_mug" / "textured_simple.obj")
    return root / "captures", root / "models"


def test_convert_gathers_several_sources_or_a_dataset_root_and_skips_missing_meshes(tmp_path):
    captures, models = _two_subjects(tmp_path)
    options = ConvertOptions(models=str(models))
    subjects = sorted(captures.iterdir())
    by_folders = convert("ho3d", subjects, tmp_path / "a", options)
    by_root = convert("ho3d", captures, tmp_path / "b", options)
    for report, out in ((by_folders, tmp_path / "a"), (by_root, tmp_path / "b")):
        assert (report["num_ok"], report["num_skipped"], report["num_failed"]) == (2, 1, 0)
        names = sorted(p.name for p in (out / "sequences").glob("*.npz"))
        assert names == [
            "ho3d_20201002-subject-08_20201002_104719.npz",
            "ho3d_20201015-subject-09_20201015_142724.npz",
        ]
        skipped = report["sequences"]["20201015-subject-09_20201015_150000"]
        assert skipped["status"] == "skipped" and "011_banana" in skipped["reason"]
        assert json.loads((out / "convert.json").read_text())["num_skipped"] == 1
    strict = convert(
        "ho3d", captures, tmp_path / "c", ConvertOptions(models=str(models), strict=True)
    )
    assert (strict["num_ok"], strict["num_failed"]) == (2, 1)
    twice = convert("ho3d", [subjects[0], subjects[0]], tmp_path / "d", options)
    assert (twice["num_ok"], twice["num_failed"]) == (1, 1)  # a name never overwrites another


def test_convert_command_exit_status(tmp_path, capsys):
    from dexflow.tools.cli import main

    captures, models = _two_subjects(tmp_path)
    subjects = [str(p) for p in sorted(captures.iterdir())]
    common = ["--models", str(models)]
    assert main(["convert", "ho3d", *subjects, str(tmp_path / "a"), *common]) == 0
    out = capsys.readouterr().out
    assert "skip 20201015-subject-09_20201015_150000: no object model of '011_banana'" in out
    assert "2/3 sequences written" in out and "0 template frames" in out
    assert main(["convert", "ho3d", *subjects, str(tmp_path / "b"), *common, "--strict"]) == 1
    assert (
        main(["convert", "ho3d", subjects[1], str(tmp_path / "c"), "--models", str(tmp_path)]) == 1
    )


def _session(folder, models, captures, camera_to_world, left=(), turn_rad=0.4):
    """A session in the HO-3D layout: ``captures`` objects resting on one table (z = 0 in the
    world), each lifted and tilted (by ``turn_rad``) after 4 frames, seen by one camera
    (``camera_to_world``); ``left`` captures are left hands. Returns per capture the object
    axis that is up at rest."""
    rng = np.random.default_rng(7)
    objects = {"025_mug": (0.06, 0.04, 0.08), "011_banana": (0.18, 0.04, 0.03)}
    for name, extents in objects.items():
        trimesh.creation.box(extents=extents).export(models / name / "textured_simple.obj")
    to_camera = np.linalg.inv(camera_to_world)
    n, ramp = 12, np.clip(np.arange(12) - 3, 0, 8)[:, None] / 8
    ups = []
    for c in range(captures):
        name = list(objects)[c % 2]
        face = Rotation.from_euler("x", 90 * (c % 3 == 2), degrees=True)  # on a side, or not
        rest = Rotation.from_euler("z", rng.uniform(-np.pi, np.pi)) * face
        ups.append(rest.inv().apply([0.0, 0.0, 1.0]))
        corners = trimesh.creation.box(extents=objects[name]).vertices
        start = [*rng.uniform(-0.15, 0.15, 2), -rest.apply(corners)[:, 2].min()]
        tilt = Rotation.from_rotvec(ramp * turn_rad * np.array([[1.0, 0.5, 0.0]]))
        poses = np.repeat(np.eye(4)[None], n, axis=0)
        poses[:, :3, :3] = (tilt * rest).as_matrix()
        poses[:, :3, 3] = start + ramp * [0.02, 0.0, 0.15]
        hand = _hand(n) @ poses[:, :3, :3].mT + poses[:, None, :3, 3]  # carried with it
        _write_ho3d(folder / f"capture_{c:02d}", hand @ to_camera[:3, :3].T + to_camera[:3, 3],
                    to_camera @ poses, obj=name, side="left" if c in left else "right")  # fmt: skip
    return ups


def _camera_over_the_table():
    """Camera-to-world (4, 4): 0.6 m from the table's centre, looking down at it, rolled 25°
    (so that up has an x component in its frame: mirroring changes it)."""
    position = np.array([0.1, -0.45, 0.4])
    forward = -position / np.linalg.norm(position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    axes = np.stack([right, np.cross(forward, right), forward], axis=1)  # x right, y down
    out = np.eye(4)
    out[:3, :3] = axes @ Rotation.from_euler("z", 25, degrees=True).as_matrix()
    out[:3, 3] = position
    return out


def _lowest_z(out, seq):
    """(T,) the lowest point of the written object's hull along the written z."""
    hull = trimesh.load(out / seq.obj_mesh, force="mesh").convex_hull.vertices
    return (hull @ seq.obj_pose[:, :3, :3].mT + seq.obj_pose[:, None, :3, 3])[..., 2].min(axis=1)


def _degrees(a, b):
    a, b = np.asarray(a) / np.linalg.norm(a), np.asarray(b) / np.linalg.norm(b)
    return np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0)))


def _in_object_frame(seq):
    return world_to_object(seq.keypoints[seq.valid], seq.obj_pose[seq.valid])


def test_ho3d_session_is_written_in_its_tables_frame(tmp_path):
    """Nine captures of one camera, three of them left hands: written z up, the table at z = 0
    (every object starts on it and never goes below), within 1 degree; each hand where it was
    on its object. The up vector is fitted in the camera's frame, before left hands are
    mirrored: fitted on the mirrored ones it would be off by the camera's roll."""
    camera = _camera_over_the_table()
    (tmp_path / "models" / "025_mug").mkdir(parents=True)
    (tmp_path / "models" / "011_banana").mkdir(parents=True)
    session = tmp_path / "src" / "20201002-subject-08"
    ups = _session(session, tmp_path / "models", 9, camera, left=(1, 4, 7))
    options = ConvertOptions(models=str(tmp_path / "models"))
    report = convert("ho3d", session, tmp_path / "up", options)
    kept = convert("ho3d", session, tmp_path / "camera", replace(options, camera_frame=True))
    assert report["num_ok"] == kept["num_ok"] == 9, report
    table = json.loads((tmp_path / "up" / "convert.json").read_text())["table_frames"]
    entry = table[str(session)]
    assert entry["applied"] and entry["captures"] == 9 and entry["dip_share"] == 0, entry
    assert entry["start_height_mad_m"] < 1e-3
    rotations = report["object_rotation"]["sessions"][str(session)]  # tilts too little to tell
    assert rotations["applied"] == rotations["found"] == "+x+y+z R +x+y+z", rotations
    assert rotations["reason"] == "0 carries turn by 10 deg or more, too few (at least 3)"
    up_in_camera = camera[:3, :3].T @ [0.0, 0.0, 1.0]
    assert _degrees(entry["up"], up_in_camera) < 1.0
    for c, up in enumerate(ups):
        name = f"ho3d_20201002-subject-08_capture_{c:02d}.npz"
        seq = load_sequence(tmp_path / "up" / "sequences" / name)
        assert seq.mirrored == (c in (1, 4, 7))
        low = _lowest_z(tmp_path / "up", seq)
        assert abs(low[0]) < 2e-3 and low.min() > -2e-3, (c, low)
        rest = unmirror_transforms(seq.obj_pose[0]) if seq.mirrored else seq.obj_pose[0]
        assert _degrees(rest[:3, :3] @ up, [0.0, 0.0, 1.0]) < 1.0, c
        camera_seq = load_sequence(tmp_path / "camera" / "sequences" / name)
        assert abs(_lowest_z(tmp_path / "camera", camera_seq)[0] - low[0]) > 0.05  # not z up
        np.testing.assert_allclose(_in_object_frame(seq), _in_object_frame(camera_seq), atol=1e-9)


def test_ho3d_camera_frame_is_kept_for_a_small_session_or_when_asked(tmp_path, caplog, capsys):
    """Fewer than 8 captures: the camera's frame, a warning naming the folder and the count.
    ``--camera-frame``: the camera's frame, whatever the session."""
    from dexflow.tools.cli import main

    camera = _camera_over_the_table()
    (tmp_path / "models" / "025_mug").mkdir(parents=True)
    (tmp_path / "models" / "011_banana").mkdir(parents=True)
    small, large = tmp_path / "src" / "small", tmp_path / "src" / "large"
    _session(small, tmp_path / "models", 5, camera)
    _session(large, tmp_path / "models", 8, camera)
    models = ["--models", str(tmp_path / "models")]
    with caplog.at_level("WARNING", logger="dexflow.data.adapters"):
        assert main(["convert", "ho3d", str(small), str(tmp_path / "a"), *models]) == 0
    (warning,) = [r.getMessage() for r in caplog.records if "camera's frame" in r.getMessage()]
    assert str(small) in warning and "5 captures, too few" in warning, warning
    assert (
        main(["convert", "ho3d", str(large), str(tmp_path / "b"), *models, "--camera-frame"]) == 0
    )
    assert main(["convert", "ho3d", str(large), str(tmp_path / "c"), *models]) == 0
    for out, folder, n in ((tmp_path / "a", small, 5), (tmp_path / "b", large, 8)):
        entry = json.loads((out / "convert.json").read_text())["table_frames"][str(folder)]
        assert not entry["applied"] and entry["captures"] == n, entry
        seq = load_sequence(out / "sequences" / f"ho3d_{folder.name}_capture_00.npz")
        with open(folder / "capture_00" / "meta" / "0000.pkl", "rb") as handle:
            first = pickle.load(handle)
        np.testing.assert_allclose(seq.obj_pose[0, :3, 3], first["objTrans"], atol=1e-12)
    entry = json.loads((tmp_path / "c" / "convert.json").read_text())["table_frames"]
    assert entry[str(large)]["applied"]  # the same 8 captures, without --camera-frame
    out = capsys.readouterr().out
    assert "kept the camera's frame" in out
    assert f"rotations {large}: read as '+x+y+z R +x+y+z'\n" in out


def _restore(folder, convention):
    """Rewrite a session's ``objRot`` so that ``convention`` reads back the rotations it had:
    ``R_stored = op(Lᵀ R_object Bᵀ)`` (``op`` its own inverse)."""
    for frame in sorted(folder.glob("*/meta/*.pkl")):
        with open(frame, "rb") as handle:
            record = pickle.load(handle)
        inner = convention.left.T @ Rotation.from_rotvec(record["objRot"]).as_matrix()
        inner = inner @ convention.right.T
        stored = inner.T if convention.transposed else inner
        record["objRot"] = Rotation.from_matrix(stored).as_rotvec()
        with open(frame, "wb") as handle:
            pickle.dump(record, handle)


def _world_hulls(out, name):
    """(T, 8, 3) the written box's corners in the written world, each frame's sorted."""
    seq = load_sequence(out / "sequences" / name)
    corners = trimesh.load(out / seq.obj_mesh, force="mesh").vertices
    world = corners @ seq.obj_pose[:, :3, :3].mT + seq.obj_pose[:, None, :3, 3]
    return np.sort(np.round(world, 9).view([("", world.dtype)] * 3), axis=1).view(world.dtype)


def test_object_rotations_written_another_way_are_found_by_hand_and_table(tmp_path, caplog):
    """A session whose objRot is written as a DexYCB export to the HO-3D layout wrote it (the
    transpose, with axes swapped on both sides): the default check keeps it as stored and warns
    with the convention that fits; ``auto`` and that convention give back the true objects, as
    a correctly written session converts; a correct session passes the check silently; a
    malformed convention is refused before anything is read."""
    from dexflow.data.rotation_convention import RotationConvention
    from dexflow.errors import ConfigError

    camera = _camera_over_the_table()
    for name in ("025_mug", "011_banana"):
        (tmp_path / "models" / name).mkdir(parents=True)
    right, wrong = tmp_path / "src" / "right", tmp_path / "src" / "wrong"
    _session(right, tmp_path / "models", 9, camera, left=(1, 4), turn_rad=2.0)  # 16° median
    _session(wrong, tmp_path / "models", 9, camera, left=(1, 4), turn_rad=2.0)
    convention = RotationConvention.parse("-z+y+x R^T +z-y+x")
    _restore(wrong, convention)
    options = ConvertOptions(models=str(tmp_path / "models"))
    with caplog.at_level("WARNING", logger="dexflow.data.adapters"):
        convert("ho3d", right, tmp_path / "truth", options)
        assert not [r for r in caplog.records if "object rotations" in r.getMessage()]
        report = convert("ho3d", wrong, tmp_path / "checked", options)
    (warning,) = [r.getMessage() for r in caplog.records if "object rotations" in r.getMessage()]
    assert str(wrong) in warning and "--object-rotation auto" in warning, warning
    truth = json.loads((tmp_path / "truth" / "convert.json").read_text())["object_rotation"]
    assert truth["sessions"][str(right)]["found"] == "+x+y+z R +x+y+z"
    entry = report["object_rotation"]["sessions"][str(wrong)]
    assert entry["applied"] == "+x+y+z R +x+y+z" and entry["carried_sequences"] == 9, entry
    found = RotationConvention.parse(entry["found"])
    assert found.transposed and np.array_equal(found.left, convention.left), entry
    assert entry["carry_spread_deg"]["found"] < 1.0 < entry["carry_spread_deg"]["as-stored"]
    assert entry["start_spread_m"]["found"] < 1e-3 < entry["start_spread_m"]["as-stored"]
    given = replace(options, object_rotation=str(convention))
    convert("ho3d", wrong, tmp_path / "auto", replace(options, object_rotation="auto"))
    convert("ho3d", wrong, tmp_path / "given", given)
    for c in range(9):
        name = f"ho3d_{right.name}_capture_{c:02d}.npz"
        other = name.replace(right.name, wrong.name)
        truth_hulls = _world_hulls(tmp_path / "truth", name)
        for out in ("auto", "given"):  # the box's own symmetries may pick another B: same box
            np.testing.assert_allclose(_world_hulls(tmp_path / out, other), truth_hulls, atol=1e-6)
        assert np.abs(_world_hulls(tmp_path / "checked", other) - truth_hulls).max() > 0.01
    for spec, words in (("+z+y R +x+y+z", "images of x, y and z"), ("+x+x+z R +x+y+z", "not a "
                        "rotation"), ("sideways", "expected 'as-stored'")):  # fmt: skip
        with pytest.raises(ConfigError, match=words):
            convert("ho3d", wrong, tmp_path / "x", replace(options, object_rotation=spec))


def test_a_given_object_rotation_convention_reads_every_adapters_poses(tmp_path):
    """``--object-rotation '<L> R^T <B>'`` applies to data without sessions too (here the
    generic adapter): each written rotation is ``L Rᵀ B`` of the stored one, translations kept;
    ``check`` leaves such data as stored (no session to check) and records nothing."""
    from dexflow.data.rotation_convention import RotationConvention

    gen = tmp_path / "gen"
    _box(gen / "box.obj")
    poses = _poses()
    np.savez(gen / "a.npz", keypoints=_hand(), obj_pose=poses, obj_mesh="box.obj", fps=30.0)
    spec = "+y-x+z R^T -x+y-z"
    convert("generic", gen, tmp_path / "given", ConvertOptions(object_rotation=spec))
    report = convert("generic", gen, tmp_path / "checked")
    assert report["object_rotation"] == {"option": "check", "sessions": {}}
    given = load_sequence(tmp_path / "given" / "sequences" / "generic_a.npz").obj_pose
    stored = load_sequence(tmp_path / "checked" / "sequences" / "generic_a.npz").obj_pose
    convention = RotationConvention.parse(spec)
    expected = convention.left @ poses[:, :3, :3].mT @ convention.right
    np.testing.assert_allclose(given[:, :3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(stored[:, :3, :3], poses[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(given[:, :3, 3], poses[:, :3, 3], atol=1e-12)


def _fake_mano(path):
    rng = np.random.default_rng(0)
    n_verts = 778
    parents = np.array([-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14])
    owner = rng.integers(0, 16, n_verts)
    owner[list(FINGERTIP_VERTICES)] = [15, 3, 6, 12, 9]  # tips ride on the distal joints
    weights = np.eye(16)[owner]
    v_template = rng.normal(scale=0.03, size=(n_verts, 3))
    regressor = np.zeros((16, n_verts))
    for j in range(16):
        mine = np.flatnonzero(owner == j)
        regressor[j, mine] = 1.0 / len(mine)
    model = {
        "v_template": v_template,
        "shapedirs": rng.normal(scale=1e-3, size=(n_verts, 3, 10)),
        "posedirs": np.zeros((n_verts, 3, 135)),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": np.vstack([np.where(parents < 0, 4294967295, parents), np.arange(16)]),
        "f": np.zeros((1, 3), dtype=int),
    }
    with open(path, "wb") as handle:
        pickle.dump(model, handle)
    return model


def test_mano_joints_from_a_structurally_valid_fake_model(tmp_path):
    model = _fake_mano(tmp_path / "MANO_RIGHT.pkl")
    mano = load_mano(tmp_path / "MANO_RIGHT.pkl")
    zero = mano.joints(np.zeros((1, 3)), np.zeros((1, 45)))[0]
    rest = np.vstack(
        [model["J_regressor"] @ model["v_template"], model["v_template"][list(FINGERTIP_VERTICES)]]
    )
    np.testing.assert_allclose(zero, rest[list(MANO_TO_DEXFLOW)], atol=1e-12)
    # A global rotation about the wrist and a translation move every joint rigidly.
    rot = Rotation.from_rotvec([0.3, -0.2, 0.5])
    moved = mano.joints(
        rot.as_rotvec()[None], np.zeros((1, 45)), transl=np.array([[0.1, 0.0, 0.2]])
    )[0]
    wrist = zero[0]
    np.testing.assert_allclose(
        moved, (zero - wrist) @ rot.as_matrix().T + wrist + [0.1, 0.0, 0.2], atol=1e-12
    )
    # Bending the index MCP moves only the index chain and its tip.
    pose = np.zeros((1, 45))
    pose[0, 2] = 0.8
    bent = mano.joints(np.zeros((1, 3)), pose)[0]
    moved_kp = np.flatnonzero(np.abs(bent - zero).max(axis=1) > 1e-9)
    assert set(moved_kp) == {6, 7, 8}
    # HO-3D frames without joints but with MANO parameters go through the model.
    meta = tmp_path / "src" / "SM1" / "meta"
    meta.mkdir(parents=True)
    for t in range(3):
        with open(meta / f"{t:04d}.pkl", "wb") as handle:
            pickle.dump(
                {
                    "handJoints3D": None,
                    "handPose": np.zeros(48),
                    "handTrans": np.array([0.0, 0.0, 0.1]),
                    "handBeta": np.zeros(10),
                    "objRot": np.zeros(3),
                    "objTrans": np.zeros(3),
                    "objName": "025_mug",
                },
                handle,
            )
    _box(tmp_path / "src" / "models" / "025_mug" / "textured_simple.obj")
    with pytest.raises(DatasetLayoutError, match="--mano"):
        convert("ho3d", tmp_path / "src", tmp_path / "out0")
    # The fake hand is tiny: skip the unit check by scaling its vertices to a hand's size.
    model["v_template"] = model["v_template"] * 3
    with open(tmp_path / "MANO_RIGHT.pkl", "wb") as handle:
        pickle.dump(model, handle)
    report = convert("ho3d", tmp_path / "src", tmp_path / "out", ConvertOptions(mano=str(tmp_path)))
    assert report["num_ok"] == 1, report
    seq = load_sequence(tmp_path / "out" / "sequences" / "ho3d_src_SM1.npz")
    expected = load_mano(tmp_path / "MANO_RIGHT.pkl").joints(
        np.zeros((3, 3)), np.zeros((3, 45)), transl=np.tile([0.0, 0.0, 0.1], (3, 1))
    )
    np.testing.assert_allclose(seq.keypoints, expected, atol=1e-12)


def test_converted_data_runs_through_the_pipeline_like_the_demo(tmp_path):
    from dexflow.io.layout import Layout
    from dexflow.params import PipelineParams
    from dexflow.stages.hand import run_hand
    from dexflow.stages.retarget import run_retarget
    from dexflow.stages.scale_align import run_scale_align

    n = 40
    gen = tmp_path / "gen"
    _box(gen / "box.obj")
    np.savez(
        gen / "a.npz",
        keypoints=_hand(n),
        obj_pose=_poses(n),
        obj_mesh="box.obj",
        fps=30.0,
        side="left",
    )
    assert convert("generic", gen, tmp_path / "data")["num_ok"] == 1
    params = PipelineParams()
    params.hand.scale = 1.0
    params.run.backend, params.run.n_jobs = "sequential", 1
    params.scale_align.sdf_spacing_m = 0.005
    params.retarget.global_search.max_evals = 100
    from dexflow.hands.spec import load_hand_spec

    params.hand, _ = load_hand_spec("allegro")
    layout = Layout.of(tmp_path / "data", root=tmp_path / "project")
    aligned = run_scale_align(params, layout)
    assert aligned["num_ok"] == 1
    run_hand(params, layout)
    summary = run_retarget(params, layout, "dexflow")
    assert summary["num_ok"] == 1 and summary["keypoint_error_mm"] < 40


@pytest.mark.parametrize(
    ("breakage", "words"),
    [
        (
            lambda root: (root / "20200709-subject-01" / "20200709_141754" / "836212060125").rename(
                root / "x"
            ),
            "camera folder",
        ),
        (
            lambda root: (root / "models" / "025_mug" / "textured_simple.obj").unlink(),
            "object model of '025_mug'",
        ),
        (
            lambda root: (
                root / "calibration" / "extrinsics_20200702_151821" / "extrinsics.yml"
            ).write_text("{}"),
            "'extrinsics'",
        ),
        (
            lambda root: _edit_extrinsics(root, lambda extr: extr.update(apriltag=[0] * 12)),
            "field 'apriltag': expected a rigid transform",
        ),
        (
            lambda root: _edit_extrinsics(root, lambda extr: extr.update(apriltag=[1, 2])),
            "field 'apriltag': expected 12 numbers",
        ),
    ],
)
def test_bad_layouts_name_the_missing_file_or_field(tmp_path, breakage, words):
    _make_dexycb(tmp_path / "src")
    breakage(tmp_path / "src")
    try:
        report = convert("dexycb", tmp_path / "src", tmp_path / "out")
        errors = " ".join(s.get("error", s.get("reason", "")) for s in report["sequences"].values())
    except DatasetLayoutError as exc:
        errors = str(exc)
    assert words in errors


def test_unknown_adapter_and_empty_source(tmp_path):
    with pytest.raises(DatasetLayoutError, match="known"):
        convert("nope", tmp_path, tmp_path / "out")
    with pytest.raises(DatasetLayoutError, match=r"meta\.yml"):
        convert("dexycb", tmp_path, tmp_path / "out")
