"""The per-frame grasp test in MuJoCo, with DexGraspBench's published protocol.

:class:`MujocoGraspWorld` has the interface and the result of the pybullet
:class:`dexflow.sim.pybullet_world.PybulletGraspWorld` (``set_object``, ``test_frame``, ``close``), so stage
simulate can run either engine on the same frames; what the two share (the push directions, the
damped push step, the perturbed trials) is :mod:`dexflow.sim.protocol`.

The scene (one ``MjSpec`` per object, compiled once per :meth:`MujocoGraspWorld.set_object`):

- Options: ``timestep_s``, ``impratio``, the implicitfast integrator, elliptic friction cones,
  two noslip iterations, no gravity, MuJoCo's native convex collision (on by default in this
  MuJoCo; the world makes sure it is not disabled).
- The hand, read by ``mujoco.MjSpec.from_file`` from its MJCF, or from its URDF as
  :func:`dexflow.hands.physics.physics_urdf` repaired it (the copy pybullet loads too). Its root
  body (``hand.model.root``, with its own offset from its parent) is attached under a **mocap
  body** held at the frame's base pose (``dexflow.hands.robot.base_transform``), so the hand's
  frames are the kinematic model's; the construction checks it (every body and site named in
  ``hand.model.frames`` within 0.1 mm of ``hand.link_transforms`` at a random configuration
  with a moved base, else :class:`~dexflow.errors.HandConfigError`). Every name the hand brings
  (bodies, joints, geoms, sites, meshes, defaults) is prefixed with :data:`HAND_PREFIX`, so that
  none clashes with the scene's own (a URDF whose links are called ``world``, ``object`` or
  ``table`` loads like any other; :func:`hand_name` maps a model name to the scene's). Only the
  root's subtree is attached: an MJCF's own lights, cameras, floor and other bodies stay out.
  Static bodies are not fused (every link stays a body). The model's own actuators, tendons,
  equalities, sensors, contact pairs and keyframes are dropped (a configuration from dexflow
  satisfies the couplings already); every hand joint gets a position actuator (gain ``kp``, no
  velocity gain, control range = the joint's limits, force unlimited) and ``joint_damping`` on
  top of its own. Inertial data is repaired as :mod:`dexflow.hands.physics` says, identically
  for pybullet: a link without it weighs ``massless_link_mass_kg`` with a diagonal inertia of
  ``massless_link_inertia_kgm2`` at its origin, moments violating the triangle inequality are
  balanced.
  Hand-hand collisions are off (as in pybullet); every hand collision geom has condim 4,
  friction ``friction`` (sliding, torsional), solimp (0.5, 0.99, 0.0001) and solref (0.005, 1).
- The object: one free body whose geoms are the convex parts of stage scale_align (object
  frame = body frame), condim 4 and the same friction, of total mass ``object_mass_kg`` at
  uniform density (the parts' total volume from their convex hulls). All margins are zero in
  the simulation.

Protocol for one frame ``(q, T)`` (numbers from ``params.mujoco`` unless said otherwise):

1. Hand at ``q``, object at ``T`` (perturbed: :meth:`Perturbation.object_pose`), at rest. With a
   contact margin (and gap) of ``contact_margin_m`` on the object's geoms (DexGraspBench's way
   of measuring contacts), MuJoCo's contacts give the deepest overlap of a hand geom with a part
   (``parts_penetration_m``, from the contacts' ``dist``), the hand bodies within the margin
   (``pushed_links``; a finger is ``touching`` if one of its ``links`` is among them) and, per
   such body, the point of its closest contact and the direction into the object there.
2. Targets along the grasp, from one damped least-squares step on the stacked translational
   Jacobians (``mj_jac``) of those points over the hand's free joints (tied joints follow their
   leaders; limits hold): **squeeze** moves every point ``push_m`` (plus its gap) into the
   object, **pregrasp** backs it off by ``push_m``; **grasp** is ``q``. Without contacts the
   three are ``q``.
3. The fingers close once, from a reset world: the hand at the pregrasp, the object at its
   pose; the actuator targets move linearly pregrasp -> grasp over ``close_steps`` control
   steps of ``steps_per_control`` physics steps, then grasp -> squeeze likewise. Every test
   below starts from that closed state (MuJoCo's whole integration state is saved and
   restored, so each steps exactly as from a fresh reset and close).
4. For each direction ``d`` of :data:`dexflow.sim.protocol.DIRECTIONS` (+x, -x, +y, -y, +z,
   -z) in turn, two tests, each from the closed state:

   - **DexGraspBench's push**: a force ``force_scale * object_mass_kg`` newtons along ``d``
     acts on the object (``xfrc_applied``, no torque) and, every ``steps_per_check`` steps
     (``hold_checks`` times), the object's displacement (of its frame's origin) and rotation
     angle are measured **from its initial pose, before the fingers closed** (as DexGraspBench
     does). The direction fails once the displacement reaches ``max_displacement_m`` or the
     rotation ``max_rotation_deg``; as in DexGraspBench, the push tests **stop at the first
     failing direction** (the remaining ones are untested: ``tested`` False, NaN displacement
     and rotation).
   - **The paper's gravity test** (the protocol of pybullet's test, so that the criterion
     means the same in both engines): the object's weight ``object_mass_kg * gravity`` acts
     along ``d`` for ``control_steps * control_dt_s`` seconds (100 control steps of 1/60 s by
     default); ``held[d]``: the object still touches the hand (a contact closer than 1 mm) at
     the end. With ``early_exit`` a test ends as failed once the object is dropped (farther
     than ``drop_distance_m`` from every hand geom and moved more than
     ``max_displacement_m``), and the gravity tests stop at the first direction not held.

Two diagnostics of why a frame fails, not criteria: how far the object moved and turned while
the fingers closed, before any push (``closing_displacement_m``, ``closing_rotation_deg``),
and how one-sided the pushes of step 2 are (``imbalance``,
:func:`dexflow.sim.protocol.imbalance` of the directions into the object at the pushed
bodies' closest contacts: 0 when they cancel, 1 when all press the same way). With gravity off
and the object free, a squeeze that is not opposed shoves the object out of the hand before any
force is applied: such a frame fails in its first direction, whatever that is.

Criteria: ``bench`` (DexGraspBench): all six pushes tested and within both thresholds;
``contact`` (the paper's): held at the end of all six gravity tests. The two are independent
tests of the same closed grasp: neither implies the other.

Deterministic: every test resets the data (``mj_resetData``) and sets everything it reads, so a
frame's result depends neither on the frames tested before it nor on the world instance.

**One file** (about 680 lines): the scene builder and the grasp test run on the scene it builds (names,
ids and the state saved between tests); stage replay extends the scene through its public builders.
"""

from __future__ import annotations

import logging
from pathlib import Path

import mujoco
import numpy as np
import torch
import trimesh

from dexflow.errors import HandConfigError
from dexflow.hands.files import urdf_mesh_path
from dexflow.hands.physics import WORLD_ALIAS, mjcf_inertials, physics_root, physics_urdf
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

__all__ = ["HAND_PREFIX", "MOUNT", "MujocoGraspWorld", "add_object", "hand_name", "hand_spec"]

_FK_CHECK_TOL_M = 1e-4  # MuJoCo's frames must match the kinematic model's
_GAP_RANGE_M = 0.01  # MujocoGraspWorld.gap: +inf beyond this (MuJoCo's distances err at 10 cm)
_HAND_SOLIMP = (0.5, 0.99, 0.0001)
_HAND_SOLREF = (0.005, 1.0)
_ROLLING_FRICTION = 1e-4  # MuJoCo's default; unused at condim 4
MOUNT = "dexflow_mount"  # the mocap body the hand hangs from (stage replay drives it)
_OBJECT = "dexflow_object"
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # what _state saves
_DROP_CHECK_S = 1 / 6  # seconds between checks for a dropped object in the gravity test
HAND_PREFIX = "hand/"  # before every name of the hand's in a scene

logger = logging.getLogger(__name__)


def _log_mujoco_warning(text: str) -> None:
    """MuJoCo's warnings (an unstable simulation, too many contacts) go to dexflow's log: its
    own handler appends them to ``MUJOCO_LOG.TXT`` in the working directory, which nobody asked
    for. The per-model warning counters (``MjData.warning``, what ``hand check`` reads) count
    them either way."""
    logger.warning("MuJoCo: %s", text)


mujoco.set_mju_user_warning(_log_mujoco_warning)


# -------------------------------------------------------------------------------- the scene


def _quat(rotation: np.ndarray) -> np.ndarray:
    """MuJoCo quaternion (w, x, y, z) of a (3, 3) rotation matrix."""
    out = np.empty(4)
    mujoco.mju_mat2Quat(out, np.ascontiguousarray(rotation, dtype=float).reshape(9))
    return out


def hand_spec(hand: RobotHand, params: SimulateParams) -> mujoco.MjSpec:
    """The scene without an object: options, mocap mount, the hand and its actuators."""
    p, mp = params, params.mujoco
    if hand.model.format == "urdf":  # the repaired copy pybullet loads too
        path, _ = physics_urdf(hand, p.massless_link_mass_kg, p.massless_link_inertia_kgm2)
    else:
        path = Path(hand.model.path)
    try:
        child = mujoco.MjSpec.from_file(str(path))
    except ValueError as exc:
        raise HandConfigError(f"hand '{hand.spec.name}': MuJoCo cannot read {path}: {exc}") from exc
    folder = Path(child.modelfiledir or path.parent)
    for mesh in child.meshes:  # absolute paths: the scene has no model directory of its own
        if mesh.file and not Path(mesh.file).is_absolute():
            if hand.model.format == "urdf":
                mesh.file = str(urdf_mesh_path(mesh.file, path.parent))
            else:
                mesh.file = str(folder / child.meshdir / mesh.file)
    for texture in child.textures:
        if texture.file and not Path(texture.file).is_absolute():
            texture.file = str(folder / child.texturedir / texture.file)
    child.meshdir = child.texturedir = ""
    root = child.body(physics_root(hand))
    if root is None or root.name == child.worldbody.name:
        raise HandConfigError(
            f"hand '{hand.spec.name}': no body '{physics_root(hand)}' in {path} for MuJoCo"
        )
    if hand.model.format == "mjcf":
        repaired, _ = mjcf_inertials(hand, p.massless_link_mass_kg, p.massless_link_inertia_kgm2)
        for name, (mass, ipos, iquat, moments) in repaired.items():
            body = child.body(name)
            body.explicitinertial = True
            body.mass, body.ipos, body.iquat = mass, ipos.tolist(), iquat.tolist()
            body.inertia = moments.tolist()
            body.fullinertia = [np.nan, 0.0, 0.0, 0.0, 0.0, 0.0]

    scene = mujoco.MjSpec()
    scene.modelname = f"dexflow_{hand.spec.name}"
    # The child's sizes and options become the scene's defaults: no attach conflicts.
    for name in [a for a in dir(scene.option) if not a.startswith("_")]:
        try:
            setattr(child.option, name, getattr(scene.option, name))
        except (AttributeError, TypeError):
            pass
    for name in ["njmax", "nconmax", "nstack", "nuserdata", "memory"] + [
        a for a in dir(scene) if a.startswith("nuser_")
    ]:
        setattr(child, name, getattr(scene, name))
    mount = scene.worldbody.add_body(name=MOUNT, mocap=True)
    try:  # every name of the hand's gets the prefix: none can clash with the scene's
        mount.add_frame().attach_body(root, HAND_PREFIX, "")
    except ValueError as exc:
        raise HandConfigError(
            f"hand '{hand.spec.name}': MuJoCo cannot attach {path} to the scene: {exc}"
        ) from exc
    for kind in ("actuators", "sensors", "tendons", "equalities", "pairs", "keys"):
        for element in list(getattr(scene, kind)):
            scene.delete(element)

    opt = scene.option
    opt.timestep = mp.timestep_s
    opt.impratio = mp.impratio
    opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    opt.noslip_iterations = 2
    opt.gravity = [0.0, 0.0, 0.0]
    opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_NATIVECCD)
    scene.compiler.fusestatic = False
    scene.compiler.degree = False

    sliding, torsional = mp.friction
    for geom in scene.geoms:
        geom.margin = geom.gap = 0.0
        if geom.contype == 0 and geom.conaffinity == 0:
            continue  # visual only
        geom.contype, geom.conaffinity = 1, 0  # touches the object, not the hand
        geom.condim = 4
        geom.friction = [sliding, torsional, _ROLLING_FRICTION]
        geom.solimp = [*_HAND_SOLIMP, *geom.solimp[3:]]
        geom.solref = list(_HAND_SOLREF)
    joints = _unprefixed(scene.joints)
    missing = [n for n in hand.hand_joint_names if n not in joints]
    if missing:
        raise HandConfigError(
            f"hand '{hand.spec.name}': joints {missing} of the kinematic model are not joints "
            f"of {path} in MuJoCo; found {sorted(joints)}"
        )
    lower, upper = hand.lower.cpu().numpy()[6:], hand.upper.cpu().numpy()[6:]
    for name, lo, hi in zip(hand.hand_joint_names, lower, upper, strict=True):
        joint = joints[name]
        damping = np.array(joint.damping, dtype=float)
        damping[0] += mp.joint_damping
        joint.damping = damping
        actuator = scene.add_actuator(name=f"dexflow_{name}", target=joint.name)
        actuator.trntype = mujoco.mjtTrn.mjTRN_JOINT
        actuator.set_to_position(kp=mp.kp, kv=0.0)
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.ctrlrange = [float(lo), float(hi)]
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_FALSE
    return scene


def _unprefixed(elements) -> dict:
    """The hand's elements of a scene by their name in the hand's model (prefix removed)."""
    return {e.name[len(HAND_PREFIX) :]: e for e in elements if e.name.startswith(HAND_PREFIX)}


def hand_name(name: str) -> str:
    """The scene's name of the hand's body, joint or site ``name`` (a frame of ``hand.model``;
    a URDF root link named 'world' is :data:`dexflow.hands.physics.WORLD_ALIAS` there)."""
    return HAND_PREFIX + (WORLD_ALIAS if name == "world" else name)


def add_object(scene: mujoco.MjSpec, parts: list[np.ndarray], params: SimulateParams) -> None:
    """A free body with one convex mesh geom per part, ``object_mass_kg`` at uniform density."""
    mp = params.mujoco
    volume = sum(trimesh.convex.convex_hull(v).volume for v in parts)
    density = mp.object_mass_kg / volume
    body = scene.worldbody.add_body(name=_OBJECT)
    body.add_freejoint(name=f"{_OBJECT}_free")
    sliding, torsional = mp.friction
    for i, vertices in enumerate(parts):
        mesh = scene.add_mesh(name=f"{_OBJECT}_part{i}")
        mesh.uservert = np.asarray(vertices, dtype=float).reshape(-1)
        mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_CONVEX
        body.add_geom(
            name=f"{_OBJECT}_part{i}",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=mesh.name,
            density=density,
            contype=1,
            conaffinity=1,
            condim=4,
            friction=[sliding, torsional, _ROLLING_FRICTION],
            margin=0.0,
            gap=0.0,
        )


# -------------------------------------------------------------------------------- the world


class MujocoGraspWorld:
    """One MuJoCo scene holding a hand and, per sequence, an object (see the module docs).

    Args:
        hand: The kinematic model (joint names, limits, couplings, forward kinematics).
        params: The protocol's parameters (``params.mujoco`` and the shared ``push_m``,
            ``contact_margin_m``, ``max_displacement_m``, ``max_rotation_deg``,
            ``massless_link_mass_kg``, ``massless_link_inertia_kgm2``).

    Raises:
        HandConfigError: The model's joints or frames in MuJoCo disagree with ``hand``.
    """

    engine = "mujoco"

    def __init__(self, hand: RobotHand, params: SimulateParams) -> None:
        self.hand, self.params = hand, params
        self._spec = self._scene()
        self._parts: list[np.ndarray] | None = None
        self._object_key: tuple | None = None
        self._compile(self._spec)
        self._check_kinematics()

    # ---------------------------------------------------------------------------- building

    def _scene(self) -> mujoco.MjSpec:
        """The scene without an object (:class:`dexflow.sim.replay_world.ReplayWorld` adds its own)."""
        return hand_spec(self.hand, self.params)

    def _with_object(self, parts: list[np.ndarray]) -> mujoco.MjSpec:
        """The scene with the object of ``parts`` added."""
        scene = self._spec.copy()
        add_object(scene, parts, self.params)
        return scene

    def _compile(self, spec: mujoco.MjSpec) -> None:
        try:
            self.model = spec.compile()
        except ValueError as exc:
            raise HandConfigError(
                f"hand '{self.hand.spec.name}': MuJoCo cannot compile the scene: {exc}"
            ) from exc
        m = self.model
        self.data = mujoco.MjData(m)
        joints = [m.joint(hand_name(n)) for n in self.hand.hand_joint_names]
        self._qpos = np.array([int(j.qposadr[0]) for j in joints])
        self._dofs = np.array([int(j.dofadr[0]) for j in joints])
        mount = m.body(MOUNT).id
        self._mocap = int(m.body_mocapid[mount])
        parents = m.body_parentid
        hand_body = np.zeros(m.nbody, bool)
        hand_body[mount] = True
        for b in range(mount + 1, m.nbody):  # bodies come after their parents
            hand_body[b] = hand_body[parents[b]]
        self._hand_body = hand_body
        self._object = m.body(_OBJECT).id if self._parts is not None else -1
        object_geoms = m.geom_bodyid == self._object
        self._object_geoms = np.flatnonzero(object_geoms)
        self._friction = m.geom_friction[:, 0].copy()
        if self._object >= 0:
            adr = int(m.jnt_qposadr[m.body_jntadr[self._object]])
            self._object_qpos = slice(adr, adr + 7)
        # the coupling map restricted to the hand's free joints: dq_hand = a_hand @ dx
        a, _ = self.hand.coupling_affine()
        free = np.asarray(self.hand.free_joints)
        self._free_hand = free[free >= 6]
        self._a_hand = a[6:][:, free >= 6]  # (H, Fh)

    def _check_kinematics(self) -> None:
        """MuJoCo's body and site frames must equal the kinematic model's at a random
        configuration with a moved base."""
        hand, m, d = self.hand, self.model, self.data
        rng = np.random.default_rng(0)
        q = hand.zero()[0].cpu().numpy().copy()
        lo, hi = hand.lower.cpu().numpy()[6:], hand.upper.cpu().numpy()[6:]
        q[6:] = lo + rng.random(len(lo)) * (hi - lo)
        q[:6] = [0.1, -0.2, 0.3, 0.4, -0.5, 0.6]
        q = hand.clamp(hand.apply_couplings(hand.as_q(q)))[0].cpu().numpy()
        mujoco.mj_resetData(m, d)
        self._place_hand(q)
        mujoco.mj_kinematics(m, d)
        bodies = {m.body(i).name: i for i in range(m.nbody)}
        sites = {m.site(i).name: i for i in range(m.nsite)}
        bodies = {n: bodies[hand_name(n)] for n in hand.model.frames if hand_name(n) in bodies}
        sites = {n: sites[hand_name(n)] for n in hand.model.frames if hand_name(n) in sites}
        names = [n for n in hand.model.frames if n in bodies or n in sites]
        absent = [n for n in hand.model.frames if n not in bodies and n not in sites]
        if absent:
            raise HandConfigError(
                f"hand '{hand.spec.name}': frames {absent} of the kinematic model are neither "
                f"bodies nor sites of {hand.model.path} in MuJoCo"
            )
        ours = hand.link_transforms(q, names)[0].cpu().numpy()[:, :3, 3]
        theirs = np.array(
            [d.xpos[bodies[n]] if n in bodies else d.site_xpos[sites[n]] for n in names]
        )
        error = float(np.abs(ours - theirs).max())
        if error > _FK_CHECK_TOL_M:
            worst = names[int(np.abs(ours - theirs).max(axis=1).argmax())]
            raise HandConfigError(
                f"hand '{hand.spec.name}': frames of {hand.model.path} in MuJoCo differ from "
                f"the kinematic model by {error * 1000:.2f} mm at '{worst}' (expected < "
                f"{_FK_CHECK_TOL_M * 1000:g} mm): the model file and the hand config disagree"
            )

    def set_object(self, convex_obj: str | Path) -> None:
        """Use the object whose convex decomposition is ``convex_obj`` (from scale_align):
        one compiled scene per object (setting the same unchanged file again is free)."""
        from dexflow.objects.convex import read_convex_obj

        stat = Path(convex_obj).stat()
        key = (str(Path(convex_obj).resolve()), stat.st_mtime_ns, stat.st_size)
        if key == self._object_key:
            return
        self._parts = read_convex_obj(convex_obj)
        self._object_key = key
        self._compile(self._with_object(self._parts))

    # ------------------------------------------------------------------------------- state

    def _place_hand(self, q: np.ndarray) -> None:
        """Base (mocap) and joint positions of ``q (dof,)``; joint velocities stay as they are."""
        d = self.data
        base = base_transform(torch.as_tensor(q[None, :6], dtype=torch.float64))[0].numpy()
        d.mocap_pos[self._mocap] = base[:3, 3]
        d.mocap_quat[self._mocap] = _quat(base[:3, :3])
        d.qpos[self._qpos] = q[6:]

    def _reset(self, q: np.ndarray, pose: np.ndarray) -> None:
        """Fresh data: hand at ``q`` (also the actuators' targets), object at ``pose``, at rest."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        self._place_hand(q)
        d.ctrl[:] = q[6:]
        d.qpos[self._object_qpos] = np.concatenate([pose[:3, 3], _quat(pose[:3, :3])])
        mujoco.mj_forward(m, d)

    def _contacts(self, margin: float) -> dict[str, np.ndarray]:
        """Hand-object contacts of the current state, closer than ``margin`` (m).

        The object's geoms get ``margin`` as contact margin and gap (so the extra contacts
        exert no force) for one ``mj_forward``, then zero again.

        Returns:
            ``body (C,)`` hand body, ``dist (C,)`` signed distance, ``point (C, 3)`` the point
            on the hand's surface, ``normal (C, 3)`` the unit direction into the object.
        """
        m, d = self.model, self.data
        m.geom_margin[self._object_geoms] = margin
        m.geom_gap[self._object_geoms] = margin
        try:
            mujoco.mj_forward(m, d)
        finally:
            m.geom_margin[self._object_geoms] = 0.0
            m.geom_gap[self._object_geoms] = 0.0
        n = d.ncon
        geom = d.contact.geom[:n].reshape(n, 2)
        body = m.geom_bodyid[geom]  # (C, 2)
        first_hand = self._hand_body[body[:, 0]] & (body[:, 1] == self._object)
        second_hand = self._hand_body[body[:, 1]] & (body[:, 0] == self._object)
        keep = (first_hand | second_hand) & (d.contact.dist[:n] < margin)
        normal = d.contact.frame[:n, :3].copy()  # geom1 -> geom2
        normal[second_hand] *= -1.0  # hand -> object
        dist = d.contact.dist[:n].copy()
        point = d.contact.pos[:n] - 0.5 * dist[:, None] * normal  # on the hand
        hand = np.where(first_hand, body[:, 0], body[:, 1])
        return {"body": hand[keep], "dist": dist[keep], "point": point[keep],
                "normal": normal[keep]}  # fmt: skip

    def gap(self, q: np.ndarray, pose: np.ndarray, links: list[str] | None = None) -> float:
        """Signed distance (m) between the hand (or only ``links``) and the object placed at
        ``q`` and ``pose``; negative when they overlap, +inf beyond 1 cm."""
        self._require_object("gap")
        self._reset(np.asarray(q, dtype=float), np.asarray(pose, dtype=float))
        found = self._contacts(_GAP_RANGE_M)
        keep = np.ones(len(found["body"]), bool)
        if links is not None:
            ids = [self.model.body(hand_name(n)).id for n in links]
            keep = np.isin(found["body"], ids)
        return float(found["dist"][keep].min()) if keep.any() else float("inf")

    def _require_object(self, what: str) -> None:
        if self._parts is None:
            raise RuntimeError(f"MujocoGraspWorld.{what}: set_object first")

    # ---------------------------------------------------------------------------- protocol

    def targets(self, q: np.ndarray, pose: np.ndarray) -> tuple[dict, float, list[str]]:
        """Steps 1 and 2 of the protocol: the pregrasp, grasp and squeeze configurations.

        Args:
            q: (dof,) the frame's configuration.
            pose: (4, 4) the object's pose (already perturbed).

        Returns:
            ``{"pregrasp", "grasp", "squeeze"}`` (dof,) each, the deepest overlap (m, >= 0)
            between a hand geom and the object's parts, and the names of the hand bodies within
            ``contact_margin_m`` of the object.
        """
        configs, penetration, names, _ = self._targets(q, pose)
        return configs, penetration, names

    def _targets(
        self, q: np.ndarray, pose: np.ndarray
    ) -> tuple[dict, float, list[str], np.ndarray]:
        """:meth:`targets`, and the (L, 3) directions in which the L pushed bodies press."""
        self._require_object("targets")
        p, hand, m = self.params, self.hand, self.model
        q, pose = np.asarray(q, dtype=float), np.asarray(pose, dtype=float)
        self._reset(q, pose)
        found = self._contacts(p.contact_margin_m)
        penetration = float(max(0.0, -found["dist"].min())) if len(found["dist"]) else 0.0
        if not len(found["body"]):
            same = {"pregrasp": q.copy(), "grasp": q.copy(), "squeeze": q.copy()}
            return same, 0.0, [], np.zeros((0, 3))
        order = np.lexsort((found["dist"], found["body"]))  # by body, closest first
        bodies, first = np.unique(found["body"][order], return_index=True)
        closest = order[first]
        names = [m.body(int(b)).name[len(HAND_PREFIX) :] for b in bodies]
        jac = np.empty((len(bodies), 3, m.nv))
        for k, (b, c) in enumerate(zip(bodies, closest, strict=True)):
            mujoco.mj_jac(m, self.data, jac[k], None, found["point"][c], int(b))
        jac = jac[:, :, self._dofs].reshape(-1, len(self._dofs)) @ self._a_hand  # (3L, Fh)
        normal = found["normal"][closest]
        gap = np.maximum(found["dist"][closest], 0.0)
        depths = {"squeeze": gap + p.push_m, "pregrasp": -np.full_like(gap, p.push_m)}
        moves = np.stack([(d[:, None] * normal).reshape(-1) for d in depths.values()], axis=1)
        steps = damped_step(jac, moves)  # (free hand joints, 2)
        out = {"grasp": q.copy()}
        for k, key in enumerate(depths):
            out[key] = pushed_configuration(hand, q, self._free_hand, steps[:, k])
        return out, penetration, names, normal

    def test_frame(
        self, q: np.ndarray, pose: np.ndarray, perturbation: Perturbation | None = None
    ) -> dict:
        """Run the six-direction test for one frame (see the module docs).

        Args:
            q: (dof,) hand configuration (base then joints, as stage retarget writes it).
            pose: (4, 4) object pose in the world.
            perturbation: Object offset, rotation and friction factor of this trial (None: the
                nominal test).

        Returns:
            ``parts_penetration_m`` (float), ``pushed_links`` (int), ``imbalance`` (float,
            :func:`dexflow.sim.protocol.imbalance` of the pushed bodies' directions into the
            object), ``closing_displacement_m`` and ``closing_rotation_deg`` (floats: how far
            the object moved and turned while the fingers closed, before any push; NaN in
            pybullet's test, which holds the object then), ``touching (F,)`` bool per finger of
            the hand config, ``held (6,)`` (held at the end of each gravity test),
            ``displacement_m (6,)``, ``rotation_deg (6,)`` and ``tested (6,)`` (of the
            pushes) and the criteria ``contact`` (the paper's), ``bench`` (bools); directions in
            :data:`dexflow.stages.simulate.DIRECTIONS` order.
        """
        self._require_object("test_frame")
        p, mp, m, d = self.params, self.params.mujoco, self.model, self.data
        q = np.asarray(q, dtype=float)
        pose = np.asarray(pose, dtype=float)
        if perturbation is not None:
            pose = perturbation.object_pose(pose)
        scale = 1.0 if perturbation is None else perturbation.friction_scale
        m.geom_friction[:, 0] = self._friction * scale
        try:
            configs, penetration, pushed, normals = self._targets(q, pose)
            touching = np.array(
                [bool(set(pushed) & set(fs.links)) for fs in self.hand.spec.fingers.values()]
            )
            held = np.zeros(6, bool)
            displacement = np.full(6, np.nan)
            rotation = np.full(6, np.nan)
            tested = np.zeros(6, bool)
            self._reset(configs["pregrasp"], pose)
            start = d.qpos[self._object_qpos].copy()
            self._drive(configs["pregrasp"], configs["grasp"])
            self._drive(configs["grasp"], configs["squeeze"])
            closing = self._moved(start)
            closed = self._state()  # every direction starts from this closed grasp
            push, weight = mp.force_scale * mp.object_mass_kg, mp.object_mass_kg * p.gravity
            bench_alive = paper_alive = True
            for k, direction in enumerate(DIRECTIONS):
                if bench_alive:
                    tested[k] = True
                    displacement[k], rotation[k] = self._push(closed, start, push * direction)
                    # DexGraspBench: the frame fails at its first failing direction
                    bench_alive = bool(_within(displacement[k], rotation[k], p))
                if paper_alive:
                    held[k] = paper_alive = self._gravity(closed, start, weight * direction)
                if not (bench_alive or paper_alive):
                    break
        finally:
            m.geom_friction[:, 0] = self._friction
        bench = bool(tested.all() and _within(displacement, rotation, p).all())
        return {
            "parts_penetration_m": penetration,
            "pushed_links": len(pushed),
            "imbalance": imbalance(normals),
            "closing_displacement_m": closing[0],
            "closing_rotation_deg": closing[1],
            "touching": touching,
            "held": held,
            "displacement_m": displacement,
            "rotation_deg": rotation,
            "tested": tested,
            "contact": bool(held.all()),
            "bench": bench,
        }

    def _state(self) -> np.ndarray:
        """Everything the next steps depend on (MuJoCo's integration state), for
        :meth:`_restore`: a restored world steps exactly as the saved one would have."""
        size = mujoco.mj_stateSize(self.model, _STATE)
        state = np.empty(size)
        mujoco.mj_getState(self.model, self.data, state, _STATE)
        return state

    def _restore(self, state: np.ndarray) -> None:
        mujoco.mj_setState(self.model, self.data, state, _STATE)

    def _push(
        self, closed: np.ndarray, start: np.ndarray, force: np.ndarray
    ) -> tuple[float, float]:
        """DexGraspBench's push from the ``closed`` state: ``force`` (3,) on the object,
        checked every ``steps_per_check`` steps until it leaves the thresholds; the object's
        displacement (m) and rotation (deg) from ``start`` (7,) when the push ends."""
        mp, m, d = self.params.mujoco, self.model, self.data
        self._restore(closed)
        d.xfrc_applied[self._object, :3] = force
        for _ in range(mp.hold_checks):
            mujoco.mj_step(m, d, nstep=mp.steps_per_check)
            moved = self._moved(start)
            if not _within(*moved, self.params):
                break
        return moved

    def _gravity(self, closed: np.ndarray, start: np.ndarray, weight: np.ndarray) -> bool:
        """The paper's test of one direction from the ``closed`` state: the object's weight
        ``weight`` (3,) acts on it for ``control_steps * control_dt_s`` seconds; whether the
        object still touches the hand (closer than :data:`TOUCH_M`) at the end. With
        ``early_exit`` the test ends once the object is dropped (farther than
        ``drop_distance_m`` from the hand and moved more than ``max_displacement_m``: under
        a constant force it does not come back)."""
        p, m, d = self.params, self.model, self.data
        self._restore(closed)
        d.xfrc_applied[self._object, :3] = weight
        steps = round(p.control_steps * p.control_dt_s / p.mujoco.timestep_s)
        chunk = max(1, round(_DROP_CHECK_S / p.mujoco.timestep_s))
        for done in range(0, steps, chunk):
            mujoco.mj_step(m, d, nstep=min(chunk, steps - done))
            if p.early_exit and self._dropped(start):
                return False
        return bool((self._contacts(TOUCH_M)["dist"] < TOUCH_M).any())

    def _dropped(self, start: np.ndarray) -> bool:
        far = not len(self._contacts(self.params.drop_distance_m)["dist"])
        return far and self._moved(start)[0] > self.params.max_displacement_m

    def _drive(self, start: np.ndarray, end: np.ndarray) -> None:
        """Move the actuator targets linearly from ``start`` to ``end`` (dof,) over
        ``close_steps`` control steps of ``steps_per_control`` physics steps."""
        mp, m, d = self.params.mujoco, self.model, self.data
        for j in range(1, mp.close_steps + 1):
            d.ctrl[:] = start[6:] + (end[6:] - start[6:]) * (j / mp.close_steps)
            mujoco.mj_step(m, d, nstep=mp.steps_per_control)

    def _moved(self, start: np.ndarray) -> tuple[float, float]:
        """Displacement (m) and rotation angle (deg) of the object from ``start`` (7,) qpos."""
        now = self.data.qpos[self._object_qpos]
        rotvec = np.empty(3)
        mujoco.mju_subQuat(rotvec, now[3:], start[3:])
        return float(np.linalg.norm(now[:3] - start[:3])), float(np.degrees(np.linalg.norm(rotvec)))

    def close(self) -> None:
        """Release the model and data (the world cannot be used afterwards)."""
        self.model = self.data = None  # type: ignore[assignment]


def _within(displacement, rotation, p: SimulateParams):
    """DexGraspBench's success of a test: displacement and rotation below the thresholds."""
    return (np.asarray(displacement) < p.max_displacement_m) & (
        np.asarray(rotation) < p.max_rotation_deg
    )
