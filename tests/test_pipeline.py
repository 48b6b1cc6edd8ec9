"""The DVC pipeline end to end on a copy of the project with a small demo (slow)."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

from tests import quick_pipeline

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("reproduced_demo")]  # one build of it


@pytest.fixture(scope="module")
def project(reproduced_demo, tmp_path_factory) -> Path:
    """A copy of the small demo project after its first `dvc repro` (tests/conftest.py)."""
    return quick_pipeline.copy_reproduced(
        reproduced_demo, tmp_path_factory.mktemp("pipeline") / "p"
    )


def _run(cmd: list[str], cwd: Path) -> str:
    return quick_pipeline.run(cmd, cwd, cwd)


def test_repro_then_noop_then_only_the_changed_stage(project, reproduced_demo):
    out = reproduced_demo[1]  # the first `dvc repro`
    assert "Running stage 'demo@demo'" in out and "Running stage 'scale_align'" in out
    summary = json.loads((project / "data/scale_align/summary.json").read_text())
    assert summary["num_ok"] == summary["num_sequences"] == 2
    assert json.loads((project / "reports/metrics/demo.json").read_text())["sequences"] == 2
    stages = ("retarget/dexflow", "retarget/position", "contact", "refine", "simulate/baseline",
              "simulate/retarget", "simulate/refine")  # fmt: skip
    for stage in stages:
        done = json.loads((project / "data" / stage / "summary.json").read_text())
        assert done["num_ok"] == done["num_sequences"] == 2, stage

    _assert_one_number_per_name(project / "reports" / "metrics")

    # Only stage hand runs again (always_changed: it copies the hand model, which DVC cannot
    # see where it lies); its copy is unchanged, so nothing below it reruns.
    again = _run(["dvc", "repro"], project)
    assert _ran(again) == ["hand"]

    # An edit to another hand's yaml is no dep of this (shadow) pipeline: nothing reruns.
    allegro = project / "conf" / "hand" / "allegro.yaml"
    allegro.write_text(allegro.read_text() + "\n# edited\n")
    assert _ran(_run(["dvc", "repro"], project)) == ["hand"]

    # A parameter of one stage reruns that stage and those that read its outputs, no other.
    _run([sys.executable, "-m", "dexflow.tools.cli", "params", "metrics.pd_violation_m=0.004"],
         project)  # fmt: skip
    assert _ran(_run(["dvc", "repro"], project)) == ["hand", "metrics", "report"]


def _ran(output: str) -> list[str]:
    """The stages ``dvc repro`` ran, from its output."""
    return re.findall(r"Running stage '([^']+)'", output)


def _assert_one_number_per_name(metrics: Path) -> None:
    """Where two metric files report a number under one name, it is the same number: each
    metric has one definition (metrics.json holds ``<method>.<name>`` and ``contact.<name>``)."""
    m = json.loads((metrics / "metrics.json").read_text())
    pairs = {
        "retarget_dexflow.json": {"keypoint_error_mm": "retarget.keypoint_error_mm",
                                  "rms_acc": "retarget.rms_acc"},
        "retarget_position.json": {"keypoint_error_mm": "baseline.keypoint_error_mm",
                                   "rms_acc": "baseline.rms_acc"},
        "contact.json": {"flicker_raw": "contact.flicker_raw",
                         "flicker_final": "contact.flicker_final"},
        "refine.json": {"pd_before_mm": "retarget.pd_mm", "pd_after_mm": "refine.pd_mm",
                        "cd_before_mm": "retarget.cd_mm", "cd_after_mm": "refine.cd_mm",
                        "rms_acc_before": "retarget.rms_acc", "rms_acc_after": "refine.rms_acc"},
    }  # fmt: skip
    for name, keys in pairs.items():
        stage = json.loads((metrics / name).read_text())
        for key, aggregate in keys.items():
            assert stage[key] == pytest.approx(m[aggregate], rel=1e-9, nan_ok=True), (name, key)
    contact = json.loads((metrics / "contact.json").read_text())
    if "contact.precision" in m:
        assert contact["final_vs_truth"]["precision"] == pytest.approx(m["contact.precision"])
        assert contact["final_vs_truth"]["recall"] == pytest.approx(m["contact.recall"])
    for name in ("refine.json", "retarget_dexflow.json", "metrics.json"):
        assert "velocity_kl" not in json.loads((metrics / name).read_text())  # only per method
    assert "spd_before_mm" not in json.loads((metrics / "refine.json").read_text())


def test_dvc_exp_run_composes_hydra_overrides(project):
    _run([sys.executable, "-m", "dexflow.tools.cli", "params"], project)  # conf/ as committed
    _run(["git", "add", "-A"], project)
    _run(["git", "commit", "-qm", "after repro", "--allow-empty"], project)
    _run(["dvc", "exp", "run", "-S", "metrics.pd_violation_m=0.0042"], project)
    params = (project / "params.yaml").read_text()
    assert "pd_violation_m: 0.0042" in params
    shown = json.loads(_run(["dvc", "exp", "show", "--json"], project))
    assert "0.0042" in json.dumps(shown)


def test_track_on_adds_a_fourth_method_the_same_on_any_worker_count(reproduced_demo, tmp_path):
    """`dexflow params track=on` adds stage track@refine and the track method to simulate,
    replay and metrics: `dvc repro` runs just those (and the report); the tracked trajectories
    are byte for byte the same from two worker processes as from one."""
    project = quick_pipeline.copy_reproduced(reproduced_demo, tmp_path / "p")
    cli = [sys.executable, "-m", "dexflow.tools.cli", "params"]
    quick = ["track=on", "track.samples=3", "track.iterations=1", "track.horizon_frames=3"]
    _run([*cli, *quick], project)
    ran = _ran(_run(["dvc", "repro"], project))
    assert sorted(ran) == sorted(
        ["hand", "track@refine", "simulate@track", "replay@track", "metrics", "report"]
    )
    track = json.loads((project / "data/track/summary.json").read_text())
    assert track["num_ok"] == track["num_sequences"] == 2
    assert track["num_tracked"] + sum(not e["tracked"] for e in track["sequences"].values()) == 2
    for entry in track["sequences"].values():
        assert entry["feasible"] == (entry["tracked"] and entry["success"])
        assert not entry["tracked"] or 0 <= entry["grip_drift_m"] < 0.05
    metrics = json.loads((project / "reports/metrics/metrics.json").read_text())
    assert {"track.keypoint_error_mm", "track.pd_mm", "refine.pd_mm"} <= set(metrics)
    # track's hand holds the simulated object: its own-object PD differs from the recorded's;
    # refine moves nothing, so its two are one number
    assert metrics["refine.pd_own_object_mm"] == metrics["refine.pd_mm"]
    assert metrics["track.pd_own_object_mm"] != metrics["track.pd_mm"]
    replayed = json.loads((project / "reports/metrics/replay_track.json").read_text())
    assert replayed["num_scored"] == track["num_tracked"]
    assert json.loads((project / "reports/metrics/track_refine.json").read_text())[
        "feasible_rate"
    ] == pytest.approx(track["feasible_rate"], nan_ok=True)

    sequences = project / "data/track/sequences"
    one = {p.name: p.read_bytes() for p in sorted(sequences.glob("*.npz"))}
    _run([*cli, *quick, "run=local", "run.n_jobs=2"], project)
    _run([sys.executable, "stages/track.py", "refine"], project)
    two = {p.name: p.read_bytes() for p in sorted(sequences.glob("*.npz"))}
    assert len(one) == 2 and one == two
