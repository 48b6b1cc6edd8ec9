"""How a dataset writes its object rotations, read back from the hands that carry the objects
and the table they rest on.

A pose file's rotation ``R`` is meant to take object-mesh coordinates to the camera's (HO-3D's
``objRot``: ``p = R m + t``). Exporters get this wrong in ways a single sequence does not show:
the transposed matrix (the camera-to-object rotation), axes swapped on either side (another
camera convention on the left, another mesh frame on the right). dexflow reads a stored ``R`` as

    ``R_object = L · op(R) · B``,  ``op`` the identity or the transpose,

``L`` and ``B`` two of the 24 rotations that take the coordinate axes to coordinate axes (the
cube's rotations): 1152 conventions, the standard one ``L = B = I`` without the transpose. A
convention is written ``"<L> R <B>"`` or ``"<L> R^T <B>"``, each matrix as the images of x, y
and z, e.g. ``"-z+y+x R^T +z-y+x"`` (``L`` takes x to -z, y to +y and z to +x: a quarter
turn about y).

Two facts of any capture session single out the right one, and neither needs ground truth:

1. **A carried object turns with the hand.** While the hand carries it, the object's rotation
   in the hand's wrist frame (:func:`dexflow.human.keypoints.wrist_frame`), ``H_kᵀ R_object,k``,
   stays about constant. With a wrong ``op`` or ``L`` it turns as much as the hand does. The
   *carry spread* of a sequence is the median angle of that relative rotation from its value at
   the middle carried frame; the session's is the median over its sequences whose hand turns
   (the same angle of the hand's own rotation) by :data:`TURNING_DEG` or more: a carry without
   a turn is steady whatever ``L``. It depends on ``op`` and ``L`` only (``B`` cancels), so it
   picks them.
2. **At its first tracked frame every object rests on the one table.** The lowest point of its
   convex hull then lies at the same height along the table's up vector in every capture. The
   *start spread* is the trimmed mean deviation of those heights from their median, minimised
   over up vectors (:func:`dexflow.data.table.start_spread`; the term the table fit minimises).
   It depends on ``op`` and ``B`` (``L`` only turns the up vector), so it picks ``B``.

:func:`check_convention` takes ``op`` and ``L`` with the smallest carry spread, then ``B`` with
the smallest start spread; it prefers the standard convention (and ``L = I``, ``B = I``) unless
the other is clearly better: both spreads at most :data:`CLEARLY_BETTER` of the standard's.
On the 83 real DexYCB captures of one HO-3D-layout export, each of the three subjects' folders
reads ``"-z+y+x R^T +z-y+x"``: carry spreads 28, 23 and 17° as stored, 9, 10 and 8° so read;
start spreads 1.0, 1.0 and 0.8 cm, then 0.1, 0.2 and 0.1 cm; and its objects rest within a
median 3° of a stable face of their hull (26° as stored).
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from dexflow.data.table import MIN_CAPTURES, start_spread
from dexflow.errors import ConfigError
from dexflow.human.keypoints import wrist_frame

__all__ = [
    "CARRIED_M",
    "CLEARLY_BETTER",
    "CUBE",
    "MIN_CARRIED_FRAMES",
    "MIN_TURNING",
    "STANDARD",
    "TURNING_DEG",
    "ConventionCheck",
    "RotationConvention",
    "carry_spread_deg",
    "check_convention",
]

CARRIED_M = 0.03  # an object this far from where it started is being carried
MIN_CARRIED_FRAMES = 5  # a sequence carried for fewer frames says nothing about rotations
TURNING_DEG = 10.0  # a carry whose hand turns less says little: every L keeps it steady
MIN_TURNING = 3  # fewer turning carries than this: no evidence on op and L
CLEARLY_BETTER = 0.7  # another convention must bring both spreads down to this share
_AXES = "xyz"


def _cube_rotations() -> np.ndarray:
    """(24, 3, 3) the rotations taking coordinate axes to coordinate axes, identity first."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[perm, range(3)] = signs  # column j: the image of axis j
            if np.linalg.det(matrix) > 0:
                out.append(matrix)
    return np.stack(out)


CUBE = _cube_rotations()


def _axes_text(matrix: np.ndarray) -> str:
    """``"+z+y-x"``: the images of x, y, z under a cube rotation."""
    out = ""
    for j in range(3):
        i = int(np.argmax(np.abs(matrix[:, j])))
        out += ("+" if matrix[i, j] > 0 else "-") + _AXES[i]
    return out


def _axes_matrix(text: str, spec: str) -> np.ndarray:
    if not re.fullmatch(r"([+-][xyz]){3}", text):
        raise ConfigError(
            f"object rotation '{spec}': '{text}' is not a matrix written as the images of x, y "
            "and z, e.g. '+z+y-x'"
        )
    matrix = np.zeros((3, 3))
    for j in range(3):
        sign, axis = text[2 * j], text[2 * j + 1]
        matrix[_AXES.index(axis), j] = 1.0 if sign == "+" else -1.0
    if not np.isclose(np.linalg.det(matrix), 1.0):
        raise ConfigError(
            f"object rotation '{spec}': '{text}' is not a rotation (each axis once, determinant +1)"
        )
    return matrix


@dataclass(frozen=True)
class RotationConvention:
    """``R_object = left · op(R) · right``, ``op`` the transpose if ``transposed``."""

    left: np.ndarray = field(default_factory=lambda: np.eye(3))
    transposed: bool = False
    right: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def is_standard(self) -> bool:
        return (
            not self.transposed
            and np.array_equal(self.left, np.eye(3))
            and np.array_equal(self.right, np.eye(3))
        )

    def __str__(self) -> str:
        middle = "R^T" if self.transposed else "R"
        return f"{_axes_text(self.left)} {middle} {_axes_text(self.right)}"

    @classmethod
    def parse(cls, spec: str) -> RotationConvention:
        """Read ``"<L> R <B>"`` or ``"<L> R^T <B>"`` (``"as-stored"``: the standard one).

        Raises:
            ConfigError: Not of that form, or a matrix that is not a cube rotation.
        """
        if spec == "as-stored":
            return STANDARD
        parts = spec.split()
        if len(parts) != 3 or parts[1] not in ("R", "R^T"):
            raise ConfigError(
                f"object rotation '{spec}': expected 'as-stored', 'check', 'auto' or "
                "'<L> R <B>' / '<L> R^T <B>', e.g. '-z+y+x R^T +z-y+x'"
            )
        return cls(_axes_matrix(parts[0], spec), parts[1] == "R^T", _axes_matrix(parts[2], spec))

    def rotations(self, stored: np.ndarray) -> np.ndarray:
        """(..., 3, 3) the object-to-camera rotations of stored ones (..., 3, 3)."""
        stored = np.asarray(stored, dtype=np.float64)
        inner = np.swapaxes(stored, -1, -2) if self.transposed else stored
        return self.left @ inner @ self.right

    def poses(self, stored: np.ndarray) -> np.ndarray:
        """(..., 4, 4) poses with their rotations read by this convention (NaN stays NaN)."""
        out = np.array(stored, dtype=np.float64)
        out[..., :3, :3] = self.rotations(out[..., :3, :3])
        return out


STANDARD = RotationConvention()


def _carried(keypoints: np.ndarray, poses: np.ndarray) -> np.ndarray | None:
    """The frames (indices) where the hand is tracked and the object more than
    :data:`CARRIED_M` from its first pose; None if fewer than :data:`MIN_CARRIED_FRAMES`."""
    tracked = np.isfinite(keypoints).all(axis=(1, 2)) & np.isfinite(poses).all(axis=(1, 2))
    if not tracked.any():
        return None
    first = poses[np.argmax(tracked), :3, 3]
    frames = np.flatnonzero(tracked & (np.linalg.norm(poses[:, :3, 3] - first, axis=1) > CARRIED_M))
    return frames if len(frames) >= MIN_CARRIED_FRAMES else None


def _angle_deg(rotations: np.ndarray) -> np.ndarray:
    cos = (np.trace(rotations, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def carry_spread_deg(
    keypoints: Sequence[np.ndarray], poses: Sequence[np.ndarray]
) -> tuple[np.ndarray, int]:
    """The session's carry spread (the module docstring's fact 1) for every ``op`` and every
    ``L`` of :data:`CUBE`.

    Args:
        keypoints: Per sequence, (T, 21, 3) in dexflow's order, NaN where not tracked.
        poses: Per sequence, (T, 4, 4) stored object poses, NaN where not annotated.

    Returns:
        ``(spread (2, 24) degrees, row 0 as stored and row 1 transposed, NaN if no carry turns;
        turning carries)``.
    """
    spreads = []
    for kp, pose in zip(keypoints, poses, strict=True):
        frames = _carried(np.asarray(kp), np.asarray(pose))
        if frames is None:
            continue
        hand = wrist_frame(kp[frames])[:, :3, :3]  # (K, 3, 3)
        middle_hand = hand[len(frames) // 2]
        if np.median(_angle_deg(middle_hand.T @ hand)) < TURNING_DEG:
            continue
        stored = pose[frames, :3, :3]
        inner = np.stack([stored, np.swapaxes(stored, -1, -2)])  # op: (2, K, 3, 3)
        # relative rotation Hᵀ L op(R) for every op and L: (2, 24, K, 3, 3); B cancels
        relative = np.swapaxes(hand, -1, -2) @ CUBE[:, None] @ inner[:, None]
        middle = relative[..., len(frames) // 2, :, :]
        turned = np.swapaxes(middle, -1, -2)[..., None, :, :] @ relative
        spreads.append(np.median(_angle_deg(turned), axis=-1))
    if not spreads:
        return np.full((2, len(CUBE)), np.nan), 0
    return np.median(np.stack(spreads), axis=0), len(spreads)


@dataclass(frozen=True)
class ConventionCheck:
    """What :func:`check_convention` found for a session.

    Attributes:
        found: The convention the evidence picks (:data:`STANDARD` unless clearly better).
        carry_spread_deg: ``{"as-stored": ..., "found": ...}`` (the module docstring's fact 1).
        start_spread_m: The same for fact 2.
        carried_sequences: Carries that turn (:data:`TURNING_DEG`), whose spread was measured.
        rests: Captures whose first pose was measured.
        reason: Why the standard convention was kept, if it was for lack of evidence.
    """

    found: RotationConvention
    carry_spread_deg: dict[str, float | None]
    start_spread_m: dict[str, float | None]
    carried_sequences: int
    rests: int
    reason: str | None = None

    def record(self) -> dict:
        """The ``convert.json`` entry."""
        return {
            "found": str(self.found),
            "carry_spread_deg": self.carry_spread_deg,
            "start_spread_m": self.start_spread_m,
            "carried_sequences": self.carried_sequences,
            "rests": self.rests,
            **({"reason": self.reason} if self.reason else {}),
        }

    def summary(self) -> str:
        def both(values: dict[str, float | None], scale: float, unit: str) -> str:
            return " -> ".join(
                "n/a" if values[k] is None else f"{values[k] * scale:.1f} {unit}"
                for k in ("as-stored", "found")
            )

        return (
            f"carried objects turn against the hand {both(self.carry_spread_deg, 1, 'deg')} "
            f"({self.carried_sequences} turning carries), start heights spread "
            f"{both(self.start_spread_m, 100, 'cm')} ({self.rests} rests)"
        )


def _number(value: float) -> float | None:
    """A score for ``convert.json``: None where it could not be measured (NaN)."""
    return None if np.isnan(value) else float(value)


def check_convention(
    keypoints: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    hulls: Sequence[np.ndarray],
    rests: Sequence[np.ndarray],
) -> ConventionCheck:
    """Find the convention of a session's stored object rotations (the module docstring).

    Args:
        keypoints: Per sequence, (T, 21, 3) in dexflow's order, NaN where not tracked, in the
            frame of the stored poses (a camera's).
        poses: Per sequence, (T, 4, 4) stored object poses, NaN where not annotated.
        hulls: Per resting capture, (V, 3) its object's convex-hull vertices (object frame).
        rests: Per resting capture, (4, 4) its stored pose at its first tracked frame.

    Returns:
        The check; ``found`` is :data:`STANDARD` when the evidence is too thin (fewer than
        :data:`MIN_TURNING` turning carries or :data:`~dexflow.data.table.MIN_CAPTURES` rests).
    """
    spread, carried = carry_spread_deg(keypoints, poses)  # (2, 24): as stored, transposed
    rest_stack = np.asarray(rests, dtype=np.float64).reshape(-1, 4, 4)

    def starts(convention: RotationConvention) -> float:
        return start_spread(hulls, convention.poses(rest_stack)) if len(rests) else np.nan

    standard = (spread[0, 0], starts(STANDARD))
    reason = None
    if carried < MIN_TURNING:
        reason = (
            f"{carried} carries turn by {TURNING_DEG:.0f} deg or more, too few "
            f"(at least {MIN_TURNING})"
        )
    elif len(rests) < MIN_CAPTURES:
        reason = f"{len(rests)} rests, too few (at least {MIN_CAPTURES})"
    found, scores = STANDARD, standard
    if reason is None:
        # op and L by the carry spread (ties keep the standard, then the identity: index 0)
        op = min((False, True), key=lambda o: (round(np.nanmin(spread[int(o)]), 1), o))
        left_index = int(np.argmin(np.round(spread[int(op)], 1)))
        left = CUBE[left_index]
        right_starts = [starts(RotationConvention(left, op, right)) for right in CUBE]
        right_index = int(np.argmin(np.round(right_starts, 4)))  # ties: 0.1 mm, identity first
        candidate = RotationConvention(left, op, CUBE[right_index])
        candidate_scores = (spread[int(op), left_index], right_starts[right_index])
        if not candidate.is_standard and all(
            c <= CLEARLY_BETTER * s for c, s in zip(candidate_scores, standard, strict=True)
        ):
            found, scores = candidate, candidate_scores
    return ConventionCheck(
        found=found,
        carry_spread_deg={"as-stored": _number(standard[0]), "found": _number(scores[0])},
        start_spread_m={"as-stored": _number(standard[1]), "found": _number(scores[1])},
        carried_sequences=carried,
        rests=len(rests),
        reason=reason,
    )
