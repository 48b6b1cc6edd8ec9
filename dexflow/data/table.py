"""The table's frame of a capture session: its up vector fitted from the objects resting on it.

Camera-frame datasets (the HO-3D layout) give no vertical, and one capture's motion does not
reveal it. A session's captures do, where they share one camera and one table: at each capture's
first tracked frame its object rests on the table, so the lowest point of the object's convex
hull along the true up ``u`` lies at about the same height in every capture, and no capture
takes its object below that height. With ``s_i(u)`` that start height of capture ``i`` and
``l_i(u)`` the lowest height its object reaches over its tracked frames, the fit minimises over
the unit sphere

    ``f(u) = trimmed_mean_i |s_i(u) - median_j s_j(u)| + mean_i (s_i(u) - l_i(u))``

(the trimmed mean keeps the 80 % smallest deviations: a capture whose object starts in the hand
does not pull the plane). The sign comes with it: along ``-u`` every lift is a dip.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from dexflow.geometry import transform_points

__all__ = [
    "DIP_M",
    "MAX_START_MAD_M",
    "MIN_CAPTURES",
    "TableFit",
    "fit_table",
    "start_spread",
    "table_frame",
]

DIP_M = 0.02  # a capture whose object goes this far below its start height "dips"
MIN_CAPTURES = 8  # fewer captures fit no table reliably
MAX_START_MAD_M = 0.03  # start heights spread wider than this: no one table (or no one camera)
_KEPT = 0.8  # share of the start heights the trimmed mean keeps
_COARSE = 256  # directions tried over the whole sphere before the local search
_CAMERA_UP = np.array([0.0, -1.0, 0.0])  # image rows grow downwards: a level camera's up is -y


@dataclass(frozen=True)
class TableFit:
    """The table of a session, in the frame the captures are given in (a camera's).

    Attributes:
        up: (3,) unit normal of the table, pointing from it to the objects.
        height_m: The table plane's offset along ``up`` (median start height): the plane is
            ``{p: up . p = height_m}``.
        start_height_mad_m: Median absolute deviation of the captures' start heights.
        dip_share: Share of the captures whose object goes more than :data:`DIP_M` below its
            start height.
        num_captures: Captures the fit used.
    """

    up: np.ndarray
    height_m: float
    start_height_mad_m: float
    dip_share: float
    num_captures: int


class _Heights:
    """The lowest hull point of every capture's object at every tracked frame, along ``u``."""

    def __init__(self, hulls: Sequence[np.ndarray], poses: Sequence[np.ndarray]) -> None:
        points, frame_sizes, capture_sizes = [], [], []
        for hull, pose in zip(hulls, poses, strict=True):
            hull, pose = np.asarray(hull, dtype=np.float64), np.asarray(pose, dtype=np.float64)
            points.append(transform_points(pose, hull).reshape(-1, 3))  # (T * V, 3)
            frame_sizes += [len(hull)] * len(pose)
            capture_sizes.append(len(pose))
        self.points = np.concatenate(points)
        self.frame_starts = np.concatenate([[0], np.cumsum(frame_sizes)[:-1]])
        self.capture_starts = np.concatenate([[0], np.cumsum(capture_sizes)[:-1]])

    def __call__(self, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(start (C,), lowest (C,))``: each capture's height at its first frame and its
        lowest over all its frames."""
        frame_low = np.minimum.reduceat(self.points @ up, self.frame_starts)
        return frame_low[self.capture_starts], np.minimum.reduceat(frame_low, self.capture_starts)

    def cost(self, up: np.ndarray) -> float:
        start, lowest = self(up)
        spread = np.sort(np.abs(start - np.median(start)))
        return float(spread[: max(1, int(_KEPT * len(start)))].mean() + (start - lowest).mean())


def _sphere(n: int) -> np.ndarray:
    """(n, 3) directions spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    angle = np.pi * (1.0 + 5**0.5) * i
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(angle), r * np.sin(angle), z], axis=1)


def _local_search(heights: _Heights, start: np.ndarray, step: float) -> tuple[np.ndarray, float]:
    """Nelder-Mead on the tangent plane at ``start``: ``u(a, b) = normalise(start + a e1 + b e2)``
    reaches the open hemisphere around it without the poles of spherical angles."""
    e1 = np.cross(start, [1.0, 0.0, 0.0] if abs(start[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(start, e1)

    def direction(ab: np.ndarray) -> np.ndarray:
        u = start + ab[0] * e1 + ab[1] * e2
        return u / np.linalg.norm(u)

    result = minimize(
        lambda ab: heights.cost(direction(ab)),
        np.zeros(2),
        method="Nelder-Mead",
        options={
            "initial_simplex": [[0.0, 0.0], [step, 0.0], [0.0, step]],
            "xatol": 1e-5,
            "fatol": 1e-7,
        },
    )
    return direction(result.x), float(result.fun)


def _best_up(heights: _Heights) -> tuple[np.ndarray, float]:
    """The up vector minimising ``heights.cost`` and its cost: a coarse search over
    :data:`_COARSE` directions of the whole sphere, then Nelder-Mead from the three best and
    from the camera's ``-y``, and once more from the best result."""
    coarse = _sphere(_COARSE)
    costs = np.array([heights.cost(u) for u in coarse])
    starts = [*coarse[np.argsort(costs)[:3]], _CAMERA_UP]
    found = [_local_search(heights, s, 0.1) for s in starts]
    up, _ = min(found, key=lambda f: f[1])
    return _local_search(heights, up, 0.01)


def start_spread(hulls: Sequence[np.ndarray], rests: np.ndarray) -> float:
    """How far a session's resting objects are from lying on one plane: the trimmed mean
    deviation of their lowest hull points' heights from the median height, minimised over up
    vectors (the first term of the module docstring's ``f``, metres).

    Args:
        hulls: Per capture, (V_i, 3) convex-hull vertices of its object, in the object's frame.
        rests: (C, 4, 4) each capture's object-to-camera pose at rest.
    """
    return _best_up(_Heights(hulls, [pose[None] for pose in np.asarray(rests)]))[1]


def fit_table(hulls: Sequence[np.ndarray], poses: Sequence[np.ndarray]) -> TableFit:
    """Fit the table's up vector to a session's captures (the module docstring's ``f``).

    The search: :func:`_best_up`.

    Args:
        hulls: Per capture, (V_i, 3) convex-hull vertices of its object, in the object's frame.
        poses: Per capture, (T_i, 4, 4) object-to-camera poses at its tracked frames, in order:
            the first is the one where the object rests on the table.

    Returns:
        The fit, in the poses' frame.

    Raises:
        ValueError: No capture, or a capture without frames.
    """
    if not len(poses) or any(len(p) == 0 for p in poses):
        raise ValueError("fit_table needs at least one capture, each with a frame")
    heights = _Heights(hulls, poses)
    up, _ = _best_up(heights)
    start, lowest = heights(up)
    return TableFit(
        up=up,
        height_m=float(np.median(start)),
        start_height_mad_m=float(np.median(np.abs(start - np.median(start)))),
        dip_share=float(np.mean(start - lowest > DIP_M)),
        num_captures=len(start),
    )


def table_frame(fit: TableFit) -> np.ndarray:
    """(4, 4) camera-to-table transform: the smallest rotation taking ``fit.up`` to +z (about
    the camera's centre), then a shift along z putting the table plane at z = 0. The origin is
    the foot of the camera on the table; the camera's heading is kept as far as it can be."""
    up = fit.up / np.linalg.norm(fit.up)
    axis = np.cross(up, [0.0, 0.0, 1.0])
    angle = np.arctan2(np.linalg.norm(axis), up[2])
    if np.linalg.norm(axis) < 1e-12:  # up is +z or -z: a half turn about x when it is -z
        axis = np.array([1.0, 0.0, 0.0])
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    out[2, 3] = -fit.height_m
    return out
