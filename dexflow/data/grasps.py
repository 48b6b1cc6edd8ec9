"""Grasp synthesis for the demo: place the human hand model and close its fingers on an object.

A grasp type is a template of joint angles: an open pose and, for the fingers that close, a
closed pose. Closing a finger sweeps its angles from open to closed and stops where its skin
(capsules around the bones) first touches the object, so contacts are where the geometry puts
them, not where a script says. The hand placement is searched: approach directions (side, top),
rolls about the approach axis and depths are scored in one batch, and a placement is accepted
when the thumb and at least one opposing finger touch while neither the palm, the open hand nor
any finger penetrates the object. There is no table: objects are taken as if from a stand.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.human.model import HandShape, finger_capsules, forward_keypoints
from dexflow.objects.sdf import SignedDistanceGrid

__all__ = ["GRASP_TYPES", "Grasp", "GraspTemplate", "synthesize_grasp"]

_THUMB_OPEN = (0.1, 0.75, 0.0, 0.0)
_FINGER_OPEN = (0.0, 0.08, 0.08, 0.05)
_TUCKED = (0.0, 1.35, 1.55, 0.95)


@dataclass(frozen=True)
class GraspTemplate:
    """Joint-angle template of a grasp type (per finger, 4 angles as in ``JOINT_NAMES``).

    Attributes:
        name: Grasp type.
        open: Per finger (thumb..little), the angles before closing.
        closed: Per finger, the angles at the end of the closing sweep; equal to ``open`` for a
            finger that does not close (it is tucked or held still).
        active: Fingers (indices) that close on the object and must touch it.
        grasp_point: Point in the wrist frame that is placed inside the object, metres.
        approach_axis: Wrist-frame axis pointing at the object: 'x' (palm first) or 'y' (the
            thumb side first, for a lateral grasp of an edge).
    """

    name: str
    open: tuple[tuple[float, ...], ...]
    closed: tuple[tuple[float, ...], ...]
    active: tuple[int, ...]
    grasp_point: tuple[float, float, float]
    approach_axis: str = "x"

    def angles(self, closure: np.ndarray) -> np.ndarray:
        """Joint angles (..., 20) for per-finger closure (..., 5) in [0, 1]."""
        open_ = np.asarray(self.open)
        closed = np.asarray(self.closed)
        closure = np.asarray(closure, dtype=np.float64)[..., None]
        return (open_ + closure * (closed - open_)).reshape((*closure.shape[:-2], 20))


def _template(name, closed_thumb, closed_finger, active, grasp_point, tucked=(), lateral=False):
    thumb_open = (0.05, 0.25, 0.0, 0.0) if lateral else _THUMB_OPEN
    open_ = [thumb_open] + [_TUCKED if f in tucked else _FINGER_OPEN for f in range(1, 5)]
    closed = [closed_thumb] + [
        _TUCKED if f in tucked else (closed_finger if f in active else _FINGER_OPEN)
        for f in range(1, 5)
    ]
    if lateral:
        open_[1:] = [(0.0, 0.7, 0.8, 0.5)] * 4
        closed[1:] = [closed_finger] * 4
    axis = "y" if lateral else "x"
    return GraspTemplate(name, tuple(open_), tuple(closed), tuple(active), grasp_point, axis)


GRASP_TYPES: dict[str, GraspTemplate] = {
    t.name: t
    for t in (
        _template(
            "power",
            (0.9, 1.0, 0.7, 0.8),
            (0.0, 1.5, 1.7, 1.0),
            (0, 1, 2, 3, 4),
            (0.040, 0.0, 0.095),
        ),
        _template(
            "pinch",
            (0.55, 1.05, 0.45, 0.55),
            (0.0, 1.25, 1.1, 0.6),
            (0, 1),
            (0.060, 0.030, 0.125),
            tucked=(3, 4),
        ),
        _template(
            "tripod",
            (0.55, 1.05, 0.45, 0.55),
            (0.0, 1.25, 1.1, 0.6),
            (0, 1, 2),
            (0.060, 0.015, 0.125),
            tucked=(4,),
        ),
        _template(
            "lateral",
            (-0.25, 0.1, 0.55, 1.4),
            (0.0, 1.3, 1.5, 0.9),
            (0, 1),
            (0.047, 0.050, 0.106),
            lateral=True,
        ),
    )
}

_PALM_POINTS = np.array(
    [[0.0, y, z] for y in np.linspace(-0.030, 0.022, 4) for z in np.linspace(0.015, 0.080, 4)]
)
_PALM_RADIUS = 0.011
_CLOSURE_STEPS = 61
_ROT_Y_TO_X = Rotation.from_euler("z", -np.pi / 2).as_matrix()


@dataclass
class Grasp:
    """A synthesised grasp in the object's resting frame.

    Attributes:
        template: The grasp type used.
        wrist_pose: (4, 4) wrist-to-world transform at the grasp.
        closure_grid: (S,) closure values the distance curves are sampled at.
        finger_distance: (S, 5) per finger, the smallest skin-to-surface distance (m) at
            each closure value (negative: penetrating).
        contact_closure: (5,) closure where each finger first touches; NaN if it never does.
        stop_closure: (5,) closure where each finger stops (contact or end of its sweep).
        score: Number of active fingers that touch (higher is better).
        approach: Unit vector along which the palm approaches the object.
    """

    template: GraspTemplate
    wrist_pose: np.ndarray
    closure_grid: np.ndarray
    finger_distance: np.ndarray
    contact_closure: np.ndarray
    stop_closure: np.ndarray
    score: float
    approach: np.ndarray

    def closure_for_distance(self, finger: int, distance: float) -> float:
        """Closure at which ``finger``'s skin is ``distance`` from the surface (< 0: inside).

        The finger keeps its contact closure where the template cannot reach that distance.
        """
        curve = self.finger_distance[:, finger]
        if np.isnan(self.contact_closure[finger]):
            return float(self.stop_closure[finger])
        deepest = int(np.argmin(curve))
        prefix = curve[: deepest + 1]
        if distance < prefix[-1]:
            return float(self.closure_grid[deepest])
        # np.interp needs increasing x: the prefix decreases with closure.
        return float(np.interp(distance, prefix[::-1], self.closure_grid[: deepest + 1][::-1]))


def _look_rotation(approach: np.ndarray, roll: float) -> np.ndarray:
    """Wrist rotation whose palm normal (x) is ``approach``, rolled by ``roll`` about it."""
    x = approach / np.linalg.norm(approach)
    helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    z = np.cross(helper, x)
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    base = np.stack([x, y, z], axis=-1)
    return base @ Rotation.from_rotvec([roll, 0.0, 0.0]).as_matrix()


def _entry_depth(sdf: SignedDistanceGrid, origin: np.ndarray, direction: np.ndarray) -> float:
    """Distance along ``direction`` from ``origin`` to the first point inside the object."""
    steps = np.arange(0.0, 0.6, 0.001)
    values = sdf.query(origin + steps[:, None] * direction)
    inside = np.flatnonzero(values <= 0.0)
    return float(steps[inside[0]]) if len(inside) else np.nan


def synthesize_grasp(
    sdf: SignedDistanceGrid,
    grasp_type: str,
    rng: np.random.Generator,
    shape: HandShape | None = None,
    n_azimuths: int = 6,
    n_rolls: int = 12,
) -> Grasp:
    """Search a hand placement for ``grasp_type`` on the object described by ``sdf``.

    Args:
        sdf: Signed distance of the object in its resting frame.
        grasp_type: A key of :data:`GRASP_TYPES`.
        rng: Source of the random azimuths, offsets and tie-breaks.
        shape: Hand geometry.
        n_azimuths: Side approach directions tried (top approaches are always tried too).
        n_rolls: Rolls about each approach direction.

    Returns:
        The best placement found (``score`` tells how many active fingers touch).
    """
    shape = shape or HandShape()
    template = GRASP_TYPES[grasp_type]
    centre = (sdf.origin + sdf.upper) / 2
    extent = sdf.upper - sdf.origin

    closure = np.linspace(0.0, 1.0, _CLOSURE_STEPS)
    angles = template.angles(np.repeat(closure[:, None], 5, axis=1))
    skin, radii = finger_capsules(forward_keypoints(angles, shape=shape), shape)  # (S,5,P,3)
    palm = _PALM_POINTS * shape.scale
    grasp_point = np.asarray(template.grasp_point) * shape.scale

    azimuths = rng.uniform(0, 2 * np.pi) + np.arange(n_azimuths) * 2 * np.pi / n_azimuths
    approaches = [np.array([np.cos(a), np.sin(a), rng.uniform(-0.35, 0.0)]) for a in azimuths]
    approaches += [
        np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), -1.0]) for _ in range(2)
    ]
    rotations, translations, used_approach = [], [], []
    for approach in approaches:
        approach = approach / np.linalg.norm(approach)
        for roll in np.arange(n_rolls) * 2 * np.pi / n_rolls + rng.uniform(0, 0.3):
            rot = _look_rotation(approach, roll)
            if template.approach_axis == "y":
                rot = rot @ _ROT_Y_TO_X
            offset = rng.uniform(-0.15, 0.15, 3) * extent
            offset -= (offset @ approach) * approach
            start = centre + offset - approach * 0.5
            entry = _entry_depth(sdf, start, approach)
            if np.isnan(entry):
                continue
            for depth in (0.004, 0.012, 0.022, 0.035):
                target = start + approach * (entry + depth)
                rotations.append(rot)
                translations.append(target - rot @ grasp_point)
                used_approach.append(approach)
    rot = np.asarray(rotations)  # (N,3,3)
    trans = np.asarray(translations)

    world = np.einsum("nij,sfpj->nsfpi", rot, skin) + trans[:, None, None, None]
    dist = sdf.query(world) - radii  # (N,S,5,P)
    finger_dist = dist.min(axis=-1)  # (N,S,5)
    palm_world = np.einsum("nij,pj->npi", rot, palm) + trans[:, None]
    palm_clear = sdf.query(palm_world).min(axis=-1) - _PALM_RADIUS

    touching = finger_dist <= 0.0
    first = np.where(touching.any(axis=1), touching.argmax(axis=1), _CLOSURE_STEPS)  # (N,5)
    # Up to the contact step nothing may penetrate, and the open hand must be clear.
    steps = np.arange(_CLOSURE_STEPS)[None, :, None]
    before = steps < first[:, None, :]
    open_clear = finger_dist[:, 0].min(axis=-1) > 0.0
    clear_object = open_clear & (np.where(before, finger_dist, np.inf).min(axis=(1, 2)) > -1e-3)
    moving = np.any(np.asarray(template.open) != np.asarray(template.closed), axis=1)
    still_clear = np.where(moving[None, :], np.inf, finger_dist[:, 0]).min(axis=1) > 1e-3
    feasible = clear_object & still_clear & (palm_clear > 0)
    in_contact = first < _CLOSURE_STEPS
    active = list(template.active)
    thumb_and_other = in_contact[:, 0] & in_contact[:, active[1:]].any(axis=1)
    score = in_contact[:, active].sum(axis=1) + 2.0 * thumb_and_other
    score = np.where(feasible, score, -1.0)
    best = np.flatnonzero(score == score.max())
    pick = int(rng.choice(best))

    wrist = np.eye(4)
    wrist[:3, :3] = rot[pick]
    wrist[:3, 3] = trans[pick]
    stop_closure = closure[np.minimum(first[pick], _CLOSURE_STEPS - 1)]
    contact = np.where(in_contact[pick], stop_closure, np.nan)
    return Grasp(
        template=template,
        wrist_pose=wrist,
        closure_grid=closure,
        finger_distance=finger_dist[pick],
        contact_closure=contact,
        stop_closure=stop_closure,
        score=float(score[pick]),
        approach=used_approach[pick],
    )
