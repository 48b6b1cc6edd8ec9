"""Robot hands: configs, model loading (URDF/MJCF), batched kinematics, URDF export, checks.

The kinematics (``RobotHand``, torch and pytorch-kinematics) load on first use, so that modules
needing only the config schema (``dexflow.hands.spec``, ``dexflow.params``) stay light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from dexflow.hands.spec import CouplingSpec, FingerSpec, HandSpec, KeypointSpec, load_hand_spec

if TYPE_CHECKING:
    from dexflow.hands.robot import BASE_JOINT_NAMES, RobotHand, load_hand

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

_FROM_ROBOT = ("BASE_JOINT_NAMES", "RobotHand", "load_hand")


def __getattr__(name: str) -> Any:
    if name in _FROM_ROBOT:
        from dexflow.hands import robot

        return getattr(robot, name)
    raise AttributeError(f"module 'dexflow.hands' has no attribute {name!r}")
