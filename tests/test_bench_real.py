"""`dexflow bench real`: the subset of a dataset it runs on, and the table it writes."""

from __future__ import annotations

import math

import numpy as np

from dexflow.io.artifacts import ENGINE_KEYS, SimulationResult, write_simulation
from dexflow.io.layout import StageDir
from dexflow.tools.bench.pipeline import subset_root as _subset_root
from dexflow.tools.bench.real import _real_table, grasp_breakdown


def test_subset_links_evenly_spaced_sequences_and_the_rest_of_the_root(tmp_path):
    root = tmp_path / "data"
    (root / "sequences").mkdir(parents=True)
    (root / "meshes").mkdir()
    for i in range(10):
        (root / "sequences" / f"s{i:02d}.npz").write_bytes(b"x")
    assert _subset_root(root, 0, tmp_path / "all") == root
    assert _subset_root(root, 10, tmp_path / "all") == root
    sub = _subset_root(root, 3, tmp_path / "sub")
    assert sorted(p.name for p in (sub / "sequences").iterdir()) == [
        "s00.npz",
        "s04.npz",
        "s09.npz",
    ]
    assert (sub / "meshes").resolve() == (root / "meshes").resolve()
    again = _subset_root(root, 2, tmp_path / "sub")  # a rerun in the same work folder
    assert sorted(p.name for p in (again / "sequences").iterdir()) == ["s00.npz", "s09.npz"]


_REPLAYED = {"num_scored": 3, "success_rate": 200 / 3, "spider_success_rate": 100.0,
             "carried_rate": 200 / 3, "lost_rate": 100 / 3, "position_error_mean_m": 0.042,
             "rotation_error_mean_rad": 0.21, "ceiling_success_rate": 100.0,
             "unstable_rest_rate": 0.0}  # fmt: skip
_TRACKED = {"num_tracked": 3, "feasible_rate": 200 / 3, "grip_drift_mean_m": 0.0104,
            "timing": {"cpu_seconds_per_70_frames": 41.5}}  # fmt: skip


def test_table_has_one_row_per_hand_and_method_and_marks_missing_values():
    metrics = {"refine.fingertip_error_mm": 7.25, "refine.pd_max_mm": 3.0, "baseline.ssr": math.nan}
    result = {
        "metrics": metrics,
        "seconds": {"retarget@dexflow": 4.0, "refine": 6.0},
        "sequences": 2,
        "frames": 100,
        "retarget_s_per_sequence": 4.0,
    }
    text = _real_table({"shadow": result, "allegro": result}, "data/real", 0, 2)
    rows = [
        line
        for line in text.splitlines()
        if line.startswith("| shadow") or line.startswith("| allegro")
    ]
    assert len(rows) == 6  # no track row without track=on
    tracked = {**result, "metrics": {**metrics, "track.pd_mm": 0.5},
               "replay": {"replay@track": _REPLAYED, "track@refine": _TRACKED}}  # fmt: skip
    text_on = _real_table({"shadow": tracked}, "data/real", 0, 2, ["track=on"])
    assert "| shadow | DexFlow + track | " in text_on and "--set track=on" in text_on
    assert (
        "| shadow | DexFlow + track | 3 | 66.7 | 100.0 | 66.7 | 33 | 4.2 | 0.21 | 100.0 | 0 |"
        in text_on
    )
    assert "- shadow, stage track: 3 tracked, feasible 66.7 %; 41.5 CPU s per 70 frames" in text_on
    assert "(one core); grip drift 10.4 mm (the human's fingertips slide" in text_on
    refine = next(r for r in rows if r.startswith("| shadow | DexFlow + refine"))
    assert refine.split("|")[3].strip() == "7.2" and refine.split("|")[7].strip() == "3.0"
    baseline = next(r for r in rows if r.startswith("| shadow | position baseline"))
    assert baseline.split("|")[8].strip() == "—"
    assert (
        "`dexflow bench real data/real`" in text
        and "100 frames" in text
        and "10.0 frames/s" in text
    )


def test_table_names_the_subset_flag_it_was_made_with():
    result = {
        "metrics": {},
        "seconds": {"retarget@dexflow": 1.0},
        "sequences": 1,
        "frames": 10,
        "retarget_s_per_sequence": 1.0,
    }
    text = _real_table({"shadow": result}, "data/real", 5, 2)
    assert "`dexflow bench real data/real --subset 5`" in text


def test_table_shows_each_engine_and_their_agreement_and_the_overrides():
    sim = {"engines": "mujoco,pybullet", "perturbations": 2, "ssr_paper_mujoco": 25.0,
           "ssr_bench_mujoco": 25.0, "flipped_mujoco": 0.02, "ssr_paper_pybullet": 50.0,
           "ssr_bench_pybullet": 37.5, "flipped_pybullet": 0.05, "agree_hold": 4,
           "agree_drop": 30, "disagree": 6, "criteria_agree_hold": 5, "criteria_agree_drop": 33,
           "criteria_disagree": 2}  # fmt: skip
    result = {
        "metrics": {},
        "simulate": {"refine": sim},
        "seconds": {"retarget@dexflow": 1.0},
        "sequences": 1,
        "frames": 10,
        "retarget_s_per_sequence": 1.0,
    }
    text = _real_table({"shadow": result}, "data/real", 0, 2, ["simulate=both"])
    assert "`dexflow bench real data/real --set simulate=both`" in text
    assert "| shadow | refine | mujoco | 25.0 | 25.0 | 2.0 |" in text
    assert "| shadow | refine | pybullet | 50.0 | 37.5 | 5.0 |" in text
    assert "| shadow | refine | 40 | 4 | 30 | 6 |" in text
    assert "| shadow | refine | 40 | 5 | 33 | 2 |" in text  # the two tests of mujoco


def test_table_says_where_refinement_moved_the_fingertips():
    """With the motion summary (dexflow.tools.tip_motion) a row per hand; without it no table."""
    motion = {"tips": 40, "tip_depth_mm": 1.44, "near_share": 0.51, "near_error_from_mm": 4.46,
              "near_error_to_mm": 13.54, "normal_mm": 7.09, "outward_mm": 4.13,
              "tangential_mm": 8.36, "far_error_from_mm": 6.25, "far_error_to_mm": 7.49,
              "far_moved_mm": 2.77, "palm_mm": 10.29}  # fmt: skip
    result = {"metrics": {}, "seconds": {"retarget@dexflow": 1.0}, "sequences": 1, "frames": 10,
              "retarget_s_per_sequence": 1.0}  # fmt: skip
    assert "Where refinement moves" not in _real_table({"shadow": result}, "data/real", 0, 2)
    text = _real_table({"shadow": {**result, "motion": motion}}, "data/real", 0, 2)
    row = next(line for line in text.splitlines() if line.startswith("| shadow | 1.44"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells == ["shadow", "1.44", "51", "4.5 → 13.5", "7.1 (+4.1) / 8.4", "6.2 → 7.5",
                     "2.8", "10.3"]  # fmt: skip


def _simulated(
    out: StageDir,
    name: str,
    touching,
    bench,
    displacement_m,
    closing_m=None,
    imbalance=None,
    contact_imbalance=None,
) -> None:
    """A simulate output of len(bench) tested frames (engine mujoco; thumb, index, middle)."""
    n = len(bench)
    rows = {"frame": np.arange(n), "penetration_m": np.zeros(n)}
    rows["contact_imbalance"] = np.array(contact_imbalance or [np.nan] * n, dtype=float)
    rows |= {f"mujoco.{k}": np.zeros(n) for k in ENGINE_KEYS}
    rows["mujoco.closing_displacement_m"] = np.array(closing_m or [0.0] * n, dtype=float)
    rows["mujoco.imbalance"] = np.array(imbalance or [np.nan] * n, dtype=float)
    for key in ("held", "rotation_deg", "tested"):
        rows[f"mujoco.{key}"] = np.zeros((n, 6))
    rows["mujoco.touching"] = np.array(touching, dtype=bool).reshape(n, 3)
    rows["mujoco.bench"] = np.array(bench, dtype=bool)
    rows["mujoco.displacement_m"] = np.tile(np.array(displacement_m)[:, None], (1, 6))
    out.sequences_dir.mkdir(parents=True, exist_ok=True)
    write_simulation(
        out.sequence(name), SimulationResult(rows, ["thumb", "index", "middle"], ["mujoco"])
    )


def test_grasp_breakdown_counts_opposed_and_held_frames(tmp_path):
    """Tested, skipped (from the summary), held, opposed (thumb + another finger touching) and
    the failed frames' median displacement under the first push, pooled over sequences."""
    out = StageDir(tmp_path / "simulate")
    _simulated(out, "a", [[1, 1, 0], [1, 0, 0], [0, 1, 1]], [True, False, False],
               [0.001, 0.2, 0.1], [0.0, 0.06, 0.01], [0.1, 0.9, 0.7],
              [0.3, 1.0, np.nan])  # fmt: skip
    _simulated(out, "b", [[1, 0, 1]], [False], [0.05], [np.nan], [np.nan], [0.6])
    out.summary.write_text('{"frames_skipped": 4}')
    g = grasp_breakdown(out)
    assert (g["tested"], g["skipped"], g["held"], g["opposed"], g["opposed_held"]) == (
        4,
        4,
        1,
        2,
        1,
    )
    assert g["displacement_mm"] == 100.0 and g["thumb"]
    # one failed frame moved 6 cm (> the 5 cm threshold) before the push; NaN (an engine that
    # holds the object while closing) counts as not lost; the medians skip NaN
    assert g["lost_closing"] == 1
    assert (g["imbalance_held"], g["imbalance_failed"]) == (0.1, 0.8)
    assert (g["contact_imbalance_held"], g["contact_imbalance_failed"]) == (0.3, 0.8)
    text = _real_table(
        {"shadow": {"metrics": {}, "seconds": {"retarget@dexflow": 1.0}, "sequences": 2,
                    "frames": 10, "retarget_s_per_sequence": 1.0, "grasps": {"refine": g}}},
        "data/real", 0, 2,
    )  # fmt: skip
    assert "| shadow | refine | 4 | 4 | 1 | 2 | 1 | 100 / 0 | 1 | 0.10 / 0.80 |" in text
