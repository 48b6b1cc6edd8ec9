"""Rerun recordings: written headless, read back with rerun's own reader, checked frame by frame."""

from __future__ import annotations

import logging
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
import trimesh

from dexflow.errors import ArtifactError
from dexflow.hands import load_hand
from dexflow.io.artifacts import ContactResult, Trajectory, write_contact, write_trajectory
from dexflow.io.layout import Layout
from dexflow.io.sequence import save_sequence
from dexflow.tools import cli, viz

from .conftest import make_sequence

NAME = "box__00_test"


@pytest.fixture(scope="module")
def hand():
    return load_hand("allegro")


def _q(hand, num_frames: int) -> np.ndarray:
    """A trajectory that moves the base along y and bends every hand joint over time."""
    q = hand.zero(num_frames).numpy().copy()
    q[:, 1] = np.linspace(0.0, 0.1, num_frames)
    lo, hi = hand.lower.numpy()[6:], hand.upper.numpy()[6:]
    q[:, 6:] = lo + np.linspace(0.2, 0.6, num_frames)[:, None] * (hi - lo)
    return q


def _contact(hand, num_frames: int) -> tuple[np.ndarray, list[str]]:
    fingers = list(hand.spec.fingers)
    rng = np.random.default_rng(0)
    return rng.random((num_frames, len(fingers))) < 0.5, fingers


def _link(link: str) -> str:
    return "/world/robot/" + rr.escape_entity_path_part(link)


def _read(path: Path) -> dict[str, list]:
    """Entity path -> its chunks, from the first recording in the file."""
    chunks = defaultdict(list)
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        chunks[chunk.entity_path].append(chunk)
    return dict(chunks)


def _temporal(chunks: dict[str, list], entity: str, component: str) -> tuple[np.ndarray, list]:
    """Frame indices and values of one temporal component, sorted by frame."""
    frames, values = [], []
    for chunk in chunks[entity]:
        batch = chunk.to_record_batch()
        if chunk.is_static or component not in batch.schema.names:
            continue
        frames += batch.column("frame").to_pylist()
        values += batch.column(component).to_pylist()
    order = np.argsort(frames, kind="stable")
    return np.asarray(frames)[order], [values[i] for i in order]


def _structure(path: Path) -> list[tuple]:
    """Everything a recording holds except rerun's own row and chunk ids."""
    out = []
    for entity, chunks in _read(path).items():
        for chunk in chunks:
            batch = chunk.to_record_batch()
            cols = {
                name: batch.column(name).to_pylist()
                for name in batch.schema.names
                if not name.startswith("rerun.controls")
            }
            out.append((entity, chunk.is_static, repr(sorted(cols.items()))))
    return sorted(out)


def _project(tmp_path: Path, hand, num_frames: int = 12, contact: bool = True) -> Path:
    """A project with one sequence and the stage outputs a recording reads."""
    layout = Layout(tmp_path)
    root = layout.scale_align.root
    (root / "meshes").mkdir(parents=True)
    trimesh.creation.box(extents=(0.06, 0.04, 0.08)).export(root / "meshes" / "box.obj")
    save_sequence(layout.scale_align.sequence(NAME), make_sequence(num_frames), data_root=root)
    trajectory = Trajectory(_q(hand, num_frames), list(hand.joint_names))
    for label in ("refine", "retarget"):
        write_trajectory(layout.trajectory(label).sequence(NAME), trajectory)
    if contact:
        final, fingers = _contact(hand, num_frames)
        empty = {k: np.zeros(0) for k in ("map_frame", "map_finger", "map_hand_index",
                                          "map_hand_point", "map_object_point",
                                          "map_object_normal")}  # fmt: skip
        distance = np.where(final, 0.0, 0.05)
        result = ContactResult(distance, final, final, fingers, 30.0, empty)
        write_contact(layout.contact.sequence(NAME), result)
    return tmp_path


def test_recording_holds_every_part_frame_by_frame(tmp_path, hand):
    seq = make_sequence(12)
    seq.valid = np.ones(12, dtype=bool)
    seq.valid[3] = False
    seq.keypoints[3] = np.nan
    q = _q(hand, 12)
    contact, fingers = _contact(hand, 12)
    box = trimesh.creation.box(extents=(0.06, 0.04, 0.08))

    out = viz.write_recording(
        tmp_path / "seq", seq, hand, q, contact, fingers, object_mesh=box, name=NAME
    )

    assert out == tmp_path / "seq.rrd" and out.stat().st_size > 20_000
    (entry,) = rr.chunk.RrdReader(out).recordings()
    assert entry.recording_id == str(viz.recording_id(NAME, "refine"))
    chunks = _read(out)
    links = sorted({g.link for g in hand.model.geometries})
    expected = {"/world/human/keypoints", "/world/human/bones", "/world/object"}
    expected |= {_link(link) for link in links} | {"/world/robot/contacts"}
    assert expected <= set(chunks)

    # Human: 21 points and 5 strips per tracked frame, nothing on the untracked one.
    frames, points = _temporal(chunks, "/world/human/keypoints", "Points3D:positions")
    assert frames.tolist() == list(range(12))
    assert [len(p) for p in points] == [0 if t == 3 else 21 for t in range(12)]
    np.testing.assert_allclose(np.array(points[5]), seq.keypoints[5], atol=1e-6)
    _, strips = _temporal(chunks, "/world/human/bones", "LineStrips3D:strips")
    assert [len(s) for s in strips] == [0 if t == 3 else 5 for t in range(12)]

    # Robot: every link's world transform per frame equals forward kinematics.
    world = hand.link_transforms(q, links).numpy()
    for i, link in enumerate(links):
        frames, trans = _temporal(chunks, _link(link), "Transform3D:translation")
        assert frames.tolist() == list(range(12))
        np.testing.assert_allclose(np.array(trans)[:, 0], world[:, i, :3, 3], atol=1e-6)
        _, rot = _temporal(chunks, _link(link), "Transform3D:mat3x3")
        # rerun stores 3x3 matrices column-major
        rot = np.array(rot).reshape(12, 3, 3).transpose(0, 2, 1)
        np.testing.assert_allclose(rot, world[:, i, :3, :3], atol=1e-6)
        static = [c for c in chunks[_link(link)] if c.is_static]
        assert static and "Mesh3D:vertex_positions" in static[0].to_record_batch().schema.names

    # Object pose per frame.
    _, trans = _temporal(chunks, "/world/object", "Transform3D:translation")
    np.testing.assert_allclose(np.array(trans)[:, 0], seq.obj_pose[:, :3, 3], atol=1e-6)

    # Contact: each finger link is green exactly on the frames its finger touches.
    green = np.array([40, 200, 60, 255], dtype=np.uint32)
    green = int((green[0] << 24) | (green[1] << 16) | (green[2] << 8) | green[3])
    for f, finger in enumerate(fingers):
        for link in hand.spec.fingers[finger].links:
            _, albedo = _temporal(chunks, _link(link), "Mesh3D:albedo_factor")
            assert len(albedo) == 12
            assert [a == [green] for a in albedo] == contact[:, f].tolist()


def test_one_batched_fk_call_and_rows_grow_with_frames(tmp_path, hand, monkeypatch):
    calls = []
    original = hand.link_transforms

    def counted(q, names):
        calls.append(np.shape(q))
        return original(q, names)

    monkeypatch.setattr(hand, "link_transforms", counted)
    link = _link(hand.model.geometries[0].link)
    rows = {}
    for num_frames in (5, 17):
        calls.clear()
        out = viz.write_recording(
            tmp_path / f"s{num_frames}.rrd", make_sequence(num_frames), hand, _q(hand, num_frames)
        )
        assert calls == [(num_frames, hand.dof)]
        chunks = _read(out)
        rows[num_frames] = len(_temporal(chunks, link, "Transform3D:translation")[0])
        assert len(_temporal(chunks, "/world/object", "Transform3D:translation")[0]) == num_frames
    assert rows == {5: 5, 17: 17}


def test_two_writes_hold_the_same_data(tmp_path, hand):
    seq, q = make_sequence(8), _q(hand, 8)
    contact, fingers = _contact(hand, 8)
    a = viz.write_recording(tmp_path / "a.rrd", seq, hand, q, contact, fingers, name=NAME)
    b = viz.write_recording(tmp_path / "b.rrd", seq, hand, q, contact, fingers, name=NAME)
    ids = {rr.chunk.RrdReader(p).recordings()[0].recording_id for p in (a, b)}
    assert ids == {str(viz.recording_id(NAME, "refine"))}
    assert _structure(a) == _structure(b)
    c = viz.write_recording(tmp_path / "c.rrd", seq, hand, q + 0.01, contact, fingers, name=NAME)
    assert _structure(a) != _structure(c)


def test_record_sequence_reads_the_project(tmp_path, hand):
    root = _project(tmp_path, hand)
    out = viz.record_sequence(NAME, trajectory="retarget", project_root=root, hand=hand)
    assert out == root / "reports" / "rerun" / f"{NAME}.retarget.rrd"
    chunks = _read(out)
    assert "/world/robot/contacts" in chunks
    static_mesh = next(c for c in chunks["/world/object"] if c.is_static).to_record_batch()
    assert len(static_mesh.column("Mesh3D:triangle_indices").to_pylist()[0]) == 12  # the box

    # A sequence given by path, and q stored in another joint order: the same link transforms.
    path = root / "data" / "scale_align" / "sequences" / f"{NAME}.npz"
    traj = root / "data" / "refine" / "sequences" / f"{NAME}.npz"
    with np.load(traj) as data:
        q, names = data["q"], data["joint_names"]
    perm = np.random.default_rng(1).permutation(len(names))
    np.savez(traj, q=q[:, perm], joint_names=names[perm])
    by_path = viz.record_sequence(path, tmp_path / "p.rrd", project_root=root, hand=hand)
    link = _link(hand.model.geometries[-1].link)
    _, t_path = _temporal(_read(by_path), link, "Transform3D:translation")
    _, t_name = _temporal(chunks, link, "Transform3D:translation")
    np.testing.assert_allclose(np.array(t_path), np.array(t_name), atol=1e-7)


@pytest.mark.parametrize(
    ("trajectory", "folder", "stage"),
    [
        ("refine", "data/refine", "refine"),
        ("retarget", "data/retarget/dexflow", "retarget@dexflow"),
        ("baseline", "data/retarget/position", "retarget@position"),
    ],
)
def test_missing_trajectory_names_the_file_and_its_stage(tmp_path, hand, trajectory, folder, stage):
    root = _project(tmp_path, hand)
    (root / folder / "sequences" / f"{NAME}.npz").unlink(missing_ok=True)
    with pytest.raises(viz.MissingInputError) as err:
        viz.record_sequence(NAME, trajectory=trajectory, project_root=root, hand=hand)
    assert f"{folder}/sequences/{NAME}.npz" in str(err.value)
    assert f"dvc repro {stage}" in str(err.value)
    assert not (root / "reports" / "rerun" / f"{NAME}.rrd").exists()


def test_missing_sequence_names_scale_align(tmp_path, hand):
    root = _project(tmp_path, hand)
    with pytest.raises(
        viz.MissingInputError, match=r"scale_align/sequences/other\.npz.*scale_align"
    ):
        viz.record_sequence("other", project_root=root, hand=hand)


def test_missing_contact_warns_and_records_without_colours(tmp_path, hand, caplog):
    root = _project(tmp_path, hand, contact=False)
    with caplog.at_level(logging.WARNING, logger="dexflow.tools.viz"):
        out = viz.record_sequence(NAME, project_root=root, hand=hand)
    assert any("contact" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)
    chunks = _read(out)
    assert "/world/robot/contacts" not in chunks
    thumb = _link(hand.spec.fingers["thumb"].links[-1])
    assert _temporal(chunks, thumb, "Mesh3D:albedo_factor")[1] == []
    assert len(_temporal(chunks, thumb, "Transform3D:translation")[1]) == 12


def test_trajectory_of_another_hand_is_refused(tmp_path, hand):
    root = _project(tmp_path, hand)
    traj = root / "data" / "refine" / "sequences" / f"{NAME}.npz"
    np.savez(traj, q=np.zeros((12, 30)), joint_names=np.array([f"j{i}" for i in range(30)]))
    with pytest.raises(ArtifactError, match="joint_names"):
        viz.record_sequence(NAME, project_root=root, hand=hand)


def test_cli_view_writes_and_opens_only_when_asked(tmp_path, monkeypatch):
    calls = {"record": [], "open": []}

    def record(sequence, out, trajectory):
        calls["record"].append((sequence, out, trajectory))
        return tmp_path / "x.rrd"

    monkeypatch.setattr(viz, "record_sequence", record)
    monkeypatch.setattr(viz, "open_viewer", lambda path: calls["open"].append(path))
    assert cli.main(["view", NAME, "--trajectory", "baseline"]) == 0
    assert calls == {"record": [(NAME, None, "baseline")], "open": []}
    assert cli.main(["view", NAME, "--out", "o.rrd", "--open"]) == 0
    assert calls["record"][-1] == (NAME, "o.rrd", "refine")
    assert calls["open"] == [tmp_path / "x.rrd"]
