"""What the grasp tests of every engine share: push directions, the push step, perturbed trials.

Stage simulate runs the same frames through pybullet
(:class:`dexflow.sim.pybullet_world.PybulletGraspWorld`) and MuJoCo
(:class:`dexflow.sim.mujoco_world.MujocoGraspWorld`); both push the object along
:data:`DIRECTIONS`, call it held when a contact is closer than :data:`TOUCH_M`, turn contact
points into joint targets with the same damped least-squares step (:func:`damped_step`,
:func:`pushed_configuration`) and test the same perturbed copies of a frame
(:func:`perturbations`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.params import PerturbationParams, SimulateParams

if TYPE_CHECKING:
    from dexflow.hands.robot import RobotHand

__all__ = [
    "DIRECTIONS",
    "DLS_DAMPING",
    "TOUCH_M",
    "Perturbation",
    "contact_imbalance",
    "damped_step",
    "imbalance",
    "lost_while_closing",
    "perturbations",
    "pushed_configuration",
]

DIRECTIONS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float
)  # the six push (or gravity) directions, in this order: +x, -x, +y, -y, +z, -z
TOUCH_M = 1e-3  # "in contact" at the end of a test: closer than this
DLS_DAMPING = 1e-2  # damping (m/rad) of the push step's least squares


def damped_step(jacobian: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """Joint steps that move contact points by ``moves``, by damped least squares.

    ``dq = Jᵀ (J Jᵀ + λ² I)⁻¹ m`` with ``λ = DLS_DAMPING``: the smallest joint change that moves
    the points as asked, bounded where the Jacobian is near singular.

    Args:
        jacobian: (3L, J) stacked translational Jacobians of L contact points over J joints.
        moves: (3L,) or (3L, K) the wanted displacement of every point, one column per target.

    Returns:
        (J,) or (J, K) joint steps.
    """
    damping = DLS_DAMPING**2 * np.eye(len(jacobian))
    return jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + damping, moves)


def imbalance(normals: np.ndarray) -> float:
    """How one-sided the pushes of a grasp are: ``||Σ n_i|| / N`` over the unit directions
    ``n_i`` (N, 3) along which the N pushed links press into the object.

    0 when the pushes cancel (opposed contacts: the squeeze tightens the grasp), 1 when all
    press the same way (the squeeze shoves the object away, which no friction resists when the
    object is free); NaN without contacts. A diagnostic of the test, not a criterion.
    """
    normals = np.asarray(normals, dtype=float).reshape(-1, 3)
    if not len(normals):
        return float("nan")
    unit = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    return float(np.linalg.norm(unit.sum(0)) / len(unit))


def contact_imbalance(contact_map: dict[str, np.ndarray], frames: np.ndarray) -> np.ndarray:
    """How one-sided the contacts that stage contact found are, at each of ``frames``.

    The contacts are those the grasp is retargeted and refined towards (stage contact's final
    states on the retargeted hand, which follows the human's keypoints: where the human
    touched). Per frame, each finger in contact presses along the mean of the inward object
    normals (``-map_object_normal``) of its mapped points, and the frame's value is
    :func:`imbalance` of those directions, one per finger: 0 when they cancel, 1 when they all
    press the same way (or only one finger touches), NaN without a finger in contact. Set next
    to the imbalance of the robot's pushes, it tells a grasp the retargeting made one-sided
    from a frame at which the human's own contacts could not enclose the object (an approach,
    a touch, a palm or table carrying it).

    Args:
        contact_map: Stage contact's ``map_frame``, ``map_finger`` and ``map_object_normal``
            (object frame: the value is invariant to the object's pose).
        frames: (N,) frame indices.

    Returns:
        (N,) the imbalance per frame.
    """
    frame = np.asarray(contact_map["map_frame"], dtype=int)
    finger = np.asarray(contact_map["map_finger"], dtype=int)
    inward = -np.asarray(contact_map["map_object_normal"], dtype=float).reshape(-1, 3)
    out = np.full(len(frames), np.nan)
    for i, t in enumerate(np.asarray(frames, dtype=int)):
        at = frame == t
        if not at.any():
            continue
        fingers = np.unique(finger[at])
        sums = np.stack([inward[at & (finger == f)].sum(0) for f in fingers])
        sums = sums[np.linalg.norm(sums, axis=1) > 0]  # a finger whose normals cancel: no push
        out[i] = imbalance(sums)
    return out


def lost_while_closing(
    displacement_m: np.ndarray, rotation_deg: np.ndarray, params: SimulateParams
) -> np.ndarray:
    """Whether the object had already moved or turned past the DexGraspBench thresholds
    (``max_displacement_m``, ``max_rotation_deg``) while the fingers closed, before any push:
    from a frame's ``closing_displacement_m`` and ``closing_rotation_deg`` (NaN, an engine that
    holds the object then: False)."""
    return (np.asarray(displacement_m) >= params.max_displacement_m) | (
        np.asarray(rotation_deg) >= params.max_rotation_deg
    )


def pushed_configuration(
    hand: RobotHand, q: np.ndarray, joints: np.ndarray | list[int], step: np.ndarray
) -> np.ndarray:
    """``q`` with ``step`` added to its ``joints``, tied joints following their leaders, within
    the joint limits, the floating base unchanged.

    Args:
        hand: The hand (couplings, limits).
        q: (dof,) configuration.
        joints: Indices into ``q`` of the stepped joints (hand joints, not the base).
        step: (len(joints),) the step.

    Returns:
        (dof,) the pushed configuration.
    """
    out = np.array(q, dtype=float)
    out[joints] += step
    out = hand.clamp(hand.apply_couplings(hand.as_q(out)))[0].cpu().numpy()
    out[:6] = q[:6]
    return out


@dataclass(frozen=True, eq=False)
class Perturbation:
    """A perturbed copy of a frame's test.

    Attributes:
        offset_m: (3,) translation of the object, in the world frame.
        rotvec_rad: (3,) rotation vector of the object, in its own frame about its origin.
        friction_scale: Factor on the sliding friction of every geom.

    The perturbed pose is ``T(offset_m) @ pose @ R(rotvec_rad)`` (:meth:`object_pose`); the
    whole test (contacts, targets, simulation) sees the object there, with the frame's ``q``
    unchanged. Two perturbations are equal when all their fields are.
    """

    offset_m: np.ndarray
    rotvec_rad: np.ndarray
    friction_scale: float = 1.0

    def __post_init__(self) -> None:
        for name in ("offset_m", "rotvec_rad"):
            value = np.array(getattr(self, name), dtype=float).reshape(3)
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        object.__setattr__(self, "friction_scale", float(self.friction_scale))

    @classmethod
    def none(cls) -> Perturbation:
        """The identity: no offset, no rotation, friction unchanged."""
        return cls(np.zeros(3), np.zeros(3), 1.0)

    def object_pose(self, pose: np.ndarray) -> np.ndarray:
        """The perturbed object pose (4, 4) of ``pose`` (4, 4), object -> world."""
        rotation = np.eye(4)
        rotation[:3, :3] = Rotation.from_rotvec(np.array(self.rotvec_rad)).as_matrix()
        out = np.asarray(pose, dtype=float) @ rotation
        out[:3, 3] += self.offset_m
        return out

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Perturbation):
            return NotImplemented
        return (
            np.array_equal(self.offset_m, other.offset_m)
            and np.array_equal(self.rotvec_rad, other.rotvec_rad)
            and self.friction_scale == other.friction_scale
        )

    __hash__ = None  # type: ignore[assignment]


def perturbations(params: PerturbationParams, frame_seed: int) -> list[Perturbation]:
    """The ``params.count`` perturbed copies of a frame's test (deterministic per frame).

    Drawn from ``np.random.default_rng([params.seed, frame_seed])``: offsets uniform in the
    ball of radius ``position_m``, rotations about a uniformly random axis by an angle uniform
    in ``[0, rotation_deg]``, friction factors uniform in ``[1 - friction_rel, 1 + friction_rel]``.

    Args:
        params: The perturbations' settings.
        frame_seed: Non-negative integer naming the frame (e.g. its index).

    Returns:
        ``count`` perturbations (an empty list for ``count == 0``).
    """
    n = int(params.count)
    if n <= 0:
        return []
    rng = np.random.default_rng([int(params.seed), int(frame_seed)])
    directions = _unit(rng.normal(size=(n, 3)))  # (n, 3)
    radii = params.position_m * rng.random(n) ** (1.0 / 3.0)  # uniform in the ball
    axes = _unit(rng.normal(size=(n, 3)))
    angles = np.radians(params.rotation_deg) * rng.random(n)
    scales = rng.uniform(1.0 - params.friction_rel, 1.0 + params.friction_rel, n)
    offsets, rotvecs = directions * radii[:, None], axes * angles[:, None]
    return [Perturbation(o, r, float(s)) for o, r, s in zip(offsets, rotvecs, scales, strict=True)]


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v (n, 3)`` scaled to unit length."""
    return v / np.linalg.norm(v, axis=1, keepdims=True)
