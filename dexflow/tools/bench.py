"""Benchmarks that print frames/s with ratios against a baseline measured in the same run."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from dexflow.io.layout import Layout, StageDir
from dexflow.params import SimulateParams
from dexflow.tools.tip_motion import NEAR_M

__all__ = [
    "bench_fk",
    "bench_long",
    "bench_pipeline",
    "bench_real",
    "bench_refine",
    "bench_retarget",
    "bench_simulate",
    "grasp_breakdown",
    "refine_motion",
]


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
    from pathlib import Path

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


def _real_engines(results: dict[str, dict]) -> list[str]:
    """Per hand, method and engine the SSRs and the frames perturbations overturn, the per-frame
    agreement of the paper's test and DexGraspBench's, and with two engines theirs (empty
    with one engine and no perturbations)."""
    sims = [(h, m, s) for h, r in results.items() for m, s in r.get("simulate", {}).items()]
    engines = sorted({e for *_, s in sims for e in str(s.get("engines", "")).split(",") if e})
    if not sims or (len(engines) < 2 and not any(s.get("perturbations") for *_, s in sims)):
        return []
    lines = [
        "| hand | method | engine | SSR paper % | SSR bench % | frames flipped by perturbations % |",
        "|---|---|---|---|---|---|",
    ]
    for hand, method, sim in sims:
        for engine in str(sim.get("engines", "")).split(","):
            cells = [sim.get(f"{k}_{engine}", float("nan")) for k in ("ssr_paper", "ssr_bench")]
            cells.append(100 * sim.get(f"flipped_{engine}", float("nan")))
            text = " | ".join(f"{c:.1f}" for c in cells)
            lines.append(f"| {hand} | {method} | {engine} | {text} |")
    pairs = [("criteria_", f"the paper's test and DexGraspBench's ({engines[0]})")]
    if len(engines) > 1:
        pairs.append(("", f"{engines[0]} and {engines[1]} (the paper's test)"))
    for prefix, what in pairs:
        lines += ["", f"Per-frame agreement of {what}:", "",
                  "| hand | method | frames | both hold | both drop | disagree |",
                  "|---|---|---|---|---|---|"]  # fmt: skip
        for hand, method, sim in sims:
            keys = (f"{prefix}agree_hold", f"{prefix}agree_drop", f"{prefix}disagree")
            counts = [int(sim.get(k, 0)) for k in keys]
            lines.append(
                f"| {hand} | {method} | {sum(counts)} | " + " | ".join(map(str, counts)) + " |"
            )
    return lines


PAPER_FRAMES = 292_000  # the DexFlow dataset: 292K frames over 50 objects


def bench_pipeline(
    sequences: int = 6,
    workers: tuple[int, ...] = (1, 2),
    out: str | None = "reports/bench.md",
    root: str | None = None,
    subset: int = 0,
    scales: tuple[int, ...] = (1,),
) -> list[dict]:
    """The whole pipeline once per worker count (and data size): frames/s of every stage, its
    share of the time, the speed-up from 1 to N workers and an estimate for the paper's 292K
    frames.

    By default on ``sequences`` demo sequences (2 per object, generated by the demo stage);
    with ``root``, on the converted sequences there (``subset > 0``: that many evenly spaced
    ones), without the demo stage. ``scales`` (demo only) repeats the whole for k times the
    sequences of the same objects (``2 k`` per object), to show how each stage grows with the
    frames while the per-object work stays. Every run starts with an empty object asset cache,
    so that scale_align is timed as on a first run. Runs in a temporary directory; writes
    ``out``.
    """
    import os
    import shutil
    import tempfile

    from dexflow.config import load_params
    from dexflow.data.ycb_standins import STANDINS
    from dexflow.objects.convex import CACHE_ENV

    base = load_params("params.yaml")
    source = None if root is None else Path(root).resolve()
    if source is not None and not StageDir(source).sequences_dir.is_dir():
        raise FileNotFoundError(f"{source}: no sequences/ folder (convert a dataset first)")
    if source is not None and tuple(scales) != (1,):
        raise ValueError("bench pipeline --scales: demo only (on your data, vary --subset)")
    if not scales or min(scales) < 1:
        raise ValueError(f"bench pipeline --scales: whole numbers >= 1, got {scales}")
    work = Path(tempfile.mkdtemp(prefix="dexflow-bench-"))
    objects = sorted(STANDINS)[: max(1, sequences // 2)]
    data = dataclasses.replace(base.data, root="data/demo")
    if source is not None:
        data_root = _subset_root(source, subset, work / "subset")
        data = dataclasses.replace(base.data, name="custom", root=str(data_root), generated_by=[])
    cache, previous = work / "asset-cache", os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(cache)  # the same path in every worker; emptied per run
    runs = []
    try:
        for scale, n in [(k, n) for k in scales for n in workers]:
            shutil.rmtree(cache, ignore_errors=True)
            folder = work / f"workers-{n}-x{scale}"
            run = dataclasses.replace(
                base.run, backend="sequential" if n == 1 else "local", n_jobs=n
            )
            demo = dataclasses.replace(base.demo, objects=objects, sequences_per_object=2 * scale)
            params = dataclasses.replace(base, demo=demo, run=run, data=data)
            seconds, frames, evaluated, num_objects = {}, 0, 0, 0
            for name, fn in _pipeline_stages(params, Layout.of(data.root, root=folder)):
                if name == "demo" and root is not None:
                    continue
                start = time.perf_counter()
                result = fn()
                seconds[name] = time.perf_counter() - start
                if name == "retarget@dexflow":
                    frames = int(result["num_frames"])
                if name == "scale_align":
                    num_objects = int(result["num_objects"])
                if name.startswith("simulate"):
                    evaluated += int(result["frames_evaluated"])
            runs.append({"workers": n, "scale": scale, "seconds": seconds, "frames": frames,
                         "evaluated": evaluated, "objects": num_objects,
                         "peak_rss_mb": _peak_rss_mb()})  # fmt: skip
            shutil.rmtree(folder, ignore_errors=True)
    finally:
        if previous is None:
            os.environ.pop(CACHE_ENV, None)
        else:
            os.environ[CACHE_ENV] = previous
        shutil.rmtree(work, ignore_errors=True)

    lengths = ",".join(str(n) for n in workers)
    if root is None:
        command = f"dexflow bench pipeline --sequences {sequences} --workers {lengths}"
        what = f"{sequences} demo sequences"
        if tuple(scales) != (1,):
            command += " --scales " + ",".join(str(k) for k in scales)
            what += " and k times as many of the same objects (×k)"
    else:
        command = f"dexflow bench pipeline {root} --workers {lengths}"
        command += f" --subset {subset}" if subset else ""
        what = f"the converted sequences in `{root}`" + (f" ({subset} of them)" if subset else "")
    lines = _bench_table(runs, command, what)
    lines[4:4] = [_machine_line(), ""]
    text = "\n".join(lines) + "\n"
    _publish(text, out)
    return runs


def _machine_line() -> str:
    """The benchmark reports' line saying how they were measured (the machine itself is in the
    provenance block :func:`_publish` adds)."""
    from dexflow.pipeline import provenance

    return (
        f"Machine: {provenance.machine_id()} (see *Measured at*). Wall-clock seconds; other load "
        "on the machine counts."
    )


def _publish(text: str, out: str | None) -> None:
    """Print a benchmark report and write it to ``out`` (atomically; None: print only), with
    where it was measured under its title: the commit and the machine
    (:func:`dexflow.pipeline.provenance.markdown`; the data is in the report's first paragraph)."""
    from dexflow.pipeline import provenance

    title, _, rest = text.partition("\n")
    block = "\n".join(["", "Measured at:", "", *provenance.markdown()])
    text = f"{title}\n{block}\n{rest}"
    print(text)
    if out:
        from dexflow.io.atomic import atomic_path

        with atomic_path(Path(out)) as tmp:
            tmp.write_text(text)


def _peak_rss_mb() -> float:
    """The largest resident set (MiB) of this process or any finished worker so far."""
    import resource

    usage = [
        resource.getrusage(w).ru_maxrss for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
    ]
    return max(usage) / 1024  # Linux reports KiB


def _pipeline_stages(params, layout) -> list[tuple[str, Callable[[], dict]]]:
    """Every stage of ``dvc.yaml`` as (name, call) on the project ``layout``, in the order of
    the registry (:func:`dexflow.pipeline.registry.load_stages` with these ``params``: refine
    after replay@retarget only with the grip on), each run by the executor
    (:func:`dexflow.pipeline.executor.run_in_process`) as its script runs it. The demo is called
    ``demo``; the report, which times nothing, is left out.

    Raises:
        ConfigError: ``dvc.yaml`` has a stage that no stage module defines.
    """
    from dexflow.pipeline.executor import run_in_process
    from dexflow.pipeline.registry import load_stages, pipeline_file, stage_spec

    def call(stage) -> Callable[[], dict]:
        return lambda: run_in_process(stage, params, layout)

    steps = []
    for stage in load_stages(pipeline_file(), dataclasses.asdict(params)):
        base = stage.name.partition("@")[0]
        if base != "report":
            stage_spec(stage.name)  # a stage no module runs fails here, before anything runs
            steps.append(("demo" if base == "demo" else stage.name, call(stage)))
    return steps


def _bench_table(runs: list[dict], command: str, what: str) -> list[str]:
    """The pipeline benchmark's report: a column per run (worker count, data size), the
    speed-up from the fewest to the most workers per data size and, with several sizes, how
    much longer each stage took on the largest than on the smallest."""
    scales = sorted({r.get("scale", 1) for r in runs})
    several = len(scales) > 1

    def label(r):
        return f"{r['workers']} worker(s)" + (f" ×{r.get('scale', 1)}" if several else "")

    def total(r):
        return sum(v for k, v in r["seconds"].items() if k != "demo")

    def at(scale):
        return [r for r in runs if r.get("scale", 1) == scale]

    pairs = [(at(k)[0], at(k)[-1], k) for k in scales]  # fewest and most workers per size
    small, large = runs[0], at(scales[-1])[-1]
    growth = next(r for r in at(scales[0]) if r["workers"] == large["workers"])
    sizes = ", ".join(
        f"{r['frames']} frames" + (f" at ×{k}" if several else "") for r, _, k in pairs
    )
    head = ["stage"] + [f"{label(r)}: s, frames/s, share" for r in runs]
    head += [f"speed-up {a['workers']} → {b['workers']}" + (f" ×{k}" if several else "")
             for a, b, k in pairs]  # fmt: skip
    if several:
        head.append(f"time ×{scales[-1]} / ×{scales[0]} ({large['workers']} workers)")
    lines = [
        "# dexflow pipeline benchmark",
        "",
        f"`{command}`: the whole pipeline on {what} ({small['objects']} objects, {sizes}), "
        "once per worker count, in one run, each from an empty object asset cache "
        "(a first run).",
        "",
        "| " + " | ".join(head) + " |",
        "|---" * len(head) + "|",
    ]
    for name in small["seconds"]:
        cells = []
        for r in runs:
            s = r["seconds"][name]
            share = "" if name == "demo" else f"{100 * s / total(r):.0f} %"
            cells.append(f"{s:.1f} s, {r['frames'] / s:.0f} f/s, {share}")
        cells += [f"{a['seconds'][name] / b['seconds'][name]:.2f}x" for a, b, _ in pairs]
        if several:
            cells.append(f"{large['seconds'][name] / growth['seconds'][name]:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    cells = [f"**{total(r):.1f} s, {r['frames'] / total(r):.1f} f/s**" for r in runs]
    cells += [f"**{total(a) / total(b):.2f}x**" for a, b, _ in pairs]
    if several:
        cells.append(f"**{total(large) / total(growth):.2f}**")
    lines.append("| **pipeline (without demo)** | " + " | ".join(cells) + " |")
    shares = sorted(((v, k) for k, v in large["seconds"].items() if k != "demo"), reverse=True)
    simulate = sum(v for k, v in large["seconds"].items() if k.startswith("simulate"))
    top = ", ".join(f"{k} {100 * v / total(large):.0f} %" for v, k in shares[:3])
    lines += [
        "",
        f"Largest shares with {label(large)}: {top}; the three simulate stages "
        f"together {100 * simulate / total(large):.0f} %.",
    ]
    if several:
        rest_growth = _per_frame(large) * large["frames"] / (_per_frame(growth) * growth["frames"])
        lines += [
            "",
            f"×{scales[-1] / scales[0]:g} the sequences ({growth['frames']} → {large['frames']} "
            f"frames, ×{large['frames'] / growth['frames']:.2f}) took ×"
            f"{total(large) / total(growth):.2f} the time with {large['workers']} workers; "
            f"without scale_align (per object, the same objects) ×{rest_growth:.2f}.",
        ]
    per_object = large["seconds"]["scale_align"] / max(large["objects"], 1)
    per_frame = _per_frame(large)
    estimate = per_frame * PAPER_FRAMES + per_object * 50
    rss = max(r["peak_rss_mb"] for r in runs)
    lines += [
        "",
        f"Peak resident memory over the benchmark: {rss:.0f} MiB (the largest single process, "
        "the main one or a worker; a high-water mark, so not per worker count).",
    ]
    lines += [
        "",
        f"Simulation evaluated {large['evaluated']} frames (stride and early stop) of the "
        f"{3 * large['frames']} trajectory frames it was given ({label(large)}).",
        "",
        f"**Estimate for the paper's dataset** ({PAPER_FRAMES:,} frames, 50 objects) from "
        f"{label(large)}: {per_frame * 1000:.1f} ms per frame after scale_align plus "
        f"{per_object:.0f} s per object = **{estimate / 3600:.1f} h**.",
    ]
    return lines


def _per_frame(run: dict) -> float:
    """Seconds per frame of a benchmark run's stages after scale_align (demo excluded)."""
    rest = sum(v for k, v in run["seconds"].items() if k not in ("demo", "scale_align"))
    return rest / run["frames"]


_STAGE_DRIVER = """
import dataclasses, json, sys, time
from dexflow.tools.bench import _pipeline_stages
from dexflow.config import load_params
from dexflow.io.layout import Layout
params_file, data_root, project, wanted = sys.argv[1:5]
params = load_params(params_file)
run = dataclasses.replace(params.run, backend="sequential", n_jobs=1)
data = dataclasses.replace(params.data, root=data_root)
params = dataclasses.replace(params, run=run, data=data)
for name, fn in _pipeline_stages(params, Layout.of(data_root, root=project)):
    if name == wanted:
        start = time.perf_counter()
        fn()
        seconds = time.perf_counter() - start
        # VmHWM: this program's own peak (ru_maxrss would carry the forking parent's over exec)
        try:
            rss = int(open("/proc/self/status").read().split("VmHWM:")[1].split()[0]) / 1024
        except (OSError, IndexError):  # not Linux: the peak since the fork, in platform units
            import resource
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(json.dumps({"seconds": seconds, "rss_mb": rss}))
"""


def _long_sequence(source: Path, frames: int, folder: Path) -> Path:
    """A data root in ``folder`` holding one sequence of ``frames`` frames: the first sequence
    of ``source`` played forward and backward in turn (a continuous motion), meshes linked."""

    from dexflow.io.sequence import load_sequence, save_sequence

    path = StageDir(source).sequence_files()[0]
    seq = load_sequence(path, source)
    n = seq.num_frames
    index = np.resize(np.concatenate([np.arange(n), np.arange(n)[::-1]]), frames)

    def tile(a):
        return a[index] if isinstance(a, np.ndarray) and a.ndim and a.shape[0] == n else a

    long = dataclasses.replace(
        seq,
        keypoints=seq.keypoints[index],
        obj_pose=seq.obj_pose[index],
        valid=tile(seq.valid),
        timestamps=None,
        gt_contact=tile(seq.gt_contact),
        extras={k: tile(v) for k, v in seq.extras.items()},
    )
    StageDir(folder).sequences_dir.mkdir(parents=True)
    for entry in source.iterdir():
        if entry.name != "sequences" and entry.is_dir():
            (folder / entry.name).symlink_to(entry.resolve())
    save_sequence(StageDir(folder).sequence(f"long_{frames}"), long, folder)
    return folder


def bench_long(
    frames: tuple[int, ...] = (600, 2400), out: str | None = "reports/bench_long.md"
) -> list[dict]:
    """Time and peak memory of every stage on one long sequence, at several lengths.

    One demo sequence is played forward and backward to ``frames`` frames; each stage runs in a
    process of its own, one sequence after another (``run=sequential``), so that its peak
    resident memory is that of the stage alone. Time and memory that grow in proportion to the
    frames show in the ratios between the lengths (4x the frames: 4x the time, and memory that
    stays bounded where the stage works through the frames in chunks).
    """
    import json
    import os
    import shutil
    import subprocess
    import sys
    import tempfile

    from dexflow.config import load_params
    from dexflow.data.demo import generate_demo
    from dexflow.objects.convex import CACHE_ENV

    if len(frames) < 2 or min(frames) < 1:
        raise ValueError(f"bench long: give two lengths or more, each >= 1 frame (got {frames})")
    params = load_params("params.yaml")
    base = Path(tempfile.mkdtemp(prefix="dexflow-long-"))
    try:
        demo = dataclasses.replace(params.demo, objects=["025_mug"], sequences_per_object=1)
        run = dataclasses.replace(params.run, backend="sequential", n_jobs=1)
        generate_demo(demo, base / "demo", run)
        stages = [name for name, _ in _pipeline_stages(params, Layout()) if name != "demo"]
        runs = []
        for n in frames:
            root = _long_sequence(base / "demo", n, base / f"data_{n}")
            results = {}
            env = {**os.environ, CACHE_ENV: str(base / f"cache_{n}")}  # every length cold
            for name in stages:
                done = subprocess.run(
                    [sys.executable, "-c", _STAGE_DRIVER, "params.yaml", str(root),
                     str(base / f"project_{n}"), name],
                    capture_output=True, text=True, env=env,
                )  # fmt: skip
                lines = [x for x in done.stdout.splitlines() if x.startswith("{")]
                if done.returncode != 0 or not lines:
                    raise RuntimeError(f"bench long: {name} on {n} frames failed:\n{done.stderr}")
                results[name] = json.loads(lines[-1])
                print(f"{n} frames, {name}: {results[name]}", flush=True)
            runs.append({"frames": n, "stages": results})
    finally:
        shutil.rmtree(base, ignore_errors=True)
    text = "\n".join(_long_table(runs)) + "\n"
    _publish(text, out)
    return runs


def _long_table(runs: list[dict]) -> list[str]:

    first, last = runs[0], runs[-1]
    scale = last["frames"] / first["frames"]
    lengths = ",".join(str(r["frames"]) for r in runs)
    lines = [
        "# dexflow on long captures",
        "",
        f"`dexflow bench long --frames {lengths}`: one demo sequence played forward and backward "
        "to each length, every stage in a process of its own (one worker), so that the peak "
        "resident memory is the stage's own. A 10-minute capture at 30 fps is 18,000 frames.",
        "",
        _machine_line(),
        "",
        "| stage | "
        + " | ".join(f"{r['frames']} frames: s, frames/s, peak MiB" for r in runs)
        + f" | time ×, memory × ({scale:g}x frames) |",
        "|---" * (len(runs) + 2) + "|",
    ]
    for name in first["stages"]:
        cells = []
        for r in runs:
            s = r["stages"][name]
            cells.append(f"{s['seconds']:.1f}, {r['frames'] / s['seconds']:.0f}, {s['rss_mb']:.0f}")
        a, b = first["stages"][name], last["stages"][name]
        ratio = f"{b['seconds'] / a['seconds']:.1f}, {b['rss_mb'] / a['rss_mb']:.2f}"
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {ratio} |")
    peaks = [max(s["rss_mb"] for s in r["stages"].values()) for r in runs]
    totals = [sum(s["seconds"] for s in r["stages"].values()) for r in runs]
    growth = (peaks[-1] - peaks[0]) / (last["frames"] - first["frames"])
    lines += [
        "",
        f"Whole pipeline: {totals[0]:.0f} s → {totals[-1]:.0f} s (×{totals[-1] / totals[0]:.1f} "
        f"for ×{scale:g} the frames); the largest stage peak {peaks[0]:.0f} → {peaks[-1]:.0f} "
        f"MiB, {growth * 1024:.0f} KiB per added frame (18,000 frames: about "
        f"{peaks[-1] + growth * (18000 - last['frames']):.0f} MiB).",
    ]
    return lines


REAL_COLUMNS = (
    ("fingertip_error_mm", "fingertip error mm", "{:.1f}"),
    ("fingertip_error_surface_mm", "vs surface tips mm", "{:.1f}"),
    ("rms_acc", "RMS acc rad/s²", "{:.2f}"),
    ("pd_mm", "PD mean mm", "{:.2f}"),
    ("pd_max_mm", "PD max mm", "{:.1f}"),
    ("cd_mm", "CD mm", "{:.2f}"),
    ("ssr", "SSR %", "{:.1f}"),
    ("ssr_paper", "SSR paper %", "{:.1f}"),
    ("ssr_bench", "SSR bench %", "{:.1f}"),
)


def _subset_root(root: Path, count: int, folder: Path) -> Path:
    """``root`` itself, or a root in ``folder`` linking ``count`` evenly spaced sequences of it."""
    source, subset = StageDir(root), StageDir(folder)
    files = source.sequence_files()
    if count <= 0 or count >= len(files):
        return root
    chosen = [files[int(i)] for i in np.linspace(0, len(files) - 1, count).round()]
    subset.sequences_dir.mkdir(parents=True, exist_ok=True)
    for old in [*subset.sequences_dir.iterdir(), *folder.iterdir()]:
        if old.is_symlink():  # a previous run's links (another --subset): made afresh
            old.unlink()
    for path in chosen:
        subset.sequence(path).symlink_to(path.resolve())
    for entry in root.iterdir():
        if entry != source.sequences_dir:
            (folder / entry.name).symlink_to(entry.resolve())
    return folder


def bench_real(
    root: str,
    hands: list[str] | None = None,
    workers: int = 2,
    sequences: int = 0,
    work: str | None = None,
    out: str | None = "reports/real.md",
    overrides: list[str] | None = None,
) -> dict[str, dict]:
    """The whole pipeline (no demo stage) on a converted dataset, per hand, with its metrics.

    ``root`` holds canonical sequences (``dexflow convert``). For every hand the stages run in
    ``work/<hand>`` (a temporary directory by default) with the project's ``conf/`` defaults
    plus ``overrides`` (Hydra syntax, e.g. ``simulate=both``), and the metrics stage's aggregates
    are tabulated per method: the numbers of the README's "Real data" section. ``sequences > 0``
    takes that many evenly spaced sequences.

    After the metrics' table the report says why targets are missed: per method how the grasp
    test's frames fail (:func:`grasp_breakdown`) and where refinement moved the fingertips
    (:func:`refine_motion`).

    Returns:
        Per hand: ``metrics`` (the metrics stage's aggregates), ``simulate`` (per trajectory
        label, the simulate stage's summary), ``grasps`` (per label, :func:`grasp_breakdown`),
        ``motion`` (:func:`refine_motion`), ``seconds`` per stage, ``sequences``, ``frames``
        and ``retarget_s_per_sequence`` (CPU seconds of retarget@dexflow per sequence:
        wall-clock time x workers / sequences).
    """
    import shutil
    import tempfile

    from dexflow.config import compose_params, load_params

    source = Path(root).resolve()  # stages run in the work folder: no relative paths
    if not StageDir(source).sequences_dir.is_dir():
        raise FileNotFoundError(f"{source}: no sequences/ folder (convert a dataset first)")
    base = Path(work).resolve() if work else Path(tempfile.mkdtemp(prefix="dexflow-real-"))
    data_root = _subset_root(source, sequences, base / "subset")
    results: dict[str, dict] = {}
    for hand in hands or ["shadow", "allegro"]:
        folder = base / hand
        folder.mkdir(parents=True, exist_ok=True)
        run = "sequential" if workers <= 1 else "local"
        fixed = [f"hand={hand}", "data=custom", f"data.root={data_root}", f"run={run}"]
        params = load_params(compose_params([*fixed, *(overrides or [])], folder / "params.yaml"))
        params = dataclasses.replace(params, run=dataclasses.replace(params.run, n_jobs=workers))
        seconds, summary, frames, simulated = {}, {}, 0, {}
        layout = Layout.of(data_root, root=folder)
        for name, fn in _pipeline_stages(params, layout):
            if name == "demo":
                continue
            start = time.perf_counter()
            summary = fn()
            seconds[name] = time.perf_counter() - start
            if name == "retarget@dexflow":
                frames, count = int(summary["num_frames"]), int(summary["num_sequences"])
            if name.startswith("simulate@"):
                simulated[name.partition("@")[2]] = {
                    k: v for k, v in summary.items() if k not in ("sequences", "timing")
                }
        results[hand] = {
            "metrics": {k: v for k, v in summary.items() if k != "sequences"},
            "simulate": simulated,
            "motion": refine_motion(params, layout),
            "grasps": {m: grasp_breakdown(layout.simulate(m), params.simulate) for m in simulated},
            "seconds": seconds,
            "sequences": count,
            "frames": frames,
            "retarget_s_per_sequence": seconds["retarget@dexflow"] * workers / max(count, 1),
        }
    if not work:
        shutil.rmtree(base, ignore_errors=True)
    text = _real_table(results, source, sequences, workers, overrides or [])
    _publish(text, out)
    return results


def refine_motion(params, layout: Layout) -> dict[str, float]:
    """:func:`dexflow.tools.tip_motion.summarize_motion` of retargeted -> refined over every
    sequence that both stages wrote (stage outputs in ``layout``)."""
    from dexflow.hands.files import staged_spec
    from dexflow.hands.robot import cached_hand
    from dexflow.io.artifacts import ObjectAssets, read_trajectory
    from dexflow.io.sequence import load_sequence
    from dexflow.tools.tip_motion import fingertip_motion, summarize_motion

    hand = cached_hand(staged_spec(params.hand, layout.hand_files.root), None)
    aligned, parts = layout.scale_align, []
    for path in layout.retarget("dexflow").sequence_files():
        refined = layout.refine.sequence(path)
        if not refined.is_file():
            continue  # failed in refine: reported there
        seq = load_sequence(aligned.sequence(path), aligned.root)
        retargeted = read_trajectory(path, hand.joint_names, frames=seq.num_frames)
        parts.append(fingertip_motion(
            hand, retargeted.q, read_trajectory(refined, hand.joint_names, seq.num_frames).q,
            retargeted["keypoints_human"], retargeted["observed"].astype(bool), seq.obj_pose,
            ObjectAssets(aligned.object_of(seq.obj_mesh)).sdf(),
        ))  # fmt: skip
    return summarize_motion(parts)


def grasp_breakdown(out: StageDir, params: SimulateParams | None = None) -> dict[str, float]:
    """Which frames a method's grasp test counts, and how the tested ones fail.

    From stage simulate's rows in ``out`` (its first engine; robust DexGraspBench criterion):
    ``tested`` and ``skipped`` frames (skipped: over the penetration tolerance, not tested),
    ``held`` (tested frames that hold), ``opposed`` (tested frames where the thumb and another
    finger touch the object at the start) and ``opposed_held`` (both 0, and ``thumb`` False,
    for a hand without a finger named ``thumb``); over the tested frames that fail, the median
    ``displacement_mm`` and ``rotation_deg`` under the first push (the test stops at the first
    failing direction) and ``lost_closing``, how many of them had already moved or turned
    beyond the criterion's thresholds (``params``: ``max_displacement_m``,
    ``max_rotation_deg``) while the fingers closed, before any push (0 for an engine that
    holds the object then); the median ``imbalance`` of the pushes
    (:func:`dexflow.sim.protocol.imbalance`: 0 opposed, 1 one-sided) of the held frames
    (``imbalance_held``) and of the failed ones (``imbalance_failed``), and likewise that of
    stage contact's contacts at those frames (``contact_imbalance_held``,
    ``contact_imbalance_failed``: :func:`dexflow.sim.protocol.contact_imbalance`).
    """
    import json

    from dexflow.io.artifacts import read_simulation
    from dexflow.sim.protocol import lost_while_closing

    p = params or SimulateParams()
    summary = json.loads(out.summary.read_text())
    counts = dict.fromkeys(("tested", "held", "opposed", "opposed_held", "lost_closing"), 0)
    displacement, rotation, thumb = [], [], True
    balance: dict[bool, list[float]] = {True: [], False: []}
    target: dict[bool, list[float]] = {True: [], False: []}
    for path in out.sequence_files():
        result = read_simulation(path)
        rows, engine = result.rows, result.engines[0]
        held = rows[f"{engine}.bench"].astype(bool)
        touching = rows[f"{engine}.touching"].astype(bool)
        thumb = thumb and "thumb" in result.fingers
        opposed = np.zeros(len(held), dtype=bool)
        if "thumb" in result.fingers:
            opposed = touching[:, result.fingers.index("thumb")] & (touching.sum(1) >= 2)
        closing = lost_while_closing(
            rows[f"{engine}.closing_displacement_m"], rows[f"{engine}.closing_rotation_deg"], p
        )
        counts["tested"] += len(held)
        counts["held"] += int(held.sum())
        counts["opposed"] += int(opposed.sum())
        counts["opposed_held"] += int((opposed & held).sum())
        counts["lost_closing"] += int((closing & ~held).sum())
        displacement += list(rows[f"{engine}.displacement_m"][~held, 0])
        rotation += list(rows[f"{engine}.rotation_deg"][~held, 0])
        for kept in (True, False):
            balance[kept] += list(rows[f"{engine}.imbalance"][held == kept])
            target[kept] += list(rows["contact_imbalance"][held == kept])
    failed = np.array(displacement, dtype=float)
    return {
        **counts,
        "skipped": int(summary.get("frames_skipped", 0)),
        "thumb": thumb,
        "displacement_mm": 1000 * float(np.nanmedian(failed)) if len(failed) else float("nan"),
        "rotation_deg": float(np.nanmedian(rotation)) if rotation else float("nan"),
        "imbalance_held": _median(balance[True]),
        "imbalance_failed": _median(balance[False]),
        "contact_imbalance_held": _median(target[True]),
        "contact_imbalance_failed": _median(target[False]),
    }


def _median(values: list[float]) -> float:
    """The median of the finite ``values`` (NaN when there are none)."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    return float(np.median(finite)) if len(finite) else float("nan")


def _grasp_lines(results: dict[str, dict]) -> list[str]:
    """The table of :func:`grasp_breakdown` per hand and method."""
    from dexflow.stages.report import cell as _cell

    rows = [(h, m, g) for h, r in results.items() for m, g in r.get("grasps", {}).items()]
    if not rows:
        return []
    lines = [
        "Which frames the grasp test counts and how they fail (robust DexGraspBench criterion, "
        "first engine; *opposed*: the thumb and another finger touch the object at the start; "
        "*lost while closing*: the object moved or turned past the criterion's thresholds "
        "while the fingers closed, before any push; *imbalance*: how one-sided the pushes into "
        "the object are, 0 when they cancel, 1 when all press the same way; *contact "
        "imbalance*: the same of the contacts stage contact found at the frame, those the grasp "
        "aims for, `dexflow/sim/protocol.py`):",
        "",
        "| hand | method | frames tested | skipped (over the penetration tolerance) | held "
        "| opposed | opposed and held | failed: median displacement mm / rotation ° "
        "under the first push | failed: lost while closing | median imbalance held / failed "
        "| median contact imbalance held / failed |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for hand, method, g in rows:
        opposed = f"{g['opposed']} | {g['opposed_held']}" if g["thumb"] else "— | —"
        lines.append(
            f"| {hand} | {method} | {g['tested']} | {g['skipped']} | {g['held']} | {opposed} "
            f"| {g['displacement_mm']:.0f} / {g['rotation_deg']:.0f} | {g['lost_closing']} "
            f"| {_cell(g['imbalance_held'])} / {_cell(g['imbalance_failed'])} "
            f"| {_cell(g['contact_imbalance_held'])} / {_cell(g['contact_imbalance_failed'])} |"
        )
    return lines


def _motion_lines(results: dict[str, dict]) -> list[str]:
    """The table of where refinement moved the fingertips (:mod:`dexflow.tools.tip_motion`)."""
    rows = [(hand, r["motion"]) for hand, r in results.items() if r.get("motion", {}).get("tips")]
    if not rows:
        return []
    lines = [
        "Where refinement moves the fingertips (retargeted -> refined, observed frames; "
        f"*near*: the human fingertip within {1000 * NEAR_M:.0f} mm of the object; "
        "definitions in `dexflow/tools/tip_motion.py`):",
        "",
        "| hand | human tips inside the object mm | near % | near: fingertip error mm "
        "| near: moved along the normal (outward) / across it mm | far: fingertip error mm "
        "| far: moved mm | palm moved mm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for hand, m in rows:
        lines.append(
            f"| {hand} | {m['tip_depth_mm']:.2f} | {100 * m['near_share']:.0f} "
            f"| {m['near_error_from_mm']:.1f} → {m['near_error_to_mm']:.1f} "
            f"| {m['normal_mm']:.1f} ({m['outward_mm']:+.1f}) / {m['tangential_mm']:.1f} "
            f"| {m['far_error_from_mm']:.1f} → {m['far_error_to_mm']:.1f} "
            f"| {m['far_moved_mm']:.1f} | {m['palm_mm']:.1f} |"
        )
    return lines


def _real_table(
    results: dict[str, dict], source, sequences: int, workers: int, overrides: list[str] = ()
) -> str:
    command = f"dexflow bench real {source}" + (f" --subset {sequences}" if sequences else "")
    command += "".join(f" --set {o}" for o in overrides)
    first = next(iter(results.values()), {})
    data = f"{first.get('sequences', '?')} sequences, {first.get('frames', '?')} frames"
    lines = [
        "# dexflow on real captures",
        "",
        f"`{command}`: the pipeline at the project's defaults, per hand, on the converted data "
        f"in `{source}` ({data}); metrics as defined in `dexflow/stages/metrics.py` (observed frames "
        "only for the errors).",
        "",
        _machine_line(),
        "",
        "| hand | method | " + " | ".join(label for _, label, _ in REAL_COLUMNS) + " |",
        "|---" * (len(REAL_COLUMNS) + 2) + "|",
    ]
    names = {"baseline": "position baseline", "retarget": "DexFlow retarget",
             "refine": "DexFlow + refine"}  # fmt: skip
    for hand, r in results.items():
        for method, label in names.items():
            cells = []
            for key, _, fmt in REAL_COLUMNS:
                value = r["metrics"].get(f"{method}.{key}", float("nan"))
                cells.append("—" if value is None or not np.isfinite(value) else fmt.format(value))
            lines.append(f"| {hand} | {label} | " + " | ".join(cells) + " |")
    lines += ["", *_real_engines(results), ""]
    for table in (_grasp_lines(results), _motion_lines(results)):
        lines += [*table, ""] if table else []
    for hand, r in results.items():
        total = sum(r["seconds"].values())
        lines.append(
            f"- {hand}: {r['sequences']} sequences, {r['frames']} frames; retarget "
            f"{r['retarget_s_per_sequence']:.1f} CPU s per sequence; whole pipeline {total:.0f} s "
            f"with {workers} worker(s) ({r['frames'] / total:.1f} frames/s)."
        )
    return "\n".join(lines) + "\n"
