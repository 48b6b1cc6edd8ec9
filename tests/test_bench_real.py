"""`dexflow bench real`: the subset of a dataset it runs on, and the table it writes."""

from __future__ import annotations

import math

from dexflow.bench import _real_table, _subset_root


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
    assert len(rows) == 6
    refine = next(r for r in rows if r.startswith("| shadow | DexFlow + refine"))
    assert refine.split("|")[3].strip() == "7.2" and refine.split("|")[6].strip() == "3.0"
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
    sim = {"engines": "mujoco,pybullet", "perturbations": 2, "ssr_mujoco": 25.0,
           "ssr_bench_mujoco": 25.0, "flipped_mujoco": 0.02, "ssr_pybullet": 50.0,
           "ssr_bench_pybullet": 37.5, "flipped_pybullet": 0.05, "agree_hold": 4,
           "agree_drop": 30, "disagree": 6}  # fmt: skip
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
