"""``dexflow bench long``: per-frame cost and peak memory of each stage on ever longer sequences
(is every stage linear in frames?), each stage in a process of its own."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from dexflow.io.layout import Layout, StageDir
from dexflow.tools.bench.pipeline import machine_line, pipeline_stages, publish

_STAGE_DRIVER = """
import dataclasses, json, sys, time
from dexflow.tools.bench.pipeline import pipeline_stages
from dexflow.config import load_params
from dexflow.io.layout import Layout
params_file, data_root, project, wanted = sys.argv[1:5]
params = load_params(params_file)
run = dataclasses.replace(params.run, backend="sequential", n_jobs=1)
data = dataclasses.replace(params.data, root=data_root)
params = dataclasses.replace(params, run=run, data=data)
for name, fn in pipeline_stages(params, Layout.of(data_root, root=project)):
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
        stages = [name for name, _ in pipeline_stages(params, Layout()) if name != "demo"]
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
    publish(text, out)
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
        machine_line(),
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
