"""Stage track's search (dexflow.sim.track) on the three-finger gripper, upside down over a box on
a table: fingers that stop short of the box drop it in the replay, and the tracked targets carry
it; the tracked trajectory replays exactly as the search simulated it; a box out of reach stays
out of reach (not feasible); the search is deterministic for a seed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from dexflow.geometry import transform_points
from dexflow.hands import load_hand
from dexflow.hands.robot import base_transform
from dexflow.measures import fingertips
from dexflow.objects.convex import write_convex_obj
from dexflow.params import ReplayParams, TrackParams
from dexflow.sim.carry import grasp_carry
from dexflow.sim.grip import grip_parts, grip_schedule, guided_targets
from dexflow.sim.replay_criteria import lift_frame, sequence_result
from dexflow.sim.replay_world import ReplayWorld
from dexflow.sim.track import replay_rank, track_sequence

from .test_hands import _gripper
from .test_replay import BOX, gripper_over_box

FPS = 30.0
APPROACH, HOLD, LIFT, TOP = 5, 8, 20, 12  # frames
RISE_M = 0.15
GAP_M = 0.003  # the "refined" fingers stop this far from the box
SETTINGS = TrackParams(  # quick: a test
    horizon_frames=4, samples=6, iterations=1, schedule_scales=[1.0, 2.0], schedule_leads=[0]
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The gripper upside down with its palm above a box; its fingers closed to ``GAP_M`` from
    the box (touching in stage contact's eyes, gripping nothing) and the box's recorded lift."""
    folder = tmp_path_factory.mktemp("track")
    hand = load_hand(_gripper(folder))
    write_convex_obj(folder / "box.obj", [trimesh.creation.box(BOX)])
    params = ReplayParams(squeeze_m=SETTINGS.squeeze_m)
    world = ReplayWorld(hand, params, SETTINGS.squeeze_reach_m)
    world.set_object(folder / "box.obj")
    opened, pose, near = gripper_over_box(hand, world, GAP_M)
    frames = APPROACH + HOLD + LIFT + TOP
    rise = np.concatenate(
        [np.zeros(APPROACH + HOLD), np.linspace(0.0, RISE_M, LIFT), np.full(TOP, RISE_M)]
    )
    poses = np.repeat(pose[None], frames, axis=0)
    poses[:, 2, 3] += rise
    closing = np.clip(np.arange(frames) / APPROACH, 0.0, 1.0)[:, None]  # fingers close, then hold
    q = opened + closing * (near - opened)
    q[:, 2] += rise
    fingers = np.zeros((frames, 3), dtype=bool)
    fingers[APPROACH:] = True  # stage contact: all three on the box from the approach's end
    window = (0, APPROACH, frames - 1)
    return world, q, poses, fingers, window


def _score(world, targets, poses, window):
    rows = world.replay(targets, poses, FPS, window)
    return rows, sequence_result(rows, window[1], poses, FPS, world.replay_params)


def test_fingers_short_of_the_box_drop_it_and_the_tracked_targets_carry_it(scene):
    world, q, poses, fingers, window = scene
    _, before = _score(world, q, poses, window)
    assert not before["carried"] and before["lost"]  # the box stays on its table
    found = track_sequence(
        world, q, poses, FPS, window, fingers, SETTINGS, np.random.default_rng(0)
    )
    rows, after = _score(world, found["targets"], poses, window)
    assert after["success"] and after["carried"] and not after["lost"]
    assert found["replayed"] == after  # what the stage reports: the replay of its targets
    assert rows["object_position"][-1, 2] > poses[0, 2, 3] + 0.1  # really up in the air
    # q is where the simulated hand was: its base within millimetres of the prior's
    assert np.abs(found["q"][:, :3] - q[:, :3]).max() < 0.01
    # the search's own rollout is the replay of its targets, to the bit
    start, _, end = window
    np.testing.assert_array_equal(rows["object_position"], found["object_pose7"][start:, :3])
    np.testing.assert_array_equal(found["q"][end], world.hand_state())


def test_a_box_out_of_reach_is_not_carried(scene):
    """The box 30 cm to the side: no target near the prior reaches it, and the search does not
    pretend so (not feasible)."""
    world, q, poses, fingers, window = scene
    far = poses.copy()
    far[:, 0, 3] += 0.3
    found = track_sequence(world, q, far, FPS, window, fingers, SETTINGS, np.random.default_rng(0))
    _, after = _score(world, found["targets"], far, window)
    assert not after["success"] and not after["carried"]
    assert np.abs(found["q"][:, :3] - q[:, :3]).max() < 0.05  # it stayed near the prior


def test_search_is_deterministic_for_a_seed(scene):
    """Two runs with one seed give the same bits (the stage seeds each sequence by its name, so
    the worker count cannot matter: tests/test_pipeline.py checks that through DVC)."""
    world, q, poses, fingers, window = scene
    short = dataclasses.replace(SETTINGS, samples=3)
    runs = [
        track_sequence(world, q, poses, FPS, window, fingers, short, np.random.default_rng(seed))
        for seed in (7, 7)
    ]
    for key in runs[0]:
        np.testing.assert_array_equal(runs[0][key], runs[1][key], key)


def test_grip_ramps_in_before_the_lift():
    """The squeeze is off while the object rests, ramps in over the frames before the lift (the
    first frame the recorded object is 1 cm from its pose at the first contact) and stays on to
    the window's end."""
    poses = np.repeat(np.eye(4)[None], 30, axis=0)
    poses[15:, 2, 3] = np.linspace(0.0, 0.1, 15)  # 1 cm up first at frame 17
    share = grip_schedule(poses, (2, 5, 25), ramp=3)
    lift = int(np.argmax(np.linalg.norm(poses[:, :3, 3], axis=1) > 0.01))
    assert lift == 17
    np.testing.assert_allclose(share[: lift - 3 + 1], 0.0)
    early = grip_schedule(poses, (2, 5, 25), ramp=3, lead=2)  # done 2 frames before the lift
    np.testing.assert_allclose(early[lift - 2 : 26], 1.0)
    assert early[lift - 3] < 1.0
    np.testing.assert_allclose(share[lift - 2 : lift], [1 / 3, 2 / 3])
    np.testing.assert_allclose(share[lift:26], 1.0)
    np.testing.assert_allclose(share[26:], 0.0)


def test_a_held_grasp_keeps_the_fingers_targets_of_the_lift(scene):
    """With the hold ``fingers`` the fingers' targets from the lift to the window's end are those at the
    lift, whatever the refined fingers do meanwhile (here: open wide mid-carry); before the
    lift and for the base the schedule is the one without the hold. The held schedule carries
    the box."""
    world, q, poses, fingers, window = scene
    jittery = q.copy()
    mid = APPROACH + HOLD + LIFT // 2
    jittery[mid : mid + 4, 6:] = q[0, 6:] + 0.5  # opened beyond the squeeze's reach
    parts = grip_parts(world, jittery, poses, window, fingers, SETTINGS)
    held, followed = (
        guided_targets(jittery, parts, poses, window, (1.0, 2, 0, 0.0, hold))
        for hold in ("fingers", "follow")
    )
    lift = lift_frame(poses, window)
    assert APPROACH + HOLD < lift < mid
    np.testing.assert_array_equal(held[: lift + 1], followed[: lift + 1])
    np.testing.assert_array_equal(held[:, :6], followed[:, :6])
    end = window[2]
    np.testing.assert_array_equal(
        held[lift : end + 1, 6:], np.tile(held[lift, 6:], (end + 1 - lift, 1))
    )
    assert np.abs(followed[mid, 6:] - held[mid, 6:]).max() > 0.1  # it did not follow the opening
    _, result = _score(world, held, poses, window)
    assert result["success"] and result["carried"]


def _turning_tips(frames: int, lift: int) -> tuple[np.ndarray, np.ndarray]:
    """Five fingertips held still until ``lift``, then turned by 1.2 turns about a tilted axis
    through a point beside them and raised: (T, 4, 4) their motion since the lift and (T, 5, 3)
    the fingertips."""
    rng = np.random.default_rng(3)
    grip = np.array([0.3, -0.1, 0.9]) + rng.normal(0.0, 0.03, (5, 3))
    axis = np.array([0.2, 0.3, 1.0]) / np.linalg.norm([0.2, 0.3, 1.0])
    turn = np.clip(np.arange(frames) - lift, 0, None) * (1.2 * 2 * np.pi / (frames - 1 - lift))
    motion = np.repeat(np.eye(4)[None], frames, axis=0)
    motion[:, :3, :3] = Rotation.from_rotvec(turn[:, None] * axis).as_matrix()
    pivot = np.array([0.35, -0.05, 0.85])
    motion[:, :3, 3] = pivot - motion[:, :3, :3] @ pivot
    motion[:, 2, 3] += 0.002 * np.clip(np.arange(frames) - lift, 0, None)
    return motion, transform_points(motion, grip)


def test_a_carried_grasp_moves_the_base_with_the_fingertips():
    """``grasp_carry`` moves the base from the lift on exactly as the fingertips move (no
    smoothing), turning more than a whole turn without a jump of the base's Euler targets, and
    fills an unobserved frame from its neighbours; before the lift it is the prior's base."""
    frames, lift = 40, 10
    poses = np.repeat(np.eye(4)[None], frames, axis=0)
    poses[lift:, 2, 3] += 0.02  # the recorded lift at frame 10
    window = (0, 5, frames - 1)
    motion, tips = _turning_tips(frames, lift)
    tips[20] = np.nan  # not observed: taken from frames 19 and 21
    base = np.zeros((frames, 6))
    base[:, :3] = [0.25, -0.15, 1.0]
    base[:, 3:] = [0.4, -0.3, 2.9]
    base[:, 0] += np.linspace(0.0, 0.05, frames)  # the prior's wrist drifts: not followed
    carried = grasp_carry(base, tips, poses, window, smooth_frames=0.0)
    np.testing.assert_array_equal(carried[:lift], base[:lift])
    np.testing.assert_allclose(carried[lift], base[lift], atol=1e-12)
    got = base_transform(torch.as_tensor(carried)).numpy()
    lifted = base_transform(torch.as_tensor(base[lift : lift + 1])).numpy()[0]
    expected = motion @ lifted
    observed = np.arange(lift, frames) != 20
    frames_ok = np.arange(lift, frames)[observed]
    np.testing.assert_allclose(got[frames_ok], expected[frames_ok], atol=1e-9)
    assert np.abs(got[20] - expected[20]).max() < 0.01  # interpolated between its neighbours
    assert np.abs(np.diff(carried[:, 3:], axis=0)).max() < 0.5  # rad per frame: no wrap
    smoothed = grasp_carry(base, tips, poses, window, smooth_frames=2.0)
    np.testing.assert_allclose(smoothed[lift], base[lift], atol=1e-12)  # starts at the lift
    assert np.abs(smoothed[lift + 10 :] - carried[lift + 10 :]).max() < 0.05


def test_a_carried_grasp_keeps_the_fingers_and_takes_the_carried_base(scene):
    """The hold ``grasp``: the fingers' targets as with ``fingers``, the base's from the lift on
    the carried ones (before the lift the prior's)."""
    world, q, poses, fingers, window = scene
    parts = grip_parts(world, q, poses, window, fingers, SETTINGS)
    lift = lift_frame(poses, window)
    carried = q[:, :6].copy()
    carried[lift:, 0] += 0.01
    held, grasped = (
        guided_targets(q, parts, poses, window, (1.0, 2, 0, 0.0, hold), carried)
        for hold in ("fingers", "grasp")
    )
    np.testing.assert_array_equal(grasped[:, 6:], held[:, 6:])
    np.testing.assert_array_equal(grasped[:lift, :6], held[:lift, :6])
    np.testing.assert_array_equal(grasped[lift:, :6], carried[lift:])
    with pytest.raises(ValueError, match="hold"):
        guided_targets(q, parts, poses, window, (1.0, 2, 0, 0.0, True), carried)
    grasp_only = dataclasses.replace(SETTINGS, schedule_holds=["grasp"])
    with pytest.raises(ValueError, match="fingertips"):  # the grasp moves with the human's
        track_sequence(world, q, poses, FPS, window, fingers, grasp_only, np.random.default_rng(0))


def test_the_fingertip_term_keeps_the_tips_near_the_refined_ones(scene):
    """With ``tip_weight`` the search prefers, among targets that carry the box, those whose
    simulated fingertips stay nearer the refined trajectory's: still carried, tips nearer."""
    world, q, poses, fingers, window = scene
    hand = world.hand
    start, _, end = window
    goal = fingertips(hand, q[start : end + 1])
    near = {}
    for weight in (0.0, 20.0):
        settings = dataclasses.replace(SETTINGS, tip_weight=weight)
        found = track_sequence(
            world, q, poses, FPS, window, fingers, settings, np.random.default_rng(0)
        )
        assert found["replayed"]["success"], weight
        tips = fingertips(hand, found["q"][start : end + 1])
        near[weight] = np.linalg.norm(tips - goal, axis=-1).mean()
    assert near[20.0] < near[0.0], near


def test_success_ranks_first_and_carried_alone_does_not_outrank_the_fingertips():
    """Among failures, a replay that drags the object along with the fingertips far from the
    refined ones ranks below one that stays on them and drops it; any success ranks above
    both."""
    settings = dataclasses.replace(SETTINGS, tip_weight=20.0)

    def replay(success, carried, position_m):
        return {"success": success, "carried": carried, "position_error_mean_m": position_m,
                "rotation_error_mean_rad": 0.3}  # fmt: skip

    dragged, dropped = replay(False, True, 0.06), replay(False, False, 0.12)
    assert replay_rank(dropped, 0.01, settings) < replay_rank(dragged, 0.05, settings)
    succeeded = replay(True, True, 0.09)
    assert replay_rank(succeeded, 0.05, settings) < replay_rank(dropped, 0.0, settings)
