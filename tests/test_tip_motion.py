"""Tests for dexflow.tools.tip_motion: a fingertip change split along and across the object normal."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from dexflow.hands import load_hand
from dexflow.human.keypoints import FINGERTIPS
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.tools.tip_motion import fingertip_motion, summarize_motion


@pytest.fixture(scope="module")
def allegro():
    return load_hand("allegro")


def _wall(hand, frames: int, gap_m: float):
    """The hand at zero (fingers along +z) beside a wall (a wide box) whose +x face lies
    ``gap_m`` behind the fingertip nearest to it; the keypoints, the wall's grid and poses."""
    q = hand.zero(frames).numpy()
    with torch.no_grad():
        keypoints = hand.keypoints(torch.as_tensor(q)).numpy()
    tips = np.isin(hand.mano_indices, FINGERTIPS)
    face = keypoints[0, tips, 0].min() - gap_m
    box = trimesh.creation.box(extents=(0.05, 0.5, 0.5))
    grid = SignedDistanceGrid.from_mesh(box, spacing=0.004, padding=0.03)
    pose = np.repeat(np.eye(4)[None], frames, axis=0)
    pose[:, :3, 3] = [face - 0.025, *keypoints[0, tips, 1:].mean(0)]
    return q, keypoints, tips, grid, pose


def test_a_shift_of_the_hand_splits_into_normal_and_tangential_parts(allegro):
    """Moving the floating base by v moves every fingertip and the palm by |v|: v·n along the
    wall's normal (+x) and the rest across it; an unchanged trajectory moves nothing."""
    q, keypoints, tips, grid, pose = _wall(allegro, 3, 0.004)
    observed = np.array([True, False, True])
    moved = q.copy()
    moved[:, :3] += [0.002, 0.003, -0.004]
    parts = fingertip_motion(allegro, q, moved, keypoints, observed, pose, grid, near_m=0.05)
    assert len(parts["normal"]) == 2 * tips.sum() and parts["near"].all()  # observed frames only
    np.testing.assert_allclose(parts["normal"], 0.002, atol=2e-4)
    np.testing.assert_allclose(parts["tangential"], 0.005, atol=2e-4)
    np.testing.assert_allclose(parts["moved"], np.sqrt(0.002**2 + 0.003**2 + 0.004**2))
    np.testing.assert_allclose(parts["palm"], parts["moved"][0])
    np.testing.assert_allclose(parts["error_to"], parts["moved"], atol=1e-12)
    np.testing.assert_allclose(parts["error_from"], 0.0, atol=1e-12)
    still = fingertip_motion(allegro, q, q, keypoints, observed, pose, grid, near_m=0.05)
    assert np.abs(still["moved"]).max() == 0.0 and np.abs(still["palm"]).max() == 0.0
    summary = summarize_motion([parts, still])
    assert summary["tips"] == 4 * tips.sum() and summary["near_share"] == 1.0
    assert summary["normal_mm"] == pytest.approx(1.0, abs=0.1)  # half the pairs moved 2 mm
    assert summary["outward_mm"] == pytest.approx(1.0, abs=0.1)
    assert np.isnan(summary["far_moved_mm"])  # no fingertip was far


def test_annotated_depth_and_near_or_far(allegro):
    """Human fingertips put 3 mm inside the wall count 3 mm deep and near; a wall 20 cm away
    makes every fingertip far and no depth."""
    q, keypoints, tips, grid, pose = _wall(allegro, 2, 0.0)
    observed = np.ones(2, dtype=bool)
    human = keypoints.copy()
    human[:, tips, 0] = pose[0, 0, 3] + 0.025 - 0.003
    parts = fingertip_motion(allegro, q, q, human, observed, pose, grid)
    np.testing.assert_allclose(parts["depth"], 0.003, atol=3e-4)
    assert parts["near"].all()
    assert summarize_motion([parts])["tip_depth_mm"] == pytest.approx(3.0, abs=0.3)
    far = pose.copy()
    far[:, 0, 3] -= 0.2
    parts = fingertip_motion(allegro, q, q, keypoints, observed, far, grid)
    assert not parts["near"].any() and parts["depth"].max() == 0.0
