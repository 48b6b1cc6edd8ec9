"""Stage simulate (paper §IV-B): does a frame's grasp hold the object in a physics engine?

Engines (``simulate.engines``, conf group ``simulate=default|pybullet|both``): MuJoCo
(:class:`dexflow.mujoco_world.MujocoGraspWorld`, the default), which runs both the paper's
gravity test and DexGraspBench's published push test (so that ``ssr_bench`` compares with
BODex and DexGraspBench), and pybullet with the paper's protocol below (:class:`GraspWorld`).
The paper's criterion (``contact``) means the same in both engines: the object's weight along
each of the six axis directions for ``control_steps * control_dt_s`` seconds, held if it still
touches the hand at the end. Every engine tests the same frames. With one engine its result is
the stage's SSR; with two, the headline SSR is the conservative one: a frame counts only if it
is held in **every** engine (``success_contact`` of a sequence, ``ssr`` of the stage; each
engine's own is kept under ``engines`` and ``ssr_<engine>``), and the summary counts the frames
on which the engines agree by the paper's criterion (``agree_hold``: both hold, ``agree_drop``:
both drop) or not (``disagree``): two independent implementations of one protocol, whose
agreement is the check that neither number is an artefact of one engine.

Robust success (``simulate.perturbations``): each frame is tested nominally and in ``count``
perturbed trials (object moved by up to ``position_m`` and turned by up to ``rotation_deg``,
friction scaled within ``1 ± friction_rel``; the same trials in every engine, seeded by the
frame); a criterion holds for the frame only if it holds in every trial, so that a grasp that
holds only on float noise (or on a lucky millimetre) is not counted. The nominal results are
kept (``*_single``) and the share of frames whose nominal success the perturbations overturn is
reported (``flipped``). With two engines a sequence's evaluation stops only once both engines
have succeeded, so the per-frame statistics (frames evaluated, ``flipped``, penetration) of an
engine depend on the engine set; the SSRs do not.

pybullet, headless (DIRECT). The hand is loaded from its URDF (MJCF hands are exported to URDF
by :func:`dexflow.hands.export.export_urdf`), its floating base held at the frame's pose by a
fixed constraint and its joints under position control. The URDF is repaired as MuJoCo's scene
is (:func:`hand_urdf`, :mod:`dexflow.hands.physics`): links without ``<inertial>`` (pybullet
would make them 1 kg) are given ``massless_link_mass_kg`` and ``massless_link_inertia_kgm2``,
inertias violating the triangle inequality are balanced, links are listed after their
parents. The object is a
compound of the convex parts that stage scale_align decomposed it into, with ``object_mass_kg``
(uniform density: centre of mass and inertia from the parts) and ``friction`` (also given to
every hand link).

Protocol for one frame ``t`` (the paper's, after DexGraspNet):

1. Hand at ``q_t``, object at its pose ``T_t``, everything at rest. The **starting penetration**
   is the depth of the deepest point of the hand's collision geometry (every shape, forearm
   and palm included: :func:`dexflow.hands.robot.measurement_hand`) inside the object's mesh
   (:func:`dexflow.measures.penetration_depth` on the signed distance grid of stage
   scale_align: the same definition as metrics' PD). The convex parts the physics uses bulge
   beyond a scanned mesh by millimetres, so their overlap with the hand (``parts_penetration_m``,
   reported as a diagnostic) would reject flush grasps on a scan.
2. Every link closer to the object than ``contact_margin_m`` is **pushed** along the contact
   normal into the object by its gap plus ``push_m``: the joint change comes from one damped
   least-squares step on the stacked Jacobian of the links' contact points (fingers only; tied
   joints follow their leaders; limits hold). That configuration is the position-control target.
3. For each of the six axis directions ``±x, ±y, ±z`` in turn, from the same start: a force
   ``m g d`` (``g = gravity``) acts on the object's centre of mass (the hand is not pulled: a real
   controller compensates its own weight) for ``control_steps`` steps of ``control_dt_s``,
   each ``substeps`` physics steps. With ``early_exit``, a test ends once the object has been
   dropped (farther than ``drop_distance_m`` from the hand and displaced by more than
   ``max_displacement_m``: under a constant force it does not come back), and a frame's remaining
   directions are skipped once both criteria have failed (their entries stay NaN).
4. Per test: **held** if the object touches the hand at the end (closer than 1 mm);
   **displacement** of its centre of mass and **rotation** angle from the start.

Criteria, per frame, both reported:

- ``contact`` (paper): held in all six tests;
- ``bench`` (DexGraspBench): displacement < ``max_displacement_m`` and rotation
  < ``max_rotation_deg`` in all six tests.

A frame counts as a success only when it starts with the hand at most ``penetration_tol_m``
inside the object, both on the object's mesh (the starting penetration above, the definition of
PD) and in the geometry the engines simulate (the convex parts: the deepest overlap any engine
finds, ``-gap``): a link wedged inside the object "holds" it without a real grasp, and the
physics wedges against the parts, which bulge beyond a scanned mesh by millimetres (measured on
83 DexYCB captures with ShadowHand: refine's tested frames start 0.97 mm into the mesh on
average but 3.4 mm into the parts; the rule on the mesh alone counted 60 % of sequences, at
most 17-25 % of which hold from a frame that is not wedged in the physics). Frames over either
tolerance cannot count, and their deep overlap makes every physics step dearer (measured on the
demo: 30 µs per MuJoCo step for a frame within the tolerance, 200-600 µs for a palm 7 mm
inside), so by default they are not tested (``skipped``; ``over_tolerance_parts`` counts those
within it on the mesh but not on the parts); their starting penetration is still measured and
reported. With ``test_over_tolerance`` they are tested too and the uncounted result is kept
(``*_raw``, ``ssr_raw``) so that reports can show what the tolerance removes; otherwise those
are null. The counted SSRs are the same either way: a frame's result does not depend on the
frames tested before it (below). A sequence succeeds (per criterion) if any evaluated frame at
or after its first contact (stage contact) succeeds; frames are taken every ``stride`` frames
and, with ``early_stop``, evaluation stops at the first frame that passes every test. SSR = the
percentage of sequences that succeed.

Deterministic: every test starts from a freshly built world state with the same calls, so a
frame's result does not depend on the frames tested before it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from dexflow.errors import HandConfigError
from dexflow.grasp_protocol import (
    DIRECTIONS,
    TOUCH_M,
    Perturbation,
    contact_imbalance,
    damped_step,
    imbalance,
    lost_while_closing,
    perturbations,
    pushed_configuration,
)
from dexflow.hands.robot import RobotHand, base_transform, measurement_hand
from dexflow.io.artifacts import (
    ENGINE_KEYS,
    SIMULATION_KEYS,
    ObjectAssets,
    SimulationResult,
    write_simulation,
)
from dexflow.io.layout import Layout
from dexflow.labelled_stage import labelled_hand, labelled_output, load_labelled
from dexflow.measures import hand_object_depths
from dexflow.mujoco_world import MujocoGraspWorld
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import PipelineParams, SimulateParams
from dexflow.runner import StageSpec

__all__ = [
    "DIRECTIONS",
    "STAGE",
    "GraspWorld",
    "object_parts",
    "run_simulate",
    "simulate_sequence",
]

_DROP_CHECK_EVERY = 10  # control steps between checks for a dropped object
_FK_CHECK_TOL_M = 1e-4  # pybullet's link frames must match the kinematic model's

logger = logging.getLogger(__name__)


def object_parts(path: str | Path) -> list[np.ndarray]:
    """Vertices (V, 3) of every convex part of a ``convex.obj`` (one ``o`` group per part, as
    pybullet reads it: a compound of convex shapes)."""
    from dexflow.objects.convex import read_convex_obj

    return read_convex_obj(path)


def _mass_frame(parts: list[np.ndarray], mass: float) -> tuple[np.ndarray, np.ndarray]:
    """Principal frame (4, 4) in the object frame and principal moments (3,) of the union of
    the convex parts at uniform density."""
    hulls = [trimesh.convex.convex_hull(v) for v in parts]
    volume = sum(h.volume for h in hulls)
    com = sum(h.volume * h.center_mass for h in hulls) / volume
    inertia = np.zeros((3, 3))
    for h in hulls:  # parallel-axis theorem to the common centre of mass, density 1
        r = h.center_mass - com
        inertia += h.moment_inertia + h.volume * (r @ r * np.eye(3) - np.outer(r, r))
    moments, axes = np.linalg.eigh(inertia * mass / volume)
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    frame = np.eye(4)
    frame[:3, :3], frame[:3, 3] = axes, com
    return frame, np.maximum(moments, 1e-9)


def _pose7(transform: np.ndarray) -> tuple[list[float], list[float]]:
    """pybullet pose of a (4, 4) transform: position and quaternion (x, y, z, w)."""
    return transform[:3, 3].tolist(), Rotation.from_matrix(transform[:3, :3]).as_quat().tolist()


def _matrix(position, quaternion) -> np.ndarray:
    """(4, 4) transform of a pybullet pose: position and quaternion (x, y, z, w).

    Not ``RigidTransform.from_components``: its rotation block differs from
    ``Rotation.as_matrix`` by about 1e-16, and these matrices feed back into the physics.
    """
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    out[:3, 3] = position
    return out


class GraspWorld:
    """One pybullet world (its own DIRECT client) holding a hand and, per sequence, an object.

    Args:
        hand: The kinematic model (joint names, limits, couplings, forward kinematics).
        urdf: The hand's URDF (the model file itself, or its export for MJCF hands).
        params: The protocol's parameters.
    """

    engine = "pybullet"

    def __init__(self, hand: RobotHand, urdf: str | Path, params: SimulateParams) -> None:
        import pybullet as pb
        from pybullet_utils.bullet_client import BulletClient

        self.pb, self.hand, self.params, self.urdf = pb, hand, params, str(urdf)
        self._friction = params.friction  # of the trial being run (perturbations scale it)
        self.client = BulletClient(connection_mode=pb.DIRECT)
        self.client.setPhysicsEngineParameter(deterministicOverlappingPairs=1)
        self._object_parts: list[np.ndarray] | None = None
        self._build()
        self._check_kinematics()

    # ------------------------------------------------------------------------------- world

    def _build(self) -> None:
        """(Re)create the world: hand, and the object if one is set."""
        c, p = self.client, self.params
        c.resetSimulation()
        c.setGravity(0, 0, 0)
        c.setTimeStep(p.control_dt_s / p.substeps)
        # the URDF's inertia tensors (pybullet's default recomputes them from collision shapes)
        flags = self.pb.URDF_MAINTAIN_LINK_ORDER | self.pb.URDF_USE_INERTIA_FROM_FILE
        try:
            self.body = c.loadURDF(self.urdf, flags=flags)
        except self.pb.error as exc:
            raise HandConfigError(
                f"hand '{self.hand.spec.name}': pybullet cannot load {self.urdf}: {exc}"
            ) from exc
        joints = {}
        self.link_index = {c.getBodyInfo(self.body)[0].decode(): -1}
        for i in range(c.getNumJoints(self.body)):
            info = c.getJointInfo(self.body, i)
            self.link_index[info[12].decode()] = i
            if info[2] in (self.pb.JOINT_REVOLUTE, self.pb.JOINT_PRISMATIC):
                joints[info[1].decode()] = i
        missing = [n for n in self.hand.hand_joint_names if n not in joints]
        if missing:
            raise HandConfigError(
                f"hand '{self.hand.spec.name}': joints {missing} of the kinematic model are not "
                f"movable joints of {self.urdf}; found {sorted(joints)}"
            )
        self.joint_ids = [joints[n] for n in self.hand.hand_joint_names]
        self.link_names = {i: n for n, i in self.link_index.items()}
        for link in self.link_index.values():
            c.changeDynamics(self.body, link, lateralFriction=self._friction)
        inertial = c.getDynamicsInfo(self.body, -1)
        self._base_inertial = _matrix(inertial[3], inertial[4])
        pos, orn = _pose7(self._base_inertial)
        self.constraint = c.createConstraint(
            self.body, -1, -1, -1, self.pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0], pos, None, orn
        )
        c.changeConstraint(self.constraint, maxForce=p.base_max_force)
        self.object = None
        if self._object_parts is not None:
            self._add_object()

    def _check_kinematics(self) -> None:
        """pybullet's link frames must equal the kinematic model's at a random configuration."""
        rng = np.random.default_rng(0)
        q = self.hand.zero()[0].numpy().copy()
        lo, hi = self.hand.lower.numpy()[6:], self.hand.upper.numpy()[6:]
        q[6:] = lo + rng.random(len(lo)) * (hi - lo)
        q[:6] = [0.1, -0.2, 0.3, 0.4, -0.5, 0.6]
        q = self.hand.clamp(self.hand.apply_couplings(self.hand.as_q(q)))[0].numpy()
        self._set_hand(q)
        names = [n for n in self.link_index if n in set(self.hand.model.frames)]
        ours = self.hand.link_transforms(q, names)[0].numpy()
        error = 0.0
        for name, t in zip(names, ours, strict=True):
            i = self.link_index[name]
            if i == -1:
                pos, orn = self.client.getBasePositionAndOrientation(self.body)
                frame = _matrix(pos, orn) @ np.linalg.inv(self._base_inertial)
            else:
                state = self.client.getLinkState(self.body, i, computeForwardKinematics=True)
                frame = _matrix(state[4], state[5])
            error = max(error, float(np.abs(frame[:3, 3] - t[:3, 3]).max()))
        if error > _FK_CHECK_TOL_M:
            raise HandConfigError(
                f"hand '{self.hand.spec.name}': link frames of {self.urdf} in pybullet differ from "
                f"the kinematic model by {error * 1000:.2f} mm (expected < "
                f"{_FK_CHECK_TOL_M * 1000:g} mm): the URDF and the hand config disagree"
            )

    def set_object(self, convex_obj: str | Path) -> None:
        """Use the object whose convex decomposition is ``convex_obj`` (from scale_align)."""
        self._object_path = Path(convex_obj)
        self._object_parts = object_parts(convex_obj)
        self._frame, self._moments = _mass_frame(self._object_parts, self.params.object_mass_kg)
        self._build()

    def _add_object(self) -> None:
        c, pb = self.client, self.pb
        pos, orn = _pose7(np.linalg.inv(self._frame))  # parts in the principal frame
        shape = c.createCollisionShape(
            pb.GEOM_MESH, fileName=str(self._object_path), collisionFramePosition=pos,
            collisionFrameOrientation=orn,
        )  # fmt: skip
        self.object = c.createMultiBody(
            baseMass=self.params.object_mass_kg, baseCollisionShapeIndex=shape
        )
        c.changeDynamics(
            self.object,
            -1,
            lateralFriction=self._friction,
            localInertiaDiagonal=self._moments.tolist(),
            collisionMargin=0.0,  # pybullet's default 1 mm would inflate the parts
        )

    # ------------------------------------------------------------------------------- state

    def _set_hand(self, q: np.ndarray) -> None:
        c = self.client
        base = base_transform(torch.as_tensor(q[None, :6], dtype=torch.float64))[0].numpy()
        pos, orn = _pose7(base @ self._base_inertial)
        c.resetBasePositionAndOrientation(self.body, pos, orn)
        c.changeConstraint(
            self.constraint, jointChildPivot=pos, jointChildFrameOrientation=orn,
            maxForce=self.params.base_max_force,
        )  # fmt: skip
        for joint, value in zip(self.joint_ids, q[6:], strict=True):
            c.resetJointState(self.body, joint, float(value), 0.0)

    def _set_object(self, pose: np.ndarray) -> np.ndarray:
        """Place the object at ``pose`` (object frame in the world); returns its mass frame."""
        frame = pose @ self._frame
        pos, orn = _pose7(frame)
        self.client.resetBasePositionAndOrientation(self.object, pos, orn)
        self.client.resetBaseVelocity(self.object, [0, 0, 0], [0, 0, 0])
        return frame

    def _closest(self, distance: float) -> list:
        return self.client.getClosestPoints(self.body, self.object, distance)

    def gap(self, q: np.ndarray, pose: np.ndarray, links: list[str] | None = None) -> float:
        """Signed distance (m) between the hand (or only ``links``) and the object placed at
        ``q`` and ``pose``; negative when they overlap, +inf beyond 10 cm."""
        self._set_hand(np.asarray(q, dtype=float))
        self._set_object(pose)
        ids = None if links is None else {self.link_index[n] for n in links}
        distances = [pt[8] for pt in self._closest(0.1) if ids is None or pt[3] in ids]
        return min(distances, default=float("inf"))

    # ---------------------------------------------------------------------------- protocol

    def push_targets(self, q: np.ndarray) -> tuple[np.ndarray, float, list[str]]:
        """Position-control targets with every touching link pushed into the object.

        Returns:
            Target ``q`` (dof,), the deepest overlap (m, >= 0) between a hand link and the
            object's convex parts, the names of the links within ``contact_margin_m``.
        """
        target, penetration, links, _ = self._push_targets(q)
        return target, penetration, links

    def _push_targets(self, q: np.ndarray) -> tuple[np.ndarray, float, list[str], np.ndarray]:
        """:meth:`push_targets`, and the (L, 3) directions in which the L links press."""
        p, hand = self.params, self.hand
        points = self._closest(p.contact_margin_m)
        penetration = max([0.0] + [-pt[8] for pt in points])
        per_link: dict[int, tuple] = {}
        for pt in points:  # the closest pair of every link
            if pt[3] not in per_link or pt[8] < per_link[pt[3]][8]:
                per_link[pt[3]] = pt
        links = [self.link_names[i] for i in sorted(per_link)]
        if not links:
            return q.copy(), penetration, [], np.zeros((0, 3))
        # Jacobian of the contact points by forward differences over the free hand joints
        free = [j for j in hand.free_joints if j >= 6]
        step = 1e-6
        qs = np.repeat(q[None], len(free) + 1, axis=0)
        qs[np.arange(1, len(free) + 1), free] += step
        qs_t = hand.apply_couplings(hand.as_q(qs))
        frames = hand.link_transforms(qs_t, links).numpy()  # (F+1, L, 4, 4)
        world = np.array([per_link[self.link_index[n]][5] for n in links])  # on the hand
        normal = np.array([per_link[self.link_index[n]][7] for n in links])  # object -> hand
        gap = np.array([max(per_link[self.link_index[n]][8], 0.0) for n in links])
        rot0, pos0 = frames[0, :, :3, :3], frames[0, :, :3, 3]
        local = np.einsum("lji,lj->li", rot0, world - pos0)
        moved = np.einsum("flij,lj->fli", frames[..., :3, :3], local) + frames[..., :3, 3]
        jac = ((moved[1:] - moved[0]) / step).reshape(len(free), -1).T  # (3L, F)
        target = (-(gap + p.push_m)[:, None] * normal).reshape(-1)
        pushed = pushed_configuration(hand, q, free, damped_step(jac, target))
        return pushed, penetration, links, -normal

    def test_frame(
        self, q: np.ndarray, pose: np.ndarray, perturbation: Perturbation | None = None
    ) -> dict:
        """Run the six-direction test for one frame.

        Args:
            q: (dof,) hand configuration (base then joints, as stage retarget writes it).
            pose: (4, 4) object pose in the world.
            perturbation: Moves the object and scales the friction for this trial (None: the
                nominal trial).

        Returns:
            ``parts_penetration_m`` (deepest overlap with the convex parts, a diagnostic; the
            penetration rule is :func:`simulate_sequence`'s, on the mesh), ``pushed_links``
            (how many links touch the object and are pushed), ``imbalance``
            (:func:`dexflow.grasp_protocol.imbalance` of their directions into the object),
            ``closing_displacement_m`` and ``closing_rotation_deg`` (NaN: this test holds the
            object still while the fingers close), ``touching (F,)`` (which of the
            hand's fingers, in the hand config's order, have such a link), ``held (6,)``,
            ``displacement_m (6,)``, ``rotation_deg (6,)``, ``tested (6,)`` and the two
            criteria ``contact``, ``bench`` (before the penetration rule).
        """
        if self.object is None:
            raise RuntimeError("GraspWorld.test_frame: set_object first")
        p, c = self.params, self.client
        q = np.asarray(q, dtype=float)
        if perturbation is not None:
            pose = perturbation.object_pose(pose)
        self._friction = p.friction * (1.0 if perturbation is None else perturbation.friction_scale)
        self._build()
        self._set_hand(q)
        self._set_object(pose)
        target, penetration, pushed, directions = self._push_targets(q)
        touching = np.array(
            [bool(set(pushed) & set(fs.links)) for fs in self.hand.spec.fingers.values()]
        )
        held = np.zeros(6, bool)
        displacement = np.full(6, np.nan)
        rotation = np.full(6, np.nan)
        tested = np.zeros(6, bool)
        for k, direction in enumerate(DIRECTIONS):
            failed = not held[:k].all() and not _bench(displacement[:k], rotation[:k], p).all()
            if p.early_exit and k and failed:
                break  # both criteria have failed already
            tested[k] = True
            self._build()
            self._set_hand(q)
            start = self._set_object(pose)
            self._control(target)
            self._settle(start)
            force = (p.object_mass_kg * p.gravity * direction).tolist()
            for step in range(p.control_steps):
                for _ in range(p.substeps):
                    pos = c.getBasePositionAndOrientation(self.object)[0]
                    c.applyExternalForce(self.object, -1, force, pos, self.pb.WORLD_FRAME)
                    c.stepSimulation()
                check = p.early_exit and (step + 1) % _DROP_CHECK_EVERY == 0
                if check and self._dropped(start):
                    break
            pos, orn = c.getBasePositionAndOrientation(self.object)
            end = _matrix(pos, orn)
            displacement[k] = float(np.linalg.norm(end[:3, 3] - start[:3, 3]))
            relative = Rotation.from_matrix(end[:3, :3] @ start[:3, :3].T)
            rotation[k] = float(np.degrees(relative.magnitude()))
            held[k] = bool(self._closest(TOUCH_M))
        result = {
            "parts_penetration_m": penetration,
            "pushed_links": len(pushed),
            "imbalance": imbalance(directions),
            "closing_displacement_m": float("nan"),
            "closing_rotation_deg": float("nan"),
            "touching": touching,
            "held": held,
            "displacement_m": displacement,
            "rotation_deg": rotation,
            "tested": tested,
            "contact": bool(tested.all() and held.all()),
            "bench": bool(tested.all() and _bench(displacement, rotation, p).all()),
        }
        self._friction = p.friction
        return result

    def _control(self, target: np.ndarray) -> None:
        """Put every hand joint under position control towards ``target (dof,)``."""
        p, n = self.params, len(self.joint_ids)
        self.client.setJointMotorControlArray(
            self.body, self.joint_ids, self.pb.POSITION_CONTROL,
            targetPositions=target[6:].tolist(), forces=[p.motor_force] * n,
            positionGains=[p.position_gain] * n, velocityGains=[p.velocity_gain] * n,
        )  # fmt: skip

    def hold(self, q: np.ndarray) -> np.ndarray:
        """Hold the hand at ``q`` with no object, under the protocol's controller.

        The check that the controller is stable for this hand: for each of the six directions
        in turn, from rest at ``q``, ``settle_steps + control_steps`` control steps (a frame's
        whole horizon) with the hand's own weight (``gravity`` along the direction) acting on
        it, stricter than the test itself, where the hand carries no weight.

        Args:
            q: (dof,) configuration, also the target.

        Returns:
            (6, S, J) hand joint angles after every control step of every direction.
        """
        p, c = self.params, self.client
        q = np.asarray(q, dtype=float)
        steps = p.settle_steps + p.control_steps
        out = np.empty((len(DIRECTIONS), steps, len(self.joint_ids)))
        for k, direction in enumerate(DIRECTIONS):
            self._build()
            if self.object is not None:
                c.removeBody(self.object)
                self.object = None
            self._set_hand(q)
            self._control(q)
            c.setGravity(*(p.gravity * direction))
            for step in range(steps):
                for _ in range(p.substeps):
                    c.stepSimulation()
                out[k, step] = [s[0] for s in c.getJointStates(self.body, self.joint_ids)]
        self._build()
        return out

    def _settle(self, start: np.ndarray) -> None:
        """Close the fingers onto the object while it is held at its start pose."""
        if self.params.settle_steps == 0:
            return
        c = self.client
        pos, orn = _pose7(start)
        hold = c.createConstraint(
            self.object, -1, -1, -1, self.pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0], pos, None, orn
        )
        c.changeConstraint(hold, maxForce=self.params.base_max_force)
        for _ in range(self.params.settle_steps * self.params.substeps):
            c.stepSimulation()
        c.removeConstraint(hold)

    def _dropped(self, start: np.ndarray) -> bool:
        pos = np.asarray(self.client.getBasePositionAndOrientation(self.object)[0])
        far = not self._closest(self.params.drop_distance_m)
        return far and np.linalg.norm(pos - start[:3, 3]) > self.params.max_displacement_m

    def close(self) -> None:
        self.client.disconnect()


def _bench(displacement: np.ndarray, rotation: np.ndarray, p: SimulateParams) -> np.ndarray:
    return (displacement < p.max_displacement_m) & (rotation < p.max_rotation_deg)


def hand_urdf(hand: RobotHand, params: SimulateParams | None = None) -> Path:
    """The URDF pybullet loads for ``hand``: :func:`dexflow.hands.physics.physics_urdf` with
    ``params.massless_link_mass_kg`` and ``massless_link_inertia_kgm2`` (defaults if None):
    the model itself where it needs no repair, else a repaired copy (an MJCF hand: its export).
    """
    from dexflow.hands.physics import physics_urdf

    p = SimulateParams() if params is None else params
    return physics_urdf(hand, p.massless_link_mass_kg, p.massless_link_inertia_kgm2)[0]


def simulate_sequence(
    worlds: Mapping[str, GraspWorld | MujocoGraspWorld] | GraspWorld | MujocoGraspWorld,
    q: np.ndarray,
    poses: np.ndarray,
    first_contact: int,
    sdf: SignedDistanceGrid,
    contact_map: Mapping[str, np.ndarray] | None = None,
) -> tuple[dict[str, np.ndarray], dict]:
    """Evaluate the frames of one trajectory from its first contact on, in every engine.

    Each frame is tested in every engine of ``worlds`` (the same frames in all), nominally and
    under ``simulate.perturbations.count`` perturbed copies (the object moved and turned a
    little, the friction scaled; the same copies in every engine). A trial's criteria are the
    engine's (``test_frame``); a frame's are robust: met in the nominal trial and in every
    perturbed one (``*_single``: the nominal trial alone).

    Args:
        worlds: Per engine name (``pybullet``, ``mujoco``) a world whose object is this
            sequence's; the first engine's result is the sequence's. A single world stands for
            ``{world.engine: world}``.
        q: (T, dof) hand trajectory.
        poses: (T, 4, 4) object poses.
        first_contact: First frame with a finger in contact (-1: none, nothing is evaluated).
        sdf: The object mesh's signed distance grid (stage scale_align's ``sdf.npz``): the
            starting penetration of the penetration rule is measured on it.
        contact_map: Stage contact's map of this trajectory (``ContactResult.contact_map``):
            each evaluated frame's ``contact_imbalance`` comes from it
            (:func:`dexflow.grasp_protocol.contact_imbalance`; NaN without a map).

    Returns:
        Per evaluated frame arrays (``frame``, ``penetration_m`` on the mesh,
        ``contact_imbalance``, and per engine
        ``<engine>.<key>`` for :data:`~dexflow.io.artifacts.ENGINE_KEYS`) and the sequence's
        result: the first engine's successes at the top level, every engine's under
        ``engines``, and with two engines the frames on which they agree (``agree_hold``,
        ``agree_drop``) or not (``disagree``) by the DexGraspBench criterion.
    """
    if not isinstance(worlds, Mapping):
        worlds = {worlds.engine: worlds}
    engines = list(worlds)
    p, hand = worlds[engines[0]].params, worlds[engines[0]].hand
    frames = [] if first_contact < 0 else list(range(first_contact, len(q), p.stride))
    if p.max_frames > 0:
        frames = frames[: p.max_frames]
    q, poses = np.asarray(q, dtype=float), np.asarray(poses, dtype=float)
    depth = np.zeros(len(q))
    if frames:  # in chunks of frames: memory bounded on long captures
        measured = measurement_hand(hand)  # every collision shape, forearm and palm included
        depth[frames] = hand_object_depths(measured, q[frames], poses[frames], sdf)[0]
    balance = np.full(len(frames), np.nan)
    if contact_map is not None:
        balance = contact_imbalance(contact_map, np.array(frames, dtype=int))
    rows: list[dict] = []
    found = {e: dict.fromkeys(("contact", "bench", "contact_raw", "bench_raw")) for e in engines}
    # per criterion, and for the headline ("all": every criterion), held in every engine
    every = dict.fromkeys(k + raw for k in (*_CRITERIA, "all") for raw in ("", "_raw"))
    considered = []  # frames reached before the early stop, tested or not
    wedged = 0  # of them, within the tolerance on the mesh but not on the convex parts
    for t, target in zip(frames, balance, strict=True):
        row: dict = {"frame": t, "penetration_m": float(depth[t])}
        row["contact_imbalance"] = float(target)
        within = row["penetration_m"] <= p.penetration_tol_m
        if within:  # and in the geometry the engines simulate (the convex parts)
            start = max(0.0, -min(w.gap(q[t], poses[t]) for w in worlds.values()))
            within = start <= p.penetration_tol_m
            wedged += not within
        considered.append(t)
        if not (within or p.test_over_tolerance):
            continue  # cannot count; a deep overlap costs the engine the most per step
        trials = perturbations(p.perturbations, t)
        for engine, world in worlds.items():
            nominal = world.test_frame(q[t], poses[t])
            robust = {k: bool(nominal[k]) for k in _CRITERIA}
            for perturbation in trials:
                if not any(robust.values()):
                    break  # every criterion has failed: more trials cannot change the frame
                trial = world.test_frame(q[t], poses[t], perturbation)
                robust = {k: robust[k] and bool(trial[k]) for k in _CRITERIA}
            row |= {f"{engine}.{k}": v for k, v in nominal.items() if k not in _CRITERIA}
            hit = found[engine]
            for key in _CRITERIA:
                row[f"{engine}.{key}_single"] = bool(nominal[key])
                row[f"{engine}.{key}"] = robust[key]
                if robust[key] and hit[f"{key}_raw"] is None:
                    hit[f"{key}_raw"] = t
                if robust[key] and within and hit[key] is None:
                    hit[key] = t
        held = {k: all(row[f"{e}.{k}"] for e in engines) for k in _CRITERIA}
        held["all"] = all(held.values())
        for key, value in held.items():
            if value and every[f"{key}_raw"] is None:
                every[f"{key}_raw"] = t
            if value and within and every[key] is None:
                every[key] = t
        rows.append(row)
        # a headline success is a success of every criterion in every engine: nothing to find
        done = every["all"] is not None
        if p.early_stop and done:
            break
    arrays = _rows_to_arrays(rows, engines, len(hand.spec.fingers))
    pen = depth[considered]
    result = {
        "frames": len(q),
        "first_contact": int(first_contact),
        "evaluated": len(rows),
        "skipped": len(considered) - len(rows),
        "over_tolerance_parts": wedged,
        "penetration_mean_mm": float(pen.mean() * 1000) if len(pen) else 0.0,
        "over_tolerance": float((pen > p.penetration_tol_m).mean()) if len(pen) else 0.0,
        "contact_imbalance_sum": float(np.nansum(arrays["contact_imbalance"])),
        "contact_imbalance_frames": int(np.isfinite(arrays["contact_imbalance"]).sum()),
        "engines": {e: _engine_result(arrays, e, found[e], p) for e in engines},
    }
    result |= result["engines"][engines[0]]
    raw = p.test_over_tolerance  # else the frames over the tolerance were not tested
    for key, name in (
        ("contact", "success_contact"),
        ("bench", "success_bench"),
        ("all", "success"),
    ):
        result[name] = every[key] is not None
        result[f"{name}_raw"] = (every[f"{key}_raw"] is not None) if raw else None
    result["success_frame"] = -1 if every["all"] is None else int(every["all"])
    first = engines[0]  # the two criteria of one engine: independent tests of the same grasp
    a, b = arrays[f"{first}.contact"], arrays[f"{first}.bench"]
    result["criteria_agree_hold"] = int(np.count_nonzero(a & b))
    result["criteria_agree_drop"] = int(np.count_nonzero(~a & ~b))
    result["criteria_disagree"] = int(np.count_nonzero(a != b))
    if len(engines) > 1:  # two engines: their per-frame agreement on the paper's criterion
        a, b = (arrays[f"{e}.contact"] for e in engines[:2])
        result["agree_hold"] = int(np.count_nonzero(a & b))
        result["agree_drop"] = int(np.count_nonzero(~a & ~b))
        result["disagree"] = int(np.count_nonzero(a != b))
    return arrays, result


_CRITERIA = ("contact", "bench")


def _engine_result(arrays: dict, engine: str, hit: dict, p: SimulateParams) -> dict:
    """One engine's result for a sequence (successes, flips, overlap with the convex parts)."""
    parts = arrays[f"{engine}.parts_penetration_m"]
    flipped = np.zeros(len(parts), dtype=bool)
    for key in _CRITERIA:
        flipped |= arrays[f"{engine}.{key}_single"] != arrays[f"{engine}.{key}"]
    raw = p.test_over_tolerance  # else the frames over the tolerance were not tested
    closing = arrays[f"{engine}.closing_displacement_m"]
    lost = lost_while_closing(closing, arrays[f"{engine}.closing_rotation_deg"], p)
    balance = arrays[f"{engine}.imbalance"]
    balance = balance[np.isfinite(balance)]
    return {
        "success_contact": hit["contact"] is not None,
        "success_bench": hit["bench"] is not None,
        "success_contact_raw": (hit["contact_raw"] is not None) if raw else None,
        "success_bench_raw": (hit["bench_raw"] is not None) if raw else None,
        "success_frame": -1 if hit["contact"] is None else int(hit["contact"]),
        "flipped_frames": int(flipped.sum()),
        "parts_penetration_mean_mm": float(parts.mean() * 1000) if len(parts) else 0.0,
        "parts_over_tolerance": float((parts > p.penetration_tol_m).mean()) if len(parts) else 0.0,
        # None: this engine's test holds the object while the fingers close (pybullet)
        "lost_closing_frames": None if np.isnan(closing).any() else int(lost.sum()),
        "imbalance_sum": float(balance.sum()),
        "imbalance_frames": len(balance),
    }


def _rows_to_arrays(rows: list[dict], engines: list[str], fingers: int) -> dict[str, np.ndarray]:
    """Stack the per-frame rows into the arrays of a simulation result (empty ones shaped)."""
    width = {"touching": fingers} | dict.fromkeys(
        ("held", "displacement_m", "rotation_deg", "tested"), 6
    )
    flags = ("contact", "bench", "contact_single", "bench_single")
    arrays = {}
    for key in [*SIMULATION_KEYS, *(f"{e}.{k}" for e in engines for k in ENGINE_KEYS)]:
        base = key.partition(".")[2] or key
        if rows:
            arrays[key] = np.array([r[key] for r in rows])
        else:
            arrays[key] = np.zeros((0, width[base]) if base in width else 0)
        if base in flags:
            arrays[key] = arrays[key].astype(bool)
    return arrays


def run_simulate(params: PipelineParams, layout: Layout, label: str) -> dict:
    """Stage runner: the six-direction test on every trajectory labelled ``label``.

    Args:
        params: Pipeline params (``hand``, ``simulate``, ``run``).
        layout: The project's paths; the trajectories are ``layout.trajectory(label)``.
        label: One of :data:`~dexflow.io.layout.TRAJECTORIES` (baseline, retarget, refine).

    Returns:
        The summary (also written to the stage's ``summary.json``), with the wall-clock speed
        under ``timing`` (returned, not written there).
    """
    out, aligned = layout.simulate(label), layout.scale_align
    stage = labelled_output("simulate", params, layout, label, out)
    files = stage.start()
    sp = params.simulate
    if files:  # a hand the engines cannot load fails the stage once (exit 2), not every sequence
        for engine in sp.engines:
            _world(engine, labelled_hand(params, layout), sp)

    def one(path: Path) -> dict:
        hand, seq, q, found = load_labelled(params, layout, path)
        worlds = {engine: _world(engine, hand, sp) for engine in sp.engines}
        assets = ObjectAssets(aligned.object_of(seq.obj_mesh))
        for world in worlds.values():
            world.set_object(assets.paths.convex)
        start = time.perf_counter()
        rows, result = simulate_sequence(
            worlds, q, seq.obj_pose, found.first_contact, assets.sdf(), found.contact_map
        )
        result["seconds"] = time.perf_counter() - start
        fingers = list(hand.spec.fingers)
        write_simulation(out.sequence(path), SimulationResult(rows, fingers, list(sp.engines)))
        return result

    tally = stage.run(one, files, params.run)
    ok = tally.ok
    seconds = sum(s.pop("seconds") for s in ok)
    evaluated = sum(s["evaluated"] for s in ok)

    summary = {
        **tally.counts("simulate"),
        "method": label,
        "engines": ",".join(sp.engines),
        "perturbations": sp.perturbations.count,
        "frames_evaluated": evaluated,
        "frames_skipped": int(sum(s["skipped"] for s in ok)),
        "frames_over_tolerance_parts": int(sum(s["over_tolerance_parts"] for s in ok)),
        "penetration_mean_mm": tally.mean("penetration_mean_mm"),
        "over_tolerance": tally.mean("over_tolerance", 0.0),
        "contact_imbalance_mean": _ratio(
            sum(s["contact_imbalance_sum"] for s in ok),
            sum(s["contact_imbalance_frames"] for s in ok),
        ),
    }
    for i, engine in enumerate(sp.engines):
        stats = _engine_summary([s["engines"][engine] for s in ok], evaluated)
        if i == 0:
            summary |= stats
        summary |= {f"{k}_{engine}": v for k, v in stats.items()}

    def percent(key: str) -> float | None:
        values = [s[key] for s in ok]
        if None in values:
            return None  # not measured (frames over the tolerance untested)
        return float(100 * np.mean(values)) if ok else float("nan")

    # across engines: the paper's criterion, DexGraspBench's, and the headline (every test)
    for key, name in (("ssr", "success"), ("ssr_paper", "success_contact"),
                      ("ssr_bench", "success_bench")):  # fmt: skip
        summary[key], summary[f"{key}_raw"] = percent(name), percent(f"{name}_raw")
    for key in ("criteria_agree_hold", "criteria_agree_drop", "criteria_disagree"):
        summary[key] = int(sum(s[key] for s in ok))
    if len(sp.engines) > 1:
        for key in ("agree_hold", "agree_drop", "disagree"):
            summary[key] = int(sum(s[key] for s in ok))
    summary["sequences"] = dict(sorted(tally.sequences.items()))
    stage.finish(summary)
    speed = evaluated / seconds if seconds else 0.0
    return {**summary, "timing": {"frames_per_second_one_core": speed}}


def _engine_summary(entries: list[dict], evaluated: int) -> dict:
    """One engine's aggregates over the sequences the stage processed (SSRs in %; ``flipped``:
    the share of evaluated frames whose nominal trial and robust result differ;
    ``lost_closing``: the share whose object moved or turned past the DexGraspBench thresholds
    while the fingers closed, before any push, None for an engine that holds it then;
    ``imbalance_mean``: the mean :func:`dexflow.grasp_protocol.imbalance` of the frames with a
    contact)."""

    def percent(key: str) -> float | None:
        values = [e[key] for e in entries]
        if any(v is None for v in values):
            return None  # not measured (frames over the tolerance untested)
        return float(100 * np.mean(values)) if entries else float("nan")

    def mean(key: str) -> float:
        return float(np.mean([e[key] for e in entries])) if entries else float("nan")

    flipped = sum(e["flipped_frames"] for e in entries)
    lost = [e["lost_closing_frames"] for e in entries]
    balanced = sum(e["imbalance_frames"] for e in entries)
    return {
        "ssr_paper": percent("success_contact"),
        "ssr_bench": percent("success_bench"),
        "ssr_paper_raw": percent("success_contact_raw"),
        "ssr_bench_raw": percent("success_bench_raw"),
        "parts_penetration_mean_mm": mean("parts_penetration_mean_mm"),
        "parts_over_tolerance": mean("parts_over_tolerance"),
        "flipped": flipped / evaluated if evaluated else 0.0,
        "lost_closing": (None if None in lost else (sum(lost) / evaluated if evaluated else 0.0)),
        "imbalance_mean": _ratio(sum(e["imbalance_sum"] for e in entries), balanced),
    }


def _ratio(total: float, count: int) -> float:
    """``total / count``, NaN when ``count`` is 0 (a mean over no frames)."""
    return total / count if count else float("nan")


STAGE = StageSpec(
    name="simulate",
    run=run_simulate,
    metric_keys=None,  # every aggregate: the first engine's, each engine's (``<key>_<engine>``)
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences; SSR {s['ssr']:.1f} % (every test), "
        f"{s['ssr_paper']:.1f} % (the paper's gravity test), {s['ssr_bench']:.1f} % "
        f"(DexGraspBench); the two agree on {_agreement(s):.0f} % of the frames; without the "
        "penetration tolerance "
        + ("not tested" if s["ssr_raw"] is None else
           f"{s['ssr_raw']:.1f} % / {s['ssr_paper_raw']:.1f} % / {s['ssr_bench_raw']:.1f} %")
        + f"; {s['frames_evaluated']} frames tested ({s['frames_skipped']} over the tolerance "
        "skipped), "
        f"mean starting penetration {s['penetration_mean_mm']:.2f} mm; "
        f"{s['timing']['frames_per_second_one_core']:.2f} frames/s per core"
    ),
)  # fmt: skip


def _agreement(summary: dict) -> float:
    """The share (%) of tested frames on which the first engine's two criteria agree."""
    agree = summary["criteria_agree_hold"] + summary["criteria_agree_drop"]
    total = agree + summary["criteria_disagree"]
    return 100.0 * agree / total if total else float("nan")


_WORLDS: dict[tuple[str, int], GraspWorld | MujocoGraspWorld] = {}


def _world(engine: str, hand: RobotHand, params: SimulateParams) -> GraspWorld | MujocoGraspWorld:
    """One world per process, engine and hand (loading and checking the model once)."""
    key = (engine, id(hand))
    world = _WORLDS.get(key)
    if world is None or world.params != params:
        if engine == "mujoco":
            world = MujocoGraspWorld(hand, params)
        else:
            world = GraspWorld(hand, hand_urdf(hand, params), params)
        _WORLDS[key] = world
    return world
