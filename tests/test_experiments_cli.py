"""`dexflow exp`: the headline metrics of every experiment side by side, on a real (small) DVC
repository and on a Hydra multirun directory; the `dvc exp show` recipe of docs/experiments.md
gives the same columns."""

from __future__ import annotations

import csv
import io
import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from dexflow.errors import ConfigError
from dexflow.tools.cli import main
from dexflow.tools.experiments import collect_dvc, collect_multirun
from dexflow.tools.headline import HEADLINE_METRICS, headline_table
from tests import quick_pipeline

ROOT = Path(__file__).resolve().parents[1]
METRICS = ROOT / "reports" / "metrics"  # the project's own, as `dvc repro` wrote them


def _run(*cmd: str, cwd: Path) -> str:
    done = subprocess.run(
        cmd, cwd=cwd, env=quick_pipeline.env(), capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, f"{' '.join(cmd)}:\n{done.stdout}\n{done.stderr}"
    return done.stdout


def _edit(path: Path, **changes) -> None:
    data = json.loads(path.read_text())
    data.update(changes)
    path.write_text(json.dumps(data, indent=2))


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    """A git + DVC repository: params.yaml and the project's reports/metrics committed, then
    one experiment (`dvc exp save`) with another contact.dis_min_m and other metrics."""
    repo = tmp_path_factory.mktemp("exp")
    _run("git", "init", "-q", cwd=repo)
    _run("dvc", "init", "-q", cwd=repo)
    shutil.copytree(METRICS, repo / "reports" / "metrics")
    (repo / "params.yaml").write_text(
        "hand:\n  name: shadow\ncontact:\n  dis_min_m: 0.01\nrefine:\n  w_pen: 1.0\nseed: 0\n"
    )
    (repo / "dvc.yaml").write_text("params:\n  - params.yaml\nmetrics:\n  - reports/metrics\n")
    _run("git", "add", "-A", cwd=repo)
    _run("git", "commit", "-qm", "baseline", cwd=repo)
    params = repo / "params.yaml"
    params.write_text(params.read_text().replace("dis_min_m: 0.01", "dis_min_m: 0.02"))
    _edit(repo / "reports/metrics/metrics.json", **{"refine.ssr": 8.5, "refine.spd_mm": 0.1})
    _edit(repo / "reports/metrics/replay_refine.json", success_rate=12.5, lost_rate=3.0)
    _edit(repo / "reports/metrics/contact.json", band_jumps=3)
    _run("dvc", "exp", "save", "-q", "-n", "dis2", cwd=repo)
    _run("git", "checkout", "-q", "--", ".", cwd=repo)
    return repo


def test_exp_prints_the_headline_metrics_and_the_parameter_that_differs(repo, monkeypatch, capsys):
    monkeypatch.chdir(repo)
    baseline = json.loads((METRICS / "metrics.json").read_text())
    assert main(["exp", "--csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    metrics = [m for m in HEADLINE_METRICS if not m.startswith("timing.")]  # not in DVC
    assert list(rows[0]) == ["experiment", "rev", "contact.dis_min_m", *metrics]
    assert [r["experiment"] for r in rows][-1] == "dis2" and len(rows) == 2  # workspace = HEAD
    head, dis2 = rows
    assert (head["contact.dis_min_m"], dis2["contact.dis_min_m"]) == ("0.01", "0.02")
    assert float(head["refine.ssr"]) == baseline["refine.ssr"]
    assert (float(dis2["refine.ssr"]), float(dis2["replay_refine.success_rate"])) == (8.5, 12.5)
    assert re.fullmatch("[0-9a-f]{7}", dis2["rev"])

    assert main(["exp"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert max(map(len, lines)) <= 120
    assert lines[0].split()[:3] == ["experiment", "rev", "contact.dis_min_m"]
    assert "SSR" in lines[0] and "replay success" in lines[0] and "% ↑" in lines[1]
    assert lines[3].split()[:4] == ["dis2", dis2["rev"], "0.02", "8.50"]


def test_exp_metrics_chooses_the_columns_and_names_an_unknown_one(repo, monkeypatch, capsys):
    experiments = collect_dvc(json.loads(_run("dvc", "exp", "show", "--json", cwd=repo)))
    table = headline_table(experiments, ["refine.spd_mm", "contact.band_jumps"])
    assert table.columns[-2:] == ["refine.spd_mm", "contact.band_jumps"]
    assert [row[-2:] for row in table.rows][1] == [0.1, 3.0]
    with pytest.raises(ConfigError, match=r"'refine.sr': no experiment has it; did you mean "):
        headline_table(experiments, ["refine.sr"])
    monkeypatch.chdir(repo.parent)  # no DVC repository: the error says why, no table
    assert main(["exp"]) == 1


def test_the_dvc_exp_show_recipe_gives_the_same_columns(repo, monkeypatch, capsys):
    """The command of docs/experiments.md, run as written (plus --csv), keeps the columns of
    `dexflow exp --csv`: the experiment, its commit, the parameter that differs, the headline
    metrics; no other metric, changed or not."""
    text = (ROOT / "docs" / "experiments.md").read_text()
    (recipe,) = re.findall(r"```sh\n(dvc exp show --only-changed.*?)\n```", text, re.S)
    shown = _run("bash", "-c", recipe + " --csv", cwd=repo)
    columns = next(csv.reader(io.StringIO(shown)))
    monkeypatch.chdir(repo)
    assert main(["exp", "--csv"]) == 0
    ours = next(csv.reader(io.StringIO(capsys.readouterr().out)))
    replay = "reports/metrics/replay_refine.json:success_rate"  # DVC names it by its file
    assert sorted(c.replace(replay, "replay_refine.success_rate") for c in columns) == sorted(
        ["Experiment", *ours[1:]]
    )


def test_exp_reads_a_multirun_with_the_retarget_speed(tmp_path, monkeypatch, capsys):
    for job, (w_pen, ssr, speed) in {"0": (1.0, 4.0, 52.0), "1": (2.0, 12.5, 48.0)}.items():
        folder = tmp_path / "multirun" / job
        shutil.copytree(METRICS, folder / "reports" / "metrics")
        _edit(folder / "reports/metrics/metrics.json", **{"refine.ssr": ssr})
        (folder / "params.yaml").write_text(f"refine:\n  w_pen: {w_pen}\nhand:\n  name: shadow\n")
        (folder / "reports" / "timing").mkdir()
        record = {"stage": "retarget_dexflow", "frames_per_second": speed}
        (folder / "reports/timing/retarget_dexflow.json").write_text(json.dumps(record))
        (folder / "sweep_status.json").write_text('{"status": "ok"}')
    broken = tmp_path / "multirun" / "2"
    broken.mkdir()
    (broken / "params.yaml").write_text("refine:\n  w_pen: 3.0\nhand:\n  name: shadow\n")
    (broken / "sweep_status.json").write_text(
        '{"status": "failed", "stage": "refine", "error": "out of memory"}'
    )
    table = headline_table(collect_multirun(tmp_path / "multirun"))
    assert table.columns == ["experiment", "rev", "refine.w_pen", *HEADLINE_METRICS]
    assert [row[-1] for row in table.rows] == [52.0, 48.0, None]
    assert table.notes == ["2: stage refine: out of memory"]
    monkeypatch.chdir(tmp_path)  # no DVC here: --multirun alone reads no DVC experiments
    assert main(["exp", "--multirun", "multirun"]) == 0
    out = capsys.readouterr().out
    assert "retarget speed" in out and "frames/s ↑" in out
    assert "  2: stage refine: out of memory" in out
    assert main(["exp", "--all", "--multirun", "multirun"]) == 0
    rows = {line.split()[0]: line.split()[1:] for line in capsys.readouterr().out.splitlines()[1:]}
    assert rows["refine.ssr"] == ["4.00", "12.5", "—"]
    assert rows["timing.retarget_dexflow.frames_per_second"] == ["52.0", "48.0", "—"]
