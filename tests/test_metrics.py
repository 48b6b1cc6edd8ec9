"""Metric definitions on hand-built cases, and the report generators on failed / partial runs."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
import trimesh

from dexflow.geometry import pose_vector
from dexflow.hands import load_hand
from dexflow.hands.robot import MEASURE_POINTS, measurement_hand
from dexflow.measures import (
    CD_CAP_M,
    SelfCollision,
    capped_contact_distance,
    chamfer_per_frame,
    contact_distance,
    grip_drift,
    penetration_depth,
    state_flicker,
    surface_distances,
)
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import MetricsParams
from dexflow.stages.metrics import _own_poses, trajectory_metrics
from dexflow.stages.report import write_summary
from dexflow.tools.experiments import Experiment, collect_dvc, collect_multirun, write_ablation


@pytest.fixture(scope="module")
def allegro():
    return load_hand("allegro")


def _wall(hand, q, depth):
    """A slab whose face is ``depth`` below the hand's extreme point along +x."""
    with torch.no_grad():
        points = hand.surface(torch.as_tensor(q))[0].numpy()[0]
    slab = trimesh.creation.box(extents=(0.1, 0.4, 0.4))
    sdf = SignedDistanceGrid.from_mesh(slab, spacing=0.004)
    pose = np.eye(4)
    pose[:3, 3] = [points[:, 0].max() - depth + 0.05, points[:, 1].mean(), points[:, 2].mean()]
    return sdf, pose


@pytest.mark.parametrize("depth", [0.0, 0.003, 0.008])
def test_penetration_depth_of_a_known_overlap(allegro, depth):
    q = allegro.zero().numpy()
    sdf, pose = _wall(allegro, q, depth)
    distances, _ = surface_distances(allegro, q, pose[None], sdf)
    assert penetration_depth(distances)[0] == pytest.approx(depth, abs=3e-4)


@pytest.mark.parametrize("depth", [0.004, 0.01])
def test_own_object_penetration_is_against_the_object_the_trajectory_holds(allegro, depth):
    """A hand ``depth`` inside the recorded object and clear of its own (moved 5 cm away):
    ``pd_mm`` sees the depth, ``pd_own_object_mm`` none; without own poses both agree."""
    q = allegro.zero(3).numpy()
    sdf, pose = _wall(allegro, q[0], depth)
    recorded = np.repeat(pose[None], 3, axis=0)
    moved = recorded.copy()
    moved[:, 0, 3] += 0.05  # the wall's face 5 cm beyond the hand
    pose7 = pose_vector(moved)
    pose7[0] = np.nan  # outside the replay window: the recorded pose
    own = _own_poses(pose7, recorded)
    assert np.allclose(own[0], recorded[0]) and np.allclose(own[1:], moved[1:], atol=1e-12)
    assert _own_poses(None, recorded) is None
    args = (q, allegro.keypoints(torch.as_tensor(q)).detach().numpy(), np.ones(3, bool))
    rest = (sdf, np.zeros((3, 4), bool), 30.0, MetricsParams())
    held, _ = trajectory_metrics(allegro, *args, recorded, *rest, own)
    assert held["pd_mm"] >= 1000 * depth - 0.3  # the measured hand reaches at least as far
    assert held["pd_own_object_mm"] == pytest.approx(held["pd_mm"] / 3)  # frame 0 only
    plain, _ = trajectory_metrics(allegro, *args, recorded, *rest)
    assert plain["pd_own_object_mm"] == plain["pd_mm"] == held["pd_mm"]


def test_grip_drift_of_a_rigid_and_a_sliding_grip():
    """Fingertips fixed on a tumbling object do not drift; a fingertip that alternates between
    two points 2 d apart on it drifts d (any point between is a median, at mean distance d)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    frames = 30
    poses = np.repeat(np.eye(4)[None], frames, axis=0)
    poses[:, :3, :3] = Rotation.random(frames, random_state=4).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(frames, 3))
    fixed = rng.normal(size=(5, 3)) * 0.05
    sliding = np.repeat(fixed[None], frames, axis=0)
    sliding[:, 1, 0] += np.where(np.arange(frames) % 2, 0.01, -0.01)  # tip 1: +-1 cm
    world = np.einsum("tij,tfj->tfi", poses[:, :3, :3], sliding) + poses[:, None, :3, 3]
    rigid = np.einsum("tij,fj->tfi", poses[:, :3, :3], fixed) + poses[:, None, :3, 3]
    assert grip_drift(rigid, poses) == pytest.approx(0.0, abs=1e-9)
    assert grip_drift(world, poses) == pytest.approx(0.01 / 5, rel=1e-6)  # one tip of five
    assert np.isnan(grip_drift(world[:1], poses[:1]))


def test_contact_distance_and_flicker_by_hand():
    per_finger = np.array([[0.004, -0.002, 0.05], [0.001, 0.003, 0.02], [0.1, 0.1, 0.1]])
    contact = np.array([[True, True, False], [False, True, False], [False, False, False]])
    cd = contact_distance(per_finger, contact)
    assert cd[0] == pytest.approx((0.004 + 0.0) / 2)  # penetration clipped at 0
    assert cd[1] == pytest.approx(0.003) and np.isnan(cd[2])
    states = np.array([[0, 0], [1, 0], [0, 0], [1, 0], [1, 0]], dtype=bool)  # 3 changes
    assert state_flicker(states, fps=10.0) == pytest.approx(3 / 2 / (4 / 10.0))


def test_bodex_contact_distance_counts_every_finger_capped_at_one_centimetre():
    """BODex's CD: every finger, inside as 0, beyond 1 cm as 1 cm; NaN outside the grasp. The
    fingers-in-contact variant (cd_contact) differs where a finger misses the object."""
    per_finger = np.array([[0.004, -0.002, 0.05], [0.001, 0.003, 0.002], [0.1, 0.1, 0.1]])
    cd = capped_contact_distance(per_finger, np.array([True, True, False]))
    assert cd[0] == pytest.approx((0.004 + 0.0 + CD_CAP_M) / 3)
    assert cd[1] == pytest.approx(0.002) and np.isnan(cd[2])
    in_contact = contact_distance(per_finger, np.array([[True, True, False]] * 3))
    assert in_contact[0] == pytest.approx(0.002) and in_contact[0] < cd[0]


def test_penetration_is_measured_on_every_collision_shape(allegro):
    """The measurement hand samples the links the config leaves out of its surface points
    (a forearm), densely; the stages' own hand keeps its points."""
    import dataclasses

    from dexflow.hands.robot import RobotHand

    q = allegro.zero().numpy()
    with torch.no_grad():
        points = measurement_hand(allegro).surface(torch.as_tensor(q))[0].numpy()[0]
    lowest = int(points[:, 2].argmin())  # leave out the link that reaches lowest
    left_out = measurement_hand(allegro).surface_point_links[lowest]
    hand = RobotHand(
        dataclasses.replace(allegro.spec, surface_exclude=[left_out]), allegro.base_dir
    )
    measured = measurement_hand(hand)
    assert left_out not in hand.surface_links and left_out in measured.surface_links
    assert set(measured.surface_links) == {g.link for g in hand.model.geometries}
    assert len(measured.surface_point_links) >= MEASURE_POINTS * 0.9
    assert measurement_hand(hand) is measured  # built once per process
    # a slab 3 mm into the lowest link: deeper than the stages' points reach, not than PD's
    slab = trimesh.creation.box(extents=(0.4, 0.4, 0.1))
    sdf = SignedDistanceGrid.from_mesh(slab, spacing=0.005)
    pose = np.eye(4)
    pose[:3, 3] = [*points[lowest, :2], points[lowest, 2] + 0.003 - 0.05]
    depth_stage = penetration_depth(surface_distances(hand, q, pose[None], sdf)[0])[0]
    depth_measured = penetration_depth(surface_distances(measured, q, pose[None], sdf)[0])[0]
    assert depth_measured == pytest.approx(0.003, abs=3e-4) and depth_stage < depth_measured


def test_chamfer_of_identical_and_shifted_sets():
    a = np.random.default_rng(0).normal(size=(5, 13, 3))
    assert np.allclose(chamfer_per_frame(a, a), 0.0)
    assert np.allclose(chamfer_per_frame(a, a + np.array([0.0, 0.0, 1e-3])), 1e-3, atol=1e-9)


def test_identical_trajectories_give_zero_error_chamfer_and_kl(allegro):
    t = np.linspace(0, 1, 40)
    q = allegro.zero(40).numpy()
    q[:, 0] = 0.1 * np.sin(3 * t)  # the hand moves, so the fingertips have speeds
    q[:, 7] = 0.3 + 0.2 * np.sin(5 * t)
    with torch.no_grad():
        human = allegro.keypoints(torch.as_tensor(q)).numpy()
    sdf, pose = _wall(allegro, allegro.zero().numpy(), -1.0)  # a metre away: no contact
    poses = np.repeat(pose[None], 40, axis=0)
    scalars, _ = trajectory_metrics(
        allegro, q, human, np.ones(40, bool), poses, sdf, np.zeros((40, 4), bool), 30.0,
        MetricsParams(),
    )  # fmt: skip
    assert scalars["keypoint_error_mm"] == pytest.approx(0.0, abs=1e-9)
    assert scalars["time_aligned_cd_mm"] == pytest.approx(0.0, abs=1e-9)
    assert scalars["velocity_kl"] == pytest.approx(0.0, abs=1e-12)
    assert scalars["pd_mm"] == 0.0 and np.isnan(scalars["cd_mm"]) and scalars["fvr"] == 0.0
    shifted = human + np.array([0.0, 0.0, 0.002])
    moved, _ = trajectory_metrics(
        allegro, q, shifted, np.ones(40, bool), poses, sdf, np.zeros((40, 4), bool), 30.0,
        MetricsParams(),
    )  # fmt: skip
    assert moved["keypoint_error_mm"] == pytest.approx(2.0, abs=1e-6)
    tips_only = human.copy()
    tips = [i for i, m in enumerate(allegro.mano_indices) if m in (4, 8, 12, 16, 20)]
    tips_only[:, tips] += np.array([0.0, 0.0, 0.005])
    moved, _ = trajectory_metrics(
        allegro, q, tips_only, np.ones(40, bool), poses, sdf, np.zeros((40, 4), bool), 30.0,
        MetricsParams(),
    )  # fmt: skip
    assert moved["fingertip_error_mm"] == pytest.approx(5.0, abs=1e-6)
    assert moved["keypoint_error_mm"] == pytest.approx(5.0 * len(tips) / len(tips_only[0]))
    # human tips outside the object: the surface-corrected error is the raw one
    assert moved["fingertip_error_surface_mm"] == pytest.approx(5.0, abs=1e-6)
    # a wall 3 mm into the hand: the human tips inside it are moved out to its face, so the
    # robot (on the human tips) is off the corrected ones by their depth
    sdf, pose = _wall(allegro, q[0], 0.003)
    inside, _ = trajectory_metrics(
        allegro, q[:1], human[:1], np.ones(1, bool), pose[None], sdf, np.zeros((1, 4), bool),
        30.0, MetricsParams(),
    )  # fmt: skip
    with torch.no_grad():
        face = allegro.surface(torch.as_tensor(q[:1]))[0].numpy()[0][:, 0].max() - 0.003
    tips_x = human[0, tips, 0]
    expected = np.clip(tips_x - face, 0, None).mean() * 1000
    assert inside["fingertip_error_mm"] == pytest.approx(0.0, abs=1e-9)
    assert inside["fingertip_error_surface_mm"] == pytest.approx(expected, abs=0.05)


def test_rms_acceleration_of_a_known_parabola(allegro):
    fps, a = 30.0, 4.0  # rad/s² on one joint, zero on the others
    t = np.arange(30) / fps
    q = allegro.zero(30).numpy()
    joint = allegro.joint_names.index("joint_1.0")
    q[:, joint] = 0.2 + 0.1 * 0.5 * a * t**2  # 0.1 a
    sdf, pose = _wall(allegro, allegro.zero().numpy(), -1.0)
    human = np.zeros((30, len(allegro.keypoint_links), 3))
    scalars, _ = trajectory_metrics(
        allegro, q, human, np.zeros(30, bool), np.repeat(pose[None], 30, axis=0), sdf,
        np.zeros((30, 4), bool), fps, MetricsParams(),
    )  # fmt: skip
    assert scalars["rms_acc"] == pytest.approx(0.1 * a / np.sqrt(allegro.dof - 6), rel=1e-9)


def test_self_penetration_and_feasibility(allegro):
    spd = SelfCollision(allegro)
    zero = allegro.zero().numpy()
    assert spd(zero)[0] == 0.0  # pairs overlapping at the zero pose are excluded by design
    thumb, index = allegro.spec.fingers["thumb"].joints, allegro.spec.fingers["index"].joints
    rng = np.random.default_rng(1)
    lo, hi = allegro.lower.numpy(), allegro.upper.numpy()
    q = np.repeat(zero, 200, axis=0)
    for name in thumb + index:
        j = allegro.joint_names.index(name)
        q[:, j] = lo[j] + rng.random(200) * (hi[j] - lo[j])
    depth = spd(q)
    assert depth.max() > 0.003  # thumb and index collide in some random configurations
    worst = q[[int(depth.argmax())]]
    params = MetricsParams(spd_violation_m=0.001)
    sdf, pose = _wall(allegro, zero, -1.0)
    human = np.zeros((1, len(allegro.keypoint_links), 3))
    args = (human, np.zeros(1, bool), pose[None], sdf, np.zeros((1, 4), bool), 30.0, params)
    assert trajectory_metrics(allegro, worst, *args)[0]["fvr"] == 1.0
    beyond = zero.copy()
    beyond[0, allegro.joint_names.index(index[0])] = hi[allegro.joint_names.index(index[0])] + 0.1
    assert trajectory_metrics(allegro, beyond, *args)[0]["fvr"] == 1.0
    assert trajectory_metrics(allegro, zero, *args)[0]["fvr"] == 0.0


# ------------------------------------------------------------------------------------ reports


def _metrics_dir(root, methods=("baseline", "retarget", "refine")):
    """What the metrics and simulate stages leave for the report: aggregates, one simulate
    summary per method, the per-sequence table and the per-frame CSVs."""
    metrics = root / "metrics"
    metrics.mkdir(parents=True)
    aggregates = {"num_sequences": 2, "num_failed": 0}
    for i, m in enumerate(("baseline", "retarget", "refine")):
        aggregates |= {f"{m}.ssr": 10.0 * i, f"{m}.ssr_paper": 15.0 * i, f"{m}.pd_mm": 3.0 - i,
                       f"{m}.rms_acc": 1.5}  # fmt: skip
    (metrics / "metrics.json").write_text(json.dumps(aggregates))
    for i, m in enumerate(methods):
        sim = {"ssr": 10.0 * i, "ssr_raw": 40.0 + i, "ssr_paper": 15.0 * i, "ssr_bench": 0.0,
               "ssr_bench_raw": 5.0, "criteria_agree_hold": 3, "criteria_agree_drop": 87 + i,
               "criteria_disagree": 10, "frames_evaluated": 100 + i, "penetration_mean_mm": 2.5, "over_tolerance": 0.25,
               "parts_penetration_mean_mm": 4.5, "parts_over_tolerance": 0.75,
               "lost_closing": 0.5 if m == "refine" else None, "imbalance_mean": 0.625,
               "contact_imbalance_mean": 0.875}  # fmt: skip
        (metrics / f"simulate_{m}.json").write_text(json.dumps(sim))
    with open(root / "sequences.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["sequence", "object", "hand", "method", "ssr", "pd_mm", "cd_mm",
                         "keypoint_error_mm"])  # fmt: skip
        for seq, obj in (("mug__00", "025_mug"), ("box__00", "003_cracker_box")):
            for i, m in enumerate(("baseline", "retarget", "refine")):
                writer.writerow([seq, obj, "shadow", m, 50.0 * (i % 2), 3 - i, 2.0, 7.0])
    plots = root / "plots"
    plots.mkdir()
    for name in ("keypoint_error.csv", "penetration.csv"):
        rows = ["step,sequence,frame,time_s,baseline,retarget,refine"]
        rows += [f"{t},mug__00,{t},{t / 30:.4f},{t},{t + 1},{t + 2}" for t in range(5)]
        (plots / name).write_text("\n".join(rows) + "\n")
    return metrics, root / "sequences.csv", plots


def _section(text: str, title: str) -> str:
    return text.split(f"## {title}")[1].split("\n## ")[0]


def test_summary_tables_simulation_and_figures(tmp_path):
    metrics, table, plots = _metrics_dir(tmp_path, methods=("baseline", "refine"))
    out = write_summary(metrics, table, plots, tmp_path / "summary.md", tmp_path / "figures")
    text = out.read_text()
    assert "Hand: **shadow**. Sequences: 2 (0 failed)" in text
    grasp = _section(text, "Grasp quality")
    # the paper's SSR beside the SSR by its protocol, not beside the headline
    assert "| DexFlow + refinement | 20.00 | 30.00 |" in grasp
    assert "| *paper: DexFlow* |  | 40.32 |" in grasp
    assert "0.41" not in grasp.split("Paper rows")[0]  # FVR: the paper defines none
    sim = _section(text, "Simulation").splitlines()
    refine = next(r for r in sim if r.startswith("| DexFlow + refinement"))
    assert refine.split("|")[1:-1] == [" DexFlow + refinement ", " 10.00 ", " 15.00 ", " 0.00 ",
                                       " 101 ", " 2.50 ", " 50 ", " 0.62 "]  # fmt: skip
    baseline = next(r for r in sim if r.startswith("| position baseline"))
    assert baseline.split("|")[7:9] == [" — ", " 0.62 "]  # None: an engine that holds it
    assert next(r for r in sim if r.startswith("| DexFlow retargeting")).count("—") == 7
    # every column, the hidden ones included, at full precision in the CSV the section links
    assert "[summary_simulation.csv](summary_simulation.csv)" in _section(text, "Simulation")
    with open(tmp_path / "summary_simulation.csv", newline="") as f:
        rows = {r["method"]: r for r in csv.DictReader(f)}
    assert [float(v) for k, v in rows["DexFlow + refinement"].items() if k != "method"] == (
        pytest.approx([10.0, 15.0, 0.0, 101, 2.5, 50.0, 0.625, 100 * 91 / 101, 25.0, 4.5, 0.875])
    )  # the two tests agree on 3 + 88 of 101 frames
    assert rows["position baseline (DexRetarget-style)"]["lost while the fingers closed %"] == ""
    assert set(rows["DexFlow retargeting"].values()) == {"DexFlow retargeting", ""}
    objects = _section(text, "Per object")
    assert objects.index("003_cracker_box") < objects.index("025_mug")
    for name in ("summary_methods.png", "summary_objects_pd.png", "summary_timeline.png"):
        assert f"(figures/{name})" in text
        assert (tmp_path / "figures" / name).stat().st_size > 5000


@pytest.mark.parametrize(
    ("data_name", "ground_truth", "demo"),
    [("demo", True, True), ("dexycb", False, False), (None, True, True), (None, False, False)],
)
def test_summary_text_says_which_data_it_is(tmp_path, data_name, ground_truth, demo):
    metrics, table, plots = _metrics_dir(tmp_path, methods=("baseline", "refine"))
    overall = json.loads((metrics / "metrics.json").read_text())
    overall = {k: v for k, v in overall.items() if not k.startswith("contact.precision")}
    if ground_truth:  # only the generated demo has contact ground truth
        overall["contact.precision"] = 0.9
    (metrics / "metrics.json").write_text(json.dumps(overall))
    text = write_summary(
        metrics, table, plots, tmp_path / "summary.md", tmp_path / "figures", data_name=data_name
    ).read_text()
    assert ("grasps are synthetic" in text) == demo
    assert f"Data: **{data_name or ('demo' if demo else 'your sequences')}**" in text
    if data_name == "dexycb":
        assert "This run's data is `dexycb`" in text


def _exp(name, value, ssr=None, error=None, source="dvc"):
    metrics = {} if ssr is None else {"refine.ssr": ssr, "refine.pd_mm": 1.0 / (1 + value)}
    return Experiment(name, source, {"contact.dis_min_m": value, "seed": 0}, metrics, error)


def test_ablation_report_with_failed_and_partial_experiments(tmp_path):
    experiments = [
        _exp("a", 0.008, ssr=10.0),
        _exp("b", 0.010, ssr=30.0),
        _exp("c", 0.012, ssr=20.0),
        _exp("broken", 0.014, error="stage refine failed"),
        _exp("empty", 0.016),  # ran, but wrote no metrics
    ]
    experiments[2].metrics.pop("refine.pd_mm")  # partial: one metric missing
    out = write_ablation(experiments, tmp_path / "ablation.md", tmp_path / "figures")
    text = out.read_text()
    section = text.split("## `contact.dis_min_m`")[1].split("##")[0]
    rows = [line for line in section.splitlines() if line.startswith("| 0.0")]
    assert [r.split("|")[1].strip() for r in rows] == ["0.008", "0.01", "0.012"]
    assert "**30.000**" in rows[1]  # the best SSR is bold
    assert "—" in rows[2]  # the missing metric is shown as missing, not dropped
    assert "failed: stage refine failed" in text and "failed: no metrics" in text
    assert (tmp_path / "figures" / "ablation_contact_dis_min_m.png").stat().st_size > 5000


def _run_of(name, hand, dis_min, ssr):
    params = {"hand.name": hand, "hand.scale": {"shadow": 1.11, "allegro": 1.67}[hand],
              "contact.dis_min_m": dis_min, "seed": 0}  # fmt: skip
    return Experiment(name, "dvc", params, {"refine.ssr": ssr})


def test_ablation_groups_covarying_keys_and_holds_the_other_factors(tmp_path):
    experiments = [
        _run_of("s8", "shadow", 0.008, 10.0),
        _run_of("s10", "shadow", 0.010, 20.0),
        _run_of("s12", "shadow", 0.012, 30.0),
        _run_of("a10", "allegro", 0.010, 90.0),
    ]
    text = write_ablation(experiments, tmp_path / "ablation.md", tmp_path / "figures").read_text()
    sections = [line for line in text.splitlines() if line.startswith("## `")]
    assert sections == ["## `contact.dis_min_m`", "## `hand.name`"]  # hand.scale goes with hand
    hand = text.split("## `hand.name`")[1].split("\n## ")[0]
    assert "Changes together with `hand.scale`" in hand
    assert "held at `contact.dis_min_m` = 0.01" in hand
    rows = {
        r.split("|")[1].strip(): r
        for r in hand.splitlines()
        if r.startswith("| ") and "runs" not in r
    }
    assert sorted(rows) == ["allegro", "shadow"]
    assert "20.000" in rows["shadow"] and "**90.000**" in rows["allegro"]  # shadow at 0.01 only
    dis = text.split("## `contact.dis_min_m`")[1].split("\n## ")[0]
    assert "held at `hand.name` = shadow" in dis
    rows = [r for r in dis.splitlines() if r.startswith("| 0.0")]
    assert [r.split("|")[2].strip() for r in rows] == [
        "1",
        "1",
        "1",
    ]  # the allegro run is not mixed in
    assert "**30.000**" in rows[2]
    assert "| a10 | dvc | ok | contact.dis_min_m=0.01, hand.name=allegro | 90.000 |" in text


def test_collect_dvc_and_multirun(tmp_path):
    show = [
        {
            "rev": "workspace", "name": None,
            "data": {"params": {"params.yaml": {"data": {"contact": {"dis_min_m": 0.01}}}},
                     "metrics": {"reports/metrics/metrics.json": {"data": {"refine.ssr": 5.0}}}},
        },
        {
            "rev": "abc", "name": "main",
            "data": {"params": {"params.yaml": {"data": {"contact": {"dis_min_m": 0.01}}}},
                     "metrics": {}},
            "experiments": [
                {"revs": [{"rev": "e1", "name": "exp-one", "data": {
                    "params": {"params.yaml": {"data": {"contact": {"dis_min_m": 0.008}}}},
                    "metrics": {"reports/metrics/metrics.json": {"data": {"refine.ssr": 7.0}},
                                "reports/metrics/contact.json": {"data": {"f": {"g": 1}}}}}}]},
                {"revs": [{"rev": "e2", "name": "exp-bad", "error": {"msg": "failed"},
                           "data": {"params": {}, "metrics": {}}}]},
                {"executor": {"state": "running"}, "name": "exp-running",
                 "revs": [{"rev": "e3", "name": "exp-running", "data": {
                     "params": {"params.yaml": {"data": {"contact": {"dis_min_m": 0.012}}}},
                     "metrics": {"reports/metrics/metrics.json": {"data": {"refine.ssr": 5.0}}}}}]},
            ],
        },
    ]  # fmt: skip
    found = {e.name: e for e in collect_dvc(show)}
    assert found["exp-one"].params["contact.dis_min_m"] == 0.008
    assert found["exp-one"].metrics == {"refine.ssr": 7.0, "contact.f.g": 1.0}
    assert found["exp-bad"].error == "failed"
    assert found["exp-running"].error.startswith("running, not finished")  # baseline's metrics
    for i, value in enumerate((0.008, 0.012)):
        job = tmp_path / "multirun" / str(i)
        (job / "reports" / "metrics").mkdir(parents=True)
        (job / "params.yaml").write_text(f"contact:\n  dis_min_m: {value}\n")
        (job / "reports" / "metrics" / "metrics.json").write_text(json.dumps({"refine.ssr": i}))
        status = (
            {"status": "ok"} if i == 0 else {"status": "failed", "stage": "refine", "error": "x"}
        )
        (job / "sweep_status.json").write_text(json.dumps(status))
    runs = collect_multirun(tmp_path / "multirun")
    assert [r.params["contact.dis_min_m"] for r in runs] == [0.008, 0.012]
    assert runs[0].error is None and runs[1].error == "stage refine: x"


def test_aggregate_velocity_kl_pools_the_sequences_with_the_configured_bins():
    """metrics.json's velocity_kl: the speeds of all sequences pooled, ``metrics.kl_bins`` bins
    (it once ignored kl_bins and used the default 30)."""
    from dexflow.io.artifacts import MetricFrames
    from dexflow.measures import velocity_kl
    from dexflow.stages.metrics import METHODS, _aggregate

    rng = np.random.default_rng(0)
    ok = {}
    for name in ("a", "b"):
        speeds = {m: {"tip_speed_human": rng.gamma(2.0, 0.1, 200),
                      "tip_speed_robot": rng.gamma(2.5, 0.1, 200)} for m in METHODS}  # fmt: skip
        frames = MetricFrames(np.zeros(0), np.zeros((0, 5), bool), speeds)
        contact = {"flicker_raw": 0.0, "flicker_final": 0.0}
        ok[name] = {"methods": {m: {} for m in METHODS}, "contact": contact, "per_frame": frames}
    human = np.concatenate([ok[n]["per_frame"].methods["refine"]["tip_speed_human"] for n in ok])
    robot = np.concatenate([ok[n]["per_frame"].methods["refine"]["tip_speed_robot"] for n in ok])
    for bins in (4, 30, 80):
        pooled = _aggregate(ok, kl_bins=bins)["refine.velocity_kl"]
        assert pooled == pytest.approx(velocity_kl(human, robot, bins=bins), rel=1e-12)
    assert _aggregate(ok, 4)["refine.velocity_kl"] != _aggregate(ok, 80)["refine.velocity_kl"]


def test_contact_precision_recall_pool_counts_over_sequences():
    """One definition: counts of every sequence summed, then the rates (not a mean of rates)."""
    from dexflow.measures import contact_counts, precision_recall

    truth = np.array([[1, 1], [1, 0], [0, 0]], dtype=bool)
    a = contact_counts(np.array([[1, 0], [1, 1], [0, 0]], dtype=bool), truth)
    assert a == {"tp": 2, "fp": 1, "fn": 1}
    b = contact_counts(np.ones((10, 2), dtype=bool), np.ones((10, 2), dtype=bool))
    pooled = precision_recall(*(a[k] + b[k] for k in ("tp", "fp", "fn")))
    assert pooled["precision"] == pytest.approx(22 / 23) and pooled["recall"] == pytest.approx(
        22 / 23
    )
    mean_of_rates = (precision_recall(**a)["precision"] + 1.0) / 2
    assert pooled["precision"] != pytest.approx(mean_of_rates)


def test_summary_shows_each_engine_flips_and_their_agreement(tmp_path):
    """Two engines: the section title names both, a row per method and engine with its SSRs and
    flipped frames, and the per-frame agreement; one engine without perturbations: no section."""
    metrics, table, plots = _metrics_dir(tmp_path, methods=("baseline", "refine"))
    sim = json.loads((metrics / "simulate_refine.json").read_text())
    sim |= {"engines": "mujoco,pybullet", "perturbations": 2, "ssr_paper_mujoco": 12.5,
            "ssr_bench_mujoco": 12.5, "flipped_mujoco": 0.05, "ssr_paper_pybullet": 25.0,
            "ssr_bench_pybullet": 20.0, "flipped_pybullet": 0.1, "agree_hold": 3,
            "agree_drop": 90, "disagree": 7}  # fmt: skip
    (metrics / "simulate_refine.json").write_text(json.dumps(sim))
    text = write_summary(metrics, table, plots, tmp_path / "s.md", tmp_path / "f").read_text()
    assert "## Simulation (mujoco and pybullet (SSR: held in both)" in text
    rows = _section(text, "Simulation").splitlines()
    assert "| DexFlow + refinement | mujoco | 12.50 | 12.50 | 5.0 |" in rows
    assert "| DexFlow + refinement | pybullet | 25.00 | 20.00 | 10.0 |" in rows
    assert "| DexFlow + refinement | 100 | 3 | 90 | 7 |" in rows
    assert "each of 2 perturbed trials" in text

    metrics, table, plots = _metrics_dir(tmp_path / "one", methods=("refine",))
    text = write_summary(metrics, table, plots, tmp_path / "o.md", tmp_path / "g").read_text()
    assert "Engines and robustness" not in text and "## Simulation (pybullet:" in text


def test_summary_reports_contact_flicker_the_papers_way(tmp_path):
    """The paper's 68 % sits beside the baseline-vs-DexFlow reduction, not beside what the
    inference alone removes; the stage's note on the inference is printed under the table."""
    metrics, table, plots = _metrics_dir(tmp_path, methods=("baseline", "refine"))
    contact = {"flicker_baseline_threshold": 0.92, "flicker_dexflow": 0.62,
               "flicker_reduction_vs_baseline": 0.331, "changes_removed_vs_threshold": 0.29,
               "changes_removed_by_inference": 0.013, "inference_note": "The inference acts."}  # fmt: skip
    (metrics / "contact.json").write_text(json.dumps(contact))
    text = write_summary(metrics, table, plots, tmp_path / "s.md", tmp_path / "f").read_text()
    rows = _section(text, "Contact detection").splitlines()
    assert "| removed, DexFlow vs the baseline (the paper's comparison) | 33 % | 68 % |" in rows
    assert "| removed by the inference after the dual threshold (same trajectory) | 1 % | |" in rows
    assert "| single threshold on the baseline retargeting | 0.92 | |" in rows
    assert "- The inference acts." in _section(text, "Definitions").splitlines()  # moved down
