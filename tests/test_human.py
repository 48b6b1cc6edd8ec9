"""The anatomical human hand model: adult proportions, canonical frame, batching."""

from __future__ import annotations

import numpy as np

from dexflow.human.keypoints import FINGERTIPS, MIDDLE_MCP, WRIST, wrist_frame
from dexflow.human.model import HandShape, finger_capsules, forward_keypoints


def test_adult_hand_proportions():
    kp = forward_keypoints(np.zeros(20))
    hand_length = np.linalg.norm(kp[12] - kp[WRIST])  # wrist to middle fingertip
    assert 0.165 <= hand_length <= 0.205  # adult hand length range (about 17-20 cm)
    palm_length = np.linalg.norm(kp[MIDDLE_MCP] - kp[WRIST])
    assert 0.08 <= palm_length <= 0.11
    palm_width = np.linalg.norm(kp[5] - kp[17])  # index MCP to little MCP
    assert 0.055 <= palm_width <= 0.09
    small = forward_keypoints(np.zeros(20), shape=HandShape(scale=0.9))
    assert np.linalg.norm(small[12] - small[0]) < hand_length


def test_model_frame_is_the_canonical_wrist_frame():
    kp = forward_keypoints(np.random.default_rng(0).uniform(0, 1, size=(5, 20)))
    np.testing.assert_allclose(wrist_frame(kp), np.broadcast_to(np.eye(4), (5, 4, 4)), atol=1e-12)


def test_fingers_flex_towards_the_palm_side():
    open_tips = forward_keypoints(np.zeros(20))[list(FINGERTIPS[1:])]
    angles = np.zeros(20)
    angles[4:] = np.tile([0.0, 0.8, 0.8, 0.4], 4)
    closed_tips = forward_keypoints(angles)[list(FINGERTIPS[1:])]
    assert (closed_tips[:, 0] > open_tips[:, 0] + 0.03).all()  # +x is out of the palm


def test_batch_equals_one_at_a_time_and_wrist_pose_is_applied():
    rng = np.random.default_rng(1)
    angles = rng.uniform(-0.2, 1.2, size=(7, 20))
    pose = np.repeat(np.eye(4)[None], 7, axis=0)
    pose[:, :3, 3] = rng.normal(size=(7, 3))
    batch = forward_keypoints(angles, pose)
    for i in range(7):
        np.testing.assert_allclose(batch[i], forward_keypoints(angles[i], pose[i]), atol=1e-12)
    np.testing.assert_allclose(batch - pose[:, None, :3, 3], forward_keypoints(angles), atol=1e-12)


def test_capsules_follow_bones():
    kp = forward_keypoints(np.zeros(20))
    points, radii = finger_capsules(kp, samples_per_segment=4)
    assert points.shape == (5, 12, 3) and radii.shape == (12,)
    np.testing.assert_allclose(points[2, -1], kp[12])
    assert radii[0] > radii[-1]  # fingers taper towards the tip
