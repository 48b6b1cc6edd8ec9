"""Stage artifacts: every reader gets back what its writer wrote and refuses what does not fit."""

from __future__ import annotations

import numpy as np
import pytest

from dexflow.errors import ArtifactError
from dexflow.io.artifacts import (
    ENGINE_KEYS,
    SIMULATION_KEYS,
    ContactResult,
    MetricFrames,
    ObjectAssets,
    SimulationResult,
    Trajectory,
    read_contact,
    read_metric_frames,
    read_simulation,
    read_trajectory,
    write_contact,
    write_metric_frames,
    write_simulation,
    write_trajectory,
)
from dexflow.io.layout import ObjectPaths

NAMES = ["a", "b", "c"]
FINGERS = ["thumb", "index"]


def _q(frames: int = 5, dof: int = 3) -> np.ndarray:
    """Every value distinct: column j of frame t is 10 * t + j."""
    return 10.0 * np.arange(frames)[:, None] + np.arange(dof)[None, :]


def _contact(frames: int = 6, first: int | None = 2) -> ContactResult:
    final = np.zeros((frames, len(FINGERS)), dtype=bool)
    if first is not None:
        final[first:, 1] = True
    pairs = 3
    return ContactResult(
        distance_m=np.linspace(0.01, 0.0, frames)[:, None] * np.ones(len(FINGERS)),
        raw=~final,
        final=final,
        fingers=list(FINGERS),
        fps=30.0,
        contact_map={
            "map_frame": np.array([2, 3, 4]),
            "map_finger": np.array([1, 1, 1]),
            "map_hand_index": np.array([7, 8, 9]),
            "map_hand_point": np.arange(pairs * 3.0).reshape(pairs, 3),
            "map_object_point": -np.arange(pairs * 3.0).reshape(pairs, 3),
            "map_object_normal": np.tile([0.0, 0.0, 1.0], (pairs, 1)),
        },
    )


ENGINES = ["mujoco", "pybullet"]
ROW_KEYS = [*SIMULATION_KEYS, *(f"{e}.{k}" for e in ENGINES for k in ENGINE_KEYS)]


def _simulation_rows(n: int = 4) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    shapes = {"touching": (n, len(FINGERS))} | {
        k: (n, 6) for k in ("held", "displacement_m", "rotation_deg", "tested")
    }
    return {k: rng.random(shapes.get(k.partition(".")[2] or k, (n,))) for k in ROW_KEYS}


# ----------------------------------------------------------------------------- round trips


def test_trajectory_round_trip_keeps_q_names_and_arrays(tmp_path):
    path = tmp_path / "sequences" / "s.npz"
    extra = {"observed": np.array([True, False, True, True, False]), "energy": np.arange(5.0)}
    write_trajectory(path, Trajectory(_q(), list(NAMES), extra))
    back = read_trajectory(path, NAMES, frames=5)
    np.testing.assert_array_equal(back.q, _q())
    assert back.q.dtype == np.float64
    assert back.joint_names == NAMES
    assert set(back.arrays) == set(extra)
    for key, value in extra.items():
        np.testing.assert_array_equal(back[key], value)


def test_trajectory_checks_are_skipped_without_names_or_frames(tmp_path):
    path = tmp_path / "s.npz"
    write_trajectory(path, Trajectory(_q(), list(NAMES)))
    back = read_trajectory(path)
    assert back.joint_names == NAMES
    np.testing.assert_array_equal(back.q, _q())


def test_contact_round_trip_keeps_every_field(tmp_path):
    path = tmp_path / "c.npz"
    result = _contact()
    write_contact(path, result)
    back = read_contact(path, FINGERS, frames=6)
    np.testing.assert_array_equal(back.distance_m, result.distance_m)
    np.testing.assert_array_equal(back.raw, result.raw)
    np.testing.assert_array_equal(back.final, result.final)
    assert back.raw.dtype == bool and back.final.dtype == bool
    assert (back.fingers, back.fps) == (FINGERS, 30.0)
    assert set(back.contact_map) == set(result.contact_map)
    for key, value in result.contact_map.items():
        np.testing.assert_array_equal(back.contact_map[key], value)


def test_simulation_round_trip_keeps_rows_and_fingers(tmp_path):
    path = tmp_path / "sim.npz"
    rows = _simulation_rows()
    write_simulation(path, SimulationResult(rows, list(FINGERS), ENGINES))
    back = read_simulation(path)
    assert back.fingers == FINGERS and back.engines == ENGINES
    assert set(back.rows) == set(ROW_KEYS)
    for key in ROW_KEYS:
        np.testing.assert_array_equal(back.rows[key], rows[key])


def test_metric_frames_round_trip_keeps_methods_and_metrics(tmp_path):
    path = tmp_path / "m.npz"
    methods = {
        label: {"keypoint_error": np.arange(4.0) + i, "penetration": np.full(4, 0.001 * i)}
        for i, label in enumerate(("baseline", "retarget", "refine"))
    }
    contact = np.eye(4, 2, dtype=bool)
    write_metric_frames(path, MetricFrames(np.arange(4) / 30.0, contact, methods))
    back = read_metric_frames(path)
    np.testing.assert_array_equal(back.time, np.arange(4) / 30.0)
    np.testing.assert_array_equal(back.contact, contact)
    assert back.methods.keys() == methods.keys()
    for label, values in methods.items():
        assert back.methods[label].keys() == values.keys()
        for metric, value in values.items():
            np.testing.assert_array_equal(back.methods[label][metric], value)


# ------------------------------------------------------------------------ read_trajectory


def test_trajectory_of_another_hand_is_refused_naming_file_and_field(tmp_path):
    path = tmp_path / "other_hand.npz"
    write_trajectory(path, Trajectory(_q(), ["a", "b", "x"]))
    with pytest.raises(ArtifactError) as err:
        read_trajectory(path, NAMES)
    assert str(path) in str(err.value)
    assert "joint_names" in str(err.value)
    assert "'x'" in str(err.value) and "'c'" in str(err.value)  # the first difference


def test_trajectory_with_fewer_joints_is_refused(tmp_path):
    path = tmp_path / "s.npz"
    write_trajectory(path, Trajectory(_q(dof=2), ["a", "b"]))
    with pytest.raises(ArtifactError, match="joint_names"):
        read_trajectory(path, NAMES)


@pytest.mark.parametrize("stored", [["c", "a", "b"], ["b", "c", "a"], ["c", "b", "a"]])
def test_permuted_columns_come_back_in_the_requested_order(tmp_path, stored):
    # Column of joint n holds values tagged by n, so a value must move with its name.
    tag = {"a": 1.0, "b": 2.0, "c": 3.0}
    frames = np.arange(4.0)[:, None]
    stored_q = frames * 10 + np.array([tag[n] for n in stored])
    path = tmp_path / "s.npz"
    write_trajectory(path, Trajectory(stored_q, list(stored)))
    back = read_trajectory(path, NAMES)
    assert back.joint_names == NAMES
    np.testing.assert_array_equal(back.q, frames * 10 + np.array([tag[n] for n in NAMES]))


def test_wrong_frame_count_is_refused_naming_both_counts(tmp_path):
    path = tmp_path / "s.npz"
    write_trajectory(path, Trajectory(_q(frames=5), list(NAMES)))
    with pytest.raises(ArtifactError, match="5 frames, expected 7") as err:
        read_trajectory(path, NAMES, frames=7)
    assert str(path) in str(err.value)


@pytest.mark.parametrize(("frame", "value"), [(0, np.nan), (3, np.inf), (4, -np.inf)])
def test_non_finite_q_is_refused_naming_the_frame(tmp_path, frame, value):
    q = _q()
    q[frame, 1] = value
    path = tmp_path / "s.npz"
    write_trajectory(path, Trajectory(q, list(NAMES)))
    with pytest.raises(ArtifactError, match=f"frame {frame}$"):
        read_trajectory(path, NAMES)


def test_missing_trajectory_file_is_refused(tmp_path):
    path = tmp_path / "absent.npz"
    with pytest.raises(ArtifactError, match="no such file") as err:
        read_trajectory(path, NAMES)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("key", ["q", "joint_names"])
def test_missing_key_is_refused_naming_it(tmp_path, key):
    path = tmp_path / "s.npz"
    arrays = {"q": _q(), "joint_names": np.array(NAMES)}
    del arrays[key]
    np.savez(path, **arrays)
    with pytest.raises(ArtifactError) as err:
        read_trajectory(path, NAMES)
    assert f"missing ['{key}']" in str(err.value)
    assert str(path) in str(err.value)


def test_q_that_does_not_fit_its_names_on_disk_is_refused(tmp_path):
    path = tmp_path / "s.npz"
    np.savez(path, q=_q(dof=4), joint_names=np.array(NAMES))
    with pytest.raises(ArtifactError, match=r"\(T, 3\)"):
        read_trajectory(path)


# ----------------------------------------------------------------------- write_trajectory


@pytest.mark.parametrize("q", [_q(dof=2), _q(dof=4), np.arange(3.0)])
def test_write_trajectory_refuses_q_not_fitting_its_names(tmp_path, q):
    path = tmp_path / "s.npz"
    with pytest.raises(ArtifactError, match=r"\(T, 3\)"):
        write_trajectory(path, Trajectory(q, list(NAMES)))
    assert not path.exists()


@pytest.mark.parametrize("name", ["q", "joint_names"])
def test_write_trajectory_refuses_arrays_clashing_with_its_fields(tmp_path, name):
    path = tmp_path / "s.npz"
    with pytest.raises(ArtifactError, match=name):
        write_trajectory(path, Trajectory(_q(), list(NAMES), {name: np.zeros(5)}))
    assert not path.exists()


# -------------------------------------------------------------------------------- contact


def test_contact_of_other_fingers_is_refused(tmp_path):
    path = tmp_path / "c.npz"
    write_contact(path, _contact())
    with pytest.raises(ArtifactError, match="fingers") as err:
        read_contact(path, ["thumb", "middle"])
    assert str(path) in str(err.value)
    with pytest.raises(ArtifactError, match="fingers"):
        read_contact(path, ["thumb", "index", "middle"])


def test_contact_of_another_frame_count_is_refused(tmp_path):
    path = tmp_path / "c.npz"
    write_contact(path, _contact(frames=6))
    with pytest.raises(ArtifactError, match="6 frames, expected 9"):
        read_contact(path, FINGERS, frames=9)


def test_write_contact_refuses_an_incomplete_map(tmp_path):
    result = _contact()
    del result.contact_map["map_object_normal"]
    with pytest.raises(ArtifactError, match="map_object_normal"):
        write_contact(tmp_path / "c.npz", result)


@pytest.mark.parametrize(("first", "expected"), [(0, 0), (2, 2), (5, 5), (None, -1)])
def test_first_contact_is_the_first_touching_frame(first, expected):
    assert _contact(frames=6, first=first).first_contact == expected


def test_first_contact_counts_any_finger(tmp_path):
    result = _contact(frames=6, first=4)
    result.final[3, 0] = True  # the other finger touches earlier
    assert result.first_contact == 3
    path = tmp_path / "c.npz"
    write_contact(path, result)
    assert read_contact(path).first_contact == 3


# ----------------------------------------------------------------------------- simulation


@pytest.mark.parametrize("key", [*SIMULATION_KEYS, "pybullet.held", "mujoco.bench_single"])
def test_write_simulation_refuses_rows_lacking_a_key(tmp_path, key):
    rows = _simulation_rows()
    del rows[key]
    path = tmp_path / "sim.npz"
    with pytest.raises(ArtifactError, match=key):
        write_simulation(path, SimulationResult(rows, list(FINGERS), ENGINES))
    assert not path.exists()


def test_write_simulation_refuses_no_engine(tmp_path):
    with pytest.raises(ArtifactError, match="engine"):
        write_simulation(tmp_path / "sim.npz", SimulationResult(_simulation_rows(), FINGERS, []))


def test_read_simulation_refuses_a_file_lacking_a_key(tmp_path):
    rows = _simulation_rows()
    del rows["mujoco.held"]
    path = tmp_path / "sim.npz"
    np.savez(path, fingers=np.array(FINGERS), engines=np.array(ENGINES), **rows)
    with pytest.raises(ArtifactError, match="held"):
        read_simulation(path)


# -------------------------------------------------------------------------------- objects


def test_object_readers_name_the_absent_file(tmp_path):
    assets = ObjectAssets(ObjectPaths(tmp_path / "objects" / "box"))
    for read, path in [
        (assets.sdf, assets.paths.sdf),
        (assets.convex_parts, assets.paths.convex),
        (assets.surface, assets.paths.surface),
    ]:
        with pytest.raises(ArtifactError, match="no such file") as err:
            read()
        assert str(path) in str(err.value)


def test_object_surface_reads_points_and_normals(tmp_path):
    paths = ObjectPaths(tmp_path / "objects" / "box")
    paths.root.mkdir(parents=True)
    points = np.arange(12.0).reshape(4, 3)
    normals = np.tile([1.0, 0.0, 0.0], (4, 1))
    np.savez(paths.surface, points=points, normals=normals)
    got_points, got_normals = ObjectAssets(paths).surface()
    np.testing.assert_array_equal(got_points, points)
    np.testing.assert_array_equal(got_normals, normals)


def test_object_surface_without_normals_is_refused(tmp_path):
    paths = ObjectPaths(tmp_path)
    np.savez(paths.surface, points=np.zeros((4, 3)))
    with pytest.raises(ArtifactError, match="normals"):
        ObjectAssets(paths).surface()


@pytest.mark.parametrize("content", [b"", b"garbage", b"PK\x03\x04truncated"])
def test_an_unreadable_file_is_an_artifact_error_naming_it(tmp_path, content):
    path = tmp_path / "broken.npz"
    path.write_bytes(content)
    with pytest.raises(ArtifactError, match=r"broken\.npz: not a readable \.npz"):
        read_trajectory(path)
