"""Stage simulate: the six-direction grasp test in pybullet on a three-finger gripper and a box;
default inertial data for URDF links without it, a stable controller at tiny inertias, and the
penetration rule measured on the object's mesh."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import trimesh

from dexflow.hands import load_hand
from dexflow.objects.convex import write_convex_obj
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import PerturbationParams, SimulateParams
from dexflow.sim.pybullet_world import PybulletGraspWorld, _mass_frame, hand_urdf, object_parts
from dexflow.stages.simulate import simulate_sequence

from .test_hands import _gripper

BOX = (0.024, 0.024, 0.03)  # sits on the gripper's palm, between its three fingers
# The single nominal trial per frame: these tests are about the protocol and the sequence logic;
# robust success under perturbations has tests of its own. Frames over the penetration tolerance
# are tested too (the uncounted ``*_raw`` results); skipping them has a test of its own.
SINGLE = SimulateParams(perturbations=PerturbationParams(count=0), test_over_tolerance=True)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A gripper, a world with a small box in it, and the box's pose on the palm."""
    folder = tmp_path_factory.mktemp("simulate")
    hand = load_hand(_gripper(folder))
    write_convex_obj(folder / "box.obj", [trimesh.creation.box(BOX)])
    world = PybulletGraspWorld(hand, hand_urdf(hand), SINGLE)
    world.set_object(folder / "box.obj")
    pose = np.eye(4)
    pose[2, 3] = 0.01 + BOX[2] / 2  # palm top at z = 1 cm
    return hand, world, pose, folder


@pytest.fixture(scope="module")
def box_sdf():
    return SignedDistanceGrid.from_mesh(trimesh.creation.box(BOX), spacing=0.001, padding=0.01)


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
    assert result["touching"].tolist() == [True, True, True]
    assert result["parts_penetration_m"] < 1e-3
    assert np.all(result["displacement_m"] < 0.01) and np.all(result["rotation_deg"] < 15)
    assert result["imbalance"] < 0.4  # three fingers around the box: the pushes nearly cancel
    # this test holds the object still while the fingers close: no closing motion to report
    assert np.isnan(result["closing_displacement_m"]) and np.isnan(result["closing_rotation_deg"])


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
    assert result["pushed_links"] == 0 and result["parts_penetration_m"] == 0.0
    assert not result["touching"].any()
    assert not result["contact"] and not result["bench"] and not result["held"].any()


def test_gravity_really_pulls_on_the_object(scene):
    """With the force off, the opened hand 'holds' the box resting on its palm; with it on, not."""
    hand, _, pose, folder = scene
    weightless = PybulletGraspWorld(hand, hand_urdf(hand), SimulateParams(gravity=1e-9))
    weightless.set_object(folder / "box.obj")
    result = weightless.test_frame(_opened(hand), pose)
    assert result["held"].all() and np.all(result["displacement_m"] < 1e-3)


def test_results_are_identical_across_runs_and_worlds(scene):
    hand, world, pose, folder = scene
    q = _closed(hand, world, pose)
    other = PybulletGraspWorld(hand, hand_urdf(hand), SimulateParams())
    other.set_object(folder / "box.obj")
    first = world.test_frame(q, pose)
    world.test_frame(_opened(hand), pose)  # history must not matter
    again = world.test_frame(q, pose)
    fresh = other.test_frame(q, pose)
    for result in (again, fresh):
        for key, value in first.items():
            np.testing.assert_array_equal(np.asarray(value), np.asarray(result[key]), err_msg=key)


def test_penetrating_start_does_not_count_and_sequence_logic(scene, box_sdf):
    """A frame that starts with the box sunk into the palm holds it but is not counted; the
    sequence succeeds at the first clean frame after first contact and stops there."""
    hand, world, pose, folder = scene
    closed = _closed(hand, world, pose)
    sunk = pose.copy()
    sunk[2, 3] -= 0.004  # 4 mm into the palm
    q = np.stack([_opened(hand), closed, closed, closed, closed])
    poses = np.stack([pose, pose, sunk, pose, pose])
    arrays, result = simulate_sequence(world, q, poses, first_contact=2, sdf=box_sdf)
    p = world.params
    assert arrays["frame"].tolist() == [2]  # stride 5 from frame 2
    params = dataclasses.replace(p, stride=1)
    world_1 = PybulletGraspWorld(hand, hand_urdf(hand), params)
    world_1.set_object(folder / "box.obj")
    opposed = {  # stage contact's map: two fingers on opposite faces at frame 3 only
        "map_frame": np.array([3, 3]),
        "map_finger": np.array([0, 1]),
        "map_object_normal": np.array([[1.0, 0, 0], [-1.0, 0, 0]]),
    }
    arrays, result = simulate_sequence(world_1, q, poses, 2, box_sdf, opposed)
    assert arrays["frame"].tolist() == [2, 3]  # early stop after the first counted success
    assert np.isnan(arrays["contact_imbalance"][0]) and arrays["contact_imbalance"][1] == 0
    assert (result["contact_imbalance_sum"], result["contact_imbalance_frames"]) == (0.0, 1)
    assert arrays["pybullet.touching"].shape == (2, 3) and arrays["pybullet.touching"][1].all()
    assert arrays["penetration_m"][0] > p.penetration_tol_m and arrays["pybullet.contact"][0]
    assert arrays["penetration_m"][0] == pytest.approx(0.004, abs=5e-4)  # on the mesh
    parts = arrays["pybullet.parts_penetration_m"][0]
    assert parts == pytest.approx(0.004, abs=5e-4)  # parts = mesh
    assert result["success_contact_raw"] and result["success_contact"]
    assert result["success_frame"] == 3 and result["evaluated"] == 2
    assert result["engines"]["pybullet"]["success_frame"] == 3
    empty, none = simulate_sequence(world_1, q, poses, first_contact=-1, sdf=box_sdf)
    assert empty["pybullet.touching"].shape == (0, 3) and empty["pybullet.held"].shape == (0, 6)
    assert none["evaluated"] == 0 and not none["success_contact"]


def test_frames_over_the_tolerance_are_skipped_by_default_with_the_same_success(scene, box_sdf):
    """By default a frame starting over the penetration tolerance is not tested (it cannot
    count): the same counted success, frame and penetration statistics; no raw results."""
    hand, world, pose, folder = scene
    closed = _closed(hand, world, pose)
    sunk = pose.copy()
    sunk[2, 3] -= 0.004  # 4 mm into the palm
    q = np.stack([_opened(hand), closed, closed, closed])
    poses = np.stack([pose, pose, sunk, pose])
    results = {}
    for test_all in (True, False):
        params = dataclasses.replace(world.params, stride=1, test_over_tolerance=test_all)
        assert SimulateParams().test_over_tolerance is False  # the default skips
        skipping = PybulletGraspWorld(hand, hand_urdf(hand), params)
        skipping.set_object(folder / "box.obj")
        results[test_all] = simulate_sequence(skipping, q, poses, 2, box_sdf)
    (tested, every), (arrays, result) = results[True], results[False]
    assert tested["frame"].tolist() == [2, 3] and arrays["frame"].tolist() == [3]
    assert result["skipped"] == 1 and every["skipped"] == 0
    for key in ("success_contact", "success_bench", "success_frame", "over_tolerance",
                "penetration_mean_mm"):  # fmt: skip
        assert result[key] == every[key], key
    assert result["over_tolerance"] == 0.5  # frames 2 (4 mm in) and 3 considered
    assert every["success_contact_raw"] and result["success_contact_raw"] is None


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


def test_links_without_inertial_get_the_default_mass(tmp_path):
    """The base and the fingertip frames lose their <inertial>; pybullet would make each 1 kg.
    The URDF pybullet loads gives them the documented default, and a mesh referenced by a
    relative path still loads from the copy."""
    yaml = _gripper(tmp_path)
    urdf = tmp_path / "gripper3.urdf"
    text = re.sub(
        r'(<link name="(base|f\d_tip)">)<inertial>.*?</inertial>', r"\1", urdf.read_text()
    )
    pad = '<collision><geometry><mesh filename="meshes/pad.obj"/></geometry></collision>'
    text = text.replace('<link name="f0_tip">', f'<link name="f0_tip">{pad}')
    urdf.write_text(text)
    (tmp_path / "meshes").mkdir()
    trimesh.creation.box((0.01, 0.01, 0.004)).export(tmp_path / "meshes" / "pad.obj")
    hand = load_hand(yaml)
    params = SimulateParams(massless_link_mass_kg=0.003, massless_link_inertia_kgm2=2e-7)
    path = hand_urdf(hand, params)
    assert path != urdf and path.parent != urdf.parent
    world, raw = PybulletGraspWorld(hand, path, params), PybulletGraspWorld(hand, urdf, params)
    for link in ("base", "f0_tip", "f1_tip", "f2_tip"):
        info = world.client.getDynamicsInfo(world.body, world.link_index[link])
        assert info[0] == pytest.approx(0.003)
        np.testing.assert_allclose(info[2], (2e-7,) * 3)
        assert raw.client.getDynamicsInfo(raw.body, raw.link_index[link])[0] == 1.0
    own = world.client.getDynamicsInfo(world.body, world.link_index["f0_prox"])
    assert own[0] == pytest.approx(0.02)  # links with inertial data keep theirs
    shapes = world.client.getCollisionShapeData(world.body, world.link_index["f0_tip"])
    assert [s[2] for s in shapes] == [world.pb.GEOM_MESH]
    (tmp_path / "complete").mkdir()
    complete = load_hand(_gripper(tmp_path / "complete"))
    assert hand_urdf(complete) == tmp_path / "complete" / "gripper3.urdf"  # loaded as it is


@pytest.mark.parametrize("name", ["tiny", "allegro"])
def test_hand_with_tiny_inertias_holds_its_pose_without_an_object(tmp_path, name):
    """Every link at 1e-6 kg·m² (the gripper) or the built-in Allegro (1 g links of 1e-7):
    under the protocol's controller, with nothing to touch and the hand's own weight along each
    of the six directions, no joint leaves its target by 0.05 rad over a frame's horizon."""
    if name == "tiny":
        yaml = _gripper(tmp_path)
        urdf = tmp_path / "gripper3.urdf"
        text = re.sub(r'i(xx|yy|zz)="[^"]*"', r'i\1="1e-6"', urdf.read_text())
        urdf.write_text(text)
        hand = load_hand(yaml)
    else:
        hand = load_hand("allegro")
    params = SimulateParams()
    world = PybulletGraspWorld(hand, hand_urdf(hand, params), params)
    rng = np.random.default_rng(0)
    lo, hi = hand.lower.numpy()[6:], hand.upper.numpy()[6:]
    q = hand.zero()[0].numpy().copy()
    q[:6] = [0.1, -0.2, 0.3, 0.4, -0.5, 0.6]
    q[6:] = lo + (0.2 + 0.6 * rng.random(len(lo))) * (hi - lo)
    q = hand.clamp(hand.apply_couplings(hand.as_q(q)))[0].numpy()
    angles = world.hold(q)
    assert angles.shape == (6, params.settle_steps + params.control_steps, hand.dof - 6)
    assert np.abs(angles - q[6:]).max() < 0.05


def test_penetration_rule_holds_on_the_mesh_and_on_the_simulated_parts(scene, box_sdf, tmp_path):
    """A flush grasp on the box, simulated with convex parts 3 mm larger than the mesh (as a
    decomposition bulges beyond a scan): the mesh overlaps the hand by none, the parts by 3 mm,
    so in the physics the fingers start wedged 3 mm inside the object and the frame cannot
    count, whatever it holds; with parts as large as the mesh it counts."""
    hand, world, pose, _ = scene
    q = _closed(hand, world, pose)
    write_convex_obj(tmp_path / "bulging.obj", [trimesh.creation.box(np.array(BOX) + 0.006)])
    bulging = PybulletGraspWorld(hand, hand_urdf(hand), SINGLE)
    bulging.set_object(tmp_path / "bulging.obj")
    arrays, result = simulate_sequence(bulging, q[None], pose[None], 0, box_sdf)
    assert arrays["pybullet.parts_penetration_m"][0] > 0.0025
    assert arrays["penetration_m"][0] < 1e-3
    assert result["over_tolerance"] == 0.0 and result["over_tolerance_parts"] == 1
    assert result["success_contact_raw"] and not result["success_contact"]
    exact = PybulletGraspWorld(hand, hand_urdf(hand), SINGLE)
    write_convex_obj(tmp_path / "exact.obj", [trimesh.creation.box(BOX)])
    exact.set_object(tmp_path / "exact.obj")
    _, counted = simulate_sequence(exact, q[None], pose[None], 0, box_sdf)
    assert counted["over_tolerance_parts"] == 0 and counted["success_contact"]


def test_both_engines_test_the_same_frames_and_their_agreement_is_counted(scene, box_sdf):
    """pybullet and MuJoCo on one trajectory: the same frames, one row set per engine, the first
    engine's DexGraspBench success at the top level, and per-frame agreement by the paper's
    criterion."""
    from dexflow.sim.mujoco_world import MujocoGraspWorld

    hand, world, pose, folder = scene
    params = dataclasses.replace(world.params, stride=1, early_stop=False)
    pybullet = PybulletGraspWorld(hand, hand_urdf(hand), params)
    mujoco = MujocoGraspWorld(hand, params)
    for w in (pybullet, mujoco):
        w.set_object(folder / "box.obj")
    closed, opened = _closed(hand, world, pose), _opened(hand)
    q = np.stack([closed, opened, closed])
    poses = np.repeat(pose[None], 3, axis=0)
    arrays, result = simulate_sequence(
        {"mujoco": mujoco, "pybullet": pybullet}, q, poses, 0, box_sdf
    )
    assert arrays["frame"].tolist() == [0, 1, 2]
    for engine in ("mujoco", "pybullet"):
        assert arrays[f"{engine}.bench"].tolist() == [True, False, True], engine
        assert result["engines"][engine]["success_bench"]
    assert result["success_bench"] == result["engines"]["mujoco"]["success_bench"]  # the first
    assert (result["agree_hold"], result["agree_drop"], result["disagree"]) == (2, 1, 0)
    assert result["success_contact"] and result["success"] and result["success_frame"] == 0
    assert (result["criteria_agree_hold"], result["criteria_disagree"]) == (2, 0)


def test_the_headline_ssr_of_two_engines_needs_a_frame_held_in_both(scene, box_sdf):
    """MuJoCo holds the wrapped box; pybullet, pulling it with fifty times its weight, drops it:
    each engine keeps its own result, the headline (the conservative SSR) fails, and the two
    engines disagree on every frame."""
    from dexflow.sim.mujoco_world import MujocoGraspWorld

    hand, world, pose, folder = scene
    params = dataclasses.replace(world.params, stride=1, early_stop=False)
    mujoco = MujocoGraspWorld(hand, params)
    pybullet = PybulletGraspWorld(hand, hand_urdf(hand), dataclasses.replace(params, gravity=500.0))
    for w in (pybullet, mujoco):
        w.set_object(folder / "box.obj")
    closed = _closed(hand, world, pose)
    q, poses = np.stack([closed, closed]), np.repeat(pose[None], 2, axis=0)
    arrays, result = simulate_sequence(
        {"mujoco": mujoco, "pybullet": pybullet}, q, poses, 0, box_sdf
    )
    assert arrays["mujoco.contact"].tolist() == [True, True]
    assert arrays["pybullet.contact"].tolist() == [False, False]
    assert result["engines"]["mujoco"]["success_contact"]
    assert not result["engines"]["pybullet"]["success_contact"]
    assert not result["success_contact"] and not result["success"]
    assert result["success_frame"] == -1
    assert (result["agree_hold"], result["agree_drop"], result["disagree"]) == (0, 0, 2)


def test_perturbed_trials_make_success_robust_and_zero_trials_are_the_single_trial(scene, box_sdf):
    """With perturbations off, robust = single trial; with a perturbation that moves the box out
    of the hand, the frame that held nominally no longer counts, and it is counted as flipped."""
    hand, world, pose, folder = scene
    closed = _closed(hand, world, pose)
    no_trials = dataclasses.replace(world.params.perturbations, count=0)
    base = dataclasses.replace(world.params, stride=1, early_stop=False, perturbations=no_trials)
    single = PybulletGraspWorld(hand, hand_urdf(hand), base)
    single.set_object(folder / "box.obj")
    arrays, result = simulate_sequence(single, closed[None], pose[None], 0, box_sdf)
    assert arrays["pybullet.bench"].tolist() == arrays["pybullet.bench_single"].tolist() == [True]
    assert result["flipped_frames"] == 0 and result["success_bench"]

    far = dataclasses.replace(base.perturbations, count=2, position_m=0.05, rotation_deg=0.0)
    shaken = PybulletGraspWorld(hand, hand_urdf(hand), dataclasses.replace(base, perturbations=far))
    shaken.set_object(folder / "box.obj")
    arrays, result = simulate_sequence(shaken, closed[None], pose[None], 0, box_sdf)
    assert arrays["pybullet.bench_single"].tolist() == [True]  # the nominal trial still holds
    assert arrays["pybullet.bench"].tolist() == [False]  # but not robustly
    assert result["flipped_frames"] == 1 and not result["success_bench"]


def test_penetrating_start_does_not_count_in_mujoco_either(scene, box_sdf):
    """The penetration rule is the stage's, whatever the engine: a box sunk 4 mm into the palm
    is not a counted success in MuJoCo; the clean frame after it is."""
    from dexflow.sim.mujoco_world import MujocoGraspWorld

    hand, world, pose, folder = scene
    closed = _closed(hand, world, pose)
    sunk = pose.copy()
    sunk[2, 3] -= 0.004
    params = dataclasses.replace(world.params, stride=1)
    mujoco = MujocoGraspWorld(hand, params)
    mujoco.set_object(folder / "box.obj")
    q = np.stack([closed, closed])
    arrays, result = simulate_sequence(mujoco, q, np.stack([sunk, pose]), 0, box_sdf)
    assert arrays["penetration_m"][0] > params.penetration_tol_m
    assert result["engines"]["mujoco"]["success_frame"] == 1  # not frame 0
    assert result["success_bench"] and result["success_contact"]


def test_summary_counts_frames_lost_while_closing_and_the_mean_imbalance():
    """Per engine: frames whose object passed either DexGraspBench threshold while the fingers
    closed (None where the engine holds the object then: NaN rows), and the mean imbalance of
    the frames with a contact, over all sequences' frames."""
    from dexflow.stages.simulate import _engine_result, _engine_summary

    p = SimulateParams()

    def arrays(closing_m, closing_deg, balance):
        n = len(balance)
        flags = {f"mujoco.{k}": np.zeros(n, bool) for k in ("contact", "bench")}
        flags |= {f"mujoco.{k}_single": np.zeros(n, bool) for k in ("contact", "bench")}
        return flags | {
            "mujoco.parts_penetration_m": np.zeros(n),
            "mujoco.closing_displacement_m": np.array(closing_m, dtype=float),
            "mujoco.closing_rotation_deg": np.array(closing_deg, dtype=float),
            "mujoco.imbalance": np.array(balance, dtype=float),
        }

    hit = dict.fromkeys(("contact", "bench", "contact_raw", "bench_raw"))
    first = _engine_result(
        arrays([0.001, 0.06, 0.0], [1.0, 0.0, 20.0], [0.2, 1.0, np.nan]), "mujoco", hit, p
    )
    second = _engine_result(arrays([0.01], [2.0], [0.3]), "mujoco", hit, p)
    assert (first["lost_closing_frames"], second["lost_closing_frames"]) == (2, 0)
    summary = _engine_summary([first, second], evaluated=4)
    assert summary["lost_closing"] == 0.5 and summary["imbalance_mean"] == pytest.approx(0.5)
    held = _engine_result(arrays([np.nan], [np.nan], [0.4]), "mujoco", hit, p)  # pybullet-like
    assert held["lost_closing_frames"] is None
    assert _engine_summary([first, held], evaluated=4)["lost_closing"] is None
