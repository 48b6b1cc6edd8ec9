"""Adapters isolate each source sequence: one unreadable file fails its sequence only, names the
file, and convert.json is always written; generic timestamps place frames on the fps grid."""

from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from dexflow.data.adapters import DatasetLayoutError, convert
from dexflow.io.sequence import load_sequence
from dexflow.tools.cli import main

from .test_adapters import _box, _hand, _make_dexycb, _poses, _write_ho3d


def _ho3d_captures(root, count=3):
    hand, poses = _hand(), _poses()
    for i in range(count):
        _write_ho3d(root / "subject" / f"take{i}", hand, poses)
    _box(root / "models" / "025_mug" / "textured_simple.obj")
    return root


@pytest.mark.parametrize(
    ("breakage", "words"),
    [
        (lambda meta: (meta / "0002.pkl").write_bytes(b"\x80\x04corrupt"), r"0002\.pkl: cannot read"),
        (lambda meta: (meta / "0002 (copy).pkl").write_bytes(b""), r"0002 \(copy\)\.pkl: unexpected "
         r"file name; frame files are named <n>\.pkl"),
        (lambda meta: (meta / "0002.pkl").write_bytes(b"\x80\x04N."), r"0002\.pkl: expected a dict"),
    ],
)  # fmt: skip
def test_one_unreadable_ho3d_frame_fails_its_sequence_only(tmp_path, breakage, words):
    src = _ho3d_captures(tmp_path / "src")
    meta = src / "subject" / "take1" / "meta"
    breakage(meta)
    (src / "subject" / "take2" / "meta" / "._0001.pkl").write_bytes(b"\x00\x05\x16\x07")  # hidden
    report = convert("ho3d", src, tmp_path / "out")
    assert (report["num_ok"], report["num_failed"]) == (2, 1)
    failed = report["sequences"]["subject_take1"]
    assert failed["status"] == "failed" and str(meta) in failed["error"]
    assert re.search(words, failed["error"])
    assert json.loads((tmp_path / "out" / "convert.json").read_text()) == report


def test_a_corrupt_dexycb_label_file_is_named(tmp_path):
    _make_dexycb(tmp_path / "src")
    label = next((tmp_path / "src").rglob("labels_000003.npz"))
    label.write_bytes(label.read_bytes()[:50])
    report = convert("dexycb", tmp_path / "src", tmp_path / "out")
    (entry,) = report["sequences"].values()
    assert entry["status"] == "failed" and f"{label}: cannot read it" in entry["error"]


def _generic_table(hand, poses):
    cols = {f"kp{i}_{c}": hand[:, i, k] for i in range(21) for k, c in enumerate("xyz")}
    rv = Rotation.from_matrix(poses[:, :3, :3]).as_rotvec()
    cols |= {f"obj_r{c}": rv[:, k] for k, c in enumerate("xyz")}
    cols |= {f"obj_t{c}": poses[:, k, 3] for k, c in enumerate("xyz")}
    return pd.DataFrame(cols)


def test_a_text_cell_in_a_csv_names_its_row_and_column_and_the_rest_converts(tmp_path, capsys):
    hand, poses = _hand(), _poses()
    src = tmp_path / "gen"
    _box(src / "box.obj")
    for name in ("good", "typo"):
        table = _generic_table(hand, poses).astype(object)
        if name == "typo":
            table.loc[3, "kp7_y"] = "0.0l2"
        table.to_csv(src / f"{name}.csv", index=False)
        (src / f"{name}.json").write_text(json.dumps({"obj_mesh": "box.obj", "fps": 30}))
    np.save(src / "not_an_archive.npy", hand)
    (src / "not_an_archive.npy").rename(src / "not_an_archive.npz")
    assert main(["convert", "generic", str(src), str(tmp_path / "out")]) == 1
    out = capsys.readouterr().out
    assert "ok   good:" in out
    assert f"FAIL typo: {src / 'typo.csv'}: column 'kp7_y', row 5: '0.0l2' is not a number" in out
    assert f"FAIL not_an_archive: {src / 'not_an_archive.npz'}: cannot read it" in out
    assert "1/3 sequences written" in out
    report = json.loads((tmp_path / "out" / "convert.json").read_text())
    assert report["num_failed"] == 2


def test_generic_timestamps_place_frames_on_the_fps_grid_with_gaps_as_invalid_frames(tmp_path):
    n = 8
    hand, poses = _hand(n), _poses(n)
    src = tmp_path / "gen"
    _box(src / "box.obj")
    ts = np.arange(n) / 30.0 + 100.0
    ts[5:] += 3 / 30.0  # three frames dropped by the capture before frame 5
    ts += np.random.default_rng(0).uniform(-0.1, 0.1, n) / 30.0  # and some jitter
    np.savez(src / "a.npz", keypoints=hand, obj_pose=poses, obj_mesh="box.obj", timestamps=ts)
    report = convert("generic", src, tmp_path / "out")
    assert report["num_ok"] == 1, report
    seq = load_sequence(tmp_path / "out" / "sequences" / "generic_a.npz")
    assert seq.fps == pytest.approx(30.0, rel=0.05) and seq.num_frames == n + 3
    assert list(np.flatnonzero(~seq.valid)) == [5, 6, 7]
    np.testing.assert_allclose(seq.keypoints[seq.valid], hand, atol=1e-12)
    assert report["sequences"]["a"]["missing_frames"] == 3


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda ts: ts[::-1], "timestamps must increase"),
        (lambda ts: ts + np.r_[0.0, 0.0, 0.0, 0.45 / 30, 0.0, 0.0, 0.0, 0.0], "off the 1/fps grid"),
        (lambda ts: ts * 1000, "are they seconds"),
    ],
)
def test_generic_timestamps_that_fit_no_grid_are_refused(tmp_path, change, words):
    n = 8
    src = tmp_path / "gen"
    _box(src / "box.obj")
    ts = change(np.arange(n) / 30.0)
    np.savez(src / "a.npz", keypoints=_hand(n), obj_pose=_poses(n), obj_mesh="box.obj",
             timestamps=ts, fps=30.0)  # fmt: skip
    report = convert("generic", src, tmp_path / "out")
    assert report["num_failed"] == 1 and words in report["sequences"]["a"]["error"]


def test_a_source_without_the_layout_still_stops_the_conversion(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetLayoutError, match="HO-3D layout"):
        convert("ho3d", tmp_path / "empty", tmp_path / "out")
