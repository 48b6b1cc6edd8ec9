"""Refinement: penetration removed, hovering contact closed, no-contact fingers still, gradients."""

from __future__ import annotations

import itertools
import json
from dataclasses import replace
from functools import partial

import numpy as np
import pytest
import scipy.linalg
import torch
import trimesh
from scipy.spatial import cKDTree

from dexflow.errors import ArtifactError
from dexflow.hands import load_hand
from dexflow.human.keypoints import FINGERTIPS
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import RefineParams
from dexflow.stages.contact import _contact_map, finger_distances
from dexflow.stages.refine import (
    TorchSDF,
    _BandedTransposedSolve,
    _second_difference_gram,
    _stacked_bands,
    energy_terms,
    fingertip_targets,
    grip_trajectory,
    refine_trajectory,
    release_hand,
    temporal_preconditioner,
)

FRAMES = 3


@pytest.fixture(scope="module")
def allegro():
    return load_hand("allegro")


def _scene(hand, gap_m: float):
    """A box whose face is ``gap_m`` from the index fingertip's pad (negative: the pad is inside).

    The box sits on the palm side of the pad (the tip frame's +x), where flexing moves it."""
    q = hand.zero(FRAMES)
    q[:, hand.joint_names.index("joint_1.0")] = 0.3  # index slightly flexed, room both ways
    tip_frame = hand.link_transforms(q[:1], ["link_3.0_tip"])[0, 0].numpy()
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    grid = SignedDistanceGrid.from_mesh(box, spacing=0.002)
    pose = np.repeat(np.eye(4)[None], FRAMES, axis=0)
    sphere_centre = tip_frame[:3, 3] - 0.012 * tip_frame[:3, 2]  # rounded tip: r = 12 mm
    pose[:, :3, 3] = sphere_centre + tip_frame[:3, 0] * (0.012 + gap_m + 0.02)
    pose[:, :3, :3] = tip_frame[:3, :3]
    return q.numpy(), pose, box, grid


def _index_distance(hand, q, pose, grid):
    per_finger, _, _ = finger_distances(hand, q, pose, grid)
    return per_finger[:, list(hand.spec.fingers).index("index")]


def _refine(hand, q, pose, box, grid, contact, pen_margin_m=0.001, release=False, **overrides):
    _, dist, local = finger_distances(hand, q, pose, grid)
    points, faces = trimesh.sample.sample_surface(box, 4000, seed=0)
    cmap = _contact_map(
        local,
        dist,
        contact,
        list(hand.finger_point_masks.values()),
        cKDTree(points),
        box.face_normals[faces],
        8,
    )
    params = RefineParams(
        blend_frames=0.0, iterations=80, pen_margin_m=pen_margin_m, release=release, **overrides
    )
    q1, e0, e1 = refine_trajectory(hand, q, pose, TorchSDF(grid), contact, cmap, params)
    return q1, e0, e1


@pytest.mark.parametrize(("gap", "label"), [(-0.005, "5 mm inside"), (0.008, "hovering 8 mm away")])
def test_contact_finger_is_brought_to_the_surface(allegro, gap, label):
    q, pose, box, grid = _scene(allegro, gap)
    before = _index_distance(allegro, q, pose, grid)
    assert np.allclose(before, gap, atol=0.0025), (label, before)
    contact = np.zeros((FRAMES, 4), dtype=bool)
    contact[:, list(allegro.spec.fingers).index("index")] = True
    q1, e0, e1 = _refine(allegro, q, pose, box, grid, contact)
    after = _index_distance(allegro, q1, pose, grid)
    assert np.all(np.abs(after) < 0.0015), (label, after)  # on the surface, not in it
    assert np.all(e1 < e0)
    lo, hi = allegro.lower.numpy(), allegro.upper.numpy()
    assert np.all(q1 >= lo - 1e-12) and np.all(q1 <= hi + 1e-12)
    # Only the index finger's joints moved.
    moved = np.flatnonzero(np.abs(q1 - q).max(axis=0) > 1e-12)
    assert set(moved) <= set(allegro.fingers["index"]) and len(moved) > 0


def test_penetration_margin_keeps_the_pad_off_the_surface(allegro):
    """Sampled surface points miss the deepest point between them; the margin makes up for it:
    the larger the margin, the farther outside the refined pad stays."""
    q, pose, box, grid = _scene(allegro, -0.005)
    contact = np.zeros((FRAMES, 4), dtype=bool)
    contact[:, list(allegro.spec.fingers).index("index")] = True
    gaps = {}
    for margin in (0.0, 0.003):
        q1, _, _ = _refine(allegro, q, pose, box, grid, contact, pen_margin_m=margin)
        gaps[margin] = _index_distance(allegro, q1, pose, grid)
    assert np.all(gaps[0.003] > gaps[0.0] + 0.001), gaps
    assert np.all(gaps[0.003] > 0.0) and np.all(gaps[0.003] < 0.004), gaps


def test_finger_without_contact_does_not_move(allegro):
    q, pose, box, grid = _scene(allegro, -0.005)
    contact = np.zeros((FRAMES, 4), dtype=bool)  # nobody in contact: nothing to refine
    q1, _, _ = _refine(allegro, q, pose, box, grid, contact)
    np.testing.assert_array_equal(q1, q)


def test_energy_gradients_match_finite_differences(allegro):
    q, pose, _, grid = _scene(allegro, -0.003)
    hand = allegro
    fingers = list(hand.spec.fingers)
    mine = np.isin(np.asarray(hand.surface_point_links), hand.spec.fingers["index"].links)
    finger_idx = torch.as_tensor(np.flatnonzero(mine))
    others = np.flatnonzero(~mine)[::10]
    with torch.no_grad():
        fixed_others, _ = hand.surface_points(torch.as_tensor(q), torch.as_tensor(others))
    rows = torch.tensor([0, 0, 1, 2])
    hand_rows = torch.tensor([0, 5, 7, 9])
    obj_pts = torch.tensor(
        [[0.0, 0.0, -0.02], [0.005, 0.0, -0.02], [0.0, 0.01, -0.02], [0.0, 0.0, -0.02]],
        dtype=torch.float64,
    )
    obj_nrm = torch.tensor([[0.0, 0.0, -1.0]] * 4, dtype=torch.float64)
    inv = torch.as_tensor(np.linalg.inv(pose))
    sdf = TorchSDF(grid)
    joints = hand.fingers["index"]
    spen_rows = torch.arange(0, int(mine.sum()), 7)

    keypoint = next(k for k in hand.fingertip_keypoints if hand.mano_indices[k] == 8)  # index
    with torch.no_grad():
        tip_goal = hand.keypoints(torch.as_tensor(q))[:, keypoint] + torch.tensor(
            [0.003, -0.002, 0.004], dtype=torch.float64
        )
    tip_normal = torch.tensor([[1.0, 1.0, 0.0]] * FRAMES, dtype=torch.float64) / np.sqrt(2)

    def terms(theta):
        qf = torch.as_tensor(q).clone()
        qf[:, joints] = theta
        return energy_terms(
            hand,
            qf,
            finger_idx,
            inv,
            (rows, hand_rows, obj_pts, obj_nrm),
            spen_rows,
            fixed_others,
            sdf,
            0.02,
            tip=(keypoint, tip_goal, tip_normal),
        )

    theta = torch.as_tensor(q[:, joints]).clone()
    values = terms(theta)
    assert values["pen"].sum() > 0 and values["dis"].sum() > 0 and values["spen"].sum() > 0
    # the tip term is the squared miss across the normal: (3, -2, 4) mm, 1/√2 mm of it along
    # (1, 1, 0)/√2, leaves 29 - 0.5 mm²
    expected = torch.full((FRAMES,), 28.5e-6, dtype=torch.float64)
    torch.testing.assert_close(values["tip"], expected, rtol=1e-9, atol=0)
    for name in ("dis", "pen", "align", "spen", "tip"):
        t = theta.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(terms(t)[name].sum(), t)
        eps = 1e-6
        fd = torch.zeros_like(theta)
        for i in range(theta.shape[0]):
            for j in range(theta.shape[1]):
                d = torch.zeros_like(theta)
                d[i, j] = eps
                fd[i, j] = (terms(theta + d)[name].sum() - terms(theta - d)[name].sum()) / (2 * eps)
        torch.testing.assert_close(grad, fd, atol=1e-5, rtol=1e-3, msg=name)
    assert fingers.index("index") == 1


def _palm_scene(hand, depth_m: float, frames: int = 6):
    """A slab in front of the little-finger half of the Allegro palm (its +x face), ``depth_m``
    into the palm's surface, drifting 1 mm per frame along the palm; the fingers and the thumb
    at zero stay clear of it."""
    q = hand.zero(frames).numpy()
    points, _ = hand.surface(torch.as_tensor(q[:1]))
    palm = np.asarray(hand.surface_point_links) == "base_link"
    front = points[0, torch.as_tensor(palm), 0].max().item()
    slab = trimesh.creation.box(extents=(0.04, 0.05, 0.09))
    grid = SignedDistanceGrid.from_mesh(slab, spacing=0.002)
    pose = np.repeat(np.eye(4)[None], frames, axis=0)
    pose[:, 0, 3] = front - depth_m + 0.02
    pose[:, 1, 3] = -0.03 + 0.001 * np.arange(frames)
    pose[:, 2, 3] = -0.05
    return q, pose, grid


def _depth(hand, q, pose, grid):
    points, _ = hand.surface(torch.as_tensor(q))
    inv = np.linalg.inv(pose)
    local = np.einsum("tij,tnj->tni", inv[:, :3, :3], points.numpy()) + inv[:, None, :3, 3]
    return np.clip(-grid.query(local).min(axis=1), 0, None)


def test_release_frees_a_palm_inside_the_object(allegro):
    """The paper's per-finger step cannot move a palm out of the object; the release does, by
    backing the whole hand out by about as much as it was in (tilting it where that moves the
    keypoints less), the same way in every frame."""
    q, pose, grid = _palm_scene(allegro, 0.006)
    assert np.all(_depth(allegro, q, pose, grid) > 0.005)
    contact = np.zeros((len(q), 4), dtype=bool)  # no finger in contact: the paper moves nothing
    paper = RefineParams(release=False)
    q_paper, _, _ = refine_trajectory(allegro, q, pose, TorchSDF(grid), contact, {}, paper)
    assert np.all(_depth(allegro, q_paper, pose, grid) > 0.005)

    q1, _, _ = refine_trajectory(allegro, q, pose, TorchSDF(grid), contact, {}, RefineParams())
    assert np.all(_depth(allegro, q1, pose, grid) < 0.0005)
    with torch.no_grad():
        moved = torch.linalg.norm(
            allegro.keypoints(torch.as_tensor(q1)) - allegro.keypoints(torch.as_tensor(q)), dim=-1
        ).numpy()
    # about the depth at most (tilting the palm out moves the keypoints near the wrist less)
    assert 0.002 < moved.mean() < 0.007 and moved.max() < 0.011, moved
    assert np.ptp(moved.mean(axis=1)) < 0.001  # the same change in every frame: no jitter
    lo, hi = allegro.lower.numpy(), allegro.upper.numpy()
    assert np.all(q1 >= lo - 1e-12) and np.all(q1 <= hi + 1e-12)


def test_release_keeps_a_contact_finger_on_the_surface(allegro):
    """A pad 5 mm inside ends on the surface: not left deeper than release_depth_m (here
    0.5 mm; the fingertip's tracking weight would otherwise keep ~1 mm of it), not pushed off."""
    q, pose, box, grid = _scene(allegro, -0.005)
    contact = np.zeros((FRAMES, 4), dtype=bool)
    contact[:, list(allegro.spec.fingers).index("index")] = True
    q1, _, _ = _refine(allegro, q, pose, box, grid, contact, release=True, release_depth_m=0.0005)
    after = _index_distance(allegro, q1, pose, grid)
    assert np.all(after > -0.0005) and np.all(after < 0.0015), after
    assert np.all(_depth(allegro, q1, pose, grid) < 0.0005)


def _release_palm(hand, depth_m, **overrides):
    q, pose, grid = _palm_scene(hand, depth_m)
    contact = np.zeros((len(q), 4), dtype=bool)
    inv = torch.as_tensor(np.linalg.inv(pose))
    q1 = release_hand(hand, q, inv, TorchSDF(grid), contact, RefineParams(**overrides))
    with torch.no_grad():
        moved = torch.linalg.norm(
            hand.keypoints(torch.as_tensor(q1)) - hand.keypoints(torch.as_tensor(q)), dim=-1
        ).numpy()
    tips = np.isin(hand.mano_indices, FINGERTIPS)
    return _depth(hand, q1, pose, grid), moved[:, tips].mean(), moved[:, ~tips].mean()


def test_release_rounds_bound_the_deepest_frame(allegro):
    """A palm 2 cm inside: one penalty solve trades part of the depth against the motion terms;
    the continuation (frames still deeper than release_depth_m get 10x w_pen) brings it under."""
    one, _, _ = _release_palm(allegro, 0.02, release_rounds=1)
    three, _, _ = _release_palm(allegro, 0.02, release_rounds=3)
    assert one.max() > RefineParams().release_depth_m
    assert three.max() <= RefineParams().release_depth_m


def test_release_moves_the_palm_before_the_fingertips(allegro):
    """With release_tip_weight > 1 the fingertips stay nearer their place than the rest of the
    hand while the palm backs out; at 1 they move further (0.73 mm against 0.50 at 10, with
    the palm's box corners among the surface points; 0.97 against 0.48 without)."""
    depth, tips, rest = _release_palm(allegro, 0.01, release_tip_weight=10.0)
    assert depth.max() < 0.0005
    assert tips < 0.4 * rest
    _, tips_equal, _ = _release_palm(allegro, 0.01, release_tip_weight=1.0)
    assert tips_equal > 1.3 * tips


def _banded_to_dense(lower: np.ndarray) -> np.ndarray:
    """(..., 3, T) lower banded form to the (..., T, T) lower triangular matrix."""
    n = lower.shape[-1]
    dense = np.zeros((*lower.shape[:-2], n, n))
    for d in range(3):
        rows = np.arange(n - d)
        dense[..., rows + d, rows] = lower[..., d, : n - d]
    return dense


@pytest.mark.parametrize("n", [1, 2, 3, 4, 9])
def test_second_difference_gram_and_the_banded_solve(n):
    """The banded D2ᵀD2 is the dense one; the solve is x = L⁻ᵀz with the gradient L⁻¹g."""
    d2 = np.zeros((max(n - 2, 0), n))
    for row in range(n - 2):
        d2[row, row : row + 3] = (1, -2, 1)
    gram = _banded_to_dense(_second_difference_gram(n))
    assert np.allclose(gram + np.tril(gram, -1).T, d2.T @ d2)

    rng = np.random.default_rng(0)
    bands = np.stack([_second_difference_gram(n) * w for w in (3.0, 0.5)])
    bands[:, 0] += rng.uniform(0.1, 1.0, (2, n))
    factors = np.stack([scipy.linalg.cholesky_banded(b, lower=True) for b in bands])
    for d in (1, 2):
        factors[:, d, n - d :] = 0
    stacked = _stacked_bands(factors)
    z = torch.tensor(rng.normal(size=(2, n)), requires_grad=True)
    x = _BandedTransposedSolve.apply(z, *stacked)
    lower = _banded_to_dense(factors)
    assert np.allclose(np.einsum("fji,fj->fi", lower, x.detach().numpy()), z.detach().numpy())
    assert torch.autograd.gradcheck(lambda v: _BandedTransposedSolve.apply(v, *stacked), (z,))


@pytest.mark.parametrize("name", ["allegro", "shadow"])
def test_release_preconditioner_is_the_curvature_of_tracking_and_smoothness(name):
    """For a trajectory holding one pose, L_j L_jᵀ of every free joint is half the Hessian of
    the release's tracking and smoothness terms in that joint's change over the frames (the
    ShadowHand's tendon followers moving with their leaders): the preconditioned coordinates
    have unit curvature there."""
    hand = load_hand(name)
    params = RefineParams()
    frames = 7
    rng = np.random.default_rng(1)
    pose = hand.clamp(hand.apply_couplings(
        torch.as_tensor(rng.uniform(hand.lower, hand.upper)[None]).clamp(-0.5, 0.5)
    ))  # fmt: skip
    q0 = pose.repeat(frames, 1)
    tips = torch.as_tensor(np.isin(hand.mano_indices, FINGERTIPS))
    track_w = torch.where(tips, params.release_tip_weight, 1.0).to(hand.dtype)
    curvature = _banded_to_dense(temporal_preconditioner(hand, q0, track_w, params))
    curvature = curvature @ np.swapaxes(curvature, -1, -2)
    with torch.no_grad():
        kp0 = hand.keypoints(q0)

    def second(x):
        return x[2:] - 2 * x[1:-1] + x[:-2]

    def energy(column, j):
        q = q0.clone()
        q[:, j] = q0[:, j] + column
        q = hand.apply_couplings(q)
        change = hand.keypoints(q) - kp0
        return (
            params.release_w_track * ((change**2).sum(-1) * track_w).sum()
            + params.release_w_smooth * (second(change) ** 2).sum()
            + params.release_w_smooth_joints * (second(q[:, 6:] - q0[:, 6:]) ** 2).sum()
            + params.release_w_joints * ((q[:, 6:] - q0[:, 6:]) ** 2).sum()
        )

    free = hand.free_joints
    leaders = {c.leader for c in hand.spec.couplings}
    led = [i for i, j in enumerate(free) if hand.joint_names[j] in leaders]
    for i in [0, 4, *led[:1], len(free) - 1]:  # base x, a base rotation, a leader, the last joint
        zero = torch.zeros(frames, dtype=hand.dtype)
        hessian = torch.autograd.functional.hessian(partial(energy, j=free[i]), zero).numpy()
        assert np.allclose(curvature[i], hessian / 2, rtol=1e-3, atol=1e-6 * np.abs(hessian).max())


def test_release_preconditioner_makes_lbfgs_converge(allegro, monkeypatch):
    """What the preconditioner is for: on a palm 8 mm inside over 30 frames, 60 energy
    evaluations of the release reach within 5 % of the lowest energy 300 iterations find; in
    plain coordinates (the factors replaced by the identity) they stay over twice as high."""
    q, pose, grid = _palm_scene(allegro, 0.008, frames=30)
    contact = np.zeros((len(q), 4), dtype=bool)
    inv = torch.as_tensor(np.linalg.inv(pose))
    energies: list[float] = []
    step = torch.optim.LBFGS.step

    def recorded(self, closure):
        def traced():
            energy = closure()
            energies.append(float(energy.detach()))
            return energy

        return step(self, traced)

    monkeypatch.setattr(torch.optim.LBFGS, "step", recorded)

    def lowest(iterations: int, evaluations: int) -> float:
        energies.clear()
        params = RefineParams(release_iterations=iterations)
        release_hand(allegro, q, inv, TorchSDF(grid), contact, params, rounds=1)
        return min(energies[:evaluations])

    optimum = lowest(300, 10**6)
    assert lowest(60, 60) < 1.05 * optimum

    def identity(hand, q0, track_w, params):
        factors = np.zeros((len(hand.free_joints), 3, len(q0)))
        factors[:, 0] = 1.0
        return factors

    monkeypatch.setattr("dexflow.stages.refine.temporal_preconditioner", identity)
    assert lowest(60, 60) > 2 * optimum


def test_long_sequences_are_refined_in_cross_faded_windows(allegro):
    """A sequence longer than window_frames is refined in overlapping windows (bounded memory):
    every frame still freed, no step at the seams, close to refining it whole; a sequence no
    longer than one window is refined whole, exactly as with windows off."""
    q, pose, grid = _palm_scene(allegro, 0.006, frames=30)
    contact = np.zeros((len(q), 4), dtype=bool)
    whole, _, _ = refine_trajectory(
        allegro, q, pose, TorchSDF(grid), contact, {}, RefineParams(window_frames=0)
    )
    windowed, e0, e1 = refine_trajectory(
        allegro, q, pose, TorchSDF(grid), contact, {},
        RefineParams(window_frames=16, window_overlap=8),
    )  # fmt: skip
    assert windowed.shape == q.shape and e0.shape == e1.shape == (30,)
    assert np.all(_depth(allegro, windowed, pose, grid) < 0.0005)
    # the same solution, nearly. Each solve stops after its iterations, so they differ: the
    # keypoints by up to 0.43 mm, the joints by 0.015 rad (0.29 mm, 0.007 rad with 60 iterations
    # in the first release instead of 20). Without release_w_joints the thumb's joints, which
    # place one keypoint, drifted apart by 0.18 rad.
    kp = [allegro.keypoints(torch.as_tensor(x)) for x in (windowed, whole)]
    assert (kp[0] - kp[1]).norm(dim=-1).max() < 0.001
    assert np.abs(windowed - whole).max() < 0.02
    steps = np.abs(np.diff(windowed, axis=0)).max(axis=1)
    smooth = np.abs(np.diff(whole, axis=0)).max(axis=1)
    # no jump where windows meet: the cross-fade spreads their difference over the shared frames
    assert steps.max() < 2 * smooth.max(), (steps, smooth)
    lo, hi = allegro.lower.numpy(), allegro.upper.numpy()
    assert np.all(windowed >= lo - 1e-12) and np.all(windowed <= hi + 1e-12)
    short, _, _ = refine_trajectory(
        allegro, q[:12], pose[:12], TorchSDF(grid), contact[:12], {},
        RefineParams(window_frames=12, window_overlap=4),
    )  # fmt: skip
    alone, _, _ = refine_trajectory(
        allegro, q[:12], pose[:12], TorchSDF(grid), contact[:12], {}, RefineParams(window_frames=0)
    )
    assert np.array_equal(short, alone)


def test_release_reach_leaves_out_only_points_that_add_nothing(allegro, monkeypatch):
    """Only points within release_reach_m of the object (in frames that have any) and every
    point of a finger in contact enter the penetration and contact terms: fewer points, the
    same release as with every point; a hand far from the object is left where it is."""
    q, pose, grid = _palm_scene(allegro, 0.006, frames=8)
    far = pose.copy()
    far[4:, 0, 3] += 0.5  # the last four frames: the object half a metre away
    contact = np.zeros((len(q), 4), dtype=bool)
    inv = torch.as_tensor(np.linalg.inv(far))
    used: list[tuple[int, torch.Tensor]] = []
    original = type(allegro).surface_points

    def spy(self, q, index, transforms=None, normals=True):
        used.append((len(q if transforms is None else transforms), torch.as_tensor(index)))
        return original(self, q, index, transforms, normals)

    monkeypatch.setattr(type(allegro), "surface_points", spy)
    near = release_hand(allegro, q, inv, TorchSDF(grid), contact, RefineParams())
    assert max(len(i) for _, i in used) < allegro.num_surface_points  # points left out
    assert max(t for t, _ in used) == 4  # frames 0-3: the object near
    every = release_hand(
        allegro, q, inv, TorchSDF(grid), contact, RefineParams(release_reach_m=10.0)
    )
    assert np.abs(near - every).max() < 1e-6
    assert np.all(_depth(allegro, near[:4], far[:4], grid) < RefineParams().pen_margin_m)
    nothing = release_hand(allegro, q[4:], inv[4:], TorchSDF(grid), contact[4:], RefineParams())
    assert np.abs(nothing - q[4:]).max() < 1e-9

    used.clear()  # the thumb, a few cm off, in contact: all of its points are in every solve
    thumb = list(allegro.spec.fingers).index("thumb")
    contact[1:4, thumb] = True
    release_hand(allegro, q, inv, TorchSDF(grid), contact, RefineParams())
    points = np.flatnonzero(allegro.finger_point_masks["thumb"])
    assert all(np.isin(points, i.numpy()).all() for _, i in used)


def test_the_first_release_runs_its_own_iterations_and_the_last_its_rounds(allegro, monkeypatch):
    from dexflow.stages import refine

    calls = []

    def fake_release(
        hand, q, world_to_obj, sdf, contact, params, reference=None, rounds=None, tip_targets=None
    ):
        calls.append((params.release_iterations, rounds, reference is None, tip_targets))
        return q

    monkeypatch.setattr(refine, "release_hand", fake_release)
    monkeypatch.setattr(refine, "_finger_step", lambda hand, q, *a: (q, None, None))
    params = RefineParams(release_iterations=50, release_first_iterations=7)
    pose = np.repeat(np.eye(4)[None], 4, 0)
    targets = np.zeros((4, 4, 3))
    refine._refine_whole(allegro, np.zeros((4, allegro.dof)), pose, None, None, {}, params, targets)
    # rounds None: release_rounds; both releases track the fingertip targets
    assert calls == [(7, 1, True, targets), (50, None, False, targets)]


def test_windows_cover_every_frame_and_cross_fade_linearly(allegro, monkeypatch):
    """Windows of at most 10 frames overlapping by at least 4 on 23 frames: four of 9 frames,
    evenly spaced ([0, 9), [5, 14), [9, 18), [14, 23)); each gets its own rows of the contact
    map, counted from its first frame, and its frames' fingertip targets; the shared frames ramp
    linearly from one window's result to the next."""
    from dexflow.stages import refine

    seen, frames_of_targets = [], []

    def fake_whole(hand, q_init, obj_pose, sdf, contact, cmap, params, tip_targets):
        k = len(seen)
        seen.append((len(q_init), cmap["map_frame"].tolist()))
        frames_of_targets.append(tip_targets[:, 0, 0].tolist())
        value = np.full_like(q_init, float(k))  # window k returns k everywhere
        return value, np.full(len(q_init), k), np.full(len(q_init), 10.0 * k)

    monkeypatch.setattr(refine, "_refine_whole", fake_whole)
    monkeypatch.setattr(type(allegro), "clamp", lambda self, q: q)
    monkeypatch.setattr(type(allegro), "apply_couplings", lambda self, q: q)
    q = np.zeros((23, allegro.dof))
    cmap = {"map_frame": np.array([0, 7, 9, 14, 22]), "map_finger": np.zeros(5, int)}
    targets = np.broadcast_to(np.arange(23.0)[:, None, None], (23, 4, 3))  # the frame number
    out, e0, e1 = refine_trajectory(
        allegro, q, np.repeat(np.eye(4)[None], 23, 0), None, np.zeros((23, 4), bool), cmap,
        RefineParams(window_frames=10, window_overlap=4), targets,
    )  # fmt: skip
    assert [n for n, _ in seen] == [9, 9, 9, 9]
    assert [f for _, f in seen] == [[0, 7], [2, 4], [0, 5], [0, 8]]
    assert frames_of_targets == [list(range(a, a + 9)) for a in (0, 5, 9, 14)]
    expected = np.r_[np.zeros(5), np.arange(1, 5) / 5, 1 + np.arange(1, 6) / 6,
                     2 + np.arange(1, 5) / 5, np.full(5, 3.0)]  # fmt: skip
    assert np.allclose(out[:, 0], expected) and np.allclose(e0, expected)
    assert np.allclose(e1, 10 * expected)


@pytest.mark.parametrize(("n", "window", "overlap"), [(401, 400, 40), (1000, 400, 40),
                                                      (23, 10, 4), (57, 12, 6), (30, 16, 8)])  # fmt: skip
def test_windows_are_few_equal_and_overlap_enough(n, window, overlap):
    from dexflow.stages.refine import _windows

    spans = _windows(n, window, overlap)
    assert spans[0][0] == 0 and spans[-1][1] == n
    assert len({b - a for a, b in spans}) == 1 and spans[0][1] - spans[0][0] <= window
    assert all(b0 - a1 >= overlap for (_, b0), (a1, _) in itertools.pairwise(spans))
    assert all(a1 > a0 for (a0, _), (a1, _) in itertools.pairwise(spans))
    fewer = len(spans) - 1  # one window less could not cover n with that overlap
    assert fewer * window - (fewer - 1) * overlap < n


def test_torch_sdf_gives_the_grids_values_and_the_exact_gradient_in_and_around_the_grid():
    """TorchSDF computes its gradient with the value (no autograd graph): equal to
    SignedDistanceGrid.query, to grid_sample's trilinear interpolation and its gradient, and to
    central differences, for points inside the grid, outside it and in a U's concavity."""
    u_shape = trimesh.creation.annulus(r_min=0.02, r_max=0.04, height=0.05)
    grid = SignedDistanceGrid.from_mesh(u_shape, spacing=0.002, padding=0.01)
    sdf = TorchSDF(grid)
    lo, hi = sdf.origin, sdf.upper
    generator = torch.Generator().manual_seed(0)
    points = lo + (hi - lo) * (
        torch.rand(7, 300, 3, dtype=torch.float64, generator=generator) * 1.4 - 0.2
    )
    mine = points.clone().requires_grad_(True)
    value = sdf(mine)
    np.testing.assert_allclose(value.detach().numpy(), grid.query(points.numpy()), atol=1e-12)
    (value**3).sum().backward()

    reference = points.clone().requires_grad_(True)  # the differentiable grid_sample query
    flat = reference.reshape(-1, 3)
    clamped = torch.maximum(torch.minimum(flat, hi), lo)
    normalised = (2 * (clamped - lo) / (hi - lo) - 1).flip(-1).reshape(1, -1, 1, 1, 3)
    values = torch.as_tensor(grid.values, dtype=torch.float64)[None, None]
    sampled = torch.nn.functional.grid_sample(
        values, normalised, align_corners=True, padding_mode="border"
    ).reshape(-1)
    expected = (sampled + torch.linalg.norm(flat - clamped, dim=-1)).reshape(points.shape[:-1])
    (expected**3).sum().backward()
    torch.testing.assert_close(value, expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(mine.grad, reference.grad, atol=1e-9, rtol=1e-9)

    inside = points[0, :40].clone().requires_grad_(True)  # against central differences
    (grad,) = torch.autograd.grad(sdf(inside).sum(), inside)
    eps = 1e-7
    for axis in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[axis] = eps
        fd = (sdf(inside.detach() + step) - sdf(inside.detach() - step)) / (2 * eps)
        torch.testing.assert_close(grad[:, axis], fd, atol=1e-5, rtol=1e-5)


def _touching_scene(hand, frames: int = 6):
    """The index pad on a box's face in ``frames`` frames, in contact, with its contact map."""
    q, pose, box, grid = _scene(hand, 0.0)
    q, pose = np.repeat(q[:1], frames, 0), np.repeat(pose[:1], frames, 0)
    return q, pose, grid, *_index_contact(hand, q, pose, box, grid)


def _index_contact(hand, q, pose, box, grid):
    """The index finger in contact in every frame, and its contact map on ``box``."""
    contact = np.zeros((len(q), 4), dtype=bool)
    contact[:, list(hand.spec.fingers).index("index")] = True
    _, dist, local = finger_distances(hand, q, pose, grid)
    points, faces = trimesh.sample.sample_surface(box, 4000, seed=0)
    masks = list(hand.finger_point_masks.values())
    cmap = _contact_map(local, dist, contact, masks, cKDTree(points), box.face_normals[faces], 8)
    return contact, cmap


def test_grip_presses_the_contact_fingers_in_from_the_given_frame_on(allegro):
    """Where physics lost the object, refine.grip_m presses the fingers in contact that far
    into it, from the start frame on; the frames before stay as they were."""
    q, pose, grid, contact, cmap = _touching_scene(allegro)
    params = RefineParams(grip_m=0.004, blend_frames=0.0, iterations=80)
    q1 = grip_trajectory(allegro, q, pose, TorchSDF(grid), contact, cmap, params, start=3)
    np.testing.assert_array_equal(q1[:3], q[:3])
    depth = _index_distance(allegro, q1, pose, grid)
    assert np.all(np.abs(_index_distance(allegro, q, pose, grid)) < 0.0015)
    assert np.all(depth[3:] < -0.002) and np.all(depth[3:] > -0.007), depth
    moved = np.flatnonzero(np.abs(q1 - q).max(axis=0) > 1e-12)
    assert set(moved) <= set(allegro.fingers["index"]) and len(moved) > 0
    # ramped in over blend_frames where it starts: no step at the start frame
    ramped = grip_trajectory(
        allegro, q, pose, TorchSDF(grid), contact, cmap, replace(params, blend_frames=2.0), 3
    )
    jump = np.abs(np.diff(ramped[:, 6:], axis=0)).max(axis=1)
    assert jump.max() < np.abs(q1[3, 6:] - q1[2, 6:]).max()
    # a start past the last contact changes nothing
    np.testing.assert_array_equal(
        grip_trajectory(allegro, q, pose, TorchSDF(grid), contact, cmap, params, start=6), q
    )


def test_refine_reads_where_replay_lost_the_object_and_says_when_it_cannot(tmp_path):
    from dexflow.io.layout import Layout
    from dexflow.stages.refine import _lost_frames

    layout = Layout.of(tmp_path / "data", root=tmp_path)
    with pytest.raises(ArtifactError, match=r"grip_m > 0 needs stage replay@retarget"):
        _lost_frames(layout)
    summary = layout.replay("retarget").summary
    summary.parent.mkdir(parents=True)
    summary.write_text(json.dumps({"sequences": {
        "a": {"replayed": True, "lost": True, "lost_frame": 40},
        "b": {"replayed": True, "lost": False, "lost_frame": -1},
        "c": {"replayed": False, "frames": 0},
    }}))  # fmt: skip
    assert _lost_frames(layout) == {"a": 40, "b": -1}


def test_fingertip_targets_are_the_human_tips_on_the_surface_where_observed(allegro):
    """On observed frames the targets are the human fingertips, one 3 mm inside a box moved
    onto its face; on the others (and with surface_tips off) the retargeted fingertips."""
    q = allegro.zero(3).numpy()
    with torch.no_grad():
        robot = allegro.keypoints(torch.as_tensor(q)).numpy()
    tips = allegro.fingertip_keypoints
    human = robot + 0.5  # every keypoint far from the box ...
    inside = np.array([0.01, 0.02, 0.03])
    human[:, tips[1]] = inside  # ... but one fingertip, 3 mm inside the box's -x face
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    grid = SignedDistanceGrid.from_mesh(box, spacing=0.002)
    pose = np.repeat(np.eye(4)[None], 3, axis=0)
    pose[:, :3, 3] = [inside[0] + 0.017, inside[1], inside[2]]  # the face at x = 7 mm
    observed = np.array([True, False, True])
    targets = fingertip_targets(allegro, q, human, observed, pose, grid)
    assert targets.shape == (3, len(tips), 3)
    np.testing.assert_allclose(targets[[0, 2], 1], [[0.007, 0.02, 0.03]] * 2, atol=1e-5)
    np.testing.assert_array_equal(
        targets[[0, 2]][:, [0, 2, 3]], human[[0, 2]][:, tips][:, [0, 2, 3]]
    )
    np.testing.assert_array_equal(targets[1], robot[1, tips])
    retargeted = fingertip_targets(allegro, q, human, observed, pose, grid, surface_tips=False)
    np.testing.assert_array_equal(retargeted, robot[:, tips])


def _flex_direction(hand, q, joint: str, keypoint: int) -> np.ndarray:
    """Unit direction in which ``keypoint`` moves when ``joint`` flexes at ``q``."""
    moved = q.copy()
    moved[:, hand.joint_names.index(joint)] += 1e-4
    with torch.no_grad():
        a, b = (hand.keypoints(torch.as_tensor(x))[0, keypoint].numpy() for x in (q, moved))
    return (b - a) / np.linalg.norm(b - a)


def test_release_tracks_the_fingertip_targets(allegro):
    """Far from the object the release only tracks: the index fingertip goes to a target 4 mm
    from where retargeting put it (its last joint flexes), the other keypoints stay; without
    targets nothing moves."""
    q, pose, grid = _palm_scene(allegro, 0.0)
    pose[:, 0, 3] += 0.5  # the object half a metre away
    contact = np.zeros((len(q), 4), dtype=bool)
    inv = torch.as_tensor(np.linalg.inv(pose))
    tips = allegro.fingertip_keypoints
    index = next(i for i, k in enumerate(tips) if allegro.mano_indices[k] == 8)
    with torch.no_grad():
        before = allegro.keypoints(torch.as_tensor(q)).numpy()
    targets = before[:, tips].copy()
    targets[:, index] += 0.004 * _flex_direction(allegro, q[:1], "joint_3.0", tips[index])
    q1 = release_hand(allegro, q, inv, TorchSDF(grid), contact, RefineParams(), tip_targets=targets)
    with torch.no_grad():
        after = allegro.keypoints(torch.as_tensor(q1)).numpy()
    assert np.linalg.norm(after[:, tips[index]] - targets[:, index], axis=-1).max() < 5e-4
    others = [k for k in range(len(allegro.mano_indices)) if k != tips[index]]
    assert np.linalg.norm(after[:, others] - before[:, others], axis=-1).max() < 5e-4
    still = release_hand(allegro, q, inv, TorchSDF(grid), contact, RefineParams())
    assert np.abs(still - q).max() < 1e-6


@pytest.mark.parametrize("gap", [-0.004, 0.008])
def test_the_finger_step_holds_the_fingertip_across_the_normal(allegro, gap):
    """Contact-map object points 6 mm along the face from the pad (nearest surface samples
    found elsewhere) pull the finger sideways along the surface, 5 mm; E_tip holds the tip
    across the normal, and the pad still reaches the surface along it (from 4 mm inside or
    8 mm away)."""
    q, pose, box, grid = _scene(allegro, gap)
    contact, cmap = _index_contact(allegro, q, pose, box, grid)
    tip = allegro.fingertip_keypoints[1]
    normal = -pose[0, :3, 0]  # the face's outward normal (the pad faces the tip frame's +x)
    sideways = _flex_direction(allegro, q[:1], "joint_0.0", tip)  # abduction
    sideways -= (sideways @ normal) * normal
    sideways /= np.linalg.norm(sideways)
    cmap["map_object_point"] = cmap["map_object_point"] + 0.006 * (pose[0, :3, :3].T @ sideways)
    across = {}
    for w_tip in (0.0, RefineParams().w_tip):
        params = RefineParams(blend_frames=0.0, iterations=80, release=False, w_tip=w_tip)
        q1, _, _ = refine_trajectory(allegro, q, pose, TorchSDF(grid), contact, cmap, params)
        with torch.no_grad():
            moved = allegro.keypoints(torch.as_tensor(q1)) - allegro.keypoints(torch.as_tensor(q))
        change = moved[:, tip].numpy()
        across[w_tip] = np.linalg.norm(change - (change @ normal)[:, None] * normal, axis=-1)
        distance = _index_distance(allegro, q1, pose, grid)
        assert np.all(np.abs(distance) < 0.0015), (w_tip, distance)  # on the surface
    assert across[0.0].min() > 0.004, across
    assert across[RefineParams().w_tip].max() < 0.001, across
