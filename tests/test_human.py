"""The anatomical human hand model: adult proportions, canonical frame, batching."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.human.keypoints import FINGER_KEYPOINTS, FINGERTIPS, MIDDLE_MCP, WRIST, wrist_frame
from dexflow.human.model import (
    _THUMB_BASE,
    _THUMB_PRONATION_PER_ABDUCTION,
    HandShape,
    finger_capsules,
    forward_keypoints,
)


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


def _about(axis: int, angle: float) -> Rotation:
    return Rotation.from_rotvec(angle * np.eye(3)[axis])


def test_joint_rotations_compose_in_the_moving_frame():
    """Bone directions from products of elementary rotations, each about the rotated axes."""
    shape = HandShape()
    angles = np.random.default_rng(2).uniform(-0.6, 0.9, size=20)
    kp = forward_keypoints(angles, shape=shape)
    cmc_flex, cmc_abd, mcp, ip = angles[:4]
    thumb = Rotation.from_matrix(_THUMB_BASE) * _about(1, cmc_flex) * _about(0, -cmc_abd)
    thumb = thumb * _about(2, _THUMB_PRONATION_PER_ABDUCTION * cmc_abd)
    abd, mcp_i, pip, dip = angles[4:8]
    index = _about(0, -(shape.spread["index"] + abd)) * _about(1, mcp_i)
    for chain, rot, flex in (
        (FINGER_KEYPOINTS["thumb"], thumb, (mcp, ip)),
        (FINGER_KEYPOINTS["index"], index, (pip, dip)),
    ):
        for j, angle in enumerate((0.0, *flex)):
            rot = rot * _about(1, angle)
            bone = kp[chain[j + 1]] - kp[chain[j]]
            np.testing.assert_allclose(
                bone / np.linalg.norm(bone), rot.apply([0.0, 0.0, 1.0]), atol=1e-12
            )


def test_batch_equals_one_at_a_time_and_wrist_pose_is_applied():
    rng = np.random.default_rng(1)
    angles = rng.uniform(-0.2, 1.2, size=(7, 20))
    pose = np.repeat(np.eye(4)[None], 7, axis=0)
    pose[:, :3, :3] = Rotation.random(7, rng=rng).as_matrix()
    pose[:, :3, 3] = rng.normal(size=(7, 3))
    batch = forward_keypoints(angles, pose)
    for i in range(7):
        np.testing.assert_allclose(batch[i], forward_keypoints(angles[i], pose[i]), atol=1e-12)
    in_wrist = forward_keypoints(angles)
    expected = np.einsum("tij,tkj->tki", pose[:, :3, :3], in_wrist) + pose[:, None, :3, 3]
    np.testing.assert_allclose(batch, expected, atol=1e-12)
    assert forward_keypoints(angles[:1]).shape == (1, 21, 3)


def test_capsules_follow_bones():
    kp = forward_keypoints(np.zeros(20))
    points, radii = finger_capsules(kp, samples_per_segment=4)
    assert points.shape == (5, 12, 3) and radii.shape == (12,)
    np.testing.assert_allclose(points[2, -1], kp[12])
    assert radii[0] > radii[-1]  # fingers taper towards the tip
