"""Tracking-loss detection: lost runs anywhere and of any length, real frames never masked."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dexflow.human.cleaning import detect_bad_frames
from dexflow.human.model import forward_keypoints

FPS = 30.0


def _real_hand(n: int, seed: int, speed_mps: float = 0.6) -> np.ndarray:
    """(n, 21, 3) keypoints of a hand moving smoothly (up to ``speed_mps``) with tracker noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FPS
    wrist = np.repeat(np.eye(4)[None], n, axis=0)
    freq = rng.uniform(0.2, 0.6, size=3)
    amp = speed_mps / (2 * np.pi * freq) / np.sqrt(3)
    wrist[:, :3, 3] = [0.4, 0.0, 0.1] + amp * np.sin(2 * np.pi * freq * t[:, None])
    wrist[:, :3, :3] = Rotation.from_rotvec(0.3 * np.sin(t)[:, None] * [0.0, 1.0, 0.5]).as_matrix()
    closure = 0.6 * (0.5 - 0.5 * np.cos(t))[:, None] * np.ones(20)
    kp = forward_keypoints(closure, wrist)
    return kp + rng.normal(scale=0.002, size=kp.shape)


def _template_hand(n: int, offset=(0.5, -0.4, 0.3)) -> np.ndarray:
    """(n, 21, 3) of the same default pose every frame, ~0.7 m from the real hand."""
    wrist = np.eye(4)
    wrist[:3, 3] = np.array([0.4, 0.0, 0.1]) + offset
    return np.repeat(forward_keypoints(np.zeros((1, 20)), wrist[None]), n, axis=0)


def _with_lost_run(n: int, where: str, length: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    kp = _real_hand(n, seed)
    start = {"start": 0, "middle": (n - length) // 2, "end": n - length}[where]
    lost = np.zeros(n, dtype=bool)
    lost[start : start + length] = True
    kp[lost] = _template_hand(length)
    return kp, lost


@pytest.mark.parametrize("where", ["start", "middle", "end"])
@pytest.mark.parametrize("length", [1, 3, 15, 25, 35])
def test_a_lost_run_is_found_at_any_position_and_length(where, length):
    n = 72  # 35 frames is just under half of it
    kp, truth = _with_lost_run(n, where, length, seed=length)
    observed, lost = detect_bad_frames(kp, None, 0.08)
    np.testing.assert_array_equal(lost, truth)
    np.testing.assert_array_equal(observed, ~truth)


def test_lost_runs_at_both_ends_and_a_moving_teleport_in_the_middle():
    n = 90
    kp = _real_hand(n, seed=3)
    truth = np.zeros(n, dtype=bool)
    truth[:20] = truth[-10:] = True
    kp[:20], kp[-10:] = _template_hand(20), _template_hand(10)  # the same template at both ends
    truth[40:44] = True
    kp[40:44] += [0.25, -0.2, 0.1]  # a default pose that follows the hand, 33 cm off
    _, lost = detect_bad_frames(kp, None, 0.08)
    np.testing.assert_array_equal(lost, truth)


def test_a_dropout_between_real_frames_is_not_lost_and_fast_real_motion_is_kept():
    n = 80
    kp = _real_hand(n, seed=4, speed_mps=1.7)  # ~57 mm per frame at the fastest
    assert np.linalg.norm(np.diff(kp[:, 0], axis=0), axis=-1).max() > 0.04
    valid = np.ones(n, dtype=bool)
    kp[30:42] = np.nan  # a 0.4 s dropout: the hand moved meanwhile
    valid[60:63] = False
    observed, lost = detect_bad_frames(kp, valid, 0.08)
    assert not lost.any()
    np.testing.assert_array_equal(observed, np.isfinite(kp).all(axis=(1, 2)) & valid)


def test_a_template_run_behind_a_dropout_is_still_lost():
    n = 72
    kp = _real_hand(n, seed=5)
    kp[:15] = _template_hand(15)
    kp[15:19] = np.nan  # no annotation at all between the template and the real hand
    observed, lost = detect_bad_frames(kp, None, 0.08)
    assert lost[:15].all() and lost.sum() == 15
    assert observed[19:].all() and not observed[:19].any()


def test_a_frame_of_the_wrong_size_is_lost_and_bad_shapes_are_rejected():
    kp = _real_hand(40, seed=6)
    kp[20, 9] = kp[20, 0] + 2.0 * (kp[20, 9] - kp[20, 0])  # middle MCP twice as far
    _, lost = detect_bad_frames(kp, None, 0.08)
    assert list(np.flatnonzero(lost)) == [20]
    with pytest.raises(ValueError, match=r"\(T, 21, 3\)"):
        detect_bad_frames(kp[:, :20], None, 0.08)
    with pytest.raises(ValueError, match="valid"):
        detect_bad_frames(kp, np.ones(39, dtype=bool), 0.08)
