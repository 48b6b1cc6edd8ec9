"""Provenance (dexflow.pipeline.provenance): the facts of the commit and the machine, the record a stage
run leaves in reports/timing, and tracing a stage's metrics back to the machine that made them."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from dexflow.config import load_params
from dexflow.io.layout import Layout
from dexflow.pipeline import provenance
from dexflow.pipeline.runner import StageSpec, run_stage

ROOT = Path(__file__).resolve().parents[1]


def test_the_machine_is_described_by_the_facts_that_can_change_a_result():
    facts = provenance.machine()
    assert set(facts) >= {"cpu", "cores", "os", "python", "torch", "mujoco", "pybullet", "numpy"}
    assert facts["torch"] not in ("", provenance.UNKNOWN)  # installed: this test imports it
    mid = provenance.machine_id()
    assert re.fullmatch(r"[0-9a-f]{12}", mid) and mid == provenance.machine_id(facts)
    # another library version or CPU is another machine; another kernel release is not
    assert provenance.machine_id({**facts, "torch": "0.0.1"}) != mid
    assert provenance.machine_id({**facts, "cpu": "Other CPU"}) != mid
    assert provenance.machine_id({**facts, "os": "Linux 0.0.0-other x86_64"}) == mid
    text = provenance.describe_machine(facts)
    assert f"torch {facts['torch']}" in text and f"{facts['cores']} cores" in text


def test_without_git_the_commit_reads_unknown(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))  # no git on the path
    assert provenance.git_commit() == provenance.UNKNOWN
    assert provenance.git_dirty() is None
    block = provenance.markdown(provenance.current(), "demo, 2 sequences, 40 frames")
    assert block[0] == "- commit: unknown (uncommitted changes: unknown)"
    assert block[2] == "- data: demo, 2 sequences, 40 frames"


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_commit_and_uncommitted_changes_of_a_checkout(tmp_path):
    def git(*args):
        return subprocess.run(
            ["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
            cwd=tmp_path, capture_output=True, text=True, check=True,
        ).stdout.strip()  # fmt: skip

    git("init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "summary.md").write_text("old\n")
    (tmp_path / "dvc.lock").write_text("old\n")
    git("add", "-A")
    git("commit", "-qm", "init")
    assert provenance.git_commit(tmp_path) == git("rev-parse", "HEAD")
    assert provenance.git_dirty(tmp_path) is False
    # the pipeline rewriting its own outputs is no uncommitted change
    (tmp_path / "reports" / "summary.md").write_text("new\n")
    (tmp_path / "dvc.lock").write_text("new\n")
    assert provenance.git_dirty(tmp_path) is False
    (tmp_path / "code.py").write_text("x = 2\n")
    assert provenance.git_dirty(tmp_path) is True
    git("checkout", "code.py")
    (tmp_path / "new.py").write_text("y = 1\n")  # a new file changes the code too
    assert provenance.git_dirty(tmp_path) is True


def test_a_stage_record_remembers_which_machine_made_which_metrics():
    data = {"name": "demo", "sequences": 2, "frames": 40}
    record = provenance.stage_record(None, {"frames_per_second": 5.0}, data, "d0")
    assert record["frames_per_second"] == 5.0 and record["metrics_digest"] == "d0"
    assert record["provenance"]["machine_id"] == provenance.machine_id()
    assert record["provenance"]["data"] == data
    for i in range(1, provenance.MADE_KEPT + 10):
        record = provenance.stage_record(record, {}, data, f"d{i}")
    assert len(record["made"]) == provenance.MADE_KEPT
    assert "d0" not in record["made"] and f"d{provenance.MADE_KEPT + 9}" in record["made"]
    kept = next(iter(record["made"]))
    record = provenance.stage_record(record, {}, data, kept)  # made again: the newest entry
    assert list(record["made"])[-1] == kept


def test_made_by_traces_metrics_to_their_record_only_when_the_digest_matches():
    metrics = {"ssr": 25.0, "num_sequences": 24, "pd_mm": None}
    record = provenance.stage_record(None, {}, {}, provenance.metrics_digest(metrics))
    here = provenance.made_by(metrics, record)
    assert here["machine_id"] == provenance.machine_id()
    assert provenance.made_by(json.loads(json.dumps(metrics)), record) == here  # as parsed
    assert provenance.made_by({**metrics, "ssr": 20.8}, record) is None  # made elsewhere
    assert provenance.made_by(metrics, None) is None  # no record at all
    assert provenance.made_by(None, record)["machine_id"] == here["machine_id"]  # no metrics
    other = {**record, "made": {provenance.metrics_digest(metrics): {"machine_id": "0ther"}}}
    stages = {"refine": provenance.made_by(metrics, other), "contact": here}
    assert provenance.machine_of(stages) is None  # two machines
    assert provenance.machine_of({"contact": here}) == here["machine_id"]
    assert provenance.machine_of({"contact": here, "refine": None}) is None


def _toy_stage(timing: bool) -> StageSpec:
    def run(params, layout):
        summary = {"num_input_sequences": 3, "num_sequences": 3, "num_frames": 90, "value": 1.5}
        return {**summary, "timing": {"frames_per_second": 9.0}} if timing else summary

    return StageSpec("toy", run, None if timing else (), lambda s: "done")


def test_every_stage_run_records_where_it_ran_and_what_it_wrote(tmp_path):
    params = load_params(ROOT / "params.yaml")
    layout = Layout.of(params.data.root, root=tmp_path)
    run_stage(_toy_stage(timing=True), params, layout)
    record = json.loads(layout.timing("toy").read_text())
    assert record["frames_per_second"] == 9.0
    prov = record["provenance"]
    assert prov["machine_id"] == provenance.machine_id()
    assert prov["commit"] == provenance.git_commit()
    assert prov["data"] == {"name": params.data.name, "root": params.data.root,
                            "sequences": 3, "frames": 90}  # fmt: skip
    metrics = json.loads(layout.stage_metrics("toy").read_text())
    assert record["metrics_digest"] == provenance.metrics_digest(metrics)
    assert "provenance" not in metrics  # the DVC metrics stay machine-free
    made = provenance.stages_of(layout.stage_metrics_dir, layout.reports / "timing")
    assert made["toy"]["machine_id"] == provenance.machine_id()

    # a stage with no metrics and no speeds still records where it ran
    layout = Layout.of(params.data.root, root=tmp_path / "other")
    run_stage(_toy_stage(timing=False), params, layout)
    record = json.loads(layout.timing("toy").read_text())
    assert record["metrics_digest"] is None
    assert record["provenance"]["machine_id"] == provenance.machine_id()
