"""``dexflow export``: a project written with the real artifact writers, exported to HDF5 and to
a LeRobot dataset and read back field by field; skipped sequences, missing stages, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from dexflow.errors import ArtifactError
from dexflow.hands.robot import BASE_JOINT_NAMES
from dexflow.io.artifacts import (
    ContactResult,
    MetricFrames,
    Trajectory,
    write_contact,
    write_metric_frames,
    write_trajectory,
)
from dexflow.io.atomic import save_json
from dexflow.io.layout import TRAJECTORIES, Layout, StageDir
from dexflow.io.sequence import save_sequence
from dexflow.tools import cli
from dexflow.tools.export import ExportError, collect_export, export_project, read_export
from dexflow.tools.export.hdf5 import read_hdf5, write_hdf5
from dexflow.tools.export.lerobot import read_lerobot, write_lerobot
from dexflow.tools.viz import MissingInputError

from .conftest import make_sequence

ROOT = Path(__file__).resolve().parents[1]
JOINTS = [*BASE_JOINT_NAMES, "ff_j0", "ff_j1", "th_j0", "th_j1"]
FINGERS = ["thumb", "index", "middle"]
# name -> frames, object; every sequence differs in length, object, side or success
SEQUENCES = {"box__00_power": (12, "box"), "box__01_pinch": (9, "box"), "mug__00_pour": (15, "mug")}
_EMPTY_MAP = {k: np.zeros(0) for k in ("map_frame", "map_finger", "map_hand_index",
                                       "map_hand_point", "map_object_point", "map_object_normal")}  # fmt: skip


def _sequence(name: str, frames: int, obj: str, index: int):
    seq = make_sequence(frames, obj_mesh=f"objects/{obj}/mesh.obj")
    seq.obj_name = obj
    rotation = Rotation.from_rotvec(np.linspace(0.0, 0.4 + index, frames)[:, None] * [0, 0.6, 0.8])
    seq.obj_pose[:, :3, :3] = rotation.as_matrix()
    seq.valid = np.arange(frames) % (4 + index) != 2
    seq.keypoints[~seq.valid] = np.nan
    if index == 1:  # a left hand, mirrored to the right one
        seq.side, seq.mirrored = "left", True
    seq.extras["scale"] = np.array(1.1 + 0.1 * index)  # stage scale_align's factor
    return seq


def _summary(out, stage: str, ok: dict[str, dict], dropped: dict | None = None) -> None:
    sequences = {n: {"status": "ok", **e} for n, e in ok.items()}
    save_json(out.summary, {"stage": stage, "sequences": sequences, "dropped": dropped or {}})


def make_project(root: Path) -> dict:
    """A project with the outputs of every stage an export reads; returns the source arrays
    per method and sequence."""
    shutil.copy(ROOT / "params.yaml", root / "params.yaml")
    layout = Layout(root)
    rng = np.random.default_rng(7)
    source: dict = {"sequences": {}, "methods": {m: {} for m in TRAJECTORIES}}
    per_frame: dict = {}
    for index, (name, (frames, obj)) in enumerate(SEQUENCES.items()):
        seq = _sequence(name, frames, obj, index)
        save_sequence(layout.scale_align.sequence(name), seq)
        contact = rng.random((frames, len(FINGERS))) < 0.5
        raw = contact ^ (rng.random(contact.shape) < 0.2)  # before smoothing: not exported
        write_contact(
            layout.contact.sequence(name),
            ContactResult(np.where(raw, 0.0, 0.02), raw, contact, FINGERS, seq.fps, _EMPTY_MAP),
        )
        source["sequences"][name] = {"seq": seq, "contact": contact}
        per_frame[name] = {}
        for m, method in enumerate(TRAJECTORIES):
            q = rng.uniform(-1.0, 1.0, (frames, len(JOINTS)))
            q[:, 3:6] *= np.pi  # base rotations over the whole circle
            pd = np.where(rng.random(frames) < 0.3, rng.uniform(0, 0.01, frames), 0.0)
            # stage track's trajectories also hold the position targets that reach q
            targets = q + 0.05 if method == "track" else q
            arrays = {"targets": targets} if method == "track" else {}
            write_trajectory(
                layout.trajectory(method).sequence(name), Trajectory(q, JOINTS, arrays)
            )
            per_frame[name][method] = {"pd_m": pd, "spd_m": np.zeros(frames)}
            flags = {
                "simulate_success": (index + m) % 2 == 0,
                "simulate_success_frame": 3 + index if (index + m) % 2 == 0 else -1,
                "replay_scored": index != 2,
                "replay_success": index == 0 and m == 2,
                "replay_not_scored_reason": "no contact" if index == 2 else "",
            }
            source["methods"][method][name] = {
                "q": q,
                "targets": targets,
                "penetration_m": pd,
                **flags,
            }
        write_metric_frames(
            layout.metrics.sequence(name),
            MetricFrames(np.arange(frames) / seq.fps, contact, per_frame[name]),
        )
    names = list(SEQUENCES)
    _summary(layout.scale_align, "scale_align", {n: {} for n in names})
    _summary(layout.contact, "contact", {n: {} for n in names})
    _summary(layout.metrics, "metrics", {n: {} for n in names})
    for method in TRAJECTORIES:
        flags = source["methods"][method]
        _summary(layout.trajectory(method), method, {n: {} for n in names})
        _summary(
            layout.simulate(method), "simulate",
            {n: {"success": f["simulate_success"], "success_frame": f["simulate_success_frame"]}
             for n, f in flags.items()},
        )  # fmt: skip
        replayed = {}
        for n, f in flags.items():
            replayed[n] = (
                {"scored": True, "replayed": True, "success": f["replay_success"],
                 "not_scored_reason": None}
                if f["replay_scored"]
                else {"scored": False, "replayed": False, "not_scored_reason": "no contact"}
            )  # fmt: skip
        _summary(layout.replay(method), "replay", replayed)
    return source


@pytest.fixture
def project(tmp_path) -> tuple[Path, dict]:
    root = tmp_path / "project"
    root.mkdir()
    return root, make_project(root)


def _base_pose(q: np.ndarray) -> np.ndarray:
    """The floating base's pose by its definition, T(x, y, z) Rx Ry Rz (independently of
    dexflow's kinematics)."""
    pose = np.repeat(np.eye(4)[None], len(q), axis=0)
    pose[:, :3, :3] = Rotation.from_euler("XYZ", q[:, 3:6]).as_matrix()
    pose[:, :3, 3] = q[:, :3]
    return pose


def _check_round_trip(export, source: dict, method: str, atol: float) -> None:
    assert export.method == method and export.hand == "shadow"
    assert export.joint_names == JOINTS and export.fingers == FINGERS
    assert [e.sequence for e in export.episodes] == sorted(SEQUENCES)
    assert export.skipped == {}
    for episode in export.episodes:
        given = source["sequences"][episode.sequence]
        seq, flags = given["seq"], source["methods"][method][episode.sequence]
        assert episode.object == seq.obj_name and episode.fps == seq.fps
        assert episode.object_mesh == f"data/scale_align/objects/{seq.obj_name}/mesh.obj"
        assert episode.scale == float(seq.extras["scale"])
        assert (episode.side, episode.mirrored) == (seq.side, seq.mirrored)
        assert episode.q.shape == (seq.num_frames, len(JOINTS))
        np.testing.assert_allclose(episode.q, flags["q"], rtol=0, atol=atol)
        base = _base_pose(flags["q"])  # another implementation: equal up to rounding
        np.testing.assert_allclose(episode.base_pose, base, rtol=0, atol=atol + 1e-12)
        np.testing.assert_allclose(episode.obj_pose, seq.obj_pose, rtol=0, atol=atol)
        np.testing.assert_allclose(episode.penetration_m, flags["penetration_m"], rtol=0, atol=atol)
        assert episode.contact.dtype == bool and np.array_equal(episode.contact, given["contact"])
        assert episode.valid.dtype == bool and np.array_equal(episode.valid, seq.valid)
        for key in ("simulate_success", "simulate_success_frame", "replay_scored",
                    "replay_success", "replay_not_scored_reason"):  # fmt: skip
            assert getattr(episode, key) == flags[key], key


@pytest.mark.parametrize("method", ["refine", "baseline"])
def test_hdf5_holds_every_field_exactly(project, tmp_path, method):
    root, source = project
    out = tmp_path / "out.h5"
    export_project(root, out, "hdf5", method)
    _check_round_trip(read_export(out), source, method, atol=0.0)
    with h5py.File(out, "r") as f:  # as docs/export.md reads it
        assert f["joint_names"].asstr()[()].tolist() == JOINTS
        group = f["episodes/mug__00_pour"]
        np.testing.assert_array_equal(
            group["q"][()], source["methods"][method]["mug__00_pour"]["q"]
        )
        assert group.attrs["fps"] == 30.0 and group.attrs["object"] == "mug"


def test_lerobot_holds_every_field_in_float32(project, tmp_path):
    root, source = project
    out = tmp_path / "lerobot"
    export_project(root, out, "lerobot")
    _check_round_trip(read_export(out), source, "refine", atol=2e-6)


def test_lerobot_layout_is_v21(project, tmp_path):
    root, source = project
    out = tmp_path / "lerobot"
    export_project(root, out, "lerobot")
    info = json.loads((out / "meta" / "info.json").read_text())
    names = sorted(SEQUENCES)
    lengths = [SEQUENCES[n][0] for n in names]
    assert (
        info["codebase_version"] == "v2.1" and info["fps"] == 30 and info["robot_type"] == "shadow"
    )
    assert (info["total_episodes"], info["total_frames"]) == (3, sum(lengths))
    assert info["total_tasks"] == 2 and info["splits"] == {"train": "0:3"}
    assert info["features"]["observation.state"] == {
        "dtype": "float32",
        "shape": [len(JOINTS)],
        "names": JOINTS,
    }
    assert info["features"]["contact"]["names"] == FINGERS
    tasks = [json.loads(line) for line in (out / "meta" / "tasks.jsonl").read_text().splitlines()]
    assert tasks == [{"task": "box", "task_index": 0}, {"task": "mug", "task_index": 1}]
    episodes = [json.loads(x) for x in (out / "meta" / "episodes.jsonl").read_text().splitlines()]
    assert [e["length"] for e in episodes] == lengths
    assert [e["tasks"] for e in episodes] == [["box"], ["box"], ["mug"]]
    stats = [
        json.loads(x) for x in (out / "meta" / "episodes_stats.jsonl").read_text().splitlines()
    ]
    first = 0
    for index, (name, length) in enumerate(zip(names, lengths, strict=True)):
        table = pq.read_table(out / f"data/chunk-000/episode_{index:06d}.parquet").to_pydict()
        assert set(table) == set(info["features"])
        frames = np.arange(length)
        assert table["frame_index"] == frames.tolist()
        assert table["index"] == (first + frames).tolist()
        assert table["episode_index"] == [index] * length
        assert table["task_index"] == [0 if name.startswith("box") else 1] * length
        np.testing.assert_allclose(table["timestamp"], frames / 30.0, atol=1e-6)
        q = np.asarray(source["methods"]["refine"][name]["q"], dtype=np.float32)
        # the action is the next frame's q; the last frame holds its own
        np.testing.assert_array_equal(np.asarray(table["action"]), np.concatenate([q[1:], q[-1:]]))
        # poses as x, y, z, qw, qx, qy, qz with qw >= 0
        for column, pose in (
            ("observation.environment_state", source["sequences"][name]["seq"].obj_pose),
            ("base_pose", _base_pose(source["methods"]["refine"][name]["q"])),
        ):
            xyzw = Rotation.from_matrix(pose[:, :3, :3]).as_quat()
            xyzw *= np.where(xyzw[:, 3:] < 0, -1.0, 1.0)
            expected = np.concatenate([pose[:, :3, 3], xyzw[:, [3, 0, 1, 2]]], axis=1)
            np.testing.assert_allclose(np.asarray(table[column]), expected, atol=1e-6)
        ep = stats[index]
        assert ep["episode_index"] == index and ep["stats"]["index"]["count"] == [length]
        np.testing.assert_allclose(ep["stats"]["observation.state"]["mean"], q.mean(0), atol=1e-6)
        first += length
    overall = json.loads((out / "meta" / "stats.json").read_text())
    assert overall["index"]["max"] == [sum(lengths) - 1]


def _files(path: Path) -> dict[Path, bytes]:
    if path.is_file():
        return {Path(): path.read_bytes()}
    return {p.relative_to(path): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.mark.parametrize(("fmt", "name"), [("hdf5", "out.h5"), ("lerobot", "out")])
def test_same_export_gives_the_same_bytes(project, tmp_path, fmt, name):
    root, _ = project
    export_project(root, tmp_path / "a" / name, fmt)
    first = _files(tmp_path / "a" / name)
    export_project(root, tmp_path / "b" / name, fmt)  # elsewhere
    export_project(root, tmp_path / "a" / name, fmt)  # over the first
    assert len(first) == (1 if fmt == "hdf5" else 8)
    assert _files(tmp_path / "a" / name) == first == _files(tmp_path / "b" / name)
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == [name]  # no temporaries left


def _drop(name: str, stage: StageDir, error: str, later: list[StageDir]) -> None:
    """Sequence ``name`` failed in ``stage``: the later stages list it as dropped."""
    summary = json.loads(stage.summary.read_text())
    summary["sequences"][name] = {"status": "failed", "error": error}
    save_json(stage.summary, summary)
    stage.sequence(name).unlink()
    for out in later:
        summary = json.loads(out.summary.read_text())
        summary["sequences"].pop(name)
        summary["dropped"][name] = {"stage": "contact", "error": error}
        save_json(out.summary, summary)
        out.sequence(name).unlink(missing_ok=True)


def test_a_sequence_dropped_upstream_is_skipped_and_the_rest_exported(project, tmp_path, capsys):
    root, source = project
    layout = Layout(root)
    later = [layout.refine, layout.simulate("refine"), layout.replay("refine"), layout.metrics]
    _drop("box__01_pinch", layout.contact, "ArtifactError: bad mesh", later)
    out = tmp_path / "out.h5"
    assert cli.main(["export", str(root), str(out), "--format", "hdf5"]) == 0
    printed = capsys.readouterr().out
    assert "skip box__01_pinch: dropped by contact: ArtifactError: bad mesh" in printed
    export = read_export(out)
    assert [e.sequence for e in export.episodes] == ["box__00_power", "mug__00_pour"]
    assert export.skipped == {"box__01_pinch": "dropped by contact: ArtifactError: bad mesh"}
    np.testing.assert_array_equal(
        export.episodes[1].q, source["methods"]["refine"]["mug__00_pour"]["q"]
    )


def test_nothing_to_export_exits_nonzero(project, tmp_path, capsys):
    root, _ = project
    layout = Layout(root)
    later = [layout.refine, layout.simulate("refine"), layout.replay("refine"), layout.metrics]
    for name in SEQUENCES:
        _drop(name, layout.contact, "ArtifactError: bad", later)
    out = tmp_path / "out.h5"
    assert cli.main(["export", str(root), str(out), "--format", "hdf5"]) == 2
    assert "nothing to export" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize(
    ("folder", "stage"),
    [
        ("data/scale_align", "scale_align"),
        ("data/refine", "refine"),
        ("data/contact", "contact"),
        ("data/simulate/refine", "simulate@refine"),
        ("data/replay/refine", "replay@refine"),
        ("data/metrics", "metrics"),
    ],
)
def test_missing_stage_output_names_the_file_and_the_stage(project, tmp_path, folder, stage):
    root, _ = project
    (root / folder / "summary.json").unlink()
    with pytest.raises(MissingInputError) as err:
        export_project(root, tmp_path / "out.h5", "hdf5")
    assert f"{folder}/summary.json" in str(err.value)
    assert f"dvc repro {stage}" in str(err.value)
    assert not (tmp_path / "out.h5").exists()


def test_missing_sequence_file_of_a_finished_stage_is_an_error(project, tmp_path):
    root, _ = project
    (root / "data/retarget/position/sequences/mug__00_pour.npz").unlink()
    with pytest.raises(MissingInputError, match=r"position/sequences/mug__00_pour\.npz.*"
                       r"dvc repro retarget@position"):  # fmt: skip
        export_project(root, tmp_path / "out.h5", "hdf5", "baseline")


def test_metrics_without_the_method_is_an_error(project, tmp_path):
    root, _ = project
    path = Layout(root).metrics.sequence("box__00_power")
    write_metric_frames(path, MetricFrames(np.zeros(12), np.zeros((12, 3), bool), {}))
    with pytest.raises(ArtifactError, match=r"refine\.pd_m"):
        export_project(root, tmp_path / "out.h5", "hdf5")


def test_unknown_method_or_format(project, tmp_path, capsys):
    root, _ = project
    with pytest.raises(ExportError, match=r"unknown method 'dexflow'.*baseline, retarget, refine"):
        collect_export(root, "dexflow")
    with pytest.raises(ExportError, match="unknown format 'csv'"):
        export_project(root, tmp_path / "x", "csv")
    with pytest.raises(SystemExit):
        cli.main(["export", str(root), "out.h5", "--format", "hdf5", "--method", "dexflow"])
    assert "invalid choice: 'dexflow'" in capsys.readouterr().err


def test_lerobot_needs_one_frame_rate_and_keeps_foreign_folders(project, tmp_path):
    root, _ = project
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(ExportError, match="not a previous export"):
        export_project(root, foreign, "lerobot")
    assert (foreign / "notes.txt").read_text() == "keep me"
    seq_path = Layout(root).scale_align.sequence("mug__00_pour")
    seq = _sequence("mug__00_pour", 15, "mug", 2)
    seq.fps = 15.0
    save_sequence(seq_path, seq)
    with pytest.raises(ExportError, match=r"one frame rate.*15 fps.*30 fps.*--format hdf5"):
        export_project(root, tmp_path / "lr", "lerobot")
    export_project(root, tmp_path / "x.h5", "hdf5")  # HDF5 keeps each episode's rate
    assert [e.fps for e in read_export(tmp_path / "x.h5").episodes] == [30.0, 30.0, 15.0]


def test_default_project_is_the_working_directory(project, tmp_path, monkeypatch):
    root, _ = project
    monkeypatch.chdir(root)
    assert cli.main(["export", str(tmp_path / "out.h5"), "--format", "hdf5"]) == 0
    assert len(read_export(tmp_path / "out.h5").episodes) == 3


def test_summary_entry_without_a_flag_is_an_error(project, tmp_path):
    root, _ = project
    out = Layout(root).simulate("refine")
    summary = json.loads(out.summary.read_text())
    del summary["sequences"]["box__01_pinch"]["success"]
    save_json(out.summary, summary)
    with pytest.raises(ArtifactError, match=r"box__01_pinch has no 'success'.*simulate@refine"):
        export_project(root, tmp_path / "out.h5", "hdf5")


def test_tracked_episodes_carry_their_targets_and_lerobot_acts_on_them(project, tmp_path):
    """Stage track's q is where the simulated hand was, its targets what drove it there: the
    export keeps both (HDF5 as they are; LeRobot's action is the next frame's target). The
    kinematic methods' targets are their q."""
    root, source = project
    export = collect_export(root, "track")
    for episode in export.episodes:
        np.testing.assert_array_equal(
            episode.targets, source["methods"]["track"][episode.sequence]["targets"]
        )
        assert not np.array_equal(episode.targets, episode.q)
    back = read_hdf5(write_hdf5(export, tmp_path / "track.h5"))
    for a, b in zip(export.episodes, back.episodes, strict=True):
        np.testing.assert_array_equal(a.targets, b.targets)
    lerobot = read_lerobot(write_lerobot(export, tmp_path / "lerobot"))
    for a, b in zip(export.episodes, lerobot.episodes, strict=True):
        np.testing.assert_allclose(b.targets[1:], a.targets[1:].astype(np.float32), rtol=0)
    refine = collect_export(root, "refine")
    for episode in refine.episodes:
        np.testing.assert_array_equal(episode.targets, episode.q)
