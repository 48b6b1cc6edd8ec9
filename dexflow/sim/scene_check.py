"""Every physics scene the pipeline builds for a hand, built and stepped before any stage runs.

``dexflow hand check`` calls :func:`check_scenes`, so that a hand the engines cannot load or
cannot step fails there, once, with the link or joint named and the fix, instead of in stage
simulate or replay after the kinematic stages ran. The scenes are the ones the stages build,
with the same parameters:

- **grasp test, MuJoCo** (:class:`dexflow.sim.mujoco_world.MujocoGraspWorld`) and, when
  ``simulate.engines`` selects it, **grasp test, pybullet**
  (:class:`dexflow.sim.pybullet_world.PybulletGraspWorld` on
  :func:`dexflow.sim.pybullet_world.hand_urdf`): the six-direction test of one frame;
- **replay** (:class:`dexflow.sim.replay_world.ReplayWorld`): a short trajectory played with the object
  free under gravity on its table.

The frame: every joint at mid-range, the base at the origin, a 4 cm cube centred between the
fingertips. Then, in each MuJoCo scene, the actuators drive the fingers to random targets
within their limits for :data:`SETTLE_STEPS` steps. A scene fails when building it raises, when
its state stops being finite, or when MuJoCo warns of an unstable simulation (bad
accelerations, positions or velocities: MuJoCo then resets the state by itself, which would
silently corrupt every result); the message names the degree of freedom's joint and link.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import mujoco
import numpy as np
import torch
import trimesh

from dexflow.errors import HandConfigError
from dexflow.hands.physics import mjcf_inertials, physics_urdf
from dexflow.hands.robot import RobotHand
from dexflow.objects.convex import write_convex_obj
from dexflow.params import ReplayParams, SimulateParams
from dexflow.sim.mujoco_world import HAND_PREFIX, MujocoGraspWorld
from dexflow.sim.pybullet_world import PybulletGraspWorld, hand_urdf
from dexflow.sim.replay_world import ReplayWorld

__all__ = ["SETTLE_STEPS", "check_scenes"]

SETTLE_STEPS = 500
_CUBE_M = 0.04
_REPLAY_FRAMES = 10
# What to do about the engines' own errors, by a clue in their message.
_FIXES = {
    "no decoder found for mesh": "fix: MuJoCo reads .obj, .stl and .msh meshes; convert that "
    "mesh (e.g. with trimesh) and name the new file in the model",
    "differ from the kinematic model": "fix: the hand yaml and its model file must describe "
    "the same hand (`dexflow hand init` writes a matching yaml)",
    "are not joints of": "fix: name the model's joints in the hand yaml (`dexflow hand check` "
    "lists them)",
}
_UNSTABLE = {
    mujoco.mjtWarning.mjWARN_BADQACC: "accelerations",
    mujoco.mjtWarning.mjWARN_BADQVEL: "velocities",
    mujoco.mjtWarning.mjWARN_BADQPOS: "positions",
}


def _frame(hand: RobotHand) -> tuple[np.ndarray, np.ndarray]:
    """The tested configuration (dof,) and the cube's pose (4, 4) between the fingertips."""
    q = ((hand.lower + hand.upper) / 2)[None].clone()
    q[:, :6] = 0.0
    q = hand.clamp(hand.apply_couplings(q))
    with torch.no_grad():
        tips = hand.keypoints(q)[0].numpy()[hand.fingertip_keypoints]
    pose = np.eye(4)
    pose[:3, 3] = tips.mean(axis=0)
    return q[0].numpy(), pose


def _unstable(hand: RobotHand, model: mujoco.MjModel, data: mujoco.MjData) -> str:
    """What MuJoCo warned of (''), naming the joint and link of the degree of freedom."""
    for warning, what in _UNSTABLE.items():
        if data.warning[warning].number:
            dof = int(data.warning[warning].lastinfo)
            joint = body = "?"
            if 0 <= dof < model.nv:
                joint = model.joint(int(model.dof_jntid[dof])).name.removeprefix(HAND_PREFIX)
                body = model.body(int(model.dof_bodyid[dof])).name.removeprefix(HAND_PREFIX)
            return (
                f"MuJoCo found unstable {what} at joint '{joint}' (link '{body}'): give that link "
                "a realistic mass and inertia in the model, or raise its joint damping"
            )
    if not np.isfinite(data.qpos).all() or not np.isfinite(data.qvel).all():
        return "the state became NaN or infinite"
    return ""


def _settle(hand: RobotHand, world: MujocoGraspWorld, q: np.ndarray, pose: np.ndarray) -> str:
    """Drive the fingers to random targets within their limits; what went wrong ('')."""
    world._reset(q, pose)
    m, d = world.model, world.data
    rng = np.random.default_rng(0)
    lo, hi = hand.lower.numpy()[6:], hand.upper.numpy()[6:]
    d.ctrl[: len(lo)] = lo + rng.random(len(lo)) * (hi - lo)
    for _ in range(SETTLE_STEPS):
        mujoco.mj_step(m, d)
        problem = _unstable(hand, m, d)
        if problem:
            return problem
    return ""


def check_scenes(
    hand: RobotHand, simulate: SimulateParams | None = None, replay: ReplayParams | None = None
) -> list[str]:
    """Build and step every scene stages simulate and replay build for ``hand``.

    Args:
        hand: The hand.
        simulate: Stage simulate's parameters (defaults if None): its engines, the inertial
            defaults, the MuJoCo protocol.
        replay: Stage replay's parameters (defaults if None).

    Returns:
        One line per repair of the model (:mod:`dexflow.hands.physics`), then one per scene:
        what was built and stepped.

    Raises:
        HandConfigError: A scene cannot be built or stepped; the message names the scene, the
            link or joint, and the fix.
    """
    simulate = SimulateParams() if simulate is None else simulate
    replay = ReplayParams() if replay is None else replay
    q, pose = _frame(hand)
    mass, inertia = simulate.massless_link_mass_kg, simulate.massless_link_inertia_kgm2
    if hand.model.format == "urdf":
        _, repairs = physics_urdf(hand, mass, inertia)
    else:
        _, repairs = mjcf_inertials(hand, mass, inertia)
    lines = [f"model repaired for the engines: {r}" for r in repairs] or [
        "model loaded as it is (no repair needed)"
    ]
    with tempfile.TemporaryDirectory(prefix="dexflow-check-") as folder:
        cube = Path(folder) / "cube_convex.obj"
        write_convex_obj(cube, [trimesh.creation.box(extents=(_CUBE_M,) * 3)])

        def fail(scene: str, problem: str) -> HandConfigError:
            fixes = [fix for clue, fix in _FIXES.items() if clue in problem]
            problem = "; ".join([" ".join(problem.split()), *fixes])
            return HandConfigError(f"hand '{hand.spec.name}': scene '{scene}': {problem}")

        def build(scene: str, make):
            try:
                world = make()
                world.set_object(cube)
                return world
            except HandConfigError as exc:
                raise fail(scene, str(exc)) from exc
            except Exception as exc:  # the engine's own error: the model is what it refused
                raise fail(scene, f"{type(exc).__name__}: {exc}") from exc

        grasp = build("grasp test (MuJoCo)", lambda: MujocoGraspWorld(hand, simulate))
        result = grasp.test_frame(q, pose)
        problem = _unstable(hand, grasp.model, grasp.data) or _settle(hand, grasp, q, pose)
        if problem:
            raise fail("grasp test (MuJoCo)", problem)
        lines.append(
            f"grasp test (MuJoCo): built, one frame tested ({int(result['tested'].sum())} "
            f"directions) and {SETTLE_STEPS} steps to random targets, stable"
        )

        world = build("replay", lambda: ReplayWorld(hand, replay))
        frames = np.repeat(q[None], _REPLAY_FRAMES, axis=0)
        poses = np.repeat(pose[None], _REPLAY_FRAMES, axis=0)
        rows = world.replay(frames, poses, 30.0, (0, 0, _REPLAY_FRAMES - 1))
        problem = _unstable(hand, world.model, world.data)
        if not problem and not np.isfinite(rows["position_error_m"]).all():
            problem = "the object's replayed position became NaN or infinite"
        if problem:
            raise fail("replay", problem)
        lines.append(f"replay (MuJoCo): built, {_REPLAY_FRAMES} frames played, stable")

        if "pybullet" in simulate.engines:
            urdf = hand_urdf(hand, simulate)
            bullet = build(
                "grasp test (pybullet)", lambda: PybulletGraspWorld(hand, urdf, simulate)
            )
            try:
                found = bullet.test_frame(q, pose)
            finally:
                bullet.close()
            tested = found["tested"]
            if not np.isfinite(found["displacement_m"][tested]).all():
                raise fail("grasp test (pybullet)", "the object's state became NaN")
            lines.append(f"grasp test (pybullet): built from {urdf.name}, one frame tested")
    return lines
