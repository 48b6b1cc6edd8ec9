"""The ablation suite: its report from fake experiment directories (complete, failed, queued),
the paired statistics it reads differences with, and resuming finished experiments."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from dexflow.io.layout import Layout
from dexflow.pipeline import provenance
from dexflow.tools import ablation
from dexflow.tools.ablation import (
    DEFAULT,
    compare,
    load_result,
    suite_experiments,
    write_suite_report,
)

OTHER = "0123456789ab"  # the machine id of a machine that is not this one

COLUMNS = ["sequence", "object", "hand", "method", "frames", "keypoint_error_mm",
           "fingertip_error_mm", "velocity_kl", "rms_acc", "pd_mm", "pd_max_mm", "cd_mm",
           "spd_mm", "ssr"]  # fmt: skip


def _record(job: Path, machine: str | None = None) -> None:
    """The ``reports/timing`` record the metrics stage leaves for the ``metrics.json`` the job
    holds: made on this machine, or on ``machine`` (as another machine's run leaves it)."""
    layout = Layout(root=job)
    metrics = json.loads(layout.stage_metrics("metrics").read_text())
    record = provenance.stage_record(None, {}, {}, provenance.metrics_digest(metrics))
    if machine is not None:
        record["provenance"]["machine_id"] = machine
        for entry in record["made"].values():
            entry["machine_id"] = machine
    layout.timing("metrics").parent.mkdir(parents=True, exist_ok=True)
    layout.timing("metrics").write_text(json.dumps(record))


def _job(
    root: Path,
    name: str,
    values: dict[str, dict[str, list[float]]],
    pooled=None,
    machine: str | None = None,
) -> Path:
    """A finished experiment directory: ``values[method][metric]`` per sequence, made on this
    machine (or on ``machine``)."""
    job = root / name
    layout = Layout(root=job)
    layout.metrics_table.parent.mkdir(parents=True)
    rows = []
    for method, metrics in values.items():
        n = len(next(iter(metrics.values())))
        for i in range(n):
            row = {c: "0" for c in COLUMNS}
            row.update(sequence=f"seq{i}", object="box", hand="shadow", method=method, frames="90")
            row.update({m: repr(float(v[i])) for m, v in metrics.items()})
            rows.append(row)
    with layout.metrics_table.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    (layout.reports / "metrics").mkdir(parents=True)
    (layout.reports / "metrics" / "metrics.json").write_text(json.dumps(pooled or {}))
    _record(job, machine)
    (job / "sweep_status.json").write_text(json.dumps({"status": "ok"}))
    return job


def _failed(root: Path, name: str) -> Path:
    job = root / name
    job.mkdir(parents=True)
    status = {"status": "failed", "stage": "refine", "error": "exit status 1: MemoryError"}
    (job / "sweep_status.json").write_text(json.dumps(status))
    return job


def _running(root: Path, name: str) -> Path:
    """An experiment in the middle of its refine stage (or killed there)."""
    from dexflow.tools.sweep import UNFINISHED

    job = root / name
    job.mkdir(parents=True)
    status = {"status": "failed", "stage": "refine", "error": UNFINISHED}
    (job / "sweep_status.json").write_text(json.dumps(status))
    return job


def test_the_paired_interval_is_students_t_over_the_per_sequence_differences(tmp_path):
    base = [1.0, 2.0, 3.0, 4.0]
    moved = [1.5, 2.4, 3.6, 4.5]  # +0.5, +0.4, +0.6, +0.5: a small but consistent shift
    a = load_result(_job(tmp_path, "a", {"refine": {"pd_mm": base}}))
    b = load_result(_job(tmp_path, "b", {"refine": {"pd_mm": moved}}))
    c = compare(a, b, "refine", "pd_mm")
    diff = np.subtract(moved, base)
    assert c.n == 4 and c.default == pytest.approx(2.5) and c.value == pytest.approx(3.0)
    assert c.delta == pytest.approx(0.5)
    # t(0.975, 3) = 3.182: the interval of a mean of 4 paired differences
    assert c.half_width == pytest.approx(3.1824 * diff.std(ddof=1) / 2, rel=1e-3)
    assert c.resolved  # the spread between sequences (1 to 4 mm) does not hide a paired shift
    noisy = load_result(_job(tmp_path, "n", {"refine": {"pd_mm": [2.0, 1.0, 4.5, 3.5]}}))
    assert not compare(a, noisy, "refine", "pd_mm").resolved  # +1, −1, +1.5, −0.5
    assert compare(a, b, "retarget", "pd_mm") is None  # no common sequences for that method


def test_sequences_are_paired_by_name_and_missing_values_are_left_out(tmp_path):
    a = load_result(_job(tmp_path, "a", {"refine": {"cd_mm": [1.0, 2.0, 3.0]}}))
    b = load_result(_job(tmp_path, "b", {"refine": {"cd_mm": [1.0, float("nan")]}}))
    c = compare(a, b, "refine", "cd_mm")
    assert (c.n, c.delta) == (1, 0.0) and math.isnan(c.half_width) and not c.resolved


def test_report_of_complete_failed_and_queued_experiments(tmp_path):
    runs = tmp_path / "multirun"
    rng = np.random.default_rng(0)
    n = 8
    base = {
        m: list(rng.uniform(1, 5, n))
        for m in ("keypoint_error_mm", "fingertip_error_mm", "rms_acc", "velocity_kl", "pd_mm")
    }
    default = {"retarget": base, "refine": base}
    no_temporal = {
        method: {**base, "rms_acc": [v * 4 + 1 for v in base["rms_acc"]]}  # clearly worse
        | {"keypoint_error_mm": list(np.add(base["keypoint_error_mm"], rng.normal(0, 1, n)))}
        for method in ("retarget", "refine")
    }
    pooled = {"contact": {"precision": 0.9}}
    results = {
        DEFAULT: load_result(_job(runs, DEFAULT, default, pooled)),
        "no_temporal": load_result(_job(runs, "no_temporal", no_temporal)),
        "global_search_off": load_result(_failed(runs, "global_search_off")),
        "refine_no_pen": load_result(_running(runs, "refine_no_pen")),
        # every other experiment of the suite: no directory yet (queued)
    }
    results |= {n: load_result(runs / n) for n in suite_experiments("paper") if n not in results}
    out = write_suite_report("paper", results, tmp_path / "ablation.md", "dexflow x", "the demo")
    text = out.read_text()

    temporal = text.split("## What do the temporal terms buy?")[1].split("\n## ")[0]
    rows = [r for r in temporal.splitlines() if r.startswith("| `no_temporal`")]
    assert len(rows) == 2  # one per method
    cells = [c.strip() for c in rows[0].split("|")[1:-1]]
    assert cells[:2] == ["`no_temporal`", "retarget"]
    rms = cells[2 + 2]  # experiment, method, keypoint, fingertip, RMS acc
    assert rms.startswith("**") and "(+" in rms  # resolved: bold, a positive Δ
    assert "RMS acc" in temporal and "worse" in temporal.split("**Findings.**")[1]
    assert "within the spread across sequences" in temporal  # the noisy keypoint error
    assert "unchanged in every sequence: fingertip error, velocity KL." in temporal
    assert len(temporal.splitlines()[2].split("|")) - 2 <= 8  # readable: at most 8 columns

    search = text.split("## What does the global search buy?")[1].split("\n## ")[0]
    assert (
        "`global_search_off` (failed)" in search
        and "`global_search_every_frame` (queued)" in search
    )
    experiments = text.split("## Experiments")[1]
    assert "| `global_search_off` | failed | — | stage refine: exit status 1: MemoryError |" in (
        experiments
    )
    assert f"| `{DEFAULT}` | complete | {n} |" in experiments
    assert "| `allegro` | queued | — | not run yet (rerun the command to run it) |" in experiments
    assert "| `refine_no_pen` | queued | — | stage refine running or interrupted (rerun" in (
        experiments
    )
    assert "Generated by `dexflow x` on the demo." in text

    table = list(csv.DictReader(out.with_suffix(".csv").open()))
    assert {r["experiment"] for r in table} == {"no_temporal"}
    rms_rows = [r for r in table if r["metric"] == "rms_acc" and r["method"] == "retarget"]
    assert rms_rows[0]["resolved"] == "True" and float(rms_rows[0]["delta"]) > 0


def test_a_report_without_a_finished_default_says_so(tmp_path):
    out = write_suite_report("paper", {}, tmp_path / "a.md", "dexflow x", "nothing")
    text = out.read_text()
    assert text.count("No numbers: the default is queued") == len(ablation.SUITES["paper"])
    assert "| `no_temporal` | queued |" in text


def _fake_run_job(ran: list[str], failing: tuple[str, ...] = ()):
    """A stand-in for dexflow.tools.sweep.run_job that records its calls and leaves an experiment
    made on this machine, finished but for those ``failing`` (the pipeline itself is tested in
    test_sweep.py)."""

    def run_job(cfg, root, job_dir, machine=None):
        job_dir = Path(job_dir)
        assert machine == provenance.machine_id()  # it reuses only what this machine made
        ran.append(job_dir.name)
        status = "failed" if job_dir.name in failing else "ok"
        (job_dir / "params.yaml").write_text((job_dir / "params.composed.yaml").read_text())
        layout = Layout(root=job_dir)
        layout.metrics_table.parent.mkdir(parents=True, exist_ok=True)
        layout.metrics_table.write_text(",".join(COLUMNS) + "\n")
        layout.stage_metrics_dir.mkdir(parents=True, exist_ok=True)
        layout.stage_metrics("metrics").write_text("{}")
        _record(job_dir)
        (job_dir / "sweep_status.json").write_text(json.dumps({"status": status}))
        return {"status": status}

    return run_job


def test_run_suite_hands_every_experiment_to_run_job_with_its_base_and_this_machine(
    tmp_path, monkeypatch
):
    """Each run of the suite passes every experiment to run_job, which keeps, reuses or runs
    each stage by its key (tests/test_sweep.py); the default reuses the project's outputs, the
    others the default's, and only this machine's."""
    calls: list[tuple[str, Path]] = []
    ran: list[str] = []
    fake = _fake_run_job(ran, failing=("allegro",))

    def run_job(cfg, root, job_dir, machine=None):
        calls.append((Path(job_dir).name, Path(root)))
        return fake(cfg, root, job_dir, machine)

    monkeypatch.setattr("dexflow.tools.sweep.run_job", run_job)
    root = Path(__file__).resolve().parents[1]
    names = suite_experiments("paper")
    results = ablation.run_suite("paper", root, tmp_path, ["seed=3"])
    assert [name for name, _ in calls] == names
    assert dict(calls)[DEFAULT] == root
    assert all(base == tmp_path / DEFAULT for name, base in calls if name != DEFAULT)
    assert (tmp_path / DEFAULT / "dvc.yaml").resolve() == root / "dvc.yaml"
    assert results["allegro"].status == "failed" and results[DEFAULT].status == "complete"
    assert "seed: 3" in (tmp_path / DEFAULT / "params.yaml").read_text()
    calls.clear()
    results = ablation.run_suite("paper", root, tmp_path, ["seed=5"], run=False)
    assert calls == [] and results["allegro"].status == "failed"


def _two_runs(tmp_path: Path, default_machine: str, experiment_machine: str) -> str:
    """The paper suite's report of a default and `no_temporal`, each made on the machine named
    (``here``: this one; ``none``: no record of where)."""
    runs = tmp_path / "multirun"
    base = {m: {"pd_mm": [1.0, 2.0, 3.0, 4.0]} for m in ("refine", "retarget")}
    moved = {m: {"pd_mm": [1.5, 2.4, 3.6, 4.5]} for m in ("refine", "retarget")}
    for name, values, machine in ((DEFAULT, base, default_machine),
                                  ("no_temporal", moved, experiment_machine)):  # fmt: skip
        job = _job(runs, name, values, machine=None if machine in ("here", "none") else machine)
        if machine == "none":
            Layout(root=job).timing("metrics").unlink()
    results = {n: load_result(runs / n) for n in suite_experiments("paper")}
    out = write_suite_report("paper", results, tmp_path / "ablation.md", "dexflow x", "the demo")
    return out.read_text()


def test_the_suite_report_compares_only_runs_of_the_same_machine(tmp_path):
    here = provenance.machine_id()
    text = _two_runs(tmp_path / "same", "here", "here")
    assert (
        "Same machine: the default and every experiment compared to it ran, every stage, on "
        f"machine {here} (this machine)"
    ) in text
    assert "- data: the demo" in text and f"- machine: {here} (" in text
    temporal = text.split("## What do the temporal terms buy?")[1].split("\n## ")[0]
    assert "| `no_temporal` |" in temporal
    assert f"| `no_temporal` | complete | 4 |  | {here} |" in text

    # the experiment made on another machine: not compared, and the report says why
    text = _two_runs(tmp_path / "other", "here", OTHER)
    temporal = text.split("## What do the temporal terms buy?")[1].split("\n## ")[0]
    assert "| `no_temporal` |" not in temporal
    assert "`no_temporal` (made on another machine, or not recorded where)" in temporal
    assert (
        f"| `no_temporal` | complete | 4 | not compared: made on machine {OTHER}, the default "
        f"on {here}; rerun it here | {OTHER} |"
    ) in text
    table = list(csv.DictReader((tmp_path / "other" / "ablation.csv").open()))
    assert table == []  # no comparison recorded either

    # the default (a committed baseline, say) without a record of its machine: no numbers
    text = _two_runs(tmp_path / "unknown", "none", "here")
    assert "**No comparison: the default's machine is not recorded**" in text
    assert text.count("No numbers: the default's machine is not recorded") == len(
        ablation.SUITES["paper"]
    )


def test_an_experiment_whose_config_is_rejected_fails_alone(tmp_path, monkeypatch):
    ran: list[str] = []

    def fake_run_job(cfg, root, job_dir, machine=None):
        ran.append(Path(job_dir).name)
        (Path(job_dir) / "sweep_status.json").write_text(json.dumps({"status": "ok"}))
        return {"status": "ok"}

    monkeypatch.setattr("dexflow.tools.sweep.run_job", fake_run_job)
    monkeypatch.setitem(
        ablation.SUITES,
        "broken",
        (
            ablation.Question(
                "q", "Q?", ("no_temporal", "no_such_experiment"), ("refine",), ("pd_mm",)
            ),
        ),
    )
    root = Path(__file__).resolve().parents[1]
    results = ablation.run_suite("broken", root, tmp_path)
    assert ran == [DEFAULT, "no_temporal"]
    assert results["no_such_experiment"].status == "failed"
    assert "stage params" in results["no_such_experiment"].error
    assert "no_such_experiment" in results["no_such_experiment"].error


def test_an_unknown_suite_is_named():
    with pytest.raises(KeyError, match="unknown ablation suite 'nope'; known: paper, track"):
        suite_experiments("nope")


def test_the_report_and_the_ablation_agree_on_which_way_is_better():
    """Every metric the report's table labels the ablation labels too, better the same way
    (one direction per metric), and the comparison of swept values bolds the best by that
    direction, also for metrics the report's table does not list (contact recall: higher)."""
    from dexflow.stages.report import METRICS
    from dexflow.tools.experiments import _ablation_table

    assert {k: METRICS[k][1] for k in METRICS} == {k: ablation.metric_label(k)[2] for k in METRICS}
    assert set(METRICS) <= set(ablation.METRIC_LABELS)
    values = ['"a"', '"b"']
    table = {"contact.recall": [0.5, 0.9], "refine.pd_mm": [1.0, 2.0]}
    lines = _ablation_table(values, {v: [None] for v in values}, table, list(table))
    assert "**0.900**" in lines[3] and "**1.000**" in lines[2]
