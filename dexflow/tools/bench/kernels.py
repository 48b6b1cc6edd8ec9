"""Kernel benchmarks: forward kinematics, retarget, refine and the grasp test, each in frames/s
with its ratio against a baseline measured in the same run (``dexflow bench fk|retarget|refine|simulate``)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from dexflow.io.layout import Layout, StageDir


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


def bench_retarget(
    hand_name: str = "shadow",
    data_root: str = "data/scale_align",
    sequences: int = 6,
    every_frame_frames: int = 20,
) -> list[dict]:
    """Retargeting throughput and accuracy on the same frames, one core, in one run.

    Rows: DexFlow default (global search on the first frame), DexFlow without any global
    search (the steady-state per-frame cost), DexFlow ``every_frame`` (the paper's exact
    setting, on the first ``every_frame_frames`` frames of one sequence: about a second a
    frame), and the position baseline. Ratios are against the baseline.
    """
    from dataclasses import replace

    from dexflow.config import load_params
    from dexflow.hands.robot import load_hand
    from dexflow.io.sequence import load_sequence
    from dexflow.stages.retarget import retarget_sequence

    torch.set_num_threads(1)
    files = StageDir(Path(data_root)).sequence_files()
    files = files[:: max(1, len(files) // sequences)][:sequences]
    seqs = [load_sequence(f) for f in files]
    hand = load_hand(hand_name)
    params = load_params("params.yaml").retarget if Path("params.yaml").is_file() else None
    if params is None:
        from dexflow.params import RetargetParams

        params = RetargetParams()
    off = replace(params, global_search=replace(params.global_search, mode="off"))
    every = replace(params, global_search=replace(params.global_search, mode="every_frame"))
    short = [
        replace(
            seqs[0],
            keypoints=seqs[0].keypoints[:every_frame_frames],
            obj_pose=seqs[0].obj_pose[:every_frame_frames],
            valid=None if seqs[0].valid is None else seqs[0].valid[:every_frame_frames],
            gt_contact=None,
            extras={},
        )
    ]
    cases = [
        ("dexflow (default: first_frame)", replace(params, method="dexflow"), seqs),
        ("dexflow (global search off)", replace(off, method="dexflow"), seqs),
        ("dexflow (every_frame)", replace(every, method="dexflow"), short),
        ("position baseline", replace(off, method="position"), seqs),
        ("position baseline (same frames)", replace(off, method="position"), short),
    ]
    rows = []
    for label, p, batch in cases:
        start = time.perf_counter()
        results = [retarget_sequence(s, hand, p) for s in batch]
        seconds = time.perf_counter() - start
        frames = sum(len(s.keypoints) for s in batch)
        error = float(np.nanmean(np.concatenate([r.error_m for r in results])) * 1000)
        acc = float(
            np.mean(
                [
                    np.sqrt(np.mean(np.diff(r.q[:, 6:], 2, axis=0) ** 2)) * batch[0].fps ** 2
                    for r in results
                ]
            )
        )
        rows.append(
            {
                "case": label,
                "frames": frames,
                "fps": frames / seconds,
                "ms_per_frame": 1000 * seconds / frames,
                "error_mm": error,
                "rms_acc": acc,
            }
        )
    base = rows[3]["fps"]
    print(f"hand {hand_name}, {len(seqs)} sequences ({rows[0]['frames']} frames), 1 thread")
    print(
        f"{'case':34s} {'frames':>6s} {'frames/s':>9s} {'ms/frame':>9s} {'vs baseline':>11s} "
        f"{'error mm':>9s} {'RMS acc':>8s}"
    )
    for r in rows:
        print(
            f"{r['case']:34s} {r['frames']:6d} {r['fps']:9.1f} {r['ms_per_frame']:9.2f} "
            f"{r['fps'] / base:10.2f}x {r['error_mm']:9.2f} {r['rms_acc']:8.2f}"
        )
    return rows


def _refined_sequences(count: int, hand) -> list[tuple]:
    """``count`` refined demo sequences spread over the project's refine stage (needs
    ``dvc repro``): per sequence its retargeted and refined ``q``, the aligned sequence, its
    object's assets and contact result."""
    from dexflow.io.artifacts import ObjectAssets, read_contact, read_trajectory
    from dexflow.io.sequence import load_sequence

    layout = Layout()
    names = layout.refine.names()
    if not names:
        raise FileNotFoundError(f"{layout.refine.root}: no sequences; run `dvc repro` first")
    out = []
    for name in names[:: max(1, len(names) // count)][:count]:
        aligned = layout.scale_align
        seq = load_sequence(aligned.sequence(name), data_root=aligned.root)
        frames = seq.num_frames
        q_retarget = read_trajectory(layout.retarget("dexflow").sequence(name), hand.joint_names)
        q_refine = read_trajectory(layout.refine.sequence(name), hand.joint_names, frames)
        found = read_contact(layout.contact.sequence(name), list(hand.spec.fingers), frames)
        assets = ObjectAssets(aligned.object_of(seq.obj_mesh))
        out.append((q_retarget.q, q_refine.q, seq, assets, found))
    return out


def bench_refine(
    hand_name: str = "shadow", sequences: int = 4, loop_frames: int = 20
) -> list[dict]:
    """Refinement throughput on demo sequences, one core: batched over frames (the stage) against
    the same frames refined one frame at a time, measured in the same run. Needs `dvc repro`."""
    from dexflow.config import load_params
    from dexflow.hands.robot import load_hand
    from dexflow.stages.refine import TorchSDF, refine_trajectory

    torch.set_num_threads(1)
    params = load_params("params.yaml").refine
    hand = load_hand(hand_name)
    jobs = []
    for q0, _, seq, assets, found in _refined_sequences(sequences, hand):
        sdf = TorchSDF(assets.sdf())
        jobs.append((q0, seq.obj_pose, sdf, found.final, found.contact_map))

    start = time.perf_counter()
    for q0, pose, sdf, contact, cmap in jobs:
        refine_trajectory(hand, q0, pose, sdf, contact, cmap, params)
    batched = sum(len(j[0]) for j in jobs) / (time.perf_counter() - start)

    q0, pose, sdf, contact, cmap = jobs[0]
    frames = np.flatnonzero(contact.any(axis=1))[:loop_frames]
    start = time.perf_counter()
    for t in frames:
        sel = cmap["map_frame"] == t
        one = {k: v[sel] for k, v in cmap.items()}
        one["map_frame"] = np.zeros(sel.sum(), dtype=int)
        refine_trajectory(
            hand, q0[t : t + 1], pose[t : t + 1], sdf, contact[t : t + 1], one, params
        )
    looped = len(frames) / (time.perf_counter() - start)
    print(f"hand {hand_name}, {sum(len(j[0]) for j in jobs)} frames, 1 thread")
    print(f"refine batched over frames: {batched:8.1f} frames/s")
    print(f"refine one frame at a time: {looped:8.1f} frames/s ({len(frames)} frames in contact)")
    print(f"batched / one at a time:    {batched / looped:8.1f}x")
    return [{"batched_fps": batched, "looped_fps": looped}]


def bench_simulate(hand_name: str = "shadow", sequences: int = 3, frames: int = 6) -> list[dict]:
    """Grasp-test throughput (tested frames per second, one core) of both engines on the same
    refined demo frames after first contact, in one run: pybullet (with the stage's early exits,
    and all six full tests), MuJoCo (DexGraspBench's protocol, the stage's default engine), and
    the ratio of MuJoCo to pybullet. Needs `dvc repro`."""

    from dexflow.config import load_params
    from dexflow.hands.robot import load_hand
    from dexflow.sim.mujoco_world import MujocoGraspWorld
    from dexflow.sim.pybullet_world import PybulletGraspWorld, hand_urdf

    torch.set_num_threads(1)
    params = load_params("params.yaml").simulate
    hand = load_hand(hand_name)
    jobs = []
    for _, q, seq, assets, found in _refined_sequences(sequences, hand):
        contact = np.flatnonzero(found.final.any(axis=1))
        picked = np.linspace(contact[0], contact[-1], frames).round().astype(int)
        jobs.append((assets.paths.convex, q, seq, picked))

    def run(world) -> tuple[float, int, int]:
        tests = held = 0
        start = time.perf_counter()
        for convex, q, seq, picked in jobs:
            world.set_object(convex)
            for t in picked:
                result = world.test_frame(q[t], seq.obj_pose[t])
                tests += int(result["tested"].sum())
                held += int(result["bench"])
        seconds = time.perf_counter() - start
        world.close()
        return len(jobs) * frames / seconds, tests, held

    fast, fast_tests, fast_held = run(PybulletGraspWorld(hand, hand_urdf(hand), params))
    full_params = dataclasses.replace(params, early_exit=False)
    full, full_tests, _ = run(PybulletGraspWorld(hand, hand_urdf(hand), full_params))
    mujoco, mujoco_tests, mujoco_held = run(MujocoGraspWorld(hand, params))
    n = len(jobs) * frames
    print(f"hand {hand_name}, {n} refined frames after first contact, 1 thread")
    print(f"pybullet, early exits:             {fast:7.2f} frames/s ({fast_tests} direction tests, "
          f"{fast_held} frames hold by DexGraspBench's criterion)")  # fmt: skip
    print(f"pybullet, all six full tests:      {full:7.2f} frames/s ({full_tests} direction tests)")
    print(f"mujoco (the stage's default):      {mujoco:7.2f} frames/s ({mujoco_tests} direction "
          f"tests, {mujoco_held} frames hold)")  # fmt: skip
    print(f"mujoco / pybullet (early exits):   {mujoco / fast:7.2f}x")
    print(f"pybullet early exits / full:       {fast / full:7.2f}x")
    steps = full_tests * params.substeps * (params.control_steps + params.settle_steps)
    print(f"pybullet physics steps/s (full):   {steps * full / n:7.0f}")
    return [{"early_exit_fps": fast, "full_fps": full, "mujoco_fps": mujoco}]
