"""Contact flicker: the paper's comparison (baseline + single threshold vs DexFlow) and what the
frame-to-frame inference can change, on hand-made states and on a stage run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from dexflow.hands import load_hand
from dexflow.hands.spec import load_hand_spec
from dexflow.io.artifacts import ObjectAssets
from dexflow.io.layout import Layout
from dexflow.io.sequence import load_sequence, save_sequence
from dexflow.measures import flicker_reduction, hand_object_depths, state_flicker
from dexflow.params import ContactParams, PipelineParams, RunParams
from dexflow.stages.contact import (
    band_jumps,
    contact_summary,
    hysteresis,
    infer_frames,
    inference_reach,
    one_frame_runs,
    run_contact,
)
from dexflow.stages.hand import run_hand
from dexflow.stages.scale_align import run_scale_align

from .conftest import make_sequence

P = ContactParams()


def _random_states(seed: int, frames: int = 400, fingers: int = 4) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.random((frames, fingers)) < rng.uniform(0.2, 0.8, fingers)


# --- what the inference can change ------------------------------------------------------------


@pytest.mark.parametrize("seed", range(3))
def test_the_inference_changes_exactly_the_one_frame_runs(seed):
    states = _random_states(seed)
    changed = infer_frames(states, 30.0, P) != states
    assert (changed == one_frame_runs(states)).all() and changed.any()
    # finger by finger the same
    for f in range(states.shape[1]):
        assert (one_frame_runs(states[:, f : f + 1])[:, 0] == changed[:, f]).all()


@pytest.mark.parametrize("seed", range(3))
def test_hysteresis_leaves_one_frame_runs_only_where_the_distance_crosses_the_band(seed):
    rng = np.random.default_rng(seed)
    band = P.dis_max_m - P.dis_min_m
    # big steps: the distance crosses the whole band now and then
    wild = 0.012 + np.cumsum(rng.normal(0, 0.006, (600, 4)), axis=0) * 0.2
    wild += rng.normal(0, 0.005, wild.shape)
    runs = one_frame_runs(hysteresis(wild, P.dis_min_m, P.dis_max_m)).sum(axis=0)
    jumps = band_jumps(wild, P.dis_min_m, P.dis_max_m).sum(axis=0)
    assert (runs <= jumps).all() and runs.sum() > 0
    # steps smaller than the band: a single threshold flickers, hysteresis has no one-frame run
    calm = 0.010 + np.cumsum(rng.uniform(-0.4, 0.4, (600, 4)) * band, axis=0) * 0.05
    calm += rng.uniform(-0.4, 0.4, calm.shape) * band
    assert (np.abs(np.diff(calm, axis=0)) < band).all()
    assert band_jumps(calm, P.dis_min_m, P.dis_max_m).sum() == 0
    assert one_frame_runs(hysteresis(calm, P.dis_min_m, P.dis_max_m)).sum() == 0
    assert one_frame_runs(calm < P.dis_min_m).sum() > 0


def test_band_jumps_count_crossings_of_the_whole_band_each_way():
    d = np.array([20, 5, 20, 12, 5, 12, 20, 9])[:, None] / 1000
    # 20 -> 5, 5 -> 20 and 20 -> 9 cross the band; 12 -> 5 and 12 -> 20 start inside it
    assert np.flatnonzero(band_jumps(d, P.dis_min_m, P.dis_max_m)).tolist() == [0, 1, 6]
    state = hysteresis(d, P.dis_min_m, P.dis_max_m)
    assert state[:, 0].astype(int).tolist() == [0, 1, 0, 0, 1, 1, 0, 1]
    assert np.flatnonzero(one_frame_runs(state)).tolist() == [1, 6]  # a contact and a gap


@pytest.mark.parametrize(
    ("fps", "tau_c", "smoothing", "only_runs"),
    [
        (30.0, 0.7, True, True),  # the paper's constants
        (0.5, 0.7, True, False),  # α v_f Δt = 0.96 > τ_c: contact between two frames out
        (30.0, 1.2, True, False),  # τ_c > 1 + α v_f Δt: contact removed between two contacts
        (30.0, 0.7, False, False),
    ],
)
def test_the_note_says_what_the_inference_does_at_these_constants(fps, tau_c, smoothing, only_runs):
    params = ContactParams(tau_c=tau_c, smoothing=smoothing)
    note = inference_reach(params, fps)
    states = _random_states(7)
    if smoothing:
        changed = infer_frames(states, fps, params) != states
        assert (changed == one_frame_runs(states)).all() == only_runs
    assert ("changes only one-frame runs" in note) == only_runs
    assert ("is off" in note) == (not smoothing)
    if only_runs:
        assert "α v_f Δt = 0.016 at 30 fps" in note
        assert "5.8 mm" in note and "0.17 m/s" in note and "fps² = 5.2 m/s²" in note
        assert "a_tol" not in inference_reach(ContactParams(guard=False), fps)
        assert "a_tol" not in inference_reach(ContactParams(accel_tolerance_mps2=6.0), fps)
        wide = inference_reach(ContactParams(dis_max_m=0.02), fps)
        assert "10.0 mm" in wide and "0.30 m/s" in wide


def test_flicker_reduction():
    assert flicker_reduction(0.8, 0.2) == pytest.approx(0.75)
    assert flicker_reduction(0.5, 1.0) == pytest.approx(-1.0)  # more flicker after
    assert math.isnan(flicker_reduction(0.0, 0.0))
    assert math.isnan(flicker_reduction(float("nan"), 0.1))
    states = np.zeros((31, 2), dtype=bool)
    states[10:20, 0] = True
    calmer = states.copy()
    states[25, 1] = True  # two more changes: 4 in all, 2 left
    assert flicker_reduction(state_flicker(states, 30), state_flicker(calmer, 30)) == 0.5


# --- the summary ------------------------------------------------------------------------------


def _entry(frames=31, **stats):
    entry = {
        "status": "ok",
        "frames": frames,
        "fps": 30.0,
        "fingers": 4,
        "changes_threshold": 6,
        "changes_raw": 4,
        "changes_final": 2,
        "flicker_threshold": 0.6,
        "flicker_raw": 0.4,
        "flicker_final": 0.2,
        "one_frame_runs_threshold": 2,
        "one_frame_runs_raw": 0,
        "one_frame_gaps_raw": 0,
        "band_jumps": 1,
        "inference_changed": 0,
        "inference_removed": 0,
        "inference_filled": 0,
        "inference_first_change": None,
    }
    return entry | stats


def test_the_summary_compares_sequences_that_have_a_baseline():
    change = {"finger": "index", "frame": 7, "frames": [5, 9], "raw": "00100", "final": "00000"}
    entries = {
        "c": _entry(
            flicker_final=0.4,
            one_frame_runs_raw=2,
            one_frame_gaps_raw=1,
            inference_changed=2,
            inference_removed=1,
            inference_filled=1,
            inference_first_change=change,
        ),
        "b": _entry(
            flicker_final=0.1,
            flicker_baseline_threshold=0.5,
            changes_baseline_threshold=15,
            one_frame_runs_raw=1,
            inference_changed=1,
            inference_removed=1,
            inference_first_change=change | {"finger": "thumb"},
        ),
        "a": _entry(
            flicker_final=0.3, flicker_baseline_threshold=1.5, changes_baseline_threshold=45
        ),
        "z": {"status": "failed", "error": "bad"},
    }
    summary = contact_summary(entries, P)
    assert summary["num_compared"] == 2
    assert summary["flicker_baseline_threshold"] == pytest.approx(1.0)
    assert summary["flicker_dexflow"] == pytest.approx(0.2)  # a and b only
    assert summary["flicker_reduction_vs_baseline"] == pytest.approx(0.8)
    assert summary["flicker_final"] == pytest.approx(0.8 / 3)  # every sequence
    assert summary["changes_baseline_threshold"] == 60
    assert summary["changes_removed_by_inference"] == pytest.approx(0.5)
    assert summary["changes_removed_vs_threshold"] == pytest.approx(2 / 3)
    assert summary["inference_changed"] == 3
    assert summary["inference_removed"] == 2 and summary["inference_filled"] == 1
    assert summary["one_frame_runs_raw"] == 3 and summary["one_frame_gaps_raw"] == 1
    assert summary["inference_changed_share"] == pytest.approx(3 / (3 * 31 * 4))
    assert (
        summary["inference_example"]
        == "b, finger thumb, frames 5-9: hysteresis 00100 -> inference 00000"
    )
    note = summary["inference_note"]
    assert "3 of 372 states" in note and "3 of 360 finger steps" in note
    assert "removed 2 of the 2 one-frame contacts and filled 1 of the 1 one-frame gaps" in note
    assert note.endswith(summary["inference_example"] + ".")
    # no baseline anywhere: no share is defined
    alone = contact_summary({"c": entries["c"]}, P)
    assert alone["num_compared"] == 0 and math.isnan(alone["flicker_reduction_vs_baseline"])


# --- the stage, on a box touched by the index finger ------------------------------------------


def allegro_box_params() -> PipelineParams:
    """The allegro hand with a coarse object grid and a few convex parts, sequentially: a
    small box scene staged in well under a second (also tests/test_report_summary.py)."""
    params = PipelineParams()
    params.hand, _ = load_hand_spec("allegro")
    params.scale_align.sdf_spacing_m = 0.004
    params.scale_align.surface_samples = 256
    params.scale_align.convex.max_hulls = 4
    params.run = RunParams("sequential", 1)
    return params


def _index_above_box(hand, layout: Layout, gap_m: np.ndarray) -> np.ndarray:
    """Per frame a configuration with the index tip ``gap_m`` below the box's bottom face (the
    hand's zero pose, moved by its base translation)."""
    seq = load_sequence(layout.scale_align.sequence("s0"), data_root=layout.scale_align.root)
    mesh = trimesh.load(layout.scale_align.object_of(seq.obj_mesh).mesh)
    bottom = np.array([*mesh.bounds.mean(axis=0)[:2], mesh.bounds[0, 2]])
    bottom_world = seq.obj_pose[:, :3, :3] @ bottom + seq.obj_pose[:, :3, 3]
    tip = hand.link_transforms(hand.zero(), ["link_3.0_tip"])[0, 0, :3, 3].numpy()
    q = hand.zero(len(gap_m)).numpy()
    q[:, :3] = bottom_world - tip - np.outer(gap_m, [0.0, 0.0, 1.0])
    return q


@pytest.fixture(scope="module")
def box_project(tmp_path_factory):
    root = tmp_path_factory.mktemp("flicker")
    (root / "meshes").mkdir()
    trimesh.creation.box(extents=(0.04, 0.04, 0.04)).export(root / "meshes" / "box.obj")
    save_sequence(root / "sequences" / "s0.npz", make_sequence(40), data_root=root)
    layout = Layout.of(root, root=root / "project")
    assert run_scale_align(allegro_box_params(), layout)["num_ok"] == 1
    run_hand(allegro_box_params(), layout)
    return layout


def _save(layout: Layout, method: str, hand, q: np.ndarray) -> None:
    folder = layout.retarget(method)
    folder.sequences_dir.mkdir(parents=True, exist_ok=True)
    np.savez(folder.sequence("s0"), q=q, joint_names=np.array(hand.joint_names))


def test_the_stage_compares_a_flickering_baseline_with_dexflow(box_project):
    """The index finger (about 1.4 mm farther from the box than its tip's gap): the baseline
    hovers across dis_min every frame; DexFlow touches once for a frame (the inference removes
    it), then holds a contact with a one-frame gap (the guard refuses to fill it: the finger
    jumps 46 mm)."""
    layout, hand = box_project, load_hand("allegro")
    hover = np.where(np.arange(40) % 2, 0.004, 0.012)
    hover[:5] = 0.05
    touch = np.full(40, 0.05)
    touch[10] = touch[15:36] = 0.004
    touch[25] = 0.05
    q_base = _index_above_box(hand, layout, hover)
    _save(layout, "dexflow", hand, _index_above_box(hand, layout, touch))
    _save(layout, "position", hand, q_base)
    summary = run_contact(allegro_box_params(), layout)
    assert summary["num_ok"] == summary["num_compared"] == 1
    seq = load_sequence(layout.scale_align.sequence("s0"), data_root=layout.scale_align.root)
    sdf = ObjectAssets(layout.scale_align.object_of(seq.obj_mesh)).sdf()
    _, d_base = hand_object_depths(hand, q_base, seq.obj_pose, sdf)
    expected = state_flicker(d_base < P.dis_min_m, seq.fps)
    assert expected > 5.0  # the baseline's index finger flickers
    assert summary["flicker_baseline_threshold"] == pytest.approx(expected)
    assert summary["flicker_dexflow"] == summary["flicker_final"] < expected
    assert summary["flicker_final"] < summary["flicker_raw"]
    assert summary["flicker_reduction_vs_baseline"] == pytest.approx(
        1 - summary["flicker_final"] / expected
    )
    assert summary["one_frame_runs_raw"] == 2 and summary["one_frame_gaps_raw"] == 1
    assert summary["band_jumps"] >= 2
    assert summary["inference_changed"] == summary["inference_removed"] == 1
    assert summary["inference_filled"] == 0
    assert summary["inference_changed_share"] == pytest.approx(1 / (40 * 4))
    example = "s0, finger index, frames 8-12: hysteresis 00100 -> inference 00000"
    assert summary["inference_example"] == example
    assert summary["inference_note"].endswith(f"e.g. {example}.")
    # without a baseline the DexFlow figures stay and the comparison is undefined
    layout.retarget("position").sequence("s0").unlink()
    alone = run_contact(allegro_box_params(), layout)
    assert alone["num_compared"] == 0 and math.isnan(alone["flicker_reduction_vs_baseline"])
    assert alone["flicker_final"] == summary["flicker_final"]
