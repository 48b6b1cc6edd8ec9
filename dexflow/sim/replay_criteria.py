"""The replay's criteria: which frames of a sequence are replayed and scored, and the scores.

Stage replay (:mod:`dexflow.stages.replay`, whose docs give the rules and their reasons) and
stage track (:mod:`dexflow.stages.track`, which optimises against them) share these: the window
(:func:`replay_window`: lead frames, first contact, release, "no support", "free fall"), the
recorded lift (:func:`lift_frame`), a replayed sequence's summary entry (:func:`sequence_result`:
SPIDER's success, carried, lost, time held) and the ceiling a trajectory's base path sets on it
(:func:`rigid_ceiling`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from dexflow.hands.robot import base_transform
from dexflow.human.keypoints import wrist_frame
from dexflow.io.sequence import Sequence
from dexflow.params import ReplayParams

__all__ = [
    "ReplayWindow",
    "grasp_window",
    "lift_frame",
    "replay_errors",
    "replay_window",
    "rigid_ceiling",
    "sequence_result",
]


def grasp_window(final: np.ndarray, lead_frames: int) -> tuple[int, int, int] | None:
    """``(start, first_contact, end)`` of the grasp phase of contact states ``final (T, F)``:
    ``lead_frames`` before the first frame with a finger in contact (not before 0) to the last
    one; None without contact."""
    touching = np.asarray(final, dtype=bool).any(axis=1)
    if not touching.any():
        return None
    frames = np.flatnonzero(touching)
    first, end = int(frames[0]), int(frames[-1])
    return max(0, first - lead_frames), first, end


@dataclass(frozen=True)
class ReplayWindow:
    """The frames a sequence is replayed over and scored on, and whether it is scored (see the
    module docs for the rules).

    Attributes:
        start: First frame replayed: ``lead_frames`` before the first contact, not before 0.
        first_contact: First frame with a finger in contact; scoring starts there.
        end: Last frame replayed and scored: the last in contact before the release, else the
            last in contact.
        last_contact: Last frame with a finger in contact.
        release_frame: Frame where the object was found to have left the hand (-1: never).
        support_drift_m: Largest change of the height of the object's lowest point from the
            first frame to the first contact, against its height at the first contact.
        free_fall_frame: First frame of a free fall within ``first_contact..end`` (-1: none).
        not_scored_reason: None when scored, else ``"no support"`` or ``"free fall"``.
    """

    start: int
    first_contact: int
    end: int
    last_contact: int
    release_frame: int
    support_drift_m: float
    free_fall_frame: int
    not_scored_reason: str | None

    @property
    def scored(self) -> bool:
        return self.not_scored_reason is None

    def entry(self) -> dict:
        """The window's keys of the sequence's summary entry."""
        return {**asdict(self), "scored": self.scored}


def replay_window(
    touching: np.ndarray, seq: Sequence, lowest_m: np.ndarray, p: ReplayParams
) -> ReplayWindow | None:
    """Where a sequence is replayed and scored, and whether it can be (module docs).

    Args:
        touching: (T,) frames with a finger in contact (stage contact's final states).
        seq: The recorded sequence: object poses, human keypoints and where they were tracked.
        lowest_m: (T,) height of the object's lowest point at each recorded pose
            (:meth:`ReplayWorld.lowest_heights`).
        p: The replay's parameters.

    Returns:
        The window; None without contact.
    """
    touching = np.asarray(touching, dtype=bool)
    contact = grasp_window(touching[:, None], p.lead_frames)
    if contact is None:
        return None
    start, first, last = contact
    in_hand = _in_wrist_frame(seq)
    release = _release_frame(touching, seq, in_hand, first, p.release_distance_m)
    end = last if release < 0 else int(np.flatnonzero(touching[:release])[-1])
    lowest_m = np.asarray(lowest_m, dtype=float)
    drift = float(np.abs(lowest_m[: first + 1] - lowest_m[first]).max())
    fall = _free_fall_frame(seq, in_hand, first, end, p)
    reason = None
    if drift > p.support_tolerance_m:
        reason = "no support"
    elif fall >= 0:
        reason = "free fall"
    return ReplayWindow(start, first, end, last, release, drift, fall, reason)


def _in_wrist_frame(seq: Sequence) -> np.ndarray:
    """(T, 3) the recorded object's position in the recorded wrist's frame (constant while the
    hand carries it rigidly)."""
    wrist = wrist_frame(seq.keypoints)
    position = seq.obj_pose[:, :3, 3]
    return np.einsum("tji,tj->ti", wrist[:, :3, :3], position - wrist[:, :3, 3])


def _release_frame(
    touching: np.ndarray, seq: Sequence, in_hand: np.ndarray, first: int, distance_m: float
) -> int:
    """First frame after ``first`` where the object has left the hand (-1: none): out of
    contact, and ``distance_m`` from where it was at the last contact both in the world and in
    the wrist's frame (``in_hand``), the hand tracked at both frames."""
    frames = np.arange(len(touching))
    held = np.maximum.accumulate(np.where(touching, frames, 0))  # last frame in contact so far
    position = seq.obj_pose[:, :3, 3]
    moved = np.linalg.norm(position - position[held], axis=1) > distance_m
    left = np.linalg.norm(in_hand - in_hand[held], axis=1) > distance_m
    tracked = seq.valid_mask
    found = ~touching & (frames > first) & tracked & tracked[held] & moved & left
    hits = np.flatnonzero(found)
    return int(hits[0]) if len(hits) else -1


def _free_fall_frame(
    seq: Sequence, in_hand: np.ndarray, first: int, end: int, p: ReplayParams
) -> int:
    """First frame ``t`` in ``first..end`` starting ``k`` frames there over which the object
    falls freely, away from the hand (-1: none): its mean vertical acceleration within
    ``free_fall_tolerance_mps2`` of ``-gravity``, and ``release_distance_m`` moved in the
    wrist's frame (``in_hand``) from frame ``t - 1`` to ``t + k``, the hand tracked at both."""
    fps, z = seq.fps, seq.obj_pose[:, 2, 3]
    k = max(1, round(p.free_fall_s * fps))
    velocity = np.diff(z) * fps  # (T-1,) between frames s and s+1
    t = np.arange(max(first, 1), min(end, len(z) - 2) - k + 2)
    mean = (velocity[t + k - 1] - velocity[t - 1]) * fps / k
    tracked = seq.valid_mask[t - 1] & seq.valid_mask[t + k]
    away = np.linalg.norm(in_hand[t + k] - in_hand[t - 1], axis=1) > p.release_distance_m
    hits = t[(np.abs(mean + p.gravity) < p.free_fall_tolerance_mps2) & tracked & away]
    return int(hits[0]) if len(hits) else -1


def sequence_result(
    rows: dict[str, np.ndarray], first: int, poses: np.ndarray, fps: float, p: ReplayParams
) -> dict:
    """A replayed sequence's summary entry from its rows (see the module docs)."""
    frames = rows["frame"]
    grasp = frames >= first
    pos, rot = rows["position_error_m"][grasp], rows["rotation_error_rad"][grasp]
    lost = np.flatnonzero((pos > p.lost_position_m) | (rot > p.lost_rotation_rad))
    lost_frame = int(frames[grasp][lost[0]]) if len(lost) else -1
    held = (lost[0] if len(lost) else len(pos)) / fps
    static = np.linalg.norm(poses[frames[grasp], :3, 3] - poses[first, :3, 3], axis=1)
    position_mean, rotation_mean = float(pos.mean()), float(rot.mean())
    spider = position_mean < p.max_position_error_m and rotation_mean < p.max_rotation_error_rad
    # carried: it ends near where the human took it, much nearer than if left where it was
    carried = pos[-1] < min(p.max_position_error_m, p.carried_fraction * static[-1])
    return {
        "replayed": True,
        "frames": len(frames),
        "first_contact": int(first),
        "end": int(frames[-1]),
        "success": bool(spider and carried),
        "spider_success": bool(spider),
        "carried": bool(carried),
        "position_error_mean_m": position_mean,
        "rotation_error_mean_rad": rotation_mean,
        "position_error_max_m": float(pos.max()),
        "rotation_error_max_rad": float(rot.max()),
        "position_error_final_m": float(pos[-1]),
        "rotation_error_final_rad": float(rot[-1]),
        "lost": lost_frame >= 0,
        "lost_frame": lost_frame,
        "held_s": float(held),
        "held_fraction": float(held * fps / len(pos)),
        "static_error_mean_m": float(static.mean()),
        "static_error_final_m": float(static[-1]),
        "recorded_travel_m": float(static.max()),
        "base_error_mean_m": float(rows["base_error_m"].mean()),
        "joint_error_mean_rad": float(rows["joint_error_rad"].mean()),
    }


def replay_errors(
    position: np.ndarray, quat: np.ndarray, poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (rad) errors of simulated object poses against recorded ones.

    Args:
        position: (N, 3) simulated positions.
        quat: (N, 4) simulated orientations (w, x, y, z).
        poses: (N, 4, 4) recorded poses.

    Returns:
        ``||p - p_rec||`` (N,) and the angle of ``R_rec^T R`` (N,).
    """
    rotation = Rotation.from_quat(np.asarray(quat)[:, [1, 2, 3, 0]])
    recorded = Rotation.from_matrix(poses[:, :3, :3])
    angle = (recorded.inv() * rotation).magnitude()
    return np.linalg.norm(position - poses[:, :3, 3], axis=1), angle


def lift_frame(poses: np.ndarray, window: tuple[int, int, int]) -> int:
    """The **lift**: the first frame after the first contact where the recorded object is 1 cm
    from where it was then (the window's end if it never is).

    Args:
        poses: (T, 4, 4) the recorded object poses.
        window: ``(start, first_contact, end)``.
    """
    _, first, end = window
    position = np.asarray(poses)[:, :3, 3]
    moved = np.linalg.norm(position[first : end + 1] - position[first], axis=1) > 0.01
    return first + (int(np.argmax(moved)) if moved.any() else end - first)


def rigid_ceiling(
    q: np.ndarray, poses: np.ndarray, fps: float, window: tuple[int, int, int], p: ReplayParams
) -> dict:
    """The **rigid-grasp ceiling** of a trajectory: how the replay would score an object that
    never slips, welded to the hand's base from the recorded lift on.

    Before the lift (:func:`lift_frame`) the object stays at its recorded pose; from there it
    moves rigidly with the base of ``q``: ``B(t) B(lift)^-1 P(lift)``. Scored against the
    recorded poses by :func:`sequence_result`'s criteria, no physics. No grip, however good,
    makes the object follow its recording better than the hand's own path allows, so where the
    ceiling fails the path is what fails: the recorded object turns in the human hand (or its
    rotations are misread: ``dexflow convert`` checks them), and a hand that follows the
    human's wrist cannot reproduce that rotation.

    Args:
        q: (T, dof) the trajectory (its base ``q[:, :6]``).
        poses: (T, 4, 4) the recorded object poses.
        fps: Frames per second.
        window: ``(start, first_contact, end)`` of the replay.
        p: The replay's parameters (its thresholds).

    Returns:
        ``ceiling_success``, ``ceiling_spider_success``, ``ceiling_position_error_mean_m`` and
        ``ceiling_rotation_error_mean_rad``.
    """
    start, first, end = window
    poses = np.asarray(poses, dtype=float)
    frames = np.arange(start, end + 1)
    lift = lift_frame(poses, window)
    base = base_transform(torch.as_tensor(np.asarray(q, dtype=float)[frames, :6])).numpy()
    carried = poses[frames].copy()
    after = frames >= lift
    attached = np.linalg.inv(base[lift - start]) @ poses[lift]
    carried[after] = base[after] @ attached
    quat = Rotation.from_matrix(carried[:, :3, :3]).as_quat(scalar_first=True)
    position, rotation = replay_errors(carried[:, :3, 3], quat, poses[frames])
    rows = {
        "frame": frames,
        "position_error_m": position,
        "rotation_error_rad": rotation,
        "base_error_m": np.zeros(len(frames)),
        "joint_error_rad": np.zeros(len(frames)),
    }
    r = sequence_result(rows, first, poses, fps, p)
    return {
        "ceiling_success": r["success"],
        "ceiling_spider_success": r["spider_success"],
        "ceiling_position_error_mean_m": r["position_error_mean_m"],
        "ceiling_rotation_error_mean_rad": r["rotation_error_mean_rad"],
    }
