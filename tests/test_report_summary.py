"""What makes the summary readable in two minutes: the key-results box, tables that fit (the
full ones in CSV files), the signals that look contradictory explained, and the robot hand on
the object drawn from the pipeline's own outputs."""

from __future__ import annotations

import csv
import json
import re

import matplotlib.image
import numpy as np
import pytest
import trimesh

from dexflow.io.sequence import save_sequence
from dexflow.stages.report import (
    HAND_FIGURE,
    MAX_COLUMNS,
    METRICS,
    TABLE_II,
    _hand_frames,
    write_hand_figure,
    write_summary,
)
from dexflow.stats import rate_interval
from tests.test_contact_flicker import allegro_box_params
from tests.test_metrics import _metrics_dir, _section

from .conftest import make_sequence

INTERVAL = r"\d+\.\d+ \[\d+\.\d+, \d+\.\d+\]"


@pytest.fixture
def full_inputs(tmp_path):
    """Report inputs with every section present: engines, replay, contact, 8 sequences."""
    metrics, table, plots = _metrics_dir(tmp_path / "in")
    aggregates = json.loads((metrics / "metrics.json").read_text())
    aggregates |= {"num_frames": 240, "num_input_sequences": 8, "num_dropped": 0,
                   "baseline.velocity_kl": 0.03, "retarget.velocity_kl": 0.27,
                   "baseline.rms_acc": 99.0, "retarget.rms_acc": 2.2,
                   "retarget.pd_mm": 6.0, "refine.pd_mm": 1.5,
                   "retarget.keypoint_error_mm": 7.5, "refine.keypoint_error_mm": 11.0,
                   "refine.cd_contact_mm": 0.6}  # fmt: skip
    (metrics / "metrics.json").write_text(json.dumps(aggregates))
    rows = []
    for i in range(8):
        for m in ("baseline", "retarget", "refine"):
            rows.append({"sequence": f"obj{i % 4}__{i}", "object": f"obj{i % 4}", "hand": "shadow",
                         "method": m, "ssr": 100.0 if m == "refine" and i < 2 else 0.0,
                         "pd_mm": {"baseline": 6.0, "retarget": 6.0, "refine": 1.0}[m] + 0.1 * i,
                         "cd_mm": 2.0, "keypoint_error_mm": 7.0 + i})  # fmt: skip
    with open(table, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    for m, spider in (("retarget", 75.0), ("refine", 62.5)):
        replay = {"num_replayed": 8, "num_scored": 8, "success_rate": 12.5,
                  "spider_success_rate": spider, "carried_rate": 12.5, "lost_rate": 87.5,
                  "position_error_mean_m": 0.08, "static_error_mean_m": 0.075,
                  "held_fraction": 0.4, "rotation_error_mean_rad": 0.3}  # fmt: skip
        (metrics / f"replay_{m}.json").write_text(json.dumps(replay))
    (metrics / "contact.json").write_text(json.dumps({"inference_note": "How it infers."}))
    return metrics, table, plots


def _summary(tmp_path, inputs, **kwargs) -> str:
    metrics, table, plots = inputs
    out = write_summary(metrics, table, plots, tmp_path / "summary.md", tmp_path / "figures",
                        data_name="demo", **kwargs)  # fmt: skip
    return out.read_text()


def test_the_summary_opens_with_five_lines_of_key_results(tmp_path, full_inputs):
    text = _summary(tmp_path, full_inputs, replay_limits={"position_m": 0.1, "rotation_rad": 0.5})
    lines = text.splitlines()
    assert lines[0] == "# dexflow summary" and lines[1] == ""
    box = lines[2 : lines.index("", 2)]
    assert len(box) == 5 and all(line.startswith("> ") for line in box)
    assert "n = 8 sequences, 240 frames; data **demo**; hand **shadow**" in box[0]
    ssr = box[1]
    assert len(re.findall(INTERVAL, ssr)) == 3  # one per method
    assert f"DexFlow + refinement {rate_interval(2, 8).text(1)}" in ssr
    assert "intervals overlap, not resolved" in ssr
    assert "intervals apart" in box[2]  # PD: 1.35 [..] against 6.35 [..]
    assert len(re.findall(INTERVAL, box[3])) == 2  # replayed: DexFlow and refinement only
    assert "grasps are synthetic" in box[4] and "SPIDER" in box[4]


def test_contradictory_signals_get_one_sentence_each(tmp_path, full_inputs):
    text = _summary(tmp_path, full_inputs, replay_limits={"position_m": 0.1, "rotation_rad": 0.5})
    notes = _section(text, "Reading the numbers")
    spider = next(n for n in notes.splitlines() if n.startswith("- **Replay"))
    assert "DexFlow retargeting: SPIDER 75 % beside 88 % lost" in spider
    assert "below 10 cm" in spider and "7.5 cm" in spider  # the threshold, the left-behind error
    assert "Velocity KL: DexFlow 0.27, 9x the baseline's 0.03" in notes
    assert "penetration 6.00 -> 1.50 mm, keypoint error 7.50 -> 11.00 mm" in notes

    assert "rigid ceiling" not in notes and "do not rest as recorded" not in notes
    metrics, _, _ = full_inputs  # real captures: the path and the rest bound the replay
    refine = json.loads((metrics / "replay_refine.json").read_text())
    refine |= {"ceiling_success_rate": 14.3, "ceiling_rotation_error_mean_rad": 1.08,
               "unstable_rest_rate": 64.3, "rest_drift_mean_m": 0.057}  # fmt: skip
    (metrics / "replay_refine.json").write_text(json.dumps(refine))
    notes = _section(_summary(tmp_path, full_inputs), "Reading the numbers")
    assert "DexFlow + refinement: rigid ceiling 14 %." in notes and "1.08 rad" in notes
    assert "64 % of the objects do not rest as recorded." in notes and "5.7 cm" in notes
    refine |= {"ceiling_success_rate": 91.7, "unstable_rest_rate": 0.0}
    (metrics / "replay_refine.json").write_text(json.dumps(refine))
    notes = _section(_summary(tmp_path, full_inputs), "Reading the numbers")
    assert "rigid ceiling" not in notes and "do not rest as recorded" not in notes

    # nothing contradicts: no section
    for m in ("retarget", "refine"):
        (metrics / f"replay_{m}.json").unlink()
    aggregates = json.loads((metrics / "metrics.json").read_text())
    aggregates |= {"retarget.velocity_kl": 0.01, "refine.keypoint_error_mm": 7.0}
    (metrics / "metrics.json").write_text(json.dumps(aggregates))
    assert "## Reading the numbers" not in _summary(tmp_path, full_inputs)


def _tables(text: str) -> list[list[str]]:
    """The header row of every Markdown table."""
    lines = text.splitlines()
    return [
        [c.strip() for c in lines[i].strip().strip("|").split("|")]
        for i in range(len(lines) - 1)
        if lines[i].startswith("|") and lines[i + 1].startswith("|---")
    ]


def test_no_table_is_wider_than_eight_columns_and_the_csvs_hold_them_whole(tmp_path, full_inputs):
    metrics, _, _ = full_inputs
    sim = json.loads((metrics / "simulate_refine.json").read_text())
    sim |= {"engines": "mujoco,pybullet", "perturbations": 2, "agree_hold": 3, "agree_drop": 90,
            "disagree": 7}  # fmt: skip
    (metrics / "simulate_refine.json").write_text(json.dumps(sim))
    text = _summary(tmp_path, full_inputs)
    headers = _tables(text)
    assert len(headers) >= 8
    assert max(len(h) for h in headers) <= MAX_COLUMNS == 8

    def read(name: str) -> list[dict]:
        assert f"[{name}]({name})" in text  # linked from the summary
        with open(tmp_path / name, newline="") as f:
            return list(csv.DictReader(f))

    grasp = read("summary_grasp.csv")
    assert list(grasp[0])[1:] == [METRICS[k][0] for k in TABLE_II]  # CD in contact included
    assert float(grasp[2]["CD in contact mm (dexflow) ↓"]) == 0.6
    assert grasp[4]["method"] == "paper: DexFlow" and grasp[4]["SSR paper protocol % ↑"] == "40.32"
    assert len(read("summary_simulation.csv")[0]) == 12
    replay = {r["method"]: r for r in read("summary_replay.csv")}
    assert float(replay["DexFlow + refinement"]["left behind (cm)"]) == pytest.approx(7.5)
    objects = read("summary_objects.csv")
    assert len(objects) == 4 and len(objects[0]) == 2 + 4 * 3  # every metric, every method
    spread = [r for r in read("summary_spread.csv") if r["metric"] == "SSR every test % ↑"]
    wilson = rate_interval(2, 8)
    refine = next(r for r in spread if r["method"] == "refine")
    assert [float(refine[k]) for k in ("value", "low", "high")] == pytest.approx(
        [25.0, wilson.low, wilson.high]
    )
    assert "- How it infers." in _section(text, "Definitions")  # moved down, kept


def test_every_figure_says_what_it_averages(tmp_path, full_inputs):
    """The figures are titled, with n; a figure of a mean draws its interval (the methods
    figure's whiskers differ from a figure without them)."""
    text = _summary(tmp_path, full_inputs)
    for name in ("summary_methods.png", "summary_objects_pd.png", "summary_timeline.png"):
        assert f"(figures/{name})" in text
        image = matplotlib.image.imread(tmp_path / "figures" / name)
        assert image.std() > 0.05, name


# --- the fourth method, track (stage track, track=on) --------------------------------------------


def _add_track(metrics, table, plots) -> None:
    """What track=on adds to the report's inputs: track's aggregates, rows of sequences.csv and
    plot columns, simulate@track, replay@track and stage track's own summary. Tracking holds
    every sequence in the replay where refinement holds 1 of 8."""
    aggregates = json.loads((metrics / "metrics.json").read_text())
    aggregates |= {"track.ssr": 30.0, "track.ssr_paper": 45.0, "track.pd_mm": 2.5,
                   "track.rms_acc": 3.0, "track.keypoint_error_mm": 12.0}  # fmt: skip
    (metrics / "metrics.json").write_text(json.dumps(aggregates))
    with open(table, newline="") as f:
        rows = list(csv.DictReader(f))
    rows += [r | {"method": "track", "pd_mm": "2.5", "ssr": "100.0" if i < 3 else "0.0"}
             for i, r in enumerate(r for r in rows if r["method"] == "refine")]  # fmt: skip
    with open(table, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    for name in ("keypoint_error.csv", "penetration.csv"):
        lines = (plots / name).read_text().splitlines()
        (plots / name).write_text("\n".join([lines[0] + ",track"] +
                                             [f"{r},{i + 5}" for i, r in enumerate(lines[1:])]) + "\n")  # fmt: skip
    sim = json.loads((metrics / "simulate_refine.json").read_text()) | {"ssr": 30.0}
    (metrics / "simulate_track.json").write_text(json.dumps(sim))
    replay = json.loads((metrics / "replay_refine.json").read_text())
    replay |= {"success_rate": 100.0, "spider_success_rate": 100.0, "carried_rate": 100.0,
               "lost_rate": 0.0}  # fmt: skip
    (metrics / "replay_track.json").write_text(json.dumps(replay))
    tracked = {"num_tracked": 8, "feasible_rate": 75.0, "position_error_mean_m": 0.02,
               "rotation_error_mean_rad": 0.1, "position_error_final_m": 0.03, "lost_rate": 12.5,
               "grip_drift_mean_m": 0.0123}  # fmt: skip
    (metrics / "track_refine.json").write_text(json.dumps(tracked))


def test_a_tracked_run_shows_the_fourth_method_wherever_the_three_are(tmp_path, full_inputs):
    _add_track(*full_inputs)
    text = _summary(tmp_path, full_inputs)
    lines = text.splitlines()
    box = lines[2 : lines.index("", 2)]
    assert len(box) == 6 and all(line.startswith("> ") for line in box)
    assert len(re.findall(INTERVAL, box[1])) == 4  # SSR: one per method, track's included
    assert f"DexFlow + tracking {rate_interval(3, 8).text(1)}" in box[1]
    tracking = box[4]
    assert tracking.startswith("> - **Tracking**")
    assert (
        f"DexFlow + tracking {rate_interval(8, 8).text(1)} vs DexFlow + refinement "
        f"{rate_interval(1, 8).text(1)} (tracking above refinement, intervals apart)"
    ) in tracking
    assert "feasible (its replay succeeds) 75.0 % of the 8 tracked sequences" in tracking
    assert "Caveats" in box[5]

    label = "| DexFlow + tracking (physics) |"
    for section in ("Grasp quality", "Simulation", "Motion quality"):
        assert sum(line.startswith(label) for line in _section(text, section).splitlines()) == 1
    replay = _section(text, "Replay")
    assert label + " 8 | 0 | 100.0 |" in replay
    assert "8 sequences tracked, *feasible* (the tracked trajectory's replay succeeds) 75.0 %" in (
        replay
    )
    assert "lost 12 %; grip drift 12.3 mm (the human's fingertips slide" in replay
    assert "| | baseline | retarget | refine | track | sequences | interval |" in text
    assert "*DexFlow + tracking (physics)*: stage track's" in _section(text, "Definitions")

    def read(name: str) -> list[dict]:
        with open(tmp_path / name, newline="") as f:
            return list(csv.DictReader(f))

    assert [r["method"] for r in read("summary_grasp.csv")][3] == "DexFlow + tracking (physics)"
    assert len(read("summary_objects.csv")[0]) == 2 + 4 * 4  # every metric, every method
    spread = {(r["metric"], r["method"]): r for r in read("summary_spread.csv")}
    assert float(spread["replay success %", "track"]["value"]) == 100.0


def test_without_track_the_summary_is_the_same_bytes_as_before_it(tmp_path, full_inputs):
    """Track's rows, columns and lines come from its inputs alone: a run without them writes
    what it wrote before, and nothing names tracking."""
    metrics, table, plots = full_inputs
    saved = {p: p.read_bytes() for p in (metrics / "metrics.json", table,
                                         plots / "keypoint_error.csv", plots / "penetration.csv")}  # fmt: skip

    def outputs(name: str) -> dict[str, bytes]:
        out = tmp_path / name
        write_summary(metrics, table, plots, out / "summary.md", out / "figures",
                      data_name="demo")  # fmt: skip
        return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*.*"))}

    before = outputs("before")
    assert b"track" not in before["summary.md"] and b"tracking" not in before["summary_grasp.csv"]
    assert len(before["summary.md"].decode().splitlines()[2:7]) == 5
    _add_track(metrics, table, plots)
    tracked = outputs("tracked")
    changed = {k for k in before if tracked[k] != before[k]}
    assert {"summary.md", "summary_grasp.csv", "summary_spread.csv", "summary_simulation.csv",
            "figures/summary_methods.png", "figures/summary_timeline.png"} <= changed  # fmt: skip
    for path, data in saved.items():
        path.write_bytes(data)
    for name in ("simulate_track", "replay_track", "track_refine"):
        (metrics / f"{name}.json").unlink()
    assert outputs("after") == before


def test_the_track_stage_summary_alone_shows_track(tmp_path, full_inputs):
    """Stage track ran, its simulate and replay not (yet): track's rows read —, its line says
    so, and the feasible rate comes from ``track_refine.json``."""
    metrics, _, _ = full_inputs
    (metrics / "track_refine.json").write_text(
        json.dumps({"num_tracked": 4, "feasible_rate": 25.0})
    )
    text = _summary(tmp_path, full_inputs)
    tracking = next(line for line in text.splitlines() if line.startswith("> - **Tracking**"))
    assert "DexFlow + tracking — vs DexFlow + refinement" in tracking
    assert "feasible (its replay succeeds) 25.0 % of the 4 tracked sequences" in tracking
    grasp = _section(text, "Grasp quality")
    assert "| DexFlow + tracking (physics) | — | — |" in grasp


# --- the robot hand on the object ------------------------------------------------------------


def test_hand_frames_follow_the_replay_or_spread_evenly():
    entry = {"start": 7, "first_contact": 12, "last_contact": 58}
    assert [f for f, _ in _hand_frames(entry, 63, 4)] == [7, 12, 35, 58]
    assert [f for f, _ in _hand_frames({}, 63, 4)] == [0, 21, 41, 62]
    assert [f for f, _ in _hand_frames({"first_contact": 12, "last_contact": 80}, 63, 4)] == [
        0, 21, 41, 62]  # fmt: skip


@pytest.fixture(scope="module")
def hand_project(tmp_path_factory):
    """A scaled box scene, the allegro hand's staged copy, and a refined trajectory holding the
    hand just above the box."""
    from dexflow.io.artifacts import Trajectory, write_trajectory
    from dexflow.io.layout import Layout
    from dexflow.pipeline.labelled import labelled_hand
    from dexflow.stages.hand import run_hand
    from dexflow.stages.scale_align import run_scale_align

    root = tmp_path_factory.mktemp("hand_figure")
    (root / "meshes").mkdir()
    trimesh.creation.box(extents=(0.06, 0.06, 0.06)).export(root / "meshes" / "box.obj")
    save_sequence(root / "sequences" / "s0.npz", make_sequence(12), data_root=root)
    params = allegro_box_params()
    layout = Layout.of(root, root=root / "project")
    assert run_scale_align(params, layout)["num_ok"] == 1
    run_hand(params, layout)
    hand = labelled_hand(params, layout)
    q = np.zeros((12, hand.dof))
    q[:, 2] = 0.05 + 0.005 * np.arange(12)  # rising above the box
    layout.refine.sequences_dir.mkdir(parents=True)
    write_trajectory(layout.refine.sequence("s0"), Trajectory(q, list(hand.joint_names)))
    return params, layout


def test_the_hand_figure_draws_the_posed_hand_and_the_object(tmp_path, hand_project):
    params, layout = hand_project
    name, caption = write_hand_figure(params, layout, tmp_path)
    assert name == HAND_FIGURE and "s0" in caption and "frames 0 (1 of 4" in caption
    image = matplotlib.image.imread(tmp_path / name)[..., :3]
    assert image.std() > 0.05  # not blank
    hand_blue = (image[..., 2] > image[..., 0] + 0.1).sum()
    object_orange = (image[..., 0] > image[..., 2] + 0.2).sum()
    assert hand_blue > 500 and object_orange > 500  # both drawn
    first = (tmp_path / name).read_bytes()
    write_hand_figure(params, layout, tmp_path)
    assert (tmp_path / name).read_bytes() == first  # deterministic


def test_the_hand_figure_is_shown_near_the_top(tmp_path, full_inputs):
    text = _summary(tmp_path, full_inputs, hand_figure=(HAND_FIGURE, "the hand"))
    assert text.index(f"(figures/{HAND_FIGURE})") < text.index("\n## ")


# --- ablation figures: the headline metrics that change -----------------------------------------


def test_ablation_figures_draw_only_headline_metrics_that_change(tmp_path):
    from dexflow.tools.experiments import Experiment, write_ablation

    def run(name: str, value: float, ssr: float) -> Experiment:
        metrics = {"refine.ssr": ssr, "refine.pd_mm": 1.5, "retarget.rms_acc": 2.0,
                   "baseline.cd_mm": 3.0 + value}  # fmt: skip
        return Experiment(name, "dvc", {"contact.dis_min_m": value}, metrics, None)

    runs = [run("a", 0.008, 10.0), run("b", 0.010, 30.0), run("c", 0.010, 20.0)]
    text = write_ablation(runs, tmp_path / "sweep.md", tmp_path / "figures").read_text()
    section = text.split("## `contact.dis_min_m`")[1].split("\n## ")[0]
    assert "Figure: 1 headline metrics" in section
    assert (
        "Not drawn, flat across the values: refine PD mm ↓, retarget RMS acc rad/s² ↓." in section
    )
    assert "| baseline CD mm ↓ |" in section  # not a headline metric: in the table only
    image = matplotlib.image.imread(tmp_path / "figures" / "ablation_contact_dis_min_m.png")
    assert image.std() > 0.05

    flat = [run("a", 0.008, 10.0), run("b", 0.010, 10.0)]
    text = write_ablation(flat, tmp_path / "flat.md", tmp_path / "flat").read_text()
    assert "No figure: every headline metric is the same at every value." in text
    assert not (tmp_path / "flat").exists() or not list((tmp_path / "flat").iterdir())
