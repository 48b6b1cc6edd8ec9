"""The canonical sequence format: every bad input is caught with a message saying where and what."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from dexflow.errors import SequenceFormatError
from dexflow.io import atomic
from dexflow.io.atomic import save_json
from dexflow.io.sequence import load_sequence, save_sequence, validate_sequence


def test_round_trip_keeps_every_field(tmp_path, sequence, data_root):
    valid = np.ones(sequence.num_frames, dtype=bool)
    valid[3] = False
    kp = sequence.keypoints.copy()
    kp[3] = np.nan
    gt = np.zeros((sequence.num_frames, 5), dtype=bool)
    gt[5:, 0] = True
    seq = replace(
        sequence, keypoints=kp, valid=valid, gt_contact=gt, extras={"mano_pose": np.arange(6.0)}
    )
    path = data_root / "sequences" / "a.npz"
    save_sequence(path, seq, data_root=data_root)
    back = load_sequence(path, data_root=data_root)
    np.testing.assert_array_equal(back.keypoints, kp)
    np.testing.assert_array_equal(back.obj_pose, seq.obj_pose)
    np.testing.assert_array_equal(back.valid, valid)
    np.testing.assert_array_equal(back.gt_contact, gt)
    np.testing.assert_array_equal(back.extras["mano_pose"], np.arange(6.0))
    assert (back.obj_mesh, back.obj_name, back.side, back.fps) == (
        "meshes/box.obj",
        "box",
        "right",
        30.0,
    )


def _bad(seq, **changes):
    return replace(seq, **changes)


def _with_keypoint(seq, frame, value):
    kp = seq.keypoints.copy()
    kp[frame, 4, 1] = value
    return kp


@pytest.mark.parametrize(
    ("make", "field", "frame", "words"),
    [
        (lambda s: _bad(s, keypoints=s.keypoints[:, :20]), "keypoints", None, "shape (T, 21, 3)"),
        (
            lambda s: _bad(s, keypoints=s.keypoints[:1], obj_pose=s.obj_pose[:1]),
            "keypoints",
            None,
            "at least 2 frames",
        ),
        (lambda s: _bad(s, obj_pose=s.obj_pose[:-1]), "obj_pose", None, "shape (10, 4, 4)"),
        (lambda s: _bad(s, keypoints=_with_keypoint(s, 6, np.nan)), "keypoints", 6, "NaN"),
        (lambda s: _bad(s, keypoints=_with_keypoint(s, 2, np.inf)), "keypoints", 2, "inf"),
        (lambda s: _bad(s, keypoints=s.keypoints * 1000), "keypoints", None, "millimetres"),
        (lambda s: _bad(s, keypoints=s.keypoints * 100), "keypoints", None, "centimetres"),
        (lambda s: _bad(s, fps=0.0), "fps", None, "> 0"),
        (lambda s: _bad(s, fps=-30.0), "fps", None, "> 0"),
        (lambda s: _bad(s, fps=float("nan")), "fps", None, "> 0"),
        (lambda s: _bad(s, side="both"), "side", None, "'right' or 'left'"),
        (
            lambda s: _bad(s, timestamps=np.r_[np.arange(5), np.arange(5)] / 30),
            "timestamps",
            5,
            "strictly increasing",
        ),
        (lambda s: _bad(s, gt_contact=np.zeros((10, 4), bool)), "gt_contact", None, "(10, 5)"),
        (lambda s: _bad(s, valid=np.zeros(10, bool)), "valid", None, "at least one tracked"),
    ],
)
def test_bad_input_is_named(sequence, make, field, frame, words):
    with pytest.raises(SequenceFormatError) as info:
        validate_sequence(make(sequence), path="seq.npz")
    err = info.value
    assert err.field == field
    assert err.frame == frame
    assert "seq.npz" in str(err) and words in str(err)


def test_nan_allowed_only_in_frames_marked_invalid(sequence):
    kp = _with_keypoint(sequence, 6, np.nan)
    valid = np.ones(10, dtype=bool)
    valid[6] = False
    validate_sequence(replace(sequence, keypoints=kp, valid=valid))


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda p: p.__setitem__((7, 0, 0), 1.1), "R^T R = I"),  # scaled / sheared rotation
        (lambda p: p.__setitem__((7, slice(0, 3), 0), -p[7, :3, 0]), "det R = -1"),  # reflection
        (lambda p: p.__setitem__((7, 3, 0), 0.5), "last row"),
        (lambda p: p.__setitem__((7, 0, 3), np.nan), "finite"),
    ],
)
def test_object_pose_must_be_rigid(sequence, change, words):
    pose = sequence.obj_pose.copy()
    change(pose)
    with pytest.raises(SequenceFormatError) as info:
        validate_sequence(replace(sequence, obj_pose=pose))
    assert info.value.field == "obj_pose" and info.value.frame == 7
    assert words in str(info.value)


def test_missing_mesh_is_named(tmp_path, sequence):
    with pytest.raises(SequenceFormatError, match=r"obj_mesh.*meshes/box\.obj"):
        validate_sequence(sequence, data_root=tmp_path)


def test_missing_field_and_broken_file(tmp_path, sequence):
    arrays = sequence.to_arrays()
    del arrays["obj_pose"]
    np.savez(tmp_path / "no_pose.npz", **arrays)
    with pytest.raises(SequenceFormatError, match=r"obj_pose.*required field"):
        load_sequence(tmp_path / "no_pose.npz")
    (tmp_path / "broken.npz").write_bytes(b"not a zip archive")
    with pytest.raises(SequenceFormatError, match=r"readable \.npz"):
        load_sequence(tmp_path / "broken.npz")
    with pytest.raises(SequenceFormatError, match="no such file"):
        load_sequence(tmp_path / "absent.npz")


def test_interrupted_save_leaves_no_partial_file(tmp_path, sequence, monkeypatch):
    path = tmp_path / "seq.npz"
    save_sequence(path, sequence)
    before = path.read_bytes()

    def dying_savez(handle, **arrays):
        handle.write(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt  # the process is stopped midway through the write

    monkeypatch.setattr(atomic.np, "savez", dying_savez)
    with pytest.raises(KeyboardInterrupt):
        save_sequence(path, replace(sequence, fps=60.0))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq.npz"]
    new_path = tmp_path / "new.npz"
    with pytest.raises(KeyboardInterrupt):
        save_sequence(new_path, sequence)
    assert not new_path.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq.npz"]


def test_save_json_writes_undefined_metrics_as_null(tmp_path):
    path = tmp_path / "metrics.json"
    save_json(path, {"cd_mm": float("nan"), "n": np.int64(3), "rows": [np.float64(0.5), np.inf]})
    assert json.loads(path.read_text()) == {"cd_mm": None, "n": 3, "rows": [0.5, None]}
