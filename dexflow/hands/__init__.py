"""Robot hands: configs, model loading (URDF/MJCF), batched kinematics, URDF export, checks."""

from dexflow.hands.robot import BASE_JOINT_NAMES, RobotHand, load_hand
from dexflow.hands.spec import CouplingSpec, FingerSpec, HandSpec, KeypointSpec, load_hand_spec

__all__ = [
    "BASE_JOINT_NAMES",
    "CouplingSpec",
    "FingerSpec",
    "HandSpec",
    "KeypointSpec",
    "RobotHand",
    "load_hand",
    "load_hand_spec",
]
