"""What the reports say about where their numbers come from: the summary's provenance, its
intervals over sequences and its determinism; the sweep report comparing runs of one machine."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

from dexflow.pipeline import provenance
from dexflow.stages.report import write_summary
from dexflow.stats import mean_interval, rate_interval
from dexflow.tools.cli import main
from dexflow.tools.experiments import Experiment, collect_dvc, collect_multirun, write_ablation
from tests.test_metrics import _metrics_dir, _section

OTHER = "0123456789ab"  # the machine id of a machine that is not this one


def _record(
    metrics_dir: Path,
    timing_dir: Path,
    tag: str,
    machine: str | None = None,
    commit: str | None = None,
) -> None:
    """The ``reports/timing`` record of a run of stage ``tag`` that wrote the metrics
    ``metrics_dir`` holds; ``machine``, ``commit``: as a run on another machine, or at another
    commit, leaves it."""
    metrics = json.loads((metrics_dir / f"{tag}.json").read_text())
    record = provenance.stage_record(None, {}, {"name": "demo"}, provenance.metrics_digest(metrics))
    if machine is not None:
        record["provenance"]["machine"] = {**record["provenance"]["machine"], "cpu": "Other CPU"}
    for entry in (record["provenance"], *record["made"].values()):
        entry["machine_id"] = machine or entry["machine_id"]
        entry["commit"] = commit or entry["commit"]
    timing_dir.mkdir(parents=True, exist_ok=True)
    (timing_dir / f"{tag}.json").write_text(json.dumps(record))


@pytest.fixture
def summary_inputs(tmp_path):
    """The report's inputs with a record of this machine for every stage."""
    metrics, table, plots = _metrics_dir(tmp_path / "in", methods=("baseline", "refine"))
    aggregates = json.loads((metrics / "metrics.json").read_text())
    (metrics / "metrics.json").write_text(json.dumps(aggregates | {"num_frames": 90}))
    timing = tmp_path / "in" / "timing"
    for tag in ("metrics", "simulate_baseline", "simulate_refine"):
        _record(metrics, timing, tag)
    return metrics, table, plots, timing


def _write(tmp_path, inputs, name="summary.md") -> str:
    metrics, table, plots, timing = inputs
    out = write_summary(metrics, table, plots, tmp_path / name, tmp_path / "figures",
                        data_name="demo", timing_dir=timing)  # fmt: skip
    return out.read_text()


def test_the_summary_says_where_it_was_written_and_on_which_data(tmp_path, summary_inputs):
    text = _write(tmp_path, summary_inputs)
    block = _section(text, "Provenance")
    here = provenance.current()
    dirty = {True: "yes", False: "no", None: "unknown"}[here["dirty"]]
    assert f"- commit: {here['commit']} (uncommitted changes: {dirty})" in block
    assert f"- machine: {here['machine_id']} ({provenance.describe_machine(here['machine'])})" in (
        block
    )
    assert "- data: demo, 2 sequences, 90 frames" in block
    assert (
        f"The stages: all 3 ran on machine {here['machine_id']}, at commit {here['commit']}"
        in block
    )
    assert "**" not in block  # nothing to flag


def test_stages_run_at_several_commits_of_one_machine_are_listed_without_a_warning(
    tmp_path, summary_inputs
):
    metrics, _, _, timing = summary_inputs
    _record(metrics, timing, "metrics", commit="f" * 40)  # rerun alone after a commit
    block = _section(_write(tmp_path, summary_inputs), "Provenance")
    assert f"The stages ran on machine {provenance.machine_id()}, at 2 commits" in block
    assert f"| metrics | {provenance.machine_id()} | ffffffffffff |" in block
    assert "**" not in block


def test_the_summary_flags_stages_made_on_another_machine_or_not_recorded(tmp_path, summary_inputs):
    metrics, _, _, timing = summary_inputs
    _record(metrics, timing, "simulate_refine", machine=OTHER)
    (timing / "simulate_baseline.json").unlink()
    block = _section(_write(tmp_path, summary_inputs), "Provenance")
    assert "**The stages ran on 2 machine(s), and 1 did not record where" in block
    rows = {r.split("|")[1].strip(): r for r in block.splitlines() if r.startswith("| ")}
    assert rows["simulate_refine"].split("|")[2].strip() == OTHER
    assert rows["metrics"].split("|")[2].strip() == provenance.machine_id()
    assert "| simulate_baseline | not recorded | — | — |" in block
    assert f"- machine {OTHER}: Other CPU," in block  # the other machine's facts, from its record

    # metrics rewritten after the record (restored from git, made elsewhere): not recorded
    (metrics / "metrics.json").write_text(json.dumps({"num_sequences": 2, "baseline.ssr": 1.0}))
    block = _section(_write(tmp_path, summary_inputs, "again.md"), "Provenance")
    assert "| metrics | not recorded | — | — |" in block


def _cells(text: str, label: str) -> list[str]:
    spread = _section(text, "Spread over sequences")
    row = next(r for r in spread.splitlines() if r.startswith(f"| {label} |"))
    return [c.strip() for c in row.split("|")[2:-1]]


def _parse(cell: str) -> tuple[float, float, float]:
    value, low, high = re.fullmatch(r"(\S+) \[(\S+), (\S+)\]", cell).groups()
    return float(value), float(low), float(high)


def test_each_rate_and_mean_has_its_interval_over_sequences(tmp_path, summary_inputs):
    metrics, table, _, _ = summary_inputs
    rows = []
    for i in range(8):  # refine holds 2 of 8 sequences, the baseline none
        for m in ("baseline", "retarget", "refine"):
            ssr = 100.0 if m == "refine" and i < 2 else 0.0
            rows.append({"sequence": f"s{i}", "object": "box", "hand": "shadow", "method": m,
                         "ssr": ssr, "pd_mm": 1.0 + i, "cd_mm": 2.0,
                         "keypoint_error_mm": 7.0})  # fmt: skip
    with open(table, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    replay = {"num_replayed": 24, "success_rate": 25.0, "spider_success_rate": 70.83333333333334,
              "carried_rate": 100 / 24, "lost_rate": 100.0}  # fmt: skip
    (metrics / "replay_refine.json").write_text(json.dumps(replay))
    sim = json.loads((metrics / "simulate_refine.json").read_text())
    (metrics / "simulate_refine.json").write_text(json.dumps(sim | {"num_ok": 8, "ssr_raw": 37.5}))
    text = _write(tmp_path, summary_inputs)

    baseline, _, refine, n, kind = _cells(text, "SSR every test % ↑")
    assert (n, kind) == ("8", "Wilson")
    wilson = rate_interval(2, 8)
    assert _parse(refine) == pytest.approx((25.0, wilson.low, wilson.high), abs=0.05)
    assert _parse(baseline)[:2] == (0.0, 0.0) and _parse(baseline)[2] > 0  # none held: not 0
    pd = mean_interval([1.0 + i for i in range(8)])
    assert _parse(_cells(text, "PD mm ↓")[2]) == pytest.approx(
        (pd.value, pd.low, pd.high), abs=0.005
    )
    assert _cells(text, "PD mm ↓")[3:] == ["8", "t"]
    assert _cells(text, "replay success %")[2] == "25.0 [12.0, 44.9]"
    assert _cells(text, "replay success %")[0] == "—"  # no replay of the baseline
    # the simulate stage's rates that sequences.csv lacks, over the sequences it counted
    without_rule = _cells(text, "SSR every test without the rule %")
    assert without_rule[2] == rate_interval(3, 8).text(1) and without_rule[0] == "—"
    assert "velocity KL" not in _section(text, "Spread over sequences").split("|---")[1]


def test_the_summary_is_written_byte_for_byte_the_same_twice(tmp_path, summary_inputs):
    first = _write(tmp_path, summary_inputs, "a.md").encode()
    figures = {p.name: p.read_bytes() for p in (tmp_path / "figures").iterdir()}
    second = _write(tmp_path, summary_inputs, "b.md").encode()
    assert first == second
    assert figures == {p.name: p.read_bytes() for p in (tmp_path / "figures").iterdir()}


# --- the sweep report (dexflow report ablation): runs of one machine -------------------------


def _made(machine: str | None) -> dict:
    return {"metrics": None if machine is None else {"machine_id": machine, "commit": "c"}}


def _run(name: str, value: float, ssr: float, machine: str | None) -> Experiment:
    params = {"contact.dis_min_m": value, "data.name": "demo"}
    metrics = {"refine.ssr": ssr, "num_input_sequences": 24.0, "num_frames": 2713.0}
    return Experiment(name, "dvc", params, metrics, None, _made(machine))


def test_the_sweep_report_compares_only_runs_of_the_given_machine(tmp_path):
    here = provenance.machine_id()
    runs = [
        _run("workspace", 0.010, 25.0, OTHER),  # the committed baseline, made elsewhere
        _run("exp-a", 0.010, 20.8, here),  # the same params rerun here
        _run("exp-b", 0.012, 30.0, here),
        _run("exp-c", 0.014, 50.0, None),  # no record of where
    ]
    text = write_ablation(runs, tmp_path / "sweep.md", tmp_path / "f", machine=here).read_text()
    assert f"every stage was made on machine {here} (this machine)" in text
    assert "- data: demo, 24 sequences, 2713 frames" in text
    table = text.split("## `contact.dis_min_m`")[1].split("\n## ")[0]
    rows = [r for r in table.splitlines() if r.startswith("| 0.0")]
    assert [r.split("|")[1].strip() for r in rows] == ["0.01", "0.012"]
    assert "20.800" in rows[0] and "25.000" not in table  # the baseline of another machine is out
    experiments = text.split("## Experiments")[1]
    assert f"| workspace | dvc | not compared: made on machine {OTHER} |" in experiments
    assert "| exp-c | dvc | not compared: not recorded on which machine |" in experiments
    assert f"| exp-a | dvc | ok | contact.dis_min_m=0.01 | 20.800 | {here} |" in experiments

    # told to compare whatever was made where: every run, flagged
    text = write_ablation(runs, tmp_path / "any.md", tmp_path / "f").read_text()
    assert "**Not checked to come from one machine**: made on 2 known machine(s)" in text
    assert "| 0.01 | 2 | 22.900 |" in text  # the mean of 25.0 (elsewhere) and 20.8 (here)


def test_multirun_and_dvc_experiments_carry_the_machine_of_their_stages(tmp_path):
    here = provenance.machine_id()
    for job, machine in (("0", None), ("1", OTHER)):
        reports = tmp_path / "multirun" / job / "reports"
        (reports / "metrics").mkdir(parents=True)
        (reports.parent / "params.yaml").write_text(f"contact:\n  dis_min_m: 0.0{job}\n")
        (reports / "metrics" / "metrics.json").write_text(json.dumps({"refine.ssr": 1.0}))
        _record(reports / "metrics", reports / "timing", "metrics", machine=machine)
    found = collect_multirun(tmp_path / "multirun")
    assert [e.machine for e in found] == [here, OTHER]

    timing = tmp_path / "timing"  # the workspace's reports/timing: its metrics were made here
    (tmp_path / "metrics").mkdir()
    (tmp_path / "metrics" / "metrics.json").write_text(json.dumps({"refine.ssr": 5.0}))
    _record(tmp_path / "metrics", timing, "metrics")
    show = [
        {"rev": "workspace", "name": None, "data": {
            "params": {"params.yaml": {"data": {"contact": {"dis_min_m": 0.01}}}},
            "metrics": {"reports/metrics/metrics.json": {"data": {"refine.ssr": 5.0}}}}},
        {"rev": "e1", "name": "exp-elsewhere", "data": {
            "params": {"params.yaml": {"data": {"contact": {"dis_min_m": 0.012}}}},
            "metrics": {"reports/metrics/metrics.json": {"data": {"refine.ssr": 7.0}}}}},
    ]  # fmt: skip
    found = {e.name: e for e in collect_dvc(show, timing)}
    assert found["workspace"].machine == here
    assert found["exp-elsewhere"].machine is None
    assert found["exp-elsewhere"].machine_text() == "not recorded"
    assert collect_dvc(show)[0].machine is None  # without the workspace's records


def test_report_ablation_command_refuses_a_baseline_of_another_machine(tmp_path):
    for job, (value, machine) in enumerate(((0.010, OTHER), (0.010, None), (0.012, None))):
        reports = tmp_path / "multirun" / str(job) / "reports"
        (reports / "metrics").mkdir(parents=True)
        (reports.parent / "params.yaml").write_text(f"contact:\n  dis_min_m: {value}\n")
        ssr = 25.0 if machine else 20.0 + job
        (reports / "metrics" / "metrics.json").write_text(json.dumps({"refine.ssr": ssr}))
        _record(reports / "metrics", reports / "timing", "metrics", machine=machine)
    out = tmp_path / "sweep.md"
    args = ["report", "ablation", "--multirun", str(tmp_path / "multirun"), "--out", str(out)]
    assert main(args) == 0
    text = out.read_text()
    assert f"| 0 | multirun | not compared: made on machine {OTHER} |" in text
    assert "| 1 | multirun | ok |" in text and "25.000" not in text
    assert main([*args, "--any-machine"]) == 0
    assert "| 0 | multirun | ok |" in out.read_text()


def test_benchmark_reports_say_where_they_were_measured(tmp_path, capsys):
    from dexflow.tools.bench.pipeline import publish as _publish
    from dexflow.tools.bench.real import _real_table

    result = {"metrics": {}, "seconds": {"retarget@dexflow": 2.0}, "sequences": 4,
              "frames": 120, "retarget_s_per_sequence": 1.0}  # fmt: skip
    _publish(_real_table({"shadow": result}, "data/real", 0, 2), str(tmp_path / "real.md"))
    lines = (tmp_path / "real.md").read_text().splitlines()
    here = provenance.current()
    assert lines[0] == "# dexflow on real captures"
    assert lines[2:6] == ["Measured at:", "", *provenance.markdown(here)]
    assert "on the converted data in `data/real` (4 sequences, 120 frames)" in lines[7]
    assert f"Machine: {here['machine_id']} (see *Measured at*)." in "\n".join(lines)
    assert capsys.readouterr().out.startswith("# dexflow on real captures\n\nMeasured at:")
