"""pybullet's grasp world: stage simulate's paper protocol in a second, independent engine.

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

The protocol itself (push, six directions, criteria) is stage simulate's
(:mod:`dexflow.stages.simulate`); this module is the engine under it, implementing
:class:`dexflow.sim.world.GraspWorld`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from dexflow.errors import HandConfigError
from dexflow.hands.robot import RobotHand, base_transform
from dexflow.params import SimulateParams
from dexflow.sim.protocol import (
    DIRECTIONS,
    TOUCH_M,
    Perturbation,
    damped_step,
    imbalance,
    pushed_configuration,
)

__all__ = ["PybulletGraspWorld", "hand_urdf", "object_parts"]

_DROP_CHECK_EVERY = 10  # control steps between checks for a dropped object
_FK_CHECK_TOL_M = 1e-4  # pybullet's link frames must match the kinematic model's


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


class PybulletGraspWorld:
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
            (:func:`dexflow.sim.protocol.imbalance` of their directions into the object),
            ``closing_displacement_m`` and ``closing_rotation_deg`` (NaN: this test holds the
            object still while the fingers close), ``touching (F,)`` (which of the
            hand's fingers, in the hand config's order, have such a link), ``held (6,)``,
            ``displacement_m (6,)``, ``rotation_deg (6,)``, ``tested (6,)`` and the two
            criteria ``contact``, ``bench`` (before the penetration rule).
        """
        if self.object is None:
            raise RuntimeError("PybulletGraspWorld.test_frame: set_object first")
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
