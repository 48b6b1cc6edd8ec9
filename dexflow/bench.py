"""Benchmarks that print frames/s with ratios against a baseline measured in the same run."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch

__all__ = ["bench_fk"]


def _rate(fn: Callable[[], object], frames: int, repeats: int) -> float:
    """Best-of-``repeats`` frames per second of ``fn`` (which processes ``frames`` frames)."""
    fn()  # warm-up
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return frames / best


def _mujoco_baseline(hand, q: np.ndarray, repeats: int) -> float | None:
    """Frames/s of MuJoCo's own forward kinematics, one frame at a time (C, no batching)."""
    if hand.model.mj_model is None:
        return None
    import mujoco

    m = hand.model.mj_model
    d = mujoco.MjData(m)
    adr = [m.joint(name).qposadr[0] for name in hand.hand_joint_names]

    def run():
        for row in q:
            d.qpos[adr] = row[6:]
            mujoco.mj_kinematics(m, d)

    return _rate(run, len(q), repeats)


def bench_fk(
    hands: list[str] | None = None, batches=(1, 64, 1024), repeats: int = 20
) -> list[dict]:
    """Forward-kinematics throughput of every hand: keypoints and full surface, per batch size.

    Baselines measured in the same run: the same batch computed one frame at a time through
    :class:`RobotHand`, and (MJCF hands) MuJoCo's C forward kinematics frame by frame.

    Returns:
        One row per hand and batch size (also printed as a table).
    """
    from dexflow.hands.robot import load_hand

    names = hands or ["shadow", "allegro"]
    rows = []
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64, CPU")
    header = f"{'hand':10s} {'batch':>6s} {'keypoints f/s':>14s} {'surface f/s':>12s} "
    header += f"{'loop f/s':>10s} {'batched/loop':>13s} {'mujoco f/s':>11s} {'vs mujoco':>10s}"
    print(header)
    for name in names:
        hand = load_hand(name)
        rng = np.random.default_rng(0)
        for batch in batches:
            q_np = rng.uniform(hand.lower.numpy(), hand.upper.numpy(), size=(batch, hand.dof))
            q_np[:, :6] = rng.uniform(-0.3, 0.3, size=(batch, 6))
            q = torch.as_tensor(q_np)
            with torch.no_grad():
                kp_rate = _rate(lambda q=q, h=hand: h.keypoints(q), batch, repeats)
                surf_rate = _rate(lambda q=q, h=hand: h.surface(q), batch, max(3, repeats // 4))
                loop_q = q[: min(batch, 64)]
                loop_rate = _rate(
                    lambda lq=loop_q, h=hand: [h.keypoints(r) for r in lq],
                    len(loop_q),
                    max(3, repeats // 4),
                )
            mj_rate = _mujoco_baseline(hand, q_np[: min(batch, 256)], max(3, repeats // 4))
            row = {
                "hand": name,
                "batch": batch,
                "keypoints_fps": kp_rate,
                "surface_fps": surf_rate,
                "loop_fps": loop_rate,
                "mujoco_fps": mj_rate,
            }
            rows.append(row)
            mj = (
                f"{mj_rate:11.0f} {kp_rate / mj_rate:9.2f}x"
                if mj_rate
                else f"{'-':>11s} {'-':>10s}"
            )
            print(
                f"{name:10s} {batch:6d} {kp_rate:14.0f} {surf_rate:12.0f} {loop_rate:10.0f} "
                f"{kp_rate / loop_rate:12.1f}x {mj}"
            )
    return rows
