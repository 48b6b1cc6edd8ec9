"""Stage refine (paper §III-D): per-finger contact refinement with five energies (and one more).

For every frame (batched over frames) the fingers are optimised one at a time, in
``finger_order`` (thumb to little by default); only the current finger's joints move (tendon
followers follow their leaders) and a finger without contact in a frame is left as it is:

    E = E_dis + w_pen E_pen + w_align E_align + w_spen E_spen + w_joints E_joints + w_tip E_tip
        (+ w_smooth E_smooth)

- ``E_dis = Σ ||p_i - o_i||²``: the finger's contact points (contact map) to their object points;
- ``E_pen = Σ max(0, m - sd(p))²`` over the finger's surface points (signed distance grid of
  the object, trilinear and differentiable; negative inside), ``m = pen_margin_m`` (0: only
  points inside count; a small margin makes up for the gaps between sampled points);
- ``E_align = Σ (1 + n_i · n_Oi)²``: the hand surface normal at a contact point against the object's
  outward normal there; a flush contact (the normals opposite) scores 0;
- ``E_spen = Σ max(δ - ||p - q||, 0)`` between the finger's points and the other fingers' and
  the palm's (subsampled), ``δ = spen_delta_m``;
- ``E_joints = ||θ - θ_init||²`` keeps the retargeted pose;
- ``E_tip = ||Δ||² - (Δ·n)²`` (dexflow's addition): ``Δ = v_tip(θ) - g`` the miss of the
  finger's fingertip keypoint from its target ``g`` (**Fingertip targets** below), measured
  across the object's outward normal ``n`` at ``g``. Nothing else in the step holds a tip, and
  a finger that frees its pad with its own joints (the palm cannot move here) swung its tip
  across the surface: 9 mm on real captures without E_tip, 5 mm with it. Along the normal the
  tip stays free, so E_dis and E_pen close a gap or free a pad as before;
- ``E_smooth = Σ ||θ_t - 2θ_{t-1} + θ_{t-2}||²`` over consecutive refined frames (optional), so
  refinement does not add jitter.

The change made by refinement is finally smoothed over time (Gaussian, ``blend_frames``) so that
it ramps in and out around contacts instead of stepping between refined and untouched frames.

**Whole-hand release** (``release: true``; dexflow's addition to the paper). On real captures the
human hand sits a few millimetres inside the scanned object while holding it (annotation and
object-pose error), the palm and the proximal links included. Moving only the contact fingers
cannot free a palm that is inside the object: the fingers are bent away from the motion and the
palm stays in. So, before the per-finger step and again after the blending, every degree of
freedom (floating base and all joints) of every frame is optimised jointly:

    E_rel = w_pen Σ_t Σ_p max(0, m - sd(p))²                 (every hand surface point)
          + w_touch Σ_t Σ_{f in contact} max(0, min_{p∈f} sd(p))²   (contact fingers keep touching)
          + w_track Σ_t Σ_k w_k ||v^k(q_t) - g^k_t||²         (keypoints stay on their targets)
          + w_smooth Σ_t ||Δ̈v_t||² + w_smooth_joints Σ_t ||Δ̈θ_t||²   (no added jitter)
          + w_joints Σ_t ||Δθ_t||²                                  (no drift unseen above)

with ``g^k_t`` the fingertip targets for the fingertip keypoints and ``v^k(q_t^0)`` (where
retargeting put them) for the others, ``Δv = v(q) - v(q^0)`` the change of the keypoints,
``Δθ`` that of the hand joints and
``Δ̈`` second differences over frames; ``w_k`` is ``release_tip_weight`` for the fingertip
keypoints and 1 for the others, so that the palm and the proximal links give way before the
fingertips (what the motion is judged by) do. The last term (``release_w_joints``, small) makes
the optimum unique where joints can move without moving a keypoint (a thumb with more joints
than keypoints): a change growing linearly over the frames has no second difference, so without
it such a joint drifted by up to 0.5 rad over a sequence. The hand backs out of the object as a
whole, the fingers flex back onto it, and the change varies smoothly over time. It is solved by L-BFGS
over all frames at once (``release_iterations``; ``release_first_iterations`` for the release
before the per-finger step, which only has to get the palm out of the way: the last one starts
from the finger step's result; over each window of a long sequence), in
coordinates where the tracking and smoothness terms have unit curvature along time
(:func:`temporal_preconditioner`: the same energy and optimum, reached in fewer iterations). A
quadratic penalty trades depth against the other terms, so the deepest frames of a real capture
(fingers 2 cm inside the scan) would keep part of theirs: the last release is solved again
(``release_rounds``) with ten times the ``w_pen`` of every frame still deeper than
``release_depth_m`` (a penalty continuation), which bounds the worst frame and not only the
mean. Only the hand points that can matter enter the penetration and contact terms of a solve
(``release_reach_m``, 3 cm: points farther from the object add exactly 0 to E_pen; every point
of a finger in contact stays in), which makes the release about 2.5x faster without changing
its result.

**Fingertip targets** (``surface_tips: true``). The fingertip error of refine is read against
the human fingertips pushed out onto the object's surface
(:func:`~dexflow.human.surface_tips.surface_corrected_tips`): on real captures the annotated
tips lie millimetres inside the scan, and a hand that penetrates nowhere cannot reach them. The
release and E_tip track exactly those targets on observed frames (:func:`fingertip_targets`;
the retargeted tips on the frames retargeting bridged). Before, both tracked the retargeted
tips, and refine moved the fingertips near the object 6.6 mm along the normal and 6.2 mm across
it (Shadow, 28 DexYCB captures): the retargeted tips lie ~5 mm deeper than the human's where
those are inside (10 mm below the surface-corrected tip along the normal), and the release,
freeing the distal links while the palm, the middle links and the knuckles keep their
retargeted places and the change stays smooth, could hold no tip there; the per-finger step
(no term holding a tip) swung them further. Pushing only the targets out (the retargeted tip
plus the human tip's correction) changed nothing (8.4 mm against the surface tips); tracking
the surface-corrected human tips brought refine's error against them from 8.4 to 6.3 mm, that
of retargeting 6.3 mm (10 captures). The Shadow's fingertip keypoints lie ~5 mm inside its
distal links (7.7 mm the thumb's), so near a contact its tips stay about that far from tips on
the surface: a floor that no penetration-free pose beats.

**Grip where physics lost the object** (``grip_m > 0``; off by default). Stage replay plays the
retargeted trajectory back with the object free; where that lost the object, the fingers in
contact from ``grip_lead_frames`` before the loss to the end are pressed ``grip_m`` into the
object after everything above (:func:`grip_trajectory`), since a position-controlled finger grips
only as hard as its target lies inside the object. Measured (12 sequences each, Shadow,
``grip_m`` 0 / 5 / 10 mm, the refined trajectory replayed): DexYCB dev captures held the object
for 10.5 / 7.9 / 8.2 % of the grasp and carried 1 / 1 / 0 of 12, with PD 0.84 / 5.4 / 7.1 mm
and SSR 50 / 0 / 0 % (Allegro: held 11.1 / 7.0 / 10.8 %, carried none, PD 0.76 / 7.1 / 8.7 mm,
SSR 25 / 0 / 0 %); the demo held 42 / 45 / 47 % and carried 0 / 0 / 1, PD 1.0 / 3.4 / 4.9 mm,
SSR 25 / 8 / 8 %. No gain beyond one sequence, a clear loss in penetration and SSR: off.

**Windows.** A sequence longer than ``window_frames`` is refined window by window (overlapping
by ``window_overlap`` frames, cross-faded there), so that memory is bounded by a window: the
release is then solved over all frames of a window at once.

Joint limits hold exactly (projection after every step and after blending). Metres.

**One file** (about 1000 lines): stage refine's energies, the per-finger solver that minimises them and the
windows it runs over share the notation of the energies (this docstring); apart, a term would be
read without the solver that weighs it.
"""

from __future__ import annotations

import itertools
import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import scipy.linalg
import torch

from dexflow.errors import ArtifactError
from dexflow.geometry import rotate_vectors, transform_points
from dexflow.hands.files import staged_spec
from dexflow.hands.robot import RobotHand, cached_hand, measurement_hand
from dexflow.human.keypoints import FINGERS, FINGERTIPS
from dexflow.human.surface_tips import surface_corrected_tips
from dexflow.io.artifacts import (
    ObjectAssets,
    Trajectory,
    read_contact,
    read_trajectory,
    write_trajectory,
)
from dexflow.io.layout import Layout
from dexflow.io.sequence import load_sequence
from dexflow.measures import (
    capped_contact_distance,
    fingertips,
    finite_mean,
    frame_chunks,
    hand_object_depths,
    rms_acceleration,
)
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import PipelineParams, RefineParams
from dexflow.pipeline.resume import StageOutput
from dexflow.pipeline.runner import StageSpec

__all__ = [
    "STAGE",
    "TorchSDF",
    "energy_terms",
    "fingertip_targets",
    "hand_object_measures",
    "refine_trajectory",
    "release_hand",
    "run_refine",
]


class TorchSDF:
    """A :class:`SignedDistanceGrid` queried in torch: trilinear, differentiable.

    The value is :meth:`SignedDistanceGrid.query`'s: trilinear inside the grid, outside it the
    value at the nearest point of the grid box plus the distance to the box. The gradient is
    computed without an autograd graph, in the backward pass and only at the points whose value
    the loss uses (the release and the per-finger step query it on every evaluation, for tens of
    thousands of points, most of which add nothing): the trilinear interpolant's exact
    derivative inside the grid, zero across the grid's boundary
    along a coordinate that sits on it (as ``torch.nn.functional.grid_sample`` with border
    padding), plus the unit vector away from the box outside it. The cells' corner values are
    stored as eight rows (8, cells) (float32, as the grid holds them), so a point's corners are
    one column, gathered with ``index_select``.
    """

    def __init__(self, grid: SignedDistanceGrid, dtype=torch.float64) -> None:
        values = torch.as_tensor(grid.values)
        size = torch.tensor(values.shape)
        self.origin = torch.as_tensor(grid.origin, dtype=dtype)
        self.upper = torch.as_tensor(grid.upper, dtype=dtype)
        self.scale = (size - 1).to(dtype) / (self.upper - self.origin)  # index per metre
        self.top = (size - 2).to(dtype)  # the last cell's first index, per axis
        nx, ny, nz = (int(n) - 1 for n in size)  # cells per axis
        corners = [
            values[i : nx + i, j : ny + j, k : nz + k]
            for i in (0, 1)
            for j in (0, 1)
            for k in (0, 1)
        ]  # corner (i, j, k) of every cell is row 4i + 2j + k
        self.corners = torch.stack([c.reshape(-1) for c in corners])  # (8, cells)
        self.cell_stride = torch.tensor([ny * nz, nz, 1])

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        """Signed distance (...,) at points (..., 3)."""
        return _GridDistance.apply(points.reshape(-1, 3), self).reshape(points.shape[:-1])

    def value(self, flat: torch.Tensor) -> torch.Tensor:
        """Signed distance (N,) at points ``flat (N, 3)``."""
        return self._interpolate(flat, gradient=False)[0]

    def value_and_gradient(self, flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance (N,) and its gradient (N, 3) at points ``flat (N, 3)``."""
        value, grad = self._interpolate(flat, gradient=True)
        assert grad is not None
        return value, grad

    def _interpolate(
        self, flat: torch.Tensor, gradient: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        clamped = torch.maximum(torch.minimum(flat, self.upper), self.origin)
        away = flat - clamped
        outside = torch.linalg.vector_norm(away, dim=-1)
        c = (clamped - self.origin) * self.scale  # continuous grid index
        first = torch.clamp(c.floor(), min=0).minimum(self.top)
        f = (c - first).T.contiguous()  # (3, N)
        cell = (first.long() * self.cell_stride).sum(-1)
        # (8, N): each point's column of corners, gathered at once (index_select is ~5x faster
        # than advanced indexing), so that every slice below is contiguous
        v = torch.index_select(self.corners, 1, cell).to(flat.dtype)
        fx, fy, fz = f[0], f[1], f[2]
        dx = v[4:8] - v[0:4]
        along_x = v[0:4] + dx * fx  # (4, N): corners (y, z)
        dy = along_x[2:4] - along_x[0:2]
        along_y = along_x[0:2] + dy * fy  # (2, N): corners z
        gz = along_y[1] - along_y[0]
        value = along_y[0] + gz * fz + outside
        if not gradient:
            return value, None
        dx_y = dx[0:2] + (dx[2:4] - dx[0:2]) * fy
        gx = dx_y[0] + (dx_y[1] - dx_y[0]) * fz
        gy = dy[0] + (dy[1] - dy[0]) * fz
        within = (c > 0) & (c < self.top + 1)  # not on the boundary along that axis
        grad = torch.where(within, torch.stack([gx, gy, gz], -1) * self.scale, 0.0)
        grad = grad + away / torch.where(outside > 0, outside, 1.0)[:, None]
        return value, grad


class _GridDistance(torch.autograd.Function):
    """:meth:`TorchSDF.value` as an autograd function of the points.

    The forward pass computes the values alone; the backward pass computes the gradient only
    at the points whose value the loss uses (a nonzero upstream gradient: the few points inside
    or within the margin, each finger's nearest point), from the same arithmetic as
    :meth:`TorchSDF.value_and_gradient`. The release's penalties are zero at most points, so
    this skips most of the gradient's work; the points left out contribute exactly 0.
    """

    @staticmethod
    def forward(ctx, flat: torch.Tensor, sdf: TorchSDF) -> torch.Tensor:
        ctx.save_for_backward(flat)
        ctx.sdf = sdf
        return sdf.value(flat)

    @staticmethod
    def backward(ctx, upstream: torch.Tensor):
        (flat,) = ctx.saved_tensors
        active = torch.nonzero(upstream).flatten()
        out = torch.zeros_like(flat)
        if len(active):
            _, grad = ctx.sdf.value_and_gradient(torch.index_select(flat, 0, active))
            out.index_copy_(0, active, upstream[active, None] * grad)
        return out, None


def hand_object_measures(
    hand: RobotHand,
    q: np.ndarray,
    obj_pose: np.ndarray,
    sdf: SignedDistanceGrid,
    contact: np.ndarray,
    spen_delta_m: float,
) -> dict[str, np.ndarray]:
    """Per-frame measures of what refinement changes (metres), each the metrics stage's own.

    - ``pd``: penetration depth on every collision shape
      (:func:`~dexflow.hands.robot.measurement_hand`, :func:`dexflow.measures.penetration_depth`:
      the metrics stage's ``pd_mm``);
    - ``cd``: BODex's contact distance on the grasp frames,
      :func:`dexflow.measures.capped_contact_distance` (``cd_mm``);
    - ``finger_overlap``: the largest ``δ - d`` (clipped at 0) between surface points of
      different fingers (subsampled): what E_spen penalises, not the link self-penetration of
      the metrics stage's ``spd_mm``.
    """
    pd, per_finger = hand_object_depths(measurement_hand(hand), q, obj_pose, sdf)
    cd = capped_contact_distance(per_finger, np.asarray(contact, dtype=bool).any(axis=1))
    masks = list(hand.finger_point_masks.values())
    rng = np.random.default_rng(0)
    picks = [
        rng.choice(np.flatnonzero(m), min(48, m.sum()), replace=False) for m in masks if m.any()
    ]
    overlap = np.zeros(len(q))
    for frames in frame_chunks(len(q)):  # memory bounded by a chunk, not the sequence
        with torch.no_grad():
            points = hand.surface(torch.as_tensor(q[frames], dtype=hand.dtype), normals=False)[0]
        points = points.cpu().numpy()
        for i in range(len(picks)):
            for j in range(i + 1, len(picks)):
                d = np.linalg.norm(points[:, picks[i], None] - points[:, None, picks[j]], axis=-1)
                gap = np.clip(spen_delta_m - d.min(axis=(1, 2)), 0, None)
                overlap[frames] = np.maximum(overlap[frames], gap)
    return {"pd": pd, "cd": cd, "finger_overlap": overlap}


def fingertip_targets(
    hand: RobotHand,
    q_init: np.ndarray,
    human: np.ndarray,
    observed: np.ndarray,
    obj_pose: np.ndarray,
    sdf: SignedDistanceGrid,
    surface_tips: bool = True,
) -> np.ndarray:
    """Where refinement holds the fingertip keypoints (``tip_targets`` of
    :func:`refine_trajectory`), world frame.

    With ``surface_tips``: on observed frames the human fingertips, those inside the object
    moved out onto its surface (:func:`~dexflow.human.surface_tips.surface_corrected_tips`: the
    physically possible targets, which refine's fingertip error is read against); on the other
    frames (retargeting bridged them) the fingertips of ``q_init``. Without: the fingertips of
    ``q_init`` everywhere (the retargeted tips, which on real captures lie deeper in the object
    than the human's; what refinement tracked before the surface-corrected tips).

    Args:
        q_init: (T, dof) retargeted trajectory.
        human: (T, K, 3) human keypoints matched to the hand's keypoints.
        observed: (T,) frames with a real observation.
        obj_pose: (T, 4, 4) object poses.
        sdf: The object's signed distance grid.

    Returns:
        (T, tips, 3) targets of ``hand.fingertip_keypoints``.
    """
    retargeted = fingertips(hand, q_init)
    if not surface_tips:
        return retargeted
    corrected = surface_corrected_tips(
        np.asarray(human)[:, hand.fingertip_keypoints], obj_pose, sdf
    )
    return np.where(np.asarray(observed, dtype=bool)[:, None, None], corrected, retargeted)


def refine_trajectory(
    hand: RobotHand,
    q_init: np.ndarray,
    obj_pose: np.ndarray,
    sdf: TorchSDF,
    contact: np.ndarray,
    cmap: dict[str, np.ndarray],
    params: RefineParams,
    tip_targets: np.ndarray | None = None,
):
    """Refine a trajectory ``q_init (T, dof)`` against contacts ``(T, F)`` and their map.

    A sequence longer than ``params.window_frames`` is refined in windows of that many frames
    overlapping by ``params.window_overlap``: each window is refined on its own and the shared
    frames are cross-faded (a linear ramp from one window's result to the next), so that memory
    is bounded by the window whatever the length. Shorter sequences are refined whole.

    Args:
        tip_targets: (T, tips, 3) where the fingertip keypoints (``hand.fingertip_keypoints``)
            should be, world frame: the release tracks them and E_tip holds the fingers to
            them (:func:`fingertip_targets`). None: the fingertips of ``q_init``.

    Returns:
        refined q (T, dof), per-frame energies before and after (T,).
    """
    if tip_targets is None:
        tip_targets = fingertips(hand, q_init)
    n, window = len(q_init), params.window_frames
    if window <= 0 or n <= window:
        return _refine_whole(hand, q_init, obj_pose, sdf, contact, cmap, params, tip_targets)
    q = np.zeros_like(q_init, dtype=float)
    energy_before, energy_after = np.zeros(n), np.zeros(n)
    end = 0  # of the previous window
    for i, (a, b) in enumerate(_windows(n, window, params.window_overlap)):
        part = dict(cmap)  # the contact map's rows of this window, frames counted from a
        if "map_frame" in cmap:
            rows = (cmap["map_frame"] >= a) & (cmap["map_frame"] < b)
            part = {k: v[rows] for k, v in cmap.items()}
            part["map_frame"] = part["map_frame"] - a
        qw, e0, e1 = _refine_whole(
            hand, q_init[a:b], obj_pose[a:b], sdf, contact[a:b], part, params, tip_targets[a:b]
        )
        # weight of this window's result: 1, but a ramp over the frames shared with the last
        shared = end - a if i else 0
        ramp = np.ones(b - a)
        ramp[:shared] = np.arange(1, shared + 1) / (shared + 1)
        q[a:b] = (1 - ramp[:, None]) * q[a:b] + ramp[:, None] * qw
        energy_before[a:b] = (1 - ramp) * energy_before[a:b] + ramp * e0
        energy_after[a:b] = (1 - ramp) * energy_after[a:b] + ramp * e1
        end = b
    with torch.no_grad():  # a blend of two valid poses: limits hold, ties restored
        q = hand.clamp(hand.apply_couplings(torch.as_tensor(q, dtype=hand.dtype))).numpy()
    return q, energy_before, energy_after


def _windows(n: int, window: int, overlap: int) -> list[tuple[int, int]]:
    """``(start, end)`` of the fewest windows of equal length (at most ``window``) covering
    ``n > window`` frames with neighbours sharing at least ``overlap`` frames, evenly spaced
    (so that the last is not a short remainder)."""
    k = math.ceil((n - overlap) / (window - overlap))
    length = math.ceil((n + (k - 1) * overlap) / k)
    while True:
        starts = [round(i * (n - length) / (k - 1)) for i in range(k)]
        shared = min(length - (b - a) for a, b in itertools.pairwise(starts))
        if shared >= overlap or length >= window:
            return [(a, a + length) for a in starts]
        length += 1  # rounding the starts took a frame off an overlap


def _refine_whole(
    hand: RobotHand,
    q_init: np.ndarray,
    obj_pose: np.ndarray,
    sdf: TorchSDF,
    contact: np.ndarray,
    cmap: dict[str, np.ndarray],
    params: RefineParams,
    tip_targets: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`refine_trajectory` of one window (or of a whole short sequence): release, the
    per-finger step, blending, release again. Same arguments and returns."""
    inv = torch.as_tensor(np.linalg.inv(obj_pose), dtype=hand.dtype)
    q_start = q_init
    if params.release:
        first = replace(params, release_iterations=params.release_first_iterations)
        q_start = release_hand(
            hand, q_init, inv, sdf, contact, first, rounds=1, tip_targets=tip_targets
        )
    q, energy_before, energy_after = _finger_step(
        hand, q_start, inv, sdf, contact, cmap, params, tip_targets
    )
    if params.release:
        q = release_hand(
            hand, q, inv, sdf, contact, params, reference=q_init, tip_targets=tip_targets
        )
    return q, energy_before, energy_after


def _finger_step(hand, q_start, world_to_obj, sdf, contact, cmap, params, tip_targets=None):
    """The per-finger step from ``q_start (T, dof)``: every finger of ``params.finger_order``
    in turn, in the frames where it is in contact; then the change blended over time.
    ``tip_targets (T, tips, 3)``: E_tip's targets (None: no E_tip).

    Returns:
        The trajectory (T, dof), per-frame energies before and after (T,).
    """
    fingers = list(hand.spec.fingers)
    q = torch.as_tensor(q_start, dtype=hand.dtype).clone()
    rng = np.random.default_rng(0)
    energy_before = np.zeros(len(q))
    energy_after = np.zeros(len(q))
    for name in params.finger_order:
        if name in fingers:
            _refine_finger(hand, q, name, contact, cmap, world_to_obj, sdf, params, rng,
                           energy_before, energy_after, tip_targets)  # fmt: skip
    q = q.numpy()
    if params.blend_frames > 0:
        q = _blend(hand, q_start, q, params.blend_frames)
    return q, energy_before, energy_after


def release_hand(
    hand: RobotHand,
    q_init: np.ndarray,
    world_to_obj: torch.Tensor,
    sdf: TorchSDF,
    contact: np.ndarray,
    params: RefineParams,
    reference: np.ndarray | None = None,
    rounds: int | None = None,
    tip_targets: np.ndarray | None = None,
) -> np.ndarray:
    """Free the whole hand from the object (``E_rel`` of the module docstring).

    Args:
        q_init: (T, dof) trajectory to start from.
        world_to_obj: (T, 4, 4) inverse object poses.
        contact: (T, F) contact states (fingers in the hand config's order).
        reference: (T, dof) trajectory whose keypoints and joints the change is measured
            against (default ``q_init``).
        rounds: Solves at most (default ``params.release_rounds``); after each, the frames
            still deeper than ``params.release_depth_m`` get ten times their ``w_pen``.
        tip_targets: (T, tips, 3) what the fingertip keypoints track (world frame); default
            the fingertips of ``reference``. The other keypoints track ``reference``'s.

    Returns:
        (T, dof) released trajectory within the joint limits, tendon ties exact.
    """
    free = torch.as_tensor(hand.free_joints)
    q0 = torch.as_tensor(q_init, dtype=hand.dtype)
    ref = q0 if reference is None else torch.as_tensor(reference, dtype=hand.dtype)
    with torch.no_grad():
        kp_ref = hand.keypoints(ref)
    kp_target = kp_ref.clone()
    if tip_targets is not None:
        kp_target[:, hand.fingertip_keypoints] = torch.as_tensor(tip_targets, dtype=hand.dtype)
    masks = torch.as_tensor(np.stack(list(hand.finger_point_masks.values())))  # (F, N)
    touching = torch.as_tensor(np.asarray(contact, dtype=bool))  # (T, F)
    lo, hi = hand.lower[free], hand.upper[free]
    track_w = torch.ones(len(hand.mano_indices), dtype=hand.dtype)
    track_w[hand.fingertip_keypoints] = params.release_tip_weight
    bands = _stacked_bands(temporal_preconditioner(hand, q0, track_w, params))
    z = torch.zeros(len(free), len(q0), dtype=hand.dtype, requires_grad=True)  # delta = L⁻ᵀ z
    margin = params.pen_margin_m
    w_pen = torch.full((len(q0),), params.release_w_pen, dtype=hand.dtype)

    def configuration() -> torch.Tensor:
        q = q0.clone()
        delta = _BandedTransposedSolve.apply(z, *bands).T
        q[:, free] = torch.maximum(torch.minimum(q0[:, free] + delta, hi), lo)
        return hand.apply_couplings(q)

    # every point of a finger that is in contact somewhere: its contact term takes the minimum
    # over all of them, however far (the contact stage may call a finger touching at 1-2 cm)
    contact_points = masks[touching.any(0)].any(0)

    def distances() -> torch.Tensor:
        """(T, N) signed distances of every surface point at the current configuration."""
        with torch.no_grad():
            points, _ = hand.surface(configuration(), normals=False)
            return sdf(transform_points(world_to_obj, points))

    def within_reach(sd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The frames with a surface point within ``release_reach_m`` of the object or a
        finger in contact, and the points within it in any of them plus every point of the
        fingers in contact: the points left out are farther than ``release_reach_m >
        pen_margin_m`` and on no contact finger, so their terms are exactly 0 unless the hand
        moves that far in one solve."""
        close = sd < params.release_reach_m
        frames = torch.nonzero(close.any(-1) | touching.any(-1)).flatten()
        points_used = close[frames].any(0) | contact_points
        return frames, torch.nonzero(points_used).flatten()

    near, index = within_reach(distances())

    def energy() -> torch.Tensor:
        q = configuration()
        transforms = hand.frame_transforms(q)
        total = q.new_zeros(())
        if len(near) and len(index):
            at = torch.index_select(transforms, 0, near)  # faster than [near], and its backward
            points, _ = hand.surface_points(None, index, at, normals=False)
            sd = sdf(transform_points(world_to_obj[near], points))  # (T near, P near)
            total = (w_pen[near] * (torch.relu(margin - sd) ** 2).sum(-1)).sum()
            if touching[near].any():
                mine = masks[:, index]  # (F, P near)
                per_finger = torch.where(mine[None], sd[:, None], torch.inf).amin(-1)
                gap = torch.relu(per_finger[touching[near]])  # every contact finger's points
                total = total + params.release_w_touch * (gap**2).sum()
        keypoints = hand.keypoints(q, transforms)
        miss = keypoints - kp_target
        total = total + params.release_w_track * ((miss**2).sum(-1) * track_w).sum()
        change = keypoints - kp_ref  # what the smoothness terms see: the change refine makes
        joints = q[:, 6:] - ref[:, 6:]
        total = total + params.release_w_joints * (joints**2).sum()
        if len(q) > 2:
            acc = change[2:] - 2 * change[1:-1] + change[:-2]
            total = total + params.release_w_smooth * (acc**2).sum()
            acc_j = joints[2:] - 2 * joints[1:-1] + joints[:-2]
            total = total + params.release_w_smooth_joints * (acc_j**2).sum()
        return total

    def closure() -> torch.Tensor:
        z.grad = None
        e = energy()
        e.backward()
        return e

    solves = params.release_rounds if rounds is None else rounds
    for solve in range(solves):
        torch.optim.LBFGS(
            [z], max_iter=params.release_iterations, line_search_fn="strong_wolfe",
            tolerance_grad=1e-10, tolerance_change=1e-14, history_size=20,
        ).step(closure)  # fmt: skip
        if solve == solves - 1:
            break
        sd = distances()
        deep = torch.relu(-sd.amin(-1)) > params.release_depth_m
        if not deep.any():
            break
        # and the frames up to two away: a second difference ties a frame to them, and raising
        # its weight alone pushed them in (one Shadow frame went from 4 to 9 mm that way)
        deep = torch.nn.functional.max_pool1d(deep[None, None].to(sd.dtype), 5, 1, 2)[0, 0] > 0
        w_pen = torch.where(deep, w_pen * 10, w_pen)
        near, index = within_reach(sd)  # from the same distances: one surface pass a round
    with torch.no_grad():
        return hand.clamp(configuration()).numpy()


def temporal_preconditioner(
    hand: RobotHand, q0: torch.Tensor, track_w: torch.Tensor, params: RefineParams
) -> np.ndarray:
    """Banded Cholesky factors of the release energy's curvature along time, per free joint.

    Without it L-BFGS converges slowly: the smoothness terms stiffen fast changes over frames
    (``w_smooth · 16`` for an alternating one) thousands of times more than the tracking term
    stiffens slow ones (a finger joint moves its tip ~3 cm per radian), and those slow joint
    changes are what the fingertip error is made of. For every free joint ``j`` the curvature
    of the tracking and smoothness terms, with the other joints and the object left out, is

        M_j = diag_t(w_track Σ_k w_k |∂v^k_t/∂q_j|² + w_joints c_j) + b_j D2ᵀD2,
        b_j = w_smooth · mean_t Σ_k |∂v^k_t/∂q_j|² + w_smooth_joints c_j,
        c_j = Σ_i (∂θ_i/∂q_j)²

    (``D2`` the second difference over frames, ``θ`` the hand joints with the tendon followers,
    ``w_joints`` = ``release_w_joints``, keypoint derivatives by finite differences at ``q0``):
    exact for a trajectory that holds one pose, pentadiagonal; with ``M_j = L_j L_jᵀ`` the
    release optimises ``z`` for ``Δq_j = L_j⁻ᵀ z_j``, along which that part of the energy has
    unit curvature. It is the same energy in other coordinates: the optimum does not change,
    L-BFGS reaches it sooner.
    Measured on 8 real captures (Shadow, 60 iterations a solve): refine's fingertip error
    10.5 → 9.9 mm, PD mean 1.39 → 1.15 mm, CD 1.38 → 1.20 mm; 200 iterations give 9.8 mm.

    Returns:
        (F, 3, T) lower banded factors (``scipy.linalg.cholesky_banded`` form), F free joints.
    """
    free, n = hand.free_joints, len(q0)
    step = 1e-5  # rad or m: slopes to 1e-4 relative (FK in float64)
    with torch.no_grad():
        # every free joint moved by `step`, in a block of frames of its own
        moved = q0.repeat(len(free), 1)
        blocks = torch.arange(len(free)).repeat_interleave(n)
        moved[torch.arange(len(moved)), torch.as_tensor(free)[blocks]] += step
        base = hand.keypoints(q0)
        kp = hand.keypoints(hand.apply_couplings(moved)).view(len(free), n, -1, 3)
        slope = (kp - base) / step
        sq = (slope**2).sum(-1)  # (F, T, K)
    ties, _ = hand.coupling_affine()  # ∂q/∂(free joints): a leader moves its followers too
    joint = (ties[6:] ** 2).sum(0)  # Σ_i (∂θ_i/∂q_j)²: 0 for the floating base
    track = (params.release_w_track * (sq * track_w).sum(-1)).numpy()  # (F, T)
    track += params.release_w_joints * joint[:, None]
    smooth = params.release_w_smooth * sq.sum(-1).mean(-1).numpy()
    smooth += params.release_w_smooth_joints * joint
    d2 = _second_difference_gram(n)
    bands = smooth[:, None, None] * d2[None]
    bands[:, 0] += track
    bands[:, 0] += 1e-6 * bands[:, 0].mean(-1, keepdims=True) + 1e-12  # positive definite
    factors = np.stack([scipy.linalg.cholesky_banded(b, lower=True) for b in bands])
    for d in (1, 2):  # outside the matrix: zero, so that the factors stack into one system
        factors[:, d, n - d :] = 0
    return factors


def _second_difference_gram(n: int) -> np.ndarray:
    """``D2ᵀD2`` for ``D2`` the (n-2, n) second difference, in lower banded form (3, n)."""
    gram, rows = np.zeros((3, n)), max(n - 2, 0)
    stencil = (1.0, -2.0, 1.0)  # row r of D2 at frames r, r+1, r+2
    for i in range(3):
        for j in range(i + 1):  # entry (r + i, r + j) of the gram, of every row r at once
            gram[i - j, j : j + rows] += stencil[i] * stencil[j]
    return gram


class _BandedTransposedSolve(torch.autograd.Function):
    """``x_j = L_j⁻ᵀ z_j`` for every row of ``z (F, T)``, with the factors ``L_j`` of
    :func:`temporal_preconditioner` stacked by :func:`_stacked_bands`; the gradient is
    ``L_j⁻¹ g_j``. All rows are one block-diagonal banded system: one LAPACK call each way."""

    @staticmethod
    def forward(ctx, z: torch.Tensor, lower: np.ndarray, upper: np.ndarray) -> torch.Tensor:
        ctx.lower = lower
        x = scipy.linalg.solve_banded((0, 2), upper, z.detach().numpy().ravel())
        return torch.as_tensor(x.reshape(z.shape), dtype=z.dtype)

    @staticmethod
    def backward(ctx, upstream: torch.Tensor):
        g = scipy.linalg.solve_banded((2, 0), ctx.lower, upstream.numpy().ravel())
        return torch.as_tensor(g.reshape(upstream.shape), dtype=upstream.dtype), None, None


def _stacked_bands(lower: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The factors ``L_j`` (F, 3, T) in lower banded form as one block-diagonal system: ``L``
    in lower banded form and ``Lᵀ`` in upper banded form (``u = 2``), each (3, F·T)."""
    n = lower.shape[-1]
    upper = np.zeros_like(lower)
    for d in range(3):  # Lᵀ[j - d, j] = L[j, j - d] = lower[d, j - d]; nothing across blocks
        upper[:, 2 - d, d:] = lower[:, d, : n - d]
    return (
        np.ascontiguousarray(lower.transpose(1, 0, 2)).reshape(3, -1),
        np.ascontiguousarray(upper.transpose(1, 0, 2)).reshape(3, -1),
    )


def energy_terms(
    hand: RobotHand,
    q: torch.Tensor,
    finger_idx: torch.Tensor,
    world_to_obj: torch.Tensor,
    contacts: tuple,
    spen_rows: torch.Tensor,
    fixed_others: torch.Tensor,
    sdf: TorchSDF,
    spen_delta_m: float,
    pen_margin_m: float = 0.0,
    tip: tuple | None = None,
) -> dict[str, torch.Tensor]:
    """Unweighted energies (B,) of one finger at configurations ``q (B, dof)``.

    Args:
        finger_idx: (P,) the finger's surface points (indices into the hand's surface points).
        world_to_obj: (B, 4, 4) inverse object poses.
        contacts: (rows, point, object_points, object_normals): per contact pair its frame row
            (into the batch), its point (into ``finger_idx``), and the object point and outward
            normal in the object frame.
        spen_rows: (S,) finger points (into ``finger_idx``) checked against ``fixed_others``.
        fixed_others: (B, O, 3) other fingers' and palm points, world.
        pen_margin_m: Points closer to the surface than this (or inside) count in ``pen``.
        tip: (keypoint, targets (B, 3), normals (B, 3)): the finger's fingertip keypoint (an
            index into the hand's keypoints), its targets and the object's outward normals
            there, world frame; adds ``tip``, the squared distance across the normal
            (``|Δ|² - (Δ·n)²``, ``Δ`` = fingertip - target). None: no ``tip``.
    """
    rows, hand_rows, obj_pts, obj_nrm = contacts
    transforms = hand.frame_transforms(hand.apply_couplings(q))
    points, normals = hand.surface_points(None, finger_idx, transforms)
    local = transform_points(world_to_obj, points)
    normals_obj = rotate_vectors(world_to_obj, normals)
    zero = torch.zeros(len(q), dtype=q.dtype)
    dis, align = zero, zero
    if len(rows):
        p, n = local[rows, hand_rows], normals_obj[rows, hand_rows]
        dis = zero.index_add(0, rows, ((p - obj_pts) ** 2).sum(-1))
        align = zero.index_add(0, rows, (1 + (n * obj_nrm).sum(-1)) ** 2)
    pen = (torch.relu(pen_margin_m - sdf(local)) ** 2).sum(-1)
    spen = _overlap(points[:, spen_rows], fixed_others, spen_delta_m)
    terms = {"dis": dis, "pen": pen, "align": align, "spen": spen}
    if tip is not None:
        keypoint, targets, tip_normals = tip
        miss = hand.keypoints(None, transforms)[:, keypoint] - targets
        terms["tip"] = (miss**2).sum(-1) - (miss * tip_normals).sum(-1) ** 2
    return terms


def _overlap(points: torch.Tensor, others: torch.Tensor, delta: float) -> torch.Tensor:
    """``Σ max(δ - ||p - o||, 0)`` per batch row over all pairs of ``points (B, S, 3)`` and
    ``others (B, O, 3)``. Only pairs closer than ``δ`` add anything (or any gradient): all pairs
    are measured without gradient and just those (a few of thousands) again with it, which
    makes E_spen, otherwise half of the per-finger step, about ten times cheaper."""
    with torch.no_grad():
        close = torch.nonzero(torch.cdist(points, others) < delta)  # (n, 3): row, s, o
    b, i, j = close.unbind(-1)
    d = torch.linalg.vector_norm(points[b, i] - others[b, j], dim=-1)
    return points.new_zeros(len(points)).index_add(0, b, delta - d)


def _refine_finger(
    hand, q, name, contact, cmap, inv, sdf, params, rng, energy_before, energy_after, tip_targets
) -> None:
    """Optimise one finger's joints in every frame where it is in contact (updates ``q``);
    ``tip_targets (T, tips, 3)`` are the targets of E_tip (see :func:`refine_trajectory`)."""
    fingers = list(hand.spec.fingers)
    lower, upper = hand.lower, hand.upper
    free = set(hand.free_joints)
    f = fingers.index(name)
    frames = np.flatnonzero(contact[:, f])
    if len(frames) == 0:
        return
    joints = [j for j in hand.fingers[name] if j in free]
    if params.refine_base:
        joints = list(range(6)) + joints
    mine = hand.finger_point_masks[name]
    others = ~mine
    finger_idx = torch.as_tensor(np.flatnonzero(mine))
    other_idx = torch.as_tensor(
        rng.choice(np.flatnonzero(others), min(params.spen_points * 4, others.sum()), replace=False)
    )
    spen_idx = torch.as_tensor(
        rng.choice(np.flatnonzero(mine), min(params.spen_points, mine.sum()), replace=False)
    )
    sel = cmap["map_finger"] == f
    row_of = {int(t): i for i, t in enumerate(frames)}
    keep = np.array([int(t) in row_of for t in cmap["map_frame"][sel]], dtype=bool)
    rows = torch.as_tensor([row_of[int(t)] for t in cmap["map_frame"][sel][keep]], dtype=torch.long)
    hand_idx = torch.as_tensor(cmap["map_hand_index"][sel][keep], dtype=torch.long)
    obj_pts = torch.as_tensor(cmap["map_object_point"][sel][keep], dtype=hand.dtype)
    obj_nrm = torch.as_tensor(cmap["map_object_normal"][sel][keep], dtype=hand.dtype)
    base = q[frames].clone()
    theta0 = base[:, joints].clone()
    with torch.no_grad():  # the other fingers do not move while this one is optimised
        fixed_others, _ = hand.surface_points(base, other_idx, normals=False)
    local_index = {int(i): k for k, i in enumerate(finger_idx.tolist())}
    hand_rows = torch.as_tensor([local_index[int(i)] for i in hand_idx.tolist()], dtype=torch.long)
    spen_rows = torch.as_tensor([local_index[int(i)] for i in spen_idx.tolist()], dtype=torch.long)
    theta = theta0.clone().requires_grad_(True)
    frames_t = torch.as_tensor(frames)
    inv_f = inv[frames_t]
    triples = np.flatnonzero(frames[2:] - frames[:-2] == 2) if len(frames) > 2 else []
    consecutive = torch.as_tensor(triples, dtype=torch.long)  # t, t+1, t+2 all refined

    contacts = (rows, hand_rows, obj_pts, obj_nrm)
    tip = _tip_term(hand, name, tip_targets, frames, inv_f, sdf) if params.w_tip > 0 else None
    weights = {
        "dis": params.w_dis,
        "pen": params.w_pen,
        "align": params.w_align,
        "spen": params.w_spen,
        "tip": params.w_tip,
    }

    def energy(theta, per_frame=False):
        qf = base.clone()
        qf[:, joints] = theta
        terms = energy_terms(
            hand, qf, finger_idx, inv_f, contacts, spen_rows, fixed_others, sdf,
            params.spen_delta_m, params.pen_margin_m, tip,
        )  # fmt: skip
        e = sum(weights[k] * v for k, v in terms.items())
        e = e + params.w_joints * ((theta - theta0) ** 2).sum(-1)
        if per_frame:
            return e
        total = e.sum()
        if params.w_smooth > 0 and len(consecutive):
            acc = theta[consecutive + 2] - 2 * theta[consecutive + 1] + theta[consecutive]
            total = total + params.w_smooth * (acc**2).sum()
        return total

    with torch.no_grad():
        energy_before[frames] += energy(theta0, per_frame=True).numpy()
    optimizer = torch.optim.Adam([theta], lr=params.learning_rate)
    lo, hi = lower[joints], upper[joints]
    for _ in range(params.iterations):
        optimizer.zero_grad()
        energy(theta).backward()
        optimizer.step()
        with torch.no_grad():
            theta.copy_(torch.maximum(torch.minimum(theta, hi), lo))
    with torch.no_grad():
        energy_after[frames] += energy(theta, per_frame=True).numpy()
        q[frames_t[:, None], torch.as_tensor(joints)[None]] = theta.detach()
        q[frames_t] = hand.clamp(hand.apply_couplings(q[frames_t]))


def _tip_term(hand, name, tip_targets, frames, world_to_obj, sdf) -> tuple | None:
    """E_tip's arguments for :func:`energy_terms` in ``frames``: the finger's fingertip
    keypoint, its targets and the object's outward normal at each target (world frame); None
    where the hand maps no fingertip keypoint to the finger."""
    mano_tip = FINGERTIPS[FINGERS.index(name)]
    tips = hand.fingertip_keypoints
    column = next((i for i, k in enumerate(tips) if hand.mano_indices[k] == mano_tip), None)
    if column is None or tip_targets is None:
        return None
    targets = torch.as_tensor(tip_targets[frames, column], dtype=hand.dtype)
    local = transform_points(world_to_obj, targets[:, None])[:, 0]
    _, gradient = sdf.value_and_gradient(local)
    normal = gradient / torch.linalg.vector_norm(gradient, dim=-1, keepdim=True).clamp_min(1e-12)
    rotation = torch.linalg.inv(world_to_obj)[:, :3, :3]  # object -> world
    return tips[column], targets, (rotation @ normal[..., None])[..., 0]


def grip_trajectory(
    hand: RobotHand,
    q: np.ndarray,
    obj_pose: np.ndarray,
    sdf: TorchSDF,
    contact: np.ndarray,
    cmap: dict[str, np.ndarray],
    params: RefineParams,
    start: int,
) -> np.ndarray:
    """Press the fingers in contact ``params.grip_m`` into the object from frame ``start`` on.

    A position-controlled finger presses only as far as its target lies inside the object, so
    a trajectory whose fingers merely touch holds nothing once the object is lifted. Here the
    per-finger step (E_dis, E_spen, E_joints, E_smooth; no E_pen) pulls each contact point of
    the contact map to ``grip_m`` below its object point, along the object's inward normal, in
    the frames ``>= start`` where its finger is in contact; the change ramps in (and out where
    a contact ends) over ``blend_frames`` (Gaussian).

    Returns:
        (T, dof) trajectory; ``q`` itself where ``start`` is past every contact.
    """
    touching = np.asarray(contact, dtype=bool).copy()
    touching[:start] = False
    if not touching.any() or "map_frame" not in cmap:
        return q
    pressed = dict(cmap)
    pressed["map_object_point"] = (
        cmap["map_object_point"] - params.grip_m * cmap["map_object_normal"]
    )
    gripping = replace(params, w_pen=0.0, w_align=0.0, w_tip=0.0)
    inv = torch.as_tensor(np.linalg.inv(obj_pose), dtype=hand.dtype)
    return _finger_step(hand, q, inv, sdf, touching, pressed, gripping)[0]


def _blend(hand: RobotHand, q_init: np.ndarray, q: np.ndarray, sigma: float) -> np.ndarray:
    """Smooth the refinement's change over time (Gaussian, ``sigma`` frames) so that it ramps in
    and out around contacts instead of stepping; limits and ties are restored afterwards."""
    from scipy.ndimage import gaussian_filter1d

    delta = gaussian_filter1d(q - q_init, sigma, axis=0, mode="nearest")
    out = torch.as_tensor(q_init + delta, dtype=hand.dtype)
    return hand.clamp(hand.apply_couplings(out)).numpy()


def run_refine(params: PipelineParams, layout: Layout) -> dict:
    """Stage runner: refine every retargeted sequence with its contacts."""
    source, contacts, aligned = layout.retarget("dexflow"), layout.contact, layout.scale_align
    out = layout.refine
    inputs = [source, contacts, aligned, layout.hand_files]
    if params.refine.grip_m > 0:
        inputs.append(layout.replay("retarget"))
    stage = StageOutput(out, "refine", {"hand": params.hand, "refine": params.refine}, inputs)
    files = stage.start()
    spec = staged_spec(params.hand, layout.hand_files.root)
    rp = params.refine
    lost = _lost_frames(layout) if rp.grip_m > 0 else {}

    def one(path: Path) -> dict:
        torch.set_num_threads(1)
        hand = cached_hand(spec, None)
        seq = load_sequence(aligned.sequence(path), data_root=aligned.root)
        retargeted = read_trajectory(path, hand.joint_names, frames=seq.num_frames)
        q0 = retargeted.q
        found = read_contact(contacts.sequence(path), list(hand.spec.fingers), seq.num_frames)
        contact, cmap = found.final, found.contact_map
        grid = ObjectAssets(aligned.object_of(seq.obj_mesh)).sdf()
        start = time.perf_counter()
        sdf = TorchSDF(grid)
        targets = fingertip_targets(
            hand, q0, retargeted["keypoints_human"], retargeted["observed"], seq.obj_pose, grid,
            rp.surface_tips,
        )  # fmt: skip
        q1, e0, e1 = refine_trajectory(hand, q0, seq.obj_pose, sdf, contact, cmap, rp, targets)
        grip_from = lost.get(path.stem, -1)
        if grip_from >= 0:
            grip_from = max(grip_from - rp.grip_lead_frames, 0)
            q1 = grip_trajectory(hand, q1, seq.obj_pose, sdf, contact, cmap, rp, grip_from)
        seconds = time.perf_counter() - start
        before = hand_object_measures(hand, q0, seq.obj_pose, grid, contact, rp.spen_delta_m)
        after = hand_object_measures(hand, q1, seq.obj_pose, grid, contact, rp.spen_delta_m)
        arrays = {
            "energy_before": e0,
            "energy_after": e1,
            **{f"{k}_before_m": v for k, v in before.items()},
            **{f"{k}_after_m": v for k, v in after.items()},
        }
        write_trajectory(out.sequence(path), Trajectory(q1, hand.joint_names, arrays))

        stats = {"frames": len(q0), "seconds": seconds}
        if rp.grip_m > 0:
            stats["grip_from_frame"] = grip_from  # -1: replay@retarget never lost the object
        for key in ("pd", "cd", "finger_overlap"):
            stats[f"{key}_before_mm"] = finite_mean(before[key]) * 1000
            stats[f"{key}_after_mm"] = finite_mean(after[key]) * 1000
        stats["rms_acc_before"] = rms_acceleration(q0[:, 6:], seq.fps)
        stats["rms_acc_after"] = rms_acceleration(q1[:, 6:], seq.fps)
        return stats

    tally = stage.run(one, files, params.run)
    summary = tally.counts("refine")
    for key in _SUMMARY_KEYS:  # like the metrics stage: over sequences where it is defined
        summary[key] = finite_mean([s[key] for s in tally.ok])
    seconds = sum(s.pop("seconds") for s in tally.ok)
    summary["sequences"] = dict(sorted(tally.sequences.items()))
    stage.finish(summary)
    speed = summary["num_frames"] / seconds if seconds else 0.0
    return {**summary, "timing": {"frames_per_second_one_core": speed}}


def _lost_frames(layout: Layout) -> dict[str, int]:
    """Per sequence, the frame where replay@retarget lost the object (-1: it never did), from
    that stage's summary.

    Raises:
        ArtifactError: replay@retarget has not run (no summary).
    """
    path = layout.replay("retarget").summary
    try:
        entries = json.loads(path.read_text(encoding="utf-8"))["sequences"]
    except (OSError, ValueError, KeyError) as exc:
        raise ArtifactError(
            f"{path}: refine.grip_m > 0 needs stage replay@retarget's summary ({exc})"
        ) from exc
    return {name: int(e.get("lost_frame", -1)) for name, e in entries.items() if e.get("replayed")}


_SUMMARY_KEYS = ("pd_before_mm", "pd_after_mm", "cd_before_mm", "cd_after_mm",
                 "finger_overlap_before_mm", "finger_overlap_after_mm", "rms_acc_before",
                 "rms_acc_after")  # fmt: skip

STAGE = StageSpec(
    name="refine",
    run=run_refine,
    metric_keys=("num_sequences", "num_ok", "num_failed", "num_frames", *_SUMMARY_KEYS),
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences; PD {s['pd_before_mm']:.2f} -> "
        f"{s['pd_after_mm']:.2f} mm, CD {s['cd_before_mm']:.2f} -> {s['cd_after_mm']:.2f} mm, "
        f"finger overlap {s['finger_overlap_before_mm']:.2f} -> "
        f"{s['finger_overlap_after_mm']:.2f} mm, RMS joint acc "
        f"{s['rms_acc_before']:.2f} -> {s['rms_acc_after']:.2f} rad/s^2; "
        f"{s['timing']['frames_per_second_one_core']:.1f} frames/s per core"
    ),
)  # fmt: skip
