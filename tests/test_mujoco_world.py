"""The grasp test in MuJoCo (DexGraspBench's protocol) on the three-finger gripper and a box:
the scene, the kinematics check, holding and dropping, determinism and perturbations."""

from __future__ import annotations

import dataclasses
import re

import mujoco
import numpy as np
import pytest
import trimesh

from dexflow.errors import HandConfigError
from dexflow.hands import load_hand
from dexflow.objects.convex import write_convex_obj
from dexflow.params import PerturbationParams, SimulateParams
from dexflow.sim.mujoco_world import MujocoGraspWorld, hand_name
from dexflow.sim.protocol import (
    Perturbation,
    contact_imbalance,
    damped_step,
    imbalance,
    perturbations,
)

from .test_hands import _gripper
from .test_simulate import _closed  # the same closing, through this world's gap

BOX = (0.024, 0.024, 0.03)  # sits on the gripper's palm, between its three fingers
KEYS = ("parts_penetration_m", "pushed_links", "imbalance", "closing_displacement_m",
        "closing_rotation_deg", "touching", "held", "displacement_m", "rotation_deg", "tested",
        "contact", "bench")  # fmt: skip


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A gripper, a MuJoCo world with a small box in it, the box's pose on the palm and the
    gripper closed around it."""
    folder = tmp_path_factory.mktemp("mujoco_world")
    hand = load_hand(_gripper(folder))
    write_convex_obj(folder / "box.obj", [trimesh.creation.box(BOX)])
    world = MujocoGraspWorld(hand, SimulateParams())
    world.set_object(folder / "box.obj")
    pose = np.eye(4)
    pose[2, 3] = 0.01 + BOX[2] / 2  # palm top at z = 1 cm
    return hand, world, pose, folder, _closed(hand, world, pose)


def _opened(hand) -> np.ndarray:
    """Fingers splayed outward, the base turned by 60° so that +x (the first direction) points
    between two fingers: nothing stops the box."""
    q = hand.zero()[0].numpy().copy()
    for f in range(3):
        q[hand.joint_names.index(f"f{f}_j0")] = 0.4
    q[5] = np.pi / 3
    return q


def _assert_same(first: dict, second: dict) -> None:
    assert set(first) == set(second) == set(KEYS)
    for key in KEYS:
        np.testing.assert_array_equal(np.asarray(first[key]), np.asarray(second[key]), key)


# ------------------------------------------------------------------------------------ scene


@pytest.mark.parametrize("name", ["gripper", "allegro", "shadow"])
def test_kinematics_check_passes_and_every_joint_has_an_actuator(name, tmp_path):
    """URDF (gripper, Allegro) and MJCF (ShadowHand, a subtree of a larger scene): the world
    builds without an object; its frames are the kinematic model's at a moved base."""
    hand = load_hand(_gripper(tmp_path) if name == "gripper" else name)
    world = MujocoGraspWorld(hand, SimulateParams())
    m = world.model
    assert m.nu == len(hand.hand_joint_names) and m.ntendon == 0 and m.neq == 0
    assert [m.actuator(i).name for i in range(m.nu)] == [
        f"dexflow_{n}" for n in hand.hand_joint_names
    ]
    world.close()


def test_kinematics_check_catches_a_frame_mismatch(tmp_path, monkeypatch):
    hand = load_hand(_gripper(tmp_path))
    shifted = hand.link_transforms

    def link_transforms(q, names):
        out = shifted(q, names).clone()
        out[..., 0, 3] += 5e-4  # half a millimetre along x
        return out

    monkeypatch.setattr(hand, "link_transforms", link_transforms)
    with pytest.raises(HandConfigError, match=r"differ from the kinematic model by 0\.50 mm"):
        MujocoGraspWorld(hand, SimulateParams())


def test_scene_follows_the_protocol_settings(scene, tmp_path):
    """Options, actuators, friction, contact softness and object mass of DexGraspBench, and a
    URDF link without <inertial> weighs the documented default."""
    hand, world, _, _, _ = scene
    m, mp = world.model, world.params.mujoco
    assert m.opt.timestep == mp.timestep_s and m.opt.impratio == mp.impratio
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.noslip_iterations == 2
    assert np.all(m.opt.gravity == 0.0)
    assert not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_NATIVECCD)
    assert m.body_mass[world._object] == pytest.approx(mp.object_mass_kg, rel=1e-6)
    mount = m.body("dexflow_mount").id
    assert m.body_mocapid[mount] == 0 and m.body_parentid[m.body(hand_name("base")).id] == mount
    np.testing.assert_allclose(m.actuator_gainprm[:, 0], mp.kp)
    np.testing.assert_allclose(m.actuator_biasprm[:, :3], [[0.0, -mp.kp, 0.0]] * m.nu)
    np.testing.assert_allclose(
        m.actuator_ctrlrange, np.stack([hand.lower.numpy(), hand.upper.numpy()], 1)[6:]
    )
    np.testing.assert_allclose(m.dof_damping[world._dofs], mp.joint_damping)
    colliding = (m.geom_contype | m.geom_conaffinity) > 0
    assert np.all(m.geom_condim[colliding] == 4)
    np.testing.assert_allclose(m.geom_friction[colliding, :2], [mp.friction] * colliding.sum())
    on_hand = colliding & world._hand_body[m.geom_bodyid]
    np.testing.assert_allclose(m.geom_solref[on_hand], [[0.005, 1.0]] * on_hand.sum())
    np.testing.assert_allclose(m.geom_solimp[on_hand, :3], [[0.5, 0.99, 1e-4]] * on_hand.sum())
    assert np.all(m.geom_margin == 0.0)
    # links without <inertial>: the base and the fingertip frames
    yaml = _gripper(tmp_path)
    urdf = tmp_path / "gripper3.urdf"
    urdf.write_text(
        re.sub(r'(<link name="(base|f\d_tip)">)<inertial>.*?</inertial>', r"\1", urdf.read_text())
    )
    params = SimulateParams(massless_link_mass_kg=0.003, massless_link_inertia_kgm2=2e-7)
    light = MujocoGraspWorld(load_hand(yaml), params).model
    for link in ("base", "f0_tip", "f1_tip", "f2_tip"):
        assert light.body(hand_name(link)).mass[0] == pytest.approx(0.003)
        np.testing.assert_allclose(light.body(hand_name(link)).inertia, (2e-7,) * 3)
    assert light.body(hand_name("f0_prox")).mass[0] == pytest.approx(0.02)  # its own inertial stays


def test_damped_step_moves_the_points_and_takes_several_targets_at_once():
    """Both engines' push step: J dq reaches the wanted moves (up to the damping), with the
    least joint motion, and a stack of targets gives the steps of each target alone."""
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(6, 9))
    moves = rng.normal(size=(6, 2)) * 0.01
    steps = damped_step(jac, moves)
    np.testing.assert_allclose(jac @ steps, moves, atol=1e-5)
    least_norm = np.linalg.pinv(jac) @ moves
    np.testing.assert_allclose(steps, least_norm, atol=1e-5)  # damping: 1e-4 of the step
    assert np.linalg.norm(steps) <= np.linalg.norm(least_norm)
    for k in range(2):
        np.testing.assert_allclose(damped_step(jac, moves[:, k]), steps[:, k], rtol=1e-12)


# --------------------------------------------------------------------------------- protocol


def test_wrapped_hand_holds_the_box_in_all_six_directions(scene):
    _, world, pose, _, closed = scene
    result = world.test_frame(closed, pose)
    assert result["tested"].all() and result["held"].all()
    assert result["contact"] and result["bench"]
    assert result["pushed_links"] >= 3  # three fingers (and the palm) touch the box
    assert result["touching"].tolist() == [True, True, True]
    assert result["parts_penetration_m"] < 1e-3
    assert np.all(result["displacement_m"] < 0.01) and np.all(result["rotation_deg"] < 15)
    assert isinstance(result["pushed_links"], int) and isinstance(result["bench"], bool)
    # the three fingers press from three sides: their pushes (and the palm's) nearly cancel,
    # and the box hardly moves while they close
    assert result["imbalance"] < 0.4
    assert result["closing_displacement_m"] < 0.003 and result["closing_rotation_deg"] < 5


def test_the_paper_and_dexgraspbench_criteria_are_independent_tests(scene):
    """The paper's criterion (contact kept under the object's weight) and DexGraspBench's (the
    object moves less than the thresholds under the push) test the same closed grasp apart:
    thresholds too tight for any push fail only ``bench``, a weight no grasp can hold fails
    only ``contact``."""
    _, world, pose, folder, closed = scene
    results = {}
    for name, change in {
        "tight": {"max_displacement_m": 1e-5},
        "heavy": {"gravity": 2000.0},
    }.items():
        other = MujocoGraspWorld(world.hand, dataclasses.replace(SimulateParams(), **change))
        other.set_object(folder / "box.obj")
        results[name] = other.test_frame(closed, pose)
    assert results["tight"]["contact"] and not results["tight"]["bench"]
    assert (
        results["tight"]["held"].all()
        and results["tight"]["tested"].tolist() == [True] + [False] * 5
    )
    assert results["heavy"]["bench"] and not results["heavy"]["contact"]
    assert not results["heavy"]["held"][0] and not results["heavy"]["held"][1:].any()


def test_a_restored_state_steps_exactly_as_the_saved_one(scene):
    """Every direction starts from the one closed grasp: MuJoCo's integration state saved and
    restored steps bit for bit as the original does."""
    _, world, pose, _, closed = scene
    m, d = world.model, world.data
    world._reset(closed, pose)
    mujoco.mj_step(m, d, nstep=50)
    saved = world._state()
    mujoco.mj_step(m, d, nstep=200)
    first = d.qpos.copy()
    world._reset(closed, pose)  # something else in between
    mujoco.mj_step(m, d, nstep=7)
    world._restore(saved)
    mujoco.mj_step(m, d, nstep=200)
    np.testing.assert_array_equal(d.qpos, first)


def test_imbalance_is_zero_for_opposed_pushes_and_one_for_one_sided_ones():
    assert imbalance([[1, 0, 0], [-2, 0, 0]]) == pytest.approx(0.0)  # lengths do not matter
    angles = np.radians([0, 120, 240])
    assert imbalance(np.stack([np.cos(angles), np.sin(angles), 0 * angles], 1)) < 1e-12
    assert imbalance([[0, 0, 1], [0, 0, 3]]) == pytest.approx(1.0)
    assert imbalance([[1, 0, 0], [0, 1, 0]]) == pytest.approx(np.sqrt(0.5))
    assert np.isnan(imbalance(np.zeros((0, 3))))


def test_contact_imbalance_takes_one_direction_per_finger_in_contact_at_each_frame():
    """Frame 3: the thumb (three points, outward normals +x) against the index (one point, -x):
    opposed, 0 whatever the point counts; frame 5: thumb and index on the same face, 1; frame 4
    has no contact: NaN; the mapped normals are outward, the pushes inward."""
    contact_map = {
        "map_frame": np.array([3, 3, 3, 3, 5, 5]),
        "map_finger": np.array([0, 0, 0, 1, 0, 1]),
        "map_object_normal": np.array(
            [[1, 0, 0], [1, 0.1, 0], [1, -0.1, 0], [-1, 0, 0], [0, 0, 1], [0, 0, 1]], dtype=float
        ),
    }
    out = contact_imbalance(contact_map, np.array([3, 4, 5]))
    assert out[0] == pytest.approx(0.0, abs=1e-12) and np.isnan(out[1])
    assert out[2] == pytest.approx(1.0)
    one_sided = dict(contact_map, map_finger=np.array([0, 0, 0, 0, 0, 1]))  # all four: thumb
    assert contact_imbalance(one_sided, np.array([3]))[0] == pytest.approx(1.0)


def test_one_sided_push_shoves_the_box_while_the_fingers_close(scene):
    """One finger presses the box from the side and the others are open: nothing opposes the
    squeeze, so the box is moved before any push, and the pushes are one-sided."""
    hand, world, pose, _, closed = scene
    q = closed.copy()
    for f in (1, 2):
        q[hand.joint_names.index(f"f{f}_j0")] = 1.2  # turned well away from the box
    result = world.test_frame(q, pose)
    wrapped = world.test_frame(closed, pose)
    assert result["touching"].tolist() == [True, False, False]
    assert result["imbalance"] > 0.5 > wrapped["imbalance"]  # the finger and the palm below
    assert result["closing_displacement_m"] > 0.005 > 0.001 > wrapped["closing_displacement_m"]
    assert not result["bench"]


def test_targets_close_along_the_grasp(scene):
    """The squeeze turns every finger further into the box, the pregrasp backs it off."""
    hand, world, pose, _, closed = scene
    configs, _, pushed = world.targets(closed, pose)
    assert {"f0_prox", "f1_prox", "f2_prox"} <= set(pushed)
    np.testing.assert_array_equal(configs["grasp"], closed)
    for f in range(3):
        j0 = hand.joint_names.index(f"f{f}_j0")
        assert configs["squeeze"][j0] < closed[j0] - 0.02 < configs["pregrasp"][j0] - 0.04
    for key in ("squeeze", "pregrasp"):
        np.testing.assert_array_equal(configs[key][:6], closed[:6])


def test_opened_hand_drops_the_box_and_the_test_stops(scene):
    """The first direction fails: the frame fails there, the other five stay untested."""
    hand, world, pose, _, _ = scene
    result = world.test_frame(_opened(hand), pose)
    assert not result["contact"] and not result["bench"] and not result["held"].any()
    assert result["displacement_m"][0] > 0.05
    assert result["tested"].tolist() == [True] + [False] * 5
    assert (
        np.isnan(result["displacement_m"][1:]).all() and np.isnan(result["rotation_deg"][1:]).all()
    )


def test_object_away_from_the_hand_is_not_touched(scene):
    _, world, pose, _, closed = scene
    away = pose.copy()
    away[0, 3] += 0.2
    result = world.test_frame(closed, away)
    assert result["pushed_links"] == 0 and result["parts_penetration_m"] == 0.0
    assert not result["touching"].any()
    assert not result["contact"] and not result["bench"] and not result["held"].any()
    assert np.isinf(world.gap(closed, away))


def test_results_are_identical_across_runs_and_worlds(scene):
    hand, world, pose, folder, closed = scene
    first = world.test_frame(closed, pose)
    world.test_frame(_opened(hand), pose)  # history must not matter
    again = world.test_frame(closed, pose)
    other = MujocoGraspWorld(hand, SimulateParams())
    other.set_object(folder / "box.obj")
    _assert_same(first, again)
    _assert_same(first, other.test_frame(closed, pose))


# ---------------------------------------------------------------------------- perturbations


def test_perturbations_are_seeded_per_frame_and_within_bounds():
    params = PerturbationParams(count=50, position_m=0.002, rotation_deg=3.0, friction_rel=0.2)
    assert perturbations(dataclasses.replace(params, count=0), 7) == []
    trials = perturbations(params, 7)
    assert len(trials) == 50 and trials == perturbations(params, 7)
    assert trials != perturbations(params, 8)
    assert trials != perturbations(dataclasses.replace(params, seed=1), 7)
    offsets = np.array([t.offset_m for t in trials])
    angles = np.degrees([np.linalg.norm(t.rotvec_rad) for t in trials])
    scales = np.array([t.friction_scale for t in trials])
    assert np.linalg.norm(offsets, axis=1).max() <= 0.002 and angles.max() <= 3.0
    assert np.all((scales >= 0.8) & (scales <= 1.2))
    assert np.abs(offsets).max() > 1e-3 and angles.max() > 1.5 and np.ptp(scales) > 0.2
    assert np.all(np.abs(offsets.mean(axis=0)) < 1e-3)  # no preferred direction


def test_perturbation_moves_the_object_in_the_world_and_turns_it_about_its_origin():
    pose = np.eye(4)
    pose[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # 90° about z
    pose[:3, 3] = [0.1, 0.2, 0.3]
    moved = Perturbation([0.01, 0.0, 0.0], [np.pi / 2, 0.0, 0.0], 1.0).object_pose(pose)
    np.testing.assert_allclose(moved[:3, 3], [0.11, 0.2, 0.3])
    np.testing.assert_allclose(moved[:3, 0], pose[:3, 0], atol=1e-12)  # the object's own x
    np.testing.assert_allclose(moved[:3, 1], pose[:3, 2], atol=1e-12)
    np.testing.assert_array_equal(Perturbation.none().object_pose(pose), pose)


def test_zero_perturbation_is_the_nominal_test(scene):
    _, world, pose, _, closed = scene
    _assert_same(
        world.test_frame(closed, pose), world.test_frame(closed, pose, Perturbation.none())
    )


def test_object_moved_out_of_the_grasp_or_slippery_fails(scene):
    """3 cm sideways the box is no longer between the fingers; at a hundredth of the friction
    the fingers cannot hold it. Both frames hold nominally (test above)."""
    _, world, pose, _, closed = scene
    sideways = world.test_frame(closed, pose, Perturbation([0.0, 0.03, 0.0], np.zeros(3), 1.0))
    assert not sideways["bench"] and not sideways["contact"]
    slippery = world.test_frame(closed, pose, Perturbation(np.zeros(3), np.zeros(3), 0.01))
    assert not slippery["bench"] and slippery["pushed_links"] >= 3


def test_test_frame_needs_an_object(tmp_path):
    world = MujocoGraspWorld(load_hand(_gripper(tmp_path)), SimulateParams())
    with pytest.raises(RuntimeError, match="set_object first"):
        world.test_frame(np.zeros(12), np.eye(4))


def test_mujoco_warnings_go_to_the_log_not_to_a_file_in_the_working_directory(
    tmp_path, monkeypatch, caplog
):
    """An unstable step makes MuJoCo warn; dexflow logs it and writes no MUJOCO_LOG.TXT where
    it runs (MuJoCo's own handler would), and the model's warning counter still counts it."""
    monkeypatch.chdir(tmp_path)
    model = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><freejoint/><geom size='0.1'/></body></worldbody></mujoco>"
    )
    data = mujoco.MjData(model)
    data.qvel[:] = np.inf
    with caplog.at_level("WARNING", logger="dexflow.sim.mujoco_world"):
        mujoco.mj_step(model, data)
    assert list(tmp_path.iterdir()) == []
    assert "MuJoCo: Nan, Inf or huge value in QVEL" in caplog.text
    assert data.warning[mujoco.mjtWarning.mjWARN_BADQVEL].number == 1
