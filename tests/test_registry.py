"""The stage registry: every stage of ``dvc.yaml`` is run by ``stages/<name>.py`` and the
``STAGE`` of ``dexflow.stages.<name>``, and every runner reads the stages from it."""

from __future__ import annotations

import sys

import pytest

from dexflow.errors import ConfigError
from dexflow.pipeline.executor import run_command
from dexflow.pipeline.registry import Stage, load_stages, pipeline_file, stage_spec
from tests.test_dvc_deps import _params_with_track
from tests.test_import_graph import ROOT, STAGE_MODULES, imports_of_file


def _stages() -> list[Stage]:
    """The stages with params.yaml as ``track=on`` composes it: every stage present."""
    return load_stages(pipeline_file(), _params_with_track())


def test_registry_reads_the_project_pipeline():
    assert pipeline_file() == ROOT / "dvc.yaml"
    names = [s.name for s in _stages()]
    assert names[0] == "demo@demo" and names[-1] == "report"
    assert names.index("refine") < names.index("simulate@refine") < names.index("metrics")


def test_every_stage_has_its_script_and_module_and_no_module_is_left_over():
    bases = {s.name.partition("@")[0] for s in _stages()}
    assert bases == {m.rpartition(".")[2] for m in STAGE_MODULES}
    for stage in _stages():
        base = stage.name.partition("@")[0]
        item = stage.name.partition("@")[2]
        script = f"stages/{base}.py"
        assert stage.cmd.split() == ["python", script, *([item] if item and base != "demo" else [])]
        imported = imports_of_file(ROOT / script)
        assert imported == {f"dexflow.stages.{base}", "dexflow.pipeline.runner"}, script
        assert stage_spec(stage.name).name == base


def test_a_stage_no_module_runs_is_refused():
    with pytest.raises(ConfigError, match=r"no module dexflow\.stages\.tidy_up"):
        stage_spec("tidy_up@x")


def test_run_command_runs_in_the_folder_and_reports_the_failing_line(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "stale").write_text("from an earlier run")
    ok = Stage(name="write", cmd="python -c \"open('data/out', 'w').write('x')\"",
               outs=("data/out", "data/stale"))  # fmt: skip
    assert run_command(ok, tmp_path) is None
    assert (tmp_path / "data" / "out").read_text() == "x"
    assert not (tmp_path / "data" / "stale").exists()  # outputs are removed before a run

    failing = Stage(name="fail", cmd=f"{sys.executable} -c \"print('no input'); exit(3)\"")
    assert run_command(failing, tmp_path) == "exit status 3: no input"
