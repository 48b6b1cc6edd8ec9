"""Stage simulate: the six-direction grasp test in pybullet on a three-finger gripper and a box."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from dexflow.hands import load_hand
from dexflow.objects.convex import write_convex_obj
from dexflow.simulate import (
    GraspWorld,
    SimulateParams,
    _mass_frame,
    hand_urdf,
    object_parts,
    simulate_sequence,
)

from .test_hands import _gripper

BOX = (0.024, 0.024, 0.03)  # sits on the gripper's palm, between its three fingers


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A gripper, a world with a small box in it, and the box's pose on the palm."""
    folder = tmp_path_factory.mktemp("simulate")
    hand = load_hand(_gripper(folder))
    write_convex_obj(folder / "box.obj", [trimesh.creation.box(BOX)])
    world = GraspWorld(hand, hand_urdf(hand), SimulateParams())
    world.set_object(folder / "box.obj")
    pose = np.eye(4)
    pose[2, 3] = 0.01 + BOX[2] / 2  # palm top at z = 1 cm
    return hand, world, pose, folder


def _closed(hand, world, pose) -> np.ndarray:
    """Tilt each finger inward (negative ``j0``) until it touches the box (within 0.5 mm)."""
    q = hand.zero()[0].numpy().copy()
    for f in range(3):
        j0 = hand.joint_names.index(f"f{f}_j0")
        for angle in np.linspace(0.0, -0.5, 501):
            q[j0] = angle
            if world.gap(q, pose, [f"f{f}_prox", f"f{f}_dist"]) < 5e-4:
                break
        else:
            raise AssertionError(f"finger {f} never reached the box")
    return q


def _opened(hand) -> np.ndarray:
    q = hand.zero()[0].numpy().copy()
    for f in range(3):
        q[hand.joint_names.index(f"f{f}_j0")] = 0.4  # fingers splayed outward
    return q


def test_wrapped_hand_holds_the_box_in_all_six_directions(scene):
    hand, world, pose, _ = scene
    result = world.test_frame(_closed(hand, world, pose), pose)
    assert result["tested"].all() and result["held"].all()
    assert result["contact"] and result["bench"]
    assert result["pushed_links"] >= 3  # three fingers (and the palm) touch the box
    assert result["penetration_m"] < 1e-3
    assert np.all(result["displacement_m"] < 0.01) and np.all(result["rotation_deg"] < 15)


def test_opened_hand_drops_the_box(scene):
    hand, world, pose, _ = scene
    result = world.test_frame(_opened(hand), pose)
    assert not result["contact"] and not result["bench"]
    assert not result["held"].all()
    assert np.nanmax(result["displacement_m"]) > 0.05


def test_object_away_from_the_hand_falls(scene):
    hand, world, pose, _ = scene
    away = pose.copy()
    away[0, 3] += 0.2
    result = world.test_frame(_closed(hand, world, pose), away)
    assert result["pushed_links"] == 0 and result["penetration_m"] == 0.0
    assert not result["contact"] and not result["bench"] and not result["held"].any()


def test_gravity_really_pulls_on_the_object(scene):
    """With the force off, the opened hand 'holds' the box resting on its palm; with it on, not."""
    hand, _, pose, folder = scene
    weightless = GraspWorld(hand, hand_urdf(hand), SimulateParams(gravity=1e-9))
    weightless.set_object(folder / "box.obj")
    result = weightless.test_frame(_opened(hand), pose)
    assert result["held"].all() and np.all(result["displacement_m"] < 1e-3)


def test_results_are_identical_across_runs_and_worlds(scene):
    hand, world, pose, folder = scene
    q = _closed(hand, world, pose)
    other = GraspWorld(hand, hand_urdf(hand), SimulateParams())
    other.set_object(folder / "box.obj")
    first = world.test_frame(q, pose)
    world.test_frame(_opened(hand), pose)  # history must not matter
    again = world.test_frame(q, pose)
    fresh = other.test_frame(q, pose)
    for result in (again, fresh):
        for key, value in first.items():
            np.testing.assert_array_equal(np.asarray(value), np.asarray(result[key]), err_msg=key)


def test_penetrating_start_does_not_count_and_sequence_logic(scene):
    """A frame that starts with the box sunk into the palm holds it but is not counted; the
    sequence succeeds at the first clean frame after first contact and stops there."""
    hand, world, pose, folder = scene
    closed = _closed(hand, world, pose)
    sunk = pose.copy()
    sunk[2, 3] -= 0.004  # 4 mm into the palm
    q = np.stack([_opened(hand), closed, closed, closed, closed])
    poses = np.stack([pose, pose, sunk, pose, pose])
    arrays, result = simulate_sequence(world, q, poses, first_contact=2)
    p = world.params
    assert arrays["frame"].tolist() == [2]  # stride 5 from frame 2
    params = dataclasses.replace(p, stride=1)
    world_1 = GraspWorld(hand, hand_urdf(hand), params)
    world_1.set_object(folder / "box.obj")
    arrays, result = simulate_sequence(world_1, q, poses, first_contact=2)
    assert arrays["frame"].tolist() == [2, 3]  # early stop after the first counted success
    assert arrays["penetration_m"][0] > p.penetration_tol_m and arrays["contact"][0]
    assert result["success_contact_raw"] and result["success_contact"]
    assert result["success_frame"] == 3 and result["evaluated"] == 2
    _, none = simulate_sequence(world_1, q, poses, first_contact=-1)
    assert none["evaluated"] == 0 and not none["success_contact"]


def test_convex_parts_round_trip_and_mass_frame_of_the_union(tmp_path):
    """Two separate cubes (an L-shaped object's parts): read back as two parts, and the centre
    of mass lies between them, not at the centre of one hull around both."""
    small = trimesh.creation.box((0.02, 0.02, 0.02))
    big = trimesh.creation.box((0.04, 0.04, 0.04))
    big.apply_translation((0.1, 0.0, 0.0))
    write_convex_obj(tmp_path / "two.obj", [small, big])
    parts = object_parts(tmp_path / "two.obj")
    assert [len(p) for p in parts] == [8, 8]
    np.testing.assert_allclose(parts[1].mean(axis=0), (0.1, 0.0, 0.0), atol=1e-7)
    frame, moments = _mass_frame(parts, mass=1.0)
    # volumes 8e-6 and 64e-6 m³: the centre of mass is 8/9 of the way to the big cube
    np.testing.assert_allclose(frame[:3, 3], (0.1 * 64 / 72, 0.0, 0.0), atol=1e-9)
    assert np.all(moments > 0)
