"""Stage replay's MuJoCo scene: a trajectory played back with the object free under gravity.

The scene (:class:`ReplayWorld`) is stage simulate's MuJoCo scene
(:class:`dexflow.sim.mujoco_world.MujocoGraspWorld`: the hand from its URDF or MJCF, position
actuators on every finger joint, the object from its convex parts, elliptic friction cones), with:

- **The base driven along the trajectory, force-limited.** The hand's mount has the six joints of
  dexflow's floating base (slides along world x, y, z, then hinges about x, y', z'': the
  intrinsic x-y-z Euler angles of :func:`dexflow.hands.robot.base_transform`), so ``q[:6]`` are
  its joint positions. Each has a position servo (critically damped at ``base_frequency_hz``,
  gains from the axis's inertia at the start) with the velocity of the trajectory fed forward,
  its total force limited to ``base_force_n`` (slides) or ``base_torque_nm`` (hinges): a hand
  that pushes into something it cannot move stops there instead of passing through.
- **Fingers by position control**: targets ``q(t)[6:]`` (``kp``, ``joint_damping``, torque limit
  ``joint_torque_nm``), or with ``squeeze_m > 0`` pushed that far into the object where a finger
  is in contact (stage contact's final states; the push step of stage simulate's test, at the
  recorded object pose). A position-controlled finger presses only as hard as its target lies
  inside the object, so recorded fingers that merely touch exert next to no grip. Yet on 12 demo
  sequences (Shadow) squeezing 5, 10 or 20 mm did not make grasps hold: the object was lost in
  83-100 % of them for every method and squeeze (92-100 % without), the share of the grasp held
  moved by under 5 points (20 mm: less held), carried went from 0-1 to at most 2 of 12 -- the
  objects are shoved off as the fingers close and left on the table. Default 0.
- **Gravity** (``gravity`` along -z) on the object; the hand's own weight is compensated
  (MuJoCo's ``gravcomp``), as the arm carrying a real hand would.
- **The support**: a static table, a 1 m x 1 m slab whose top is at the lowest point of the
  object's convex parts at its starting pose, centred under it. It touches only the object:
  recorded hands never knew of a table and a kinematic hand under its top would be shoved out.
- **The object** free (a free joint), ``object_mass_kg`` at uniform density, ``friction``.
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.hands.robot import RobotHand
from dexflow.params import MujocoParams, ReplayParams, SimulateParams
from dexflow.sim.mujoco_world import MOUNT, MujocoGraspWorld, add_object, hand_spec
from dexflow.sim.replay_criteria import replay_errors

__all__ = ["ReplayWorld", "replay_world"]

_TABLE = "dexflow_table"
_TABLE_HALF_SIZE_M = (0.5, 0.5, 0.02)
_BASE_AXES = ("x", "y", "z", "rx", "ry", "rz")
_OBJECT_BITS = 3  # the object collides with the hand (bit 1) and the table (bit 2)
_TABLE_BITS = 2


def _pose7(pose: np.ndarray) -> np.ndarray:
    """MuJoCo free-joint position (x, y, z, qw, qx, qy, qz) of a (4, 4) pose."""
    xyzw = Rotation.from_matrix(pose[:3, :3]).as_quat()
    return np.concatenate([pose[:3, 3], xyzw[[3, 0, 1, 2]]])


def _simulate_params(params: ReplayParams, squeeze_reach_m: float | None) -> SimulateParams:
    """The settings of the shared MuJoCo scene (and of its squeeze step) for ``params``."""
    reach = {} if squeeze_reach_m is None else {"contact_margin_m": squeeze_reach_m}
    return SimulateParams(
        **reach,
        mujoco=MujocoParams(
            kp=params.kp,
            joint_damping=params.joint_damping,
            object_mass_kg=params.object_mass_kg,
            friction=tuple(params.friction),
        ),
        push_m=params.squeeze_m,
    )


class ReplayWorld(MujocoGraspWorld):
    """Stage simulate's MuJoCo scene with a driven, force-limited base, gravity and a table.

    Args:
        hand: The kinematic model.
        params: The replay's parameters.
        squeeze_reach_m: :meth:`squeezed` pushes the links this close to the object (None:
            stage simulate's ``contact_margin_m``, the links in contact).

    Raises:
        HandConfigError: The model's joints or frames in MuJoCo disagree with ``hand``.
    """

    engine = "mujoco"

    def __init__(
        self, hand: RobotHand, params: ReplayParams, squeeze_reach_m: float | None = None
    ) -> None:
        self.replay_params = params
        self.squeeze_reach_m = squeeze_reach_m
        super().__init__(hand, _simulate_params(params, squeeze_reach_m))

    # ---------------------------------------------------------------------------- building

    def _scene(self) -> mujoco.MjSpec:
        rp = self.replay_params
        scene = hand_spec(self.hand, self.params)
        scene.option.gravity = [0.0, 0.0, -rp.gravity]
        mount = scene.body(MOUNT)
        mount.mocap = False
        for body in [mount, *mount.find_all(mujoco.mjtObj.mjOBJ_BODY)]:
            body.gravcomp = 1.0
        if rp.joint_torque_nm > 0:
            for actuator in scene.actuators:
                actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
                actuator.forcerange = [-rp.joint_torque_nm, rp.joint_torque_nm]
        for k, axis in enumerate(_BASE_AXES):
            kind = mujoco.mjtJoint.mjJNT_SLIDE if k < 3 else mujoco.mjtJoint.mjJNT_HINGE
            limit = rp.base_force_n if k < 3 else rp.base_torque_nm
            joint = mount.add_joint(
                name=f"dexflow_base_{axis}", type=kind, axis=np.eye(3)[k % 3].tolist()
            )
            joint.actfrclimited = mujoco.mjtLimited.mjLIMITED_TRUE
            joint.actfrcrange = [-limit, limit]
        for role in ("position", "velocity"):  # gains are set per sequence (_drive_gains)
            for axis in _BASE_AXES:
                actuator = scene.add_actuator(
                    name=f"dexflow_base_{axis}_{role}", target=f"dexflow_base_{axis}"
                )
                actuator.trntype = mujoco.mjtTrn.mjTRN_JOINT
                if role == "position":
                    actuator.set_to_position(kp=1.0, kv=0.0)
                else:
                    actuator.set_to_velocity(kv=1.0)
                actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        sliding, torsional = self.params.mujoco.friction
        table = scene.worldbody.add_body(name=_TABLE, mocap=True)  # moved per sequence
        table.add_geom(
            name=_TABLE,
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=list(_TABLE_HALF_SIZE_M),
            contype=_TABLE_BITS,
            conaffinity=_TABLE_BITS,
            condim=4,
            friction=[sliding, torsional, 1e-4],
        )
        return scene

    def _with_object(self, parts: list[np.ndarray]) -> mujoco.MjSpec:
        scene = self._spec.copy()
        add_object(scene, parts, self.params)
        for geom in scene.geoms:
            if geom.name.startswith("dexflow_object_part"):
                geom.conaffinity = _OBJECT_BITS
        return scene

    def _compile(self, spec: mujoco.MjSpec) -> None:
        super()._compile(spec)
        m = self.model
        joints = [m.joint(f"dexflow_base_{a}") for a in _BASE_AXES]
        self._base_qpos = np.array([int(j.qposadr[0]) for j in joints])
        self._base_dofs = np.array([int(j.dofadr[0]) for j in joints])
        hand = len(self.hand.hand_joint_names)
        self._hand_act = np.arange(hand)
        self._base_pos_act = np.arange(hand, hand + 6)
        self._base_vel_act = np.arange(hand + 6, hand + 12)
        self._table = int(m.body_mocapid[m.body(_TABLE).id])
        self._table_pos = np.array([0.0, 0.0, -10.0])
        self._fractions = np.zeros(0)
        # the friction the grasp test scales per trial: the table's too
        self._friction = m.geom_friction[:, 0].copy()

    # ------------------------------------------------------------------------------- state

    def _place_hand(self, q: np.ndarray) -> None:
        d = self.data
        d.qpos[self._base_qpos] = q[:6]
        d.qpos[self._qpos] = q[6:]

    def _reset(self, q: np.ndarray, pose: np.ndarray) -> None:
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        self._place_hand(q)
        d.ctrl[self._hand_act] = q[6:]
        d.ctrl[self._base_pos_act] = q[:6]
        d.ctrl[self._base_vel_act] = 0.0
        d.qpos[self._object_qpos] = _pose7(pose)
        d.mocap_pos[self._table] = self._table_pos
        mujoco.mj_forward(m, d)

    def place_table(self, pose: np.ndarray) -> float:
        """Put the table's top at the lowest point of the object's parts at ``pose`` (4, 4),
        centred under it (from the next reset on); returns the top's height (m).

        The table is a mocap body: MuJoCo's collision detection takes geoms of the world body
        for static, so moving one of those at run time would leave it out of the collisions.
        """
        self._require_object("place_table")
        points = np.concatenate(self._parts) @ pose[:3, :3].T + pose[:3, 3]
        top = float(points[:, 2].min())
        centre = points[:, :2].mean(axis=0)
        self._table_pos = np.array([*centre, top - _TABLE_HALF_SIZE_M[2]])
        self.data.mocap_pos[self._table] = self._table_pos
        return top

    def lowest_heights(self, poses: np.ndarray) -> np.ndarray:
        """World height (z) of the lowest point of the object's parts at each of ``poses``
        (T, 4, 4), (T,) metres: at a resting pose, the top of what it rests on."""
        self._require_object("lowest_heights")
        points = np.concatenate(self._parts)  # (P, 3)
        poses = np.asarray(poses, dtype=float)
        return (points @ poses[:, 2, :3].T).min(axis=0) + poses[:, 2, 3]

    def _drive_gains(self) -> None:
        """Critically damped base servos at ``base_frequency_hz`` for the current state's
        inertia along each base axis."""
        m, d = self.model, self.data
        full = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, full)
        inertia = np.diag(full)[self._base_dofs]
        omega = 2 * np.pi * self.replay_params.base_frequency_hz
        kp, kv = inertia * omega**2, 2.0 * inertia * omega
        m.actuator_gainprm[self._base_pos_act, 0] = kp
        m.actuator_biasprm[self._base_pos_act, 1] = -kp
        m.actuator_gainprm[self._base_vel_act, 0] = kv
        m.actuator_biasprm[self._base_vel_act, 2] = -kv

    # ------------------------------------------------------------------------------ replay

    def squeezed(self, q: np.ndarray, poses: np.ndarray, touching: np.ndarray) -> np.ndarray:
        """Finger targets pushed ``squeeze_m`` into the object at the frames in contact.

        Args:
            q: (T, dof) the trajectory.
            poses: (T, 4, 4) the recorded object poses.
            touching: (T,) frames whose targets are pushed (a finger in contact).

        Returns:
            (T, dof) the targets (``q`` where not touching or ``squeeze_m`` is 0).
        """
        out = np.array(q, dtype=float)
        if self.replay_params.squeeze_m <= 0:
            return out
        for t in np.flatnonzero(touching):
            out[t] = self.targets(q[t], poses[t])[0]["squeeze"]
        return out

    def begin(
        self, q: np.ndarray, poses: np.ndarray, fps: float, window: tuple[int, int, int]
    ) -> None:
        """Reset for a replay of ``window = (start, first_contact, end)``: the time step, the
        table under the object at the first contact, the hand at ``q[start]`` moving at the
        trajectory's base velocity there, the object at rest at ``poses[first_contact]`` and
        the base servos' gains for that state."""
        rp, m, d = self.replay_params, self.model, self.data
        start, first, end = window
        m.opt.timestep = 1.0 / (fps * rp.substeps)
        self.place_table(poses[first])
        self._reset(q[start], poses[first])
        if start < end:
            d.qvel[self._base_dofs] = (q[start + 1, :6] - q[start, :6]) * fps
        self._drive_gains()
        mujoco.mj_forward(m, d)

    def advance(self, a: np.ndarray, b: np.ndarray, fps: float) -> None:
        """One recorded frame: ``substeps`` physics steps with the targets moving linearly from
        ``a`` to ``b`` (dof,), the base's velocity ``(b - a) * fps`` fed forward."""
        rp, m, d = self.replay_params, self.model, self.data
        fractions = self._fractions
        if len(fractions) != rp.substeps:
            fractions = self._fractions = np.arange(1, rp.substeps + 1) / rp.substeps
        path = a + fractions[:, None] * (b - a)
        d.ctrl[self._base_vel_act] = (b[:6] - a[:6]) * fps
        for k in range(rp.substeps):
            d.ctrl[self._hand_act] = path[k, 6:]
            d.ctrl[self._base_pos_act] = path[k, :6]
            mujoco.mj_step(m, d)

    def rest_drift(self, pose: np.ndarray, fps: float, frames: int) -> tuple[float, float]:
        """How far the object moves and turns (m, rad) left alone for ``frames`` recorded
        frames at ``pose`` (4, 4) on its table, the hand 10 m above it.

        A recorded resting pose the replay's table cannot hold (the object rests on an edge, so
        the annotation or the table's frame is tilted, or its rotations are misread) topples or
        rocks here on its own.
        """
        self._require_object("rest_drift")
        m, d = self.model, self.data
        m.opt.timestep = 1.0 / (fps * self.replay_params.substeps)
        self.place_table(pose)
        away = self.hand.zero()[0].cpu().numpy().astype(np.float64)
        away[:3] = pose[:3, 3] + [0.0, 0.0, 10.0]
        self._reset(away, pose)
        for _ in range(frames * self.replay_params.substeps):
            mujoco.mj_step(m, d)
        now = self.object_pose7()
        position, rotation = replay_errors(now[None, :3], now[None, 3:], pose[None])
        return float(position[0]), float(rotation[0])

    def hand_state(self) -> np.ndarray:
        """(dof,) the hand's configuration now: base joints, then finger joints."""
        d = self.data
        return np.concatenate([d.qpos[self._base_qpos], d.qpos[self._qpos]])

    def object_pose7(self) -> np.ndarray:
        """(7,) the object's position and orientation (w, x, y, z) now."""
        return self.data.qpos[self._object_qpos].copy()

    def replay(
        self,
        q: np.ndarray,
        poses: np.ndarray,
        fps: float,
        window: tuple[int, int, int],
        targets: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Play frames ``start..end`` of the trajectory with the object free.

        Args:
            q: (T, dof) the trajectory (base then joints).
            poses: (T, 4, 4) the recorded object poses.
            fps: Frames per second of the sequence.
            window: ``(start, first_contact, end)`` frame indices, ``start <= first_contact
                <= end`` (:func:`replay_window`); the object starts at its pose at
                ``first_contact``.
            targets: (T, dof) the finger targets (``q`` if None, e.g. :meth:`squeezed`).

        Returns:
            The rows of :class:`~dexflow.io.artifacts.ReplayResult` (errors against ``poses``)
            and ``hand_q`` (N, dof), the simulated hand's states.
        """
        self._require_object("replay")
        start, _, end = window
        q = np.array(q, dtype=float)
        q[:, 3:6] = np.unwrap(q[:, 3:6], axis=0)  # hinge targets without 2 pi jumps
        targets = q if targets is None else np.asarray(targets, dtype=float)
        poses = np.asarray(poses, dtype=float)
        self.begin(q, poses, fps, window)
        frames = np.arange(start, end + 1)
        state = [self.hand_state()]
        objects = [self.object_pose7()]
        for t in frames[:-1]:
            a = np.concatenate([q[t, :6], targets[t, 6:]])
            b = np.concatenate([q[t + 1, :6], targets[t + 1, 6:]])
            self.advance(a, b, fps)
            state.append(self.hand_state())
            objects.append(self.object_pose7())
        hand, pose7 = np.array(state), np.array(objects)
        position, quat, base, joints = pose7[:, :3], pose7[:, 3:], hand[:, :6], hand[:, 6:]
        position_error, rotation_error = replay_errors(position, quat, poses[frames])
        return {
            "frame": frames,
            "position_error_m": position_error,
            "rotation_error_rad": rotation_error,
            "object_position": position,
            "object_quat": quat,
            "base_error_m": np.linalg.norm(base[:, :3] - q[frames, :3], axis=1),
            "joint_error_rad": np.abs(joints - q[frames, 6:]).mean(axis=1),
            "hand_q": hand,
        }


_WORLDS: dict[int, ReplayWorld] = {}


def replay_world(
    hand: RobotHand, params: ReplayParams, squeeze_reach_m: float | None = None
) -> ReplayWorld:
    """One world per process and hand (loading and checking the model once)."""
    world = _WORLDS.get(id(hand))
    if world is None or world.replay_params != params or world.squeeze_reach_m != squeeze_reach_m:
        world = ReplayWorld(hand, params, squeeze_reach_m)
        _WORLDS[id(hand)] = world
    return world
