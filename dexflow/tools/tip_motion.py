"""Where one trajectory's fingertips move relative to another's, and how deep the data puts them.

Refinement must take the hand out of the object, and the fingertip error is measured against
the annotated human fingertips, which on real captures lie inside the object. This module
splits the change of the robot fingertips between two trajectories (retargeted -> refined) into
its parts, so that a report can say how much of the added fingertip error the data forces:

- ``tip_depth_mm``: how deep the annotated human fingertips lie inside the object, ``max(0,
  -sd(h))`` averaged over observed frames and fingertips. A hand whose fingertip keypoints lie
  inside its own links is at least this far from them once it penetrates nowhere.
- For fingertips whose human tip is within ``near_m`` of the object: the displacement ``Δ`` of
  the robot fingertip split along the object's outward normal ``n`` at the first trajectory's
  fingertip (``normal_mm = mean |Δ·n|``, ``outward_mm = mean Δ·n``) and across it
  (``tangential_mm = mean |Δ - (Δ·n) n|``), and both trajectories' fingertip errors there;
- for the fingertips farther away: the mean displacement and both errors;
- ``palm_mm``: the mean displacement of the palm keypoint (MANO joint 0), i.e. how far the
  hand as a whole moved.

Lengths in millimetres, means over observed frames (valid and not tracking-lost).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from dexflow.geometry import world_to_object

if TYPE_CHECKING:
    from dexflow.hands.robot import RobotHand
    from dexflow.objects.sdf import SignedDistanceGrid

__all__ = ["NEAR_M", "fingertip_motion", "summarize_motion"]

NEAR_M = 0.02  # a human fingertip this close to the object counts as near it


def fingertip_motion(
    hand: RobotHand,
    q_from: np.ndarray,
    q_to: np.ndarray,
    human: np.ndarray,
    observed: np.ndarray,
    obj_pose: np.ndarray,
    sdf: SignedDistanceGrid,
    near_m: float = NEAR_M,
) -> dict[str, np.ndarray]:
    """Per observed frame and fingertip, the parts of the change from ``q_from`` to ``q_to``.

    Args:
        q_from, q_to: (T, dof) robot trajectories (e.g. retargeted and refined).
        human: (T, K, 3) human keypoints matched to the hand's keypoints.
        observed: (T,) frames with a real observation.
        obj_pose: (T, 4, 4) object poses.
        near_m: A fingertip counts as near when its human tip is closer to the object.

    Returns:
        Arrays over the (observed frame, fingertip) pairs, flattened: ``depth`` (human tip
        inside the object, m, >= 0), ``near`` (bool), ``normal`` (signed, outward +),
        ``tangential``, ``moved`` (|Δ|), ``error_from``, ``error_to``; and ``palm`` (observed
        frames,) the palm keypoint's displacement (empty if the hand maps no palm keypoint).
    """
    observed = np.asarray(observed, dtype=bool)
    with torch.no_grad():
        keypoints = [
            hand.keypoints(torch.as_tensor(q[observed], dtype=hand.dtype)).numpy()
            for q in (q_from, q_to)
        ]
    tips = hand.fingertip_keypoints
    palm = [i for i, m in enumerate(hand.mano_indices) if m == 0]
    start, end = (k[:, tips] for k in keypoints)
    human_tips = np.asarray(human)[observed][:, tips]
    pose = np.asarray(obj_pose)[observed]
    sd_human = sdf.query(world_to_object(human_tips, pose))
    _, gradient = sdf.query(world_to_object(start, pose), with_gradient=True)
    normal_obj = gradient / np.maximum(np.linalg.norm(gradient, axis=-1, keepdims=True), 1e-12)
    normal = np.einsum("tij,tkj->tki", pose[:, :3, :3], normal_obj)  # object -> world
    change = end - start
    along = (change * normal).sum(-1)
    return {
        "depth": np.clip(-sd_human, 0.0, None).ravel(),
        "near": (sd_human < near_m).ravel(),
        "normal": along.ravel(),
        "tangential": np.linalg.norm(change - along[..., None] * normal, axis=-1).ravel(),
        "moved": np.linalg.norm(change, axis=-1).ravel(),
        "error_from": np.linalg.norm(start - human_tips, axis=-1).ravel(),
        "error_to": np.linalg.norm(end - human_tips, axis=-1).ravel(),
        "palm": np.linalg.norm(keypoints[1][:, palm] - keypoints[0][:, palm], axis=-1).ravel(),
    }


def summarize_motion(parts: list[dict[str, np.ndarray]]) -> dict[str, float]:
    """The means of the module docstring (mm; ``near_share`` a fraction) over the pairs of
    several sequences' :func:`fingertip_motion`."""
    keys = ("depth", "near", "normal", "tangential", "moved", "error_from", "error_to", "palm")
    pooled = {k: np.concatenate([p[k] for p in parts]) if parts else np.zeros(0) for k in keys}
    near = pooled["near"].astype(bool)

    def mm(values: np.ndarray) -> float:
        return 1000 * float(values.mean()) if len(values) else float("nan")

    return {
        "tips": len(near),
        "tip_depth_mm": mm(pooled["depth"]),
        "near_share": float(near.mean()) if len(near) else float("nan"),
        "near_error_from_mm": mm(pooled["error_from"][near]),
        "near_error_to_mm": mm(pooled["error_to"][near]),
        "normal_mm": mm(np.abs(pooled["normal"][near])),
        "outward_mm": mm(pooled["normal"][near]),
        "tangential_mm": mm(pooled["tangential"][near]),
        "far_error_from_mm": mm(pooled["error_from"][~near]),
        "far_error_to_mm": mm(pooled["error_to"][~near]),
        "far_moved_mm": mm(pooled["moved"][~near]),
        "palm_mm": mm(pooled["palm"]),
    }
