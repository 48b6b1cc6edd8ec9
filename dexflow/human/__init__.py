"""Human hand conventions and the anatomical keypoint model used by the demo generator."""

from dexflow.human.keypoints import FINGERS, FINGERTIPS, KEYPOINT_NAMES, NUM_KEYPOINTS, wrist_frame
from dexflow.human.model import JOINT_NAMES, HandShape, finger_capsules, forward_keypoints

__all__ = [
    "FINGERS",
    "FINGERTIPS",
    "JOINT_NAMES",
    "KEYPOINT_NAMES",
    "NUM_KEYPOINTS",
    "HandShape",
    "finger_capsules",
    "forward_keypoints",
    "wrist_frame",
]
