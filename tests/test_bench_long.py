"""`dexflow bench long`: the long sequence it builds and the table it writes."""

from __future__ import annotations

import numpy as np
import pytest

from dexflow.io.sequence import load_sequence, save_sequence
from dexflow.tools.bench.long import _long_sequence, _long_table

from .conftest import make_sequence


def test_a_long_sequence_plays_a_recorded_one_forward_and_backward(tmp_path, data_root):
    seq = make_sequence(10)
    seq.valid = np.arange(10) != 3
    seq.extras = {"gt_tracking_lost": np.arange(10) == 5, "grasp": np.array("power")}
    (data_root / "sequences").mkdir()
    save_sequence(data_root / "sequences" / "s.npz", seq, data_root)
    root = _long_sequence(data_root, 25, tmp_path / "long")
    long = load_sequence(root / "sequences" / "long_25.npz", root)  # valid, and its mesh found
    index = np.concatenate([np.arange(10), np.arange(10)[::-1], np.arange(5)])
    assert long.num_frames == 25
    assert np.array_equal(long.keypoints, seq.keypoints[index])  # no jump where it turns
    assert np.array_equal(long.obj_pose, seq.obj_pose[index])
    assert np.array_equal(long.valid, seq.valid[index])
    assert np.array_equal(long.extras["gt_tracking_lost"], seq.extras["gt_tracking_lost"][index])
    assert str(long.extras["grasp"]) == "power"  # not per frame: kept as it is


def test_the_table_gives_time_and_memory_ratios_and_a_10_minute_estimate():
    def run(frames, scale):
        stages = {"contact": {"seconds": 2.0 * scale, "rss_mb": 500.0 + 0.1 * frames},
                  "refine": {"seconds": 40.0 * scale, "rss_mb": 800.0}}  # fmt: skip
        return {"frames": frames, "stages": stages}

    lines = _long_table([run(600, 1), run(2400, 4)])
    text = "\n".join(lines)
    assert "`dexflow bench long --frames 600,2400`" in text
    row = next(x for x in lines if x.startswith("| contact |"))
    assert row.endswith("| 4.0, 1.32 |")  # time x4, memory 560 -> 740 MiB
    assert "2.0, 300, 560" in row  # s, frames/s, MiB at 600 frames
    # largest peak 800 -> 800: nothing grows, 18,000 frames stay at 800 MiB
    assert "800 → 800 MiB, 0 KiB per added frame" in text and "about 800 MiB" in text


def test_the_pipeline_table_on_user_data_has_no_demo_row_and_names_the_command():
    from dexflow.tools.bench.pipeline import _bench_table

    def run(workers, scale):
        seconds = {"scale_align": 10.0 * scale, "retarget@dexflow": 2.0 * scale,
                   "refine": 20.0 * scale}  # fmt: skip
        return {"workers": workers, "seconds": seconds, "frames": 640, "evaluated": 40,
                "objects": 4, "peak_rss_mb": 900.0}  # fmt: skip

    lines = _bench_table([run(1, 1.0), run(2, 0.5)], "dexflow bench pipeline /d --workers 1,2", "x")
    text = "\n".join(lines)
    assert "`dexflow bench pipeline /d --workers 1,2`: the whole pipeline on x (4 objects" in text
    assert "| demo |" not in text
    assert (
        "| **pipeline (without demo)** | **32.0 s, 20.0 f/s** | **16.0 s, 40.0 f/s** | **2.00x** |"
        in text
    )
    assert "| refine | 20.0 s, 32 f/s, 62 % |" in text


def test_the_pipeline_table_at_two_data_sizes_shows_speed_ups_and_growth():
    from dexflow.tools.bench.pipeline import _bench_table

    def run(workers, scale):
        # scale_align is per object (the same at both sizes); the rest grows with the frames
        seconds = {"demo": 3.0, "scale_align": 8.0 / workers, "refine": 40.0 * scale / workers}
        return {"workers": workers, "scale": scale, "seconds": seconds, "frames": 400 * scale,
                "evaluated": 10, "objects": 2, "peak_rss_mb": 700.0}  # fmt: skip

    runs = [run(1, 1), run(2, 1), run(1, 4), run(2, 4)]
    lines = _bench_table(runs, "dexflow bench pipeline --scales 1,4", "x")
    text = "\n".join(lines)
    assert "(2 objects, 400 frames at ×1, 1600 frames at ×4)" in text
    head = next(x for x in lines if x.startswith("| stage |"))
    assert head.count("|") == 9  # stage, 4 runs, 2 speed-ups, growth: 8 columns
    assert "| refine | 40.0 s, 10 f/s, 83 % | 20.0 s, 20 f/s, 83 % |" in text
    assert next(x for x in lines if x.startswith("| refine |")).endswith("| 2.00x | 2.00x | 4.00 |")
    # 2 workers: 24 s at x1, 84 s at x4; without scale_align 20 -> 80 s
    assert (
        "×4 the sequences (400 → 1600 frames, ×4.00) took ×3.50 the time with 2 workers; " in text
    )
    assert "objects) ×4.00." in text
    # the estimate comes from the largest run: 80 s / 1600 frames = 50 ms per frame
    assert "from 2 worker(s) ×4: 50.0 ms per frame after scale_align plus 2 s per object" in text


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--scales", "x"], "whole numbers"),
        (["--scales", "0"], "whole numbers >= 1"),
        (["/nowhere", "--scales", "1,4"], "no sequences/ folder"),
    ],
)
def test_bench_pipeline_refuses_bad_scales_before_running_anything(argv, words, tmp_path):
    from dexflow.tools.cli import main

    with pytest.raises((SystemExit, ValueError, FileNotFoundError), match=words):
        main(["bench", "pipeline", *argv])
