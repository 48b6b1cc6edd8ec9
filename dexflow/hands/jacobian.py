"""Analytic keypoint Jacobians of a :class:`RobotHand`, batched over frames.

For a revolute joint with world axis ``a`` through ``o``, a point ``x`` moved by it changes as
``dx/dθ = a × (x - o)``; for a prismatic joint ``dx/dθ = a``. The floating base contributes
the identity (translation) and its three rotation axes ``x``, ``Rx y``, ``Rx Ry z`` through the
base origin. One forward-kinematics call gives every axis and origin, so a Jacobian of all
keypoints for T frames costs about as much as the keypoints themselves.
"""

from __future__ import annotations

import numpy as np
import torch

from dexflow.errors import HandConfigError
from dexflow.hands.robot import RobotHand, base_transform

__all__ = ["KeypointJacobian"]


class KeypointJacobian:
    """Keypoints and their Jacobian with respect to the full configuration ``q``.

    Args:
        hand: The hand.
    """

    def __init__(self, hand: RobotHand) -> None:
        self.hand = hand
        chain = hand.chain
        joint_frames, axes, kinds = [], [], []
        for name in hand.hand_joint_names:
            frame = next(f for f in _frames(chain._root) if f.joint.name == name)
            offset = frame.link.offset
            if hand.model.format == "mjcf" and frame.joint.offset is not None:
                if frame.joint.offset.get_matrix()[0, :3, 3].abs().max() > 1e-12:
                    raise HandConfigError(
                        f"joint '{name}' is offset from its body frame; "
                        "analytic Jacobians need joints at body origins"
                    )
            if hand.model.format == "urdf" and offset is not None:
                if (offset.get_matrix()[0] - torch.eye(4, dtype=offset.dtype)).abs().max() > 1e-12:
                    raise HandConfigError(f"link of joint '{name}' has an offset after the joint")
            joint_frames.append(frame.name)
            axes.append(frame.joint.axis.detach().cpu().numpy())
            kinds.append(frame.joint.joint_type)
        self.joint_frames = joint_frames
        self._axes = torch.as_tensor(np.asarray(axes), dtype=hand.dtype, device=hand.device)
        self._prismatic = torch.tensor([k == "prismatic" for k in kinds], device=hand.device)
        self._frames = list(dict.fromkeys(hand.keypoint_links + joint_frames))
        self._kp_idx = torch.tensor([self._frames.index(n) for n in hand.keypoint_links])
        self._joint_idx = torch.tensor([self._frames.index(n) for n in joint_frames])
        self._pk_indices = chain.get_frame_indices(*self._frames)
        ancestors = _ancestor_joints(hand)
        pairs = [
            (k, j)
            for k, link in enumerate(hand.keypoint_links)
            for j, name in enumerate(hand.hand_joint_names)
            if name in ancestors[link]
        ]
        self._pair_k = torch.tensor([k for k, _ in pairs], dtype=torch.long)  # keypoint moved ...
        self._pair_j = torch.tensor([j for _, j in pairs], dtype=torch.long)  # ... by this joint
        self._offsets = hand.keypoint_offsets

    def __call__(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoints (T, K, 3) and Jacobian (T, K, 3, dof) at ``q (T, dof)``."""
        hand = self.hand
        q = hand.as_q(q)
        ret = hand.chain.forward_kinematics(q[:, 6:], frame_indices=self._pk_indices)
        local = torch.stack([ret[n].get_matrix() for n in self._frames], dim=1)  # (T, F, 4, 4)
        rot_base = base_transform(q[:, :6])[:, :3, :3]
        pos_base = q[:, :3]
        world_rot = rot_base[:, None] @ local[..., :3, :3]
        world_pos = (rot_base[:, None] @ local[..., :3, 3:])[..., 0] + pos_base[:, None]

        kp_rot, kp_pos = world_rot[:, self._kp_idx], world_pos[:, self._kp_idx]
        keypoints = (kp_rot @ self._offsets[..., None])[..., 0] + kp_pos  # (T, K, 3)

        axes = (world_rot[:, self._joint_idx] @ self._axes[..., None])[..., 0]  # (T, J, 3)
        origins = world_pos[:, self._joint_idx]
        # Only (keypoint, joint) pairs where the joint is an ancestor of the keypoint's link.
        pair_axes = axes[:, self._pair_j]  # (T, P, 3)
        lever = keypoints[:, self._pair_k] - origins[:, self._pair_j]
        cols = torch.cross(pair_axes, lever, dim=-1)
        cols = torch.where(self._prismatic[self._pair_j][None, :, None], pair_axes, cols)

        t, k = keypoints.shape[:2]
        jac = torch.zeros(t, k, 3, hand.dof, dtype=q.dtype, device=q.device)
        jac[:, :, :, :3] = torch.eye(3, dtype=q.dtype, device=q.device)
        # The base's rotation axes x, Rx y, Rx Ry z: each moved by the rotations before it.
        rot_x = base_transform(q[:, :6] * q.new_tensor([0, 0, 0, 1, 0, 0]))[:, :3, :3]  # Rx
        base_axes = torch.stack([rot_x[:, :, 0], rot_x[:, :, 1], rot_base[:, :, 2]], dim=1)
        arm = keypoints - pos_base[:, None]
        for i in range(3):
            jac[:, :, :, 3 + i] = torch.cross(base_axes[:, i, None].expand_as(arm), arm, dim=-1)
        jac[:, self._pair_k, :, 6 + self._pair_j] = cols.permute(1, 0, 2)  # advanced dims first
        return keypoints, jac


def _frames(root):
    yield root
    for child in root.children:
        yield from _frames(child)


def _ancestor_joints(hand: RobotHand) -> dict[str, set[str]]:
    """Frame -> the actuated joints between the root and it."""
    out: dict[str, set[str]] = {}
    for name in hand.model.frames:
        joints, current = set(), name
        while current is not None:
            parent, joint = hand.model.parents[current]
            if joint is not None:
                joints.add(joint)
            current = parent
        out[name] = joints
    return out
