"""Tests for dexflow.human.surface_tips: tips inside an object pushed onto its surface."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from dexflow.geometry import transform_points
from dexflow.human.surface_tips import surface_corrected_tips
from dexflow.objects.sdf import SignedDistanceGrid

HALF = np.array([0.01, 0.04, 0.04])  # a slab: its x faces are the nearest inside |y|, |z| <= 2 cm


@pytest.fixture(scope="module")
def slab():
    return SignedDistanceGrid.from_mesh(
        trimesh.creation.box(extents=2 * HALF), spacing=0.002, padding=0.01
    )


@pytest.fixture(scope="module")
def ball():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.03)
    return SignedDistanceGrid.from_mesh(sphere, spacing=0.002, padding=0.01)


def _poses(frames: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pose = np.repeat(np.eye(4)[None], frames, axis=0)
    pose[:, :3, :3] = Rotation.random(frames, random_state=seed).as_matrix()
    pose[:, :3, 3] = rng.uniform(-0.5, 0.5, size=(frames, 3))
    return pose


def _slab_tips(frames: int = 7, tips: int = 5, seed: int = 0):
    """Tips in the slab's frame: inside by 0.5 to 5 mm through an x face, or outside it."""
    rng = np.random.default_rng(seed)
    local = rng.uniform(-0.02, 0.02, size=(frames, tips, 3))
    side = rng.choice([-1.0, 1.0], size=(frames, tips))
    depth = rng.uniform(0.0005, 0.005, size=(frames, tips))
    outside = rng.random((frames, tips)) < 0.3
    depth[outside] = -rng.uniform(0.0005, 0.01, size=outside.sum())
    local[..., 0] = side * (HALF[0] - depth)
    return local, side, outside


def test_tips_inside_a_box_land_on_the_nearest_face_and_tips_outside_stay(slab):
    """Inside a box the signed distance is linear near a face, so the corrected tip is exactly
    the foot of the perpendicular on that face; in every frame's own object pose."""
    local, side, outside = _slab_tips()
    pose = _poses(len(local), 1)
    tips = transform_points(pose, local)
    corrected = surface_corrected_tips(tips, pose, slab)
    expected = local.copy()
    expected[..., 0] = np.where(outside, local[..., 0], side * HALF[0])
    np.testing.assert_allclose(corrected, transform_points(pose, expected), atol=2e-6)
    assert np.array_equal(corrected[outside], tips[outside])  # untouched, bit for bit
    moved = np.linalg.norm(corrected - tips, axis=-1)[~outside]
    np.testing.assert_allclose(moved, HALF[0] - np.abs(local[..., 0][~outside]), atol=2e-6)


def test_tips_inside_a_sphere_move_radially_onto_it_and_never_end_inside(ball):
    rng = np.random.default_rng(2)
    direction = rng.normal(size=(40, 5, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    local = direction * rng.uniform(0.01, 0.0295, size=(40, 5, 1))  # 0.5 to 20 mm deep
    pose = _poses(40, 3)
    corrected = surface_corrected_tips(transform_points(pose, local), pose, ball, tolerance_m=1e-7)
    back = transform_points(np.linalg.inv(pose), corrected)
    assert np.linalg.norm(back - 0.03 * direction, axis=-1).max() < 1.5e-4
    sd = ball.query(back)
    assert sd.min() >= -1e-15 and sd.max() <= 1e-7  # -1e-15: the pose's rounding


def test_a_batch_equals_its_frames_one_at_a_time(slab):
    local, _, _ = _slab_tips(frames=6, seed=4)
    pose = _poses(6, 5)
    tips = transform_points(pose, local)
    batch = surface_corrected_tips(tips, pose, slab)
    for t in range(len(tips)):
        one = surface_corrected_tips(tips[t : t + 1], pose[t : t + 1], slab)
        np.testing.assert_allclose(batch[t], one[0], rtol=0, atol=1e-12)


def test_a_tip_at_the_centre_of_a_symmetric_object_still_leaves_it(ball):
    """The gradient vanishes at the centre of a ball: the tip is still moved onto the surface."""
    corrected = surface_corrected_tips(np.zeros((1, 1, 3)), np.eye(4)[None], ball)
    assert np.linalg.norm(corrected) == pytest.approx(0.03, abs=1e-4)


def test_nan_tips_stay_nan_and_wrong_shapes_are_refused(slab):
    tips = np.full((2, 3, 3), np.nan)
    assert np.isnan(surface_corrected_tips(tips, _poses(2, 6), slab)).all()
    with pytest.raises(ValueError, match=r"\(T, 4, 4\)"):
        surface_corrected_tips(tips, _poses(3, 6), slab)
    with pytest.raises(ValueError, match=r"\(T, K, 3\)"):
        surface_corrected_tips(tips[0], _poses(2, 6), slab)
