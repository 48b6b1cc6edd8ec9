"""Hydra multirun sweeps without DVC experiments (dexflow.tools.sweep): dvc.yaml reading, the reuse
rule on a toy pipeline, and the real pipeline fanned out by the joblib launcher (slow)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from dvc.utils.serialize import load_yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from dexflow.config import compose_params
from dexflow.errors import ConfigError
from dexflow.pipeline import provenance
from dexflow.pipeline.executor import record_key, run_command
from dexflow.pipeline.registry import load_stages, upstream_stages
from dexflow.pipeline.validity import params_values, stage_key
from dexflow.tools.experiments import collect_multirun
from dexflow.tools.sweep import main, run_job
from tests import quick_pipeline

ROOT = Path(__file__).resolve().parents[1]
UPSTREAM_OF_CONTACT = [
    "demo@demo", "hand", "scale_align", "retarget@dexflow", "retarget@position"
]  # fmt: skip


def _run(cmd: list[str], cwd: Path, project: Path) -> str:
    return quick_pipeline.run(cmd, cwd, project)


def _compose(overrides: list[str] | None = None):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("config", overrides=list(overrides or []))


def _status(job: Path) -> dict:
    return json.loads((job / "sweep_status.json").read_text())


# --- dvc.yaml as the sweep reads it -------------------------------------------------------------


def test_load_stages_expands_foreach_and_interpolates_params():
    params = load_yaml(ROOT / "params.yaml")
    stages = {s.name: s for s in load_stages(ROOT / "dvc.yaml", params)}
    assert list(stages)[:5] == UPSTREAM_OF_CONTACT
    assert {"simulate@baseline", "simulate@retarget", "simulate@refine"} <= set(stages)
    retarget = stages["retarget@position"]
    assert retarget.cmd == "python stages/retarget.py position"
    assert retarget.outs == ("data/retarget/position",)
    assert retarget.copies == ("reports/metrics/retarget_position.json",)
    assert "data/retarget/position" in stages["simulate@baseline"].deps  # dict foreach: ${item}
    assert stages["contact"].params == ("hand", "contact")
    assert params["data"]["root"] in stages["scale_align"].deps  # ${data.root}

    params["data"]["root"] = "data/mine"
    moved = {s.name: s for s in load_stages(ROOT / "dvc.yaml", params)}
    assert "data/mine" in moved["scale_align"].deps
    assert moved["scale_align"] != stages["scale_align"] and moved["contact"] == stages["contact"]


def test_upstream_stages_follow_the_outputs_each_stage_depends_on():
    stages = load_stages(ROOT / "dvc.yaml", load_yaml(ROOT / "params.yaml"))
    upstream = upstream_stages(stages)
    assert upstream["demo@demo"] == []
    assert upstream["scale_align"] == ["demo@demo"]  # through ${data.root} = data/demo
    # contact reads both retargetings (the baseline's for the flicker comparison)
    assert sorted(upstream["contact"]) == [
        "hand", "retarget@dexflow", "retarget@position", "scale_align"
    ]  # fmt: skip
    assert upstream["hand"] == []
    assert "retarget@position" in upstream["simulate@baseline"]
    assert "retarget@position" not in upstream["simulate@refine"]
    assert "refine" in upstream["simulate@refine"]
    # `report` reads reports/metrics, which every stage but hand (a copy) writes into, and
    # data/hand (the hand it draws)
    assert set(upstream["report"]) == {s.name for s in stages} - {"report"}


# --- the reuse rule on a toy pipeline (in process, seconds) --------------------------------------

WRITE = """\
import json, os, sys
from pathlib import Path
import yaml

name, key = sys.argv[1:]
value = yaml.safe_load(open("params.yaml"))
for part in key.split("."):
    value = value[part]
if value == 0.999:
    sys.exit(f"boom: {key} = {value}")
Path("data", name).mkdir(parents=True, exist_ok=True)
Path("data", name, "value.txt").write_text(str(value))
Path("reports/metrics").mkdir(parents=True, exist_ok=True)
Path("reports/metrics", name + ".json").write_text(json.dumps({"value": value}))
"""

TOY_DVC_YAML = """\
stages:
  up:
    cmd: python stages/write.py up seed
    params: [seed]
    outs: [data/up]
    metrics:
      - reports/metrics/up.json:
          cache: false
  down:
    foreach: [dis_min_m, dis_max_m]
    do:
      cmd: python stages/write.py down_${item} contact.${item}
      deps: [data/up]
      params:
        - contact.${item}
      outs:
        - data/down_${item}:
            persist: true
      metrics:
        - reports/metrics/down_${item}.json:
            cache: false
"""


@pytest.fixture
def toy(tmp_path) -> Path:
    """A project with a three-stage pipeline (up -> down@dis_min_m, down@dis_max_m) whose
    outputs exist, made with the default params."""
    root = tmp_path / "toy"
    (root / "stages").mkdir(parents=True)
    (root / "stages" / "write.py").write_text(WRITE)
    (root / "dvc.yaml").write_text(TOY_DVC_YAML)
    (root / "params.yaml").write_text(OmegaConf.to_yaml(_compose(), resolve=True))
    params, values = load_yaml(root / "params.yaml"), params_values(root / "params.yaml")
    for stage in load_stages(root / "dvc.yaml", params):  # as `dvc repro` and a sweep run them
        assert run_command(stage, root, stage_key(stage, values, root)) is None
    return root


def _metric(job: Path, name: str) -> float:
    return json.loads((job / "reports" / "metrics" / f"{name}.json").read_text())["value"]


def test_job_reuses_what_its_params_leave_unchanged(toy, tmp_path):
    job = tmp_path / "job"
    status = run_job(_compose(["contact.dis_min_m=0.012"]), toy, job)

    assert status == _status(job)
    assert status["status"] == "ok" and status["stage"] is None and status["error"] is None
    assert status["reused"] == ["up", "down@dis_max_m"] and status["ran"] == ["down@dis_min_m"]
    assert (job / "data" / "up").resolve() == (toy / "data" / "up").resolve()
    assert (job / "data" / "down_dis_max_m").is_symlink()
    assert not (job / "data" / "down_dis_min_m").is_symlink()
    metrics = job / "reports" / "metrics"
    assert not any(p.is_symlink() for p in metrics.iterdir())  # cache: false -> copies
    assert sorted(p.name for p in metrics.iterdir()) == [
        "down_dis_max_m.json", "down_dis_min_m.json", "up.json",
    ]  # fmt: skip
    assert _metric(job, "down_dis_min_m") == 0.012
    assert _metric(toy, "down_dis_min_m") != 0.012  # the project's outputs are untouched
    job_params = (job / "params.yaml").read_text().splitlines()
    project_params = (toy / "params.yaml").read_text().splitlines()
    assert [a for a, b in zip(job_params, project_params, strict=True) if a != b] == [
        "  dis_min_m: 0.012"
    ]


def test_a_changed_upstream_reruns_everything_downstream(toy, tmp_path):
    status = run_job(_compose(["seed=7"]), toy, tmp_path / "job")
    assert status["status"] == "ok"
    assert status["reused"] == [] and status["ran"] == ["up", "down@dis_min_m", "down@dis_max_m"]
    assert _metric(tmp_path / "job", "up") == 7


def test_outputs_recorded_with_another_key_are_not_reused(toy, tmp_path):
    """The key decides, not the params alone: outputs made from other inputs (here: a record
    left by a run with another dis_max_m, as after a hand-edited params.yaml) are made again."""
    params = load_yaml(toy / "params.yaml")
    stage = next(s for s in load_stages(toy / "dvc.yaml", params) if s.name == "down@dis_max_m")
    values = params_values(toy / "params.yaml")
    other = {**values, "contact": {**values["contact"], "dis_max_m": 0.5}}
    record_key(stage, toy, stage_key(stage, other, toy))
    status = run_job(_compose(), toy, tmp_path / "job")
    assert status["reused"] == ["up", "down@dis_min_m"] and status["ran"] == ["down@dis_max_m"]
    value = (tmp_path / "job" / "data" / "down_dis_max_m" / "value.txt").read_text()
    assert float(value) == params["contact"]["dis_max_m"]


def test_an_upstream_rerun_that_writes_the_same_bytes_reruns_nothing_below(toy, tmp_path):
    """A change upstream that leaves its outputs as they were (here: `up`'s command, which it
    runs again in the job) keeps the key of what reads them: only `up` runs."""
    (toy / "dvc.yaml").write_text(TOY_DVC_YAML.replace("write.py up seed", "write.py up  seed"))
    status = run_job(_compose(), toy, tmp_path / "job")
    assert status["status"] == "ok"
    assert status["ran"] == ["up"] and status["reused"] == ["down@dis_min_m", "down@dis_max_m"]
    # with new bytes (another seed), what reads them runs too
    status = run_job(_compose(["seed=7"]), toy, tmp_path / "seed")
    assert status["ran"] == ["up", "down@dis_min_m", "down@dis_max_m"]


def test_an_experiment_run_before_in_its_folder_is_kept(toy, tmp_path):
    job = tmp_path / "job"
    first = run_job(_compose(["contact.dis_min_m=0.012"]), toy, job)
    assert first["ran"] == ["down@dis_min_m"]
    again = run_job(_compose(["contact.dis_min_m=0.012"]), toy, job)
    assert again["kept"] == ["down@dis_min_m"] and again["ran"] == []
    assert again["reused"] == ["up", "down@dis_max_m"]
    changed = run_job(_compose(["contact.dis_min_m=0.013"]), toy, job)
    assert changed["ran"] == ["down@dis_min_m"] and changed["kept"] == []
    assert _metric(job, "down_dis_min_m") == 0.013
    # kept only where made on the machine the suite keeps to
    _record(job, "down_dis_min_m", machine="0123456789ab")
    here = run_job(_compose(["contact.dis_min_m=0.013"]), toy, job, machine=provenance.machine_id())
    assert "down@dis_min_m" in here["ran"] and here["kept"] == []


def test_a_failing_stage_or_invalid_params_fail_the_job_without_raising(toy, tmp_path):
    status = run_job(_compose(["contact.dis_max_m=0.999"]), toy, tmp_path / "a")
    assert status["status"] == "failed" and status["stage"] == "down@dis_max_m"
    assert "exit status 1" in status["error"] and "boom: contact.dis_max_m" in status["error"]
    assert status["reused"] == ["up", "down@dis_min_m"] and status["ran"] == []
    assert _status(tmp_path / "a") == status

    status = run_job(_compose(["simulate.stride=0"]), toy, tmp_path / "b")
    assert status["status"] == "failed" and status["stage"] == "params"
    assert "simulate.stride" in status["error"] and status["ran"] == status["reused"] == []
    assert "stride: 0" in (tmp_path / "b" / "params.yaml").read_text()  # kept for the report

    with pytest.raises(ValueError, match="the project itself"):
        run_job(_compose(), toy, toy)


def _record(project: Path, tag: str, machine: str | None = None) -> None:
    """The ``reports/timing`` record a run of stage ``tag`` leaves for the project's metrics:
    made on this machine, or on ``machine`` (as another machine's run leaves it)."""
    metrics = json.loads((project / "reports" / "metrics" / f"{tag}.json").read_text())
    key = json.loads((project / "reports" / "timing" / f"{tag}.json").read_text())["key"]
    record = provenance.stage_record(None, {}, {}, provenance.metrics_digest(metrics), key)
    for entry in (record["provenance"], *record["made"].values()):
        entry["machine_id"] = machine or entry["machine_id"]
    (project / "reports" / "timing").mkdir(parents=True, exist_ok=True)
    (project / "reports" / "timing" / f"{tag}.json").write_text(json.dumps(record))


def test_a_job_reuses_only_outputs_this_machine_made(toy, tmp_path):
    here = provenance.machine_id()
    _record(toy, "up")
    _record(toy, "down_dis_min_m")
    _record(toy, "down_dis_max_m", machine="0123456789ab")  # committed from another machine
    status = run_job(_compose(), toy, tmp_path / "job", machine=here)
    assert status["reused"] == ["up", "down@dis_min_m"] and status["ran"] == ["down@dis_max_m"]
    timing = tmp_path / "job" / "reports" / "timing"
    assert (timing / "up.json").read_bytes() == (toy / "reports/timing/up.json").read_bytes()
    # the stage that ran has the key recorded (the toy stage writes no record of its own)
    assert set(json.loads((timing / "down_dis_max_m.json").read_text())) == {"key"}

    # a stage without a record (restored from git or the DVC cache) is made again; what reads
    # its outputs is reused where it wrote the same bytes (the key is the same)
    (toy / "reports" / "timing" / "up.json").unlink()
    status = run_job(_compose(), toy, tmp_path / "again", machine=here)
    assert status["reused"] == ["down@dis_min_m"] and status["ran"] == ["up", "down@dis_max_m"]
    # without a machine to keep to, wherever the outputs were made
    status = run_job(_compose(), toy, tmp_path / "any")
    assert status["reused"] == ["down@dis_min_m", "down@dis_max_m"] and status["ran"] == ["up"]


def test_raw_inputs_under_data_are_linked_into_the_job(tmp_path):
    root = tmp_path / "project"
    (root / "stages").mkdir(parents=True)
    (root / "stages" / "copy.py").write_text(
        "from pathlib import Path\n"
        "Path('data/copy').mkdir(parents=True)\n"
        "Path('data/copy/out.txt').write_text(Path('data/raw/in.txt').read_text())\n"
    )
    (root / "dvc.yaml").write_text(
        "stages:\n  copy:\n    cmd: python stages/copy.py\n    deps: [data/raw]\n"
        "    outs: [data/copy]\n"
    )
    (root / "params.yaml").write_text(OmegaConf.to_yaml(_compose(), resolve=True))
    (root / "data" / "raw").mkdir(parents=True)
    (root / "data" / "raw" / "in.txt").write_text("captured")

    status = run_job(_compose(), root, tmp_path / "job")
    assert status["status"] == "ok" and status["ran"] == ["copy"]
    assert (tmp_path / "job" / "data" / "raw").is_symlink()
    assert (tmp_path / "job" / "data" / "copy" / "out.txt").read_text() == "captured"


def _show(args: list[str], monkeypatch, capsys) -> str:
    """What ``dexflow-sweep ARGS`` prints, run in this process from the project."""
    from hydra.core.global_hydra import GlobalHydra

    monkeypatch.chdir(ROOT)
    monkeypatch.setattr(sys, "argv", ["dexflow-sweep", *args])
    capsys.readouterr()
    try:
        main()
    finally:
        GlobalHydra.instance().clear()
    return capsys.readouterr().out


def test_the_app_composes_params_as_dvc_does(tmp_path, monkeypatch, capsys):
    overrides = ["experiment=no_temporal", "contact.dis_min_m=0.012"]
    shown = _show(["--cfg", "job", "--resolve", *overrides], monkeypatch, capsys)
    composed = compose_params(overrides, tmp_path / "params.yaml", ROOT / "conf")
    assert shown == composed.read_text()
    hydra = _show(["--cfg", "hydra"], monkeypatch, capsys)
    assert f"dir: {ROOT.as_posix()}/multirun/" in hydra and "chdir: true" in hydra


# --- the real pipeline, swept with Hydra launchers (slow) ---------------------------------------


@pytest.fixture(scope="module")
def project(reproduced_demo, tmp_path_factory) -> Path:
    """A copy of the small demo project after its first `dvc repro` (tests/conftest.py)."""
    return quick_pipeline.copy_reproduced(reproduced_demo, tmp_path_factory.mktemp("sweep") / "p")


@pytest.mark.slow
@pytest.mark.xdist_group("reproduced_demo")  # one build of it per worker
def test_joblib_sweep_reuses_upstream_and_gives_each_job_its_metrics(project, tmp_path):
    """A parameter of the last stages (metrics): each job reruns only them, its own copy of
    every output it writes, the rest linked to the project's (the toy pipeline above covers
    reruns from further up)."""
    project_metrics = (project / "reports/metrics/metrics.json").read_bytes()
    stages = [s.name for s in load_stages(project / "dvc.yaml", load_yaml(project / "params.yaml"))]
    sweep = tmp_path / "multirun"
    _run([sys.executable, "-m", "dexflow.tools.sweep", "-m", "hydra/launcher=joblib",
          "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}",
          "metrics.pd_violation_m=0.001,0.008"], project, project)  # fmt: skip

    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert [j.name for j in jobs] == ["0", "1"]
    metrics = []
    for job, value in zip(jobs, (0.001, 0.008), strict=True):
        status = _status(job)
        assert status["status"] == "ok", status
        assert status["ran"] == ["metrics", "report"]
        assert status["reused"] == [s for s in stages if s not in status["ran"]]
        assert load_yaml(job / "params.yaml")["metrics"]["pd_violation_m"] == value
        overrides = (job / ".hydra" / "overrides.yaml").read_text()
        assert f"metrics.pd_violation_m={value}" in overrides
        assert (job / "data/refine").resolve() == (project / "data/refine").resolve()
        path = job / "reports/metrics/metrics.json"
        assert path.is_file() and not path.is_symlink() and (job / "reports/summary.md").is_file()
        metrics.append(json.loads(path.read_text()))
    assert metrics[0]["baseline.fvr"] > metrics[1]["baseline.fvr"]  # frames beyond the threshold
    assert (project / "reports/metrics/metrics.json").read_bytes() == project_metrics

    found = collect_multirun(sweep)  # what `dexflow report ablation --multirun` reads
    assert [e.params["metrics.pd_violation_m"] for e in found] == [0.001, 0.008]
    assert all(e.error is None and "contact.flicker_raw" in e.metrics for e in found)


@pytest.mark.slow
@pytest.mark.xdist_group("reproduced_demo")  # one build of it per worker
def test_failed_jobs_are_recorded_while_the_others_complete(project):
    _run([sys.executable, "-m", "dexflow.tools.sweep", "-m", "simulate.stride=0,5",
          "data.root=data/demo,data/missing"], project, project)  # fmt: skip

    (sweep,) = (project / "multirun").glob("*/*")  # the default: multirun/<date>/<time>
    by_params = {}
    for job in sorted(p for p in sweep.iterdir() if p.is_dir()):
        params = load_yaml(job / "params.yaml")
        by_params[params["simulate"]["stride"], params["data"]["root"]] = (job, _status(job))
    assert len(by_params) == 4

    for root in ("data/demo", "data/missing"):
        _, status = by_params[0, root]
        assert status["status"] == "failed" and status["stage"] == "params"
        assert "simulate.stride" in status["error"]

    job, status = by_params[5, "data/missing"]
    assert status["status"] == "failed" and status["stage"] == "scale_align"
    assert status["error"] and status["reused"] == ["demo@demo", "hand"] and status["ran"] == []

    job, status = by_params[5, "data/demo"]
    assert status == {"status": "ok", "stage": None, "error": None, "ran": [], "kept": [],
                      "reused": status["reused"]}  # fmt: skip
    stages = load_stages(project / "dvc.yaml", load_yaml(project / "params.yaml"))
    assert status["reused"] == [s.name for s in stages]
    assert load_yaml(job / "params.yaml") == load_yaml(project / "params.yaml")
    assert (job / "reports/metrics/metrics.json").read_bytes() == (
        project / "reports/metrics/metrics.json"
    ).read_bytes()


def test_stages_run_after_the_stages_whose_outputs_they_read():
    """With the grip on, refine reads replay@retarget (``refine.grip_input``), a foreach stage
    further down dvc.yaml: the sweep runs it first; with it off (the default) refine waits on
    no replay. A cycle is an error naming the stages."""
    params = load_yaml(ROOT / "params.yaml")
    off = load_stages(ROOT / "dvc.yaml", params)
    assert not any(u.startswith("replay") for u in upstream_stages(off)["refine"])
    params["refine"] |= {"grip_m": 0.005, "grip_input": "data/replay/retarget"}
    for stages in (off, load_stages(ROOT / "dvc.yaml", params)):
        names = [s.name for s in stages]
        upstream = upstream_stages(stages)
        for stage in stages:
            assert all(names.index(u) < names.index(stage.name) for u in upstream[stage.name])
    assert "replay@retarget" in upstream["refine"]
    assert names.index("replay@retarget") < names.index("refine") < names.index("replay@refine")


def test_a_cycle_in_dvc_yaml_is_named(tmp_path):
    (tmp_path / "dvc.yaml").write_text(
        "stages:\n"
        "  a: {cmd: python a.py, deps: [data/b], outs: [data/a]}\n"
        "  b: {cmd: python b.py, deps: [data/a], outs: [data/b]}\n"
    )
    with pytest.raises(ConfigError, match=r"\['a', 'b'\] depend on each other"):
        load_stages(tmp_path / "dvc.yaml", {})


def test_a_folder_holding_links_has_the_digest_of_what_they_point_to(tmp_path):
    """A job's ``data/retarget`` is a folder of its own holding links to the project's outputs:
    its digest is that of the project's folder."""
    from dexflow.pipeline.validity import path_digest

    project = tmp_path / "project" / "retarget"
    for method in ("dexflow", "position"):
        (project / method).mkdir(parents=True)
        (project / method / "a.npz").write_bytes(method.encode())
    job = tmp_path / "job" / "retarget"
    job.mkdir(parents=True)
    for method in ("dexflow", "position"):
        (job / method).symlink_to(project / method, target_is_directory=True)
    assert path_digest(job) == path_digest(project)
    (project / "position" / "a.npz").write_bytes(b"other")
    assert path_digest(job) == path_digest(project) != path_digest(tmp_path / "missing")
