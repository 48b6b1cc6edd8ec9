"""The project layout: its paths agree with dvc.yaml and its helpers parse and find what they say."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from dexflow.errors import ConfigError
from dexflow.io.layout import TRAJECTORIES, Layout, StageDir, project_root

REPO = Path(__file__).parents[1]


def _declared(entries: list | None, **subst: str) -> list[Path]:
    """The paths of a stage's ``outs``/``metrics`` (plain or with options), ``${...}`` filled."""
    paths = []
    for entry in entries or []:
        (text,) = entry if isinstance(entry, dict) else (entry,)
        for name, value in subst.items():
            text = text.replace(f"${{{name}}}", value)
        paths.append(Path(text))
    return paths


def _params_with_track(tmp: Path) -> Path:
    """params.yaml as ``dexflow params track=on`` composes it: every stage present."""
    from dexflow.config import compose_params

    return compose_params(["track=on"], tmp / "params.yaml")


def _foreach(foreach, params: dict):
    """A ``foreach`` as DVC expands it: ``${a.b}`` looked up in ``params``."""
    if isinstance(foreach, str):
        for key in foreach.removeprefix("${").removesuffix("}").split("."):
            params = params[key]
        return params
    return foreach


def _stages(params: dict) -> dict[str, tuple[list[Path], list[Path]]]:
    """Every dvc.yaml stage, foreach expanded as DVC names it (``name@key``) with ``params``:
    (outs, metrics)."""
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text(encoding="utf-8"))
    stages = {}
    for name, stage in dvc["stages"].items():
        if "foreach" not in stage:
            stages[name] = (_declared(stage.get("outs")), _declared(stage.get("metrics")))
            continue
        foreach, do = _foreach(stage["foreach"], params), stage["do"]
        if name == "demo":  # the input, written only where the data is the demo
            continue
        items = foreach.items() if isinstance(foreach, dict) else ((i, i) for i in foreach)
        for key, item in items:
            subst = {"key": str(key), "item": str(item)}
            stages[f"{name}@{key}"] = (
                _declared(do.get("outs"), **subst),
                _declared(do.get("metrics"), **subst),
            )
    return stages


@pytest.fixture(scope="module")
def params_file(tmp_path_factory):
    return _params_with_track(tmp_path_factory.mktemp("params"))


@pytest.fixture(scope="module")
def params(params_file):
    return yaml.safe_load(params_file.read_text())


@pytest.fixture(scope="module")
def stages(params):
    return _stages(params)


@pytest.fixture(scope="module", params=["simulate", "replay"])
def simulate_foreach(request, params):
    """The ``foreach`` of simulate and of replay (params.yaml's ``methods``): both run on every
    trajectory, track's with track=on."""
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text(encoding="utf-8"))
    return _foreach(dvc["stages"][request.param]["foreach"], params)


# ------------------------------------------------------------------------ dvc.yaml agreement

_LAYOUT = Layout()
_STAGE_PATHS = {
    # dvc stage: (its data directory, its metrics tag)
    "scale_align": (_LAYOUT.scale_align.root, "scale_align"),
    "retarget@dexflow": (_LAYOUT.retarget("dexflow").root, "retarget_dexflow"),
    "retarget@position": (_LAYOUT.retarget("position").root, "retarget_position"),
    "contact": (_LAYOUT.contact.root, "contact"),
    "refine": (_LAYOUT.refine.root, "refine"),
    "track@refine": (_LAYOUT.track.root, "track_refine"),
    **{f"simulate@{t}": (_LAYOUT.simulate(t).root, f"simulate_{t}") for t in TRAJECTORIES},
    **{f"replay@{t}": (_LAYOUT.replay(t).root, f"replay_{t}") for t in TRAJECTORIES},
    "metrics": (_LAYOUT.metrics.root, "metrics"),
}


@pytest.mark.parametrize("stage", sorted(_STAGE_PATHS))
def test_stage_outputs_in_dvc_yaml_are_the_layouts(stages, stage):
    assert stage in stages, f"dvc.yaml has no stage {stage}"
    outs, metrics = stages[stage]
    root, tag = _STAGE_PATHS[stage]
    assert root in outs, f"{stage}: outs {outs} lack {root}"
    assert metrics == [Layout().stage_metrics(tag)]


def test_every_dvc_stage_data_output_is_checked(stages):
    # A new stage writing under data/ must be added to the agreement above (demo writes the input).
    data_outs = {
        stage
        for stage, (outs, _) in stages.items()
        for out in outs
        if out.parts[0] == "data" and out != Layout().data.root
    }
    assert data_outs == {*_STAGE_PATHS, "hand"}


def test_hand_stage_writes_the_layouts_hand_files_on_every_repro(stages):
    """Stage hand copies the model (it has no metrics) and runs on every ``dvc repro``: the
    model files it copies may lie outside the project, where DVC cannot hash them."""
    outs, metrics = stages["hand"]
    assert outs == [Layout().hand_files.root] and metrics == []
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text(encoding="utf-8"))
    assert dvc["stages"]["hand"]["always_changed"] is True
    loading = [s for s, spec in dvc["stages"].items() if "hand" in spec.get("do", spec)["params"]]
    for name in loading:  # every stage that loads the hand reads the copy
        assert "data/hand" in dvc["stages"][name].get("do", dvc["stages"][name])["deps"], name


def test_simulate_foreach_is_the_trajectories_by_label(simulate_foreach):
    assert set(simulate_foreach) == set(TRAJECTORIES)
    for label, trajectories in simulate_foreach.items():
        assert Path(trajectories) == Layout().trajectory(label).root
        assert trajectories == str(Layout().trajectory(label).root)


def test_metrics_stage_plots_lie_under_the_layouts_plots(stages):
    outs, _ = stages["metrics"]
    csvs = [out for out in outs if out.suffix == ".csv"]
    assert len(csvs) >= 1
    assert all(out.parent == Layout().plots for out in csvs), csvs
    assert set(outs) == {Layout().metrics.root, *csvs}


def test_report_stage_writes_the_layouts_summary_and_figures(stages):
    outs, _ = stages["report"]
    assert Layout().summary_report in outs
    others = [out for out in outs if out != Layout().summary_report]
    tables = [out for out in others if out.suffix == ".csv"]  # the summary's full tables
    assert tables and all(
        out == Layout().summary_table(out.stem.removeprefix("summary_")) for out in tables
    ), tables
    figures = [out for out in others if out not in tables]
    assert figures and all(out.parent == Layout().figures for out in figures), figures


def test_layout_paths_follow_its_root():
    root = Path("/project")
    layout = Layout(root)
    assert layout.scale_align.root == root / "data" / "scale_align"
    assert layout.simulate("refine").root == root / "data" / "simulate" / "refine"
    assert layout.replay("baseline").root == root / "data" / "replay" / "baseline"
    assert layout.stage_metrics("contact") == root / "reports" / "metrics" / "contact.json"
    assert layout.metrics_table == root / "data" / "metrics" / "sequences.csv"
    assert layout.hand_dir == root / "conf" / "hand"


# ---------------------------------------------------------------------------------- StageDir


@pytest.mark.parametrize(
    "name",
    ["walk", "walk.npz", "sequences/walk.npz", "/elsewhere/dir/walk.npz", Path("a/walk.npz")],
)
def test_sequence_is_the_stem_under_sequences(tmp_path, name):
    assert StageDir(tmp_path).sequence(name) == tmp_path / "sequences" / "walk.npz"


def test_sequence_files_refuses_an_empty_stage(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no \*\.npz"):
        StageDir(tmp_path).sequence_files()  # no sequences/ at all
    (tmp_path / "sequences").mkdir()
    (tmp_path / "sequences" / "notes.txt").write_text("not a sequence")
    with pytest.raises(FileNotFoundError):
        StageDir(tmp_path).sequence_files()
    assert StageDir(tmp_path).names() == []


def test_sequence_files_are_sorted_npz_files(tmp_path):
    stage = StageDir(tmp_path)
    stage.sequences_dir.mkdir()
    for name in ("c", "a", "b"):
        stage.sequence(name).write_bytes(b"")
    (stage.sequences_dir / "z.txt").write_text("ignored")
    assert stage.sequence_files() == [stage.sequence(n) for n in ("a", "b", "c")]
    assert stage.names() == ["a", "b", "c"]


def test_object_key_parses_the_scaled_mesh_path(tmp_path):
    stage = StageDir(tmp_path)
    assert stage.object_key("objects/mug_2/mesh.obj") == "mug_2"
    assert stage.object_of("objects/mug_2/mesh.obj").mesh == tmp_path / "objects/mug_2/mesh.obj"


@pytest.mark.parametrize(
    "obj_mesh",
    [
        "meshes/box.obj",
        "objects/box.obj",
        "objects/box/sub/mesh.obj",
        "/objects/box/mesh.obj",
        "other/box/mesh.obj",
        "",
        "objects/box/sdf.npz",
        "objects/../mesh.obj",
    ],
)
def test_object_key_refuses_anything_else(tmp_path, obj_mesh):
    with pytest.raises(ValueError, match=r"objects/<key>/mesh\.obj"):
        StageDir(tmp_path).object_key(obj_mesh)


# ------------------------------------------------------------------------------------ Layout


def test_trajectory_labels_map_to_their_stages():
    layout = Layout()
    assert layout.trajectory("baseline") == layout.retarget("position")
    assert layout.trajectory("retarget") == layout.retarget("dexflow")
    assert layout.trajectory("refine") == layout.refine


@pytest.mark.parametrize("label", ["dexflow", "position", "contact", ""])
def test_trajectory_refuses_an_unknown_label(label):
    with pytest.raises(ValueError, match="expected one of"):
        Layout().trajectory(label)


def test_absolute_data_root_is_used_as_is(tmp_path):
    assert Layout(Path("/project"), tmp_path).data.root == tmp_path
    assert Layout.of(tmp_path, "/project").data.root == tmp_path


def test_relative_data_root_is_under_the_project():
    assert Layout.of("data/mine", "/project").data.root == Path("/project/data/mine")
    assert Layout().data.root == Path("data/demo")


def test_of_puts_stage_dirs_under_root(tmp_path):
    layout = Layout.of("data/mine", tmp_path)
    assert layout.root == tmp_path
    assert layout.contact.root == tmp_path / "data" / "contact"
    assert layout.retarget("dexflow").root == tmp_path / "data" / "retarget" / "dexflow"
    assert layout.summary_report == tmp_path / "reports" / "summary.md"


# ------------------------------------------------------------------------------ project_root


def test_project_root_is_found_from_a_subdirectory(tmp_path, monkeypatch):
    project = tmp_path / "project"
    (project / "conf").mkdir(parents=True)
    (project / "conf" / "config.yaml").write_text("defaults: []\n")
    deep = project / "stages" / "sub"
    deep.mkdir(parents=True)
    monkeypatch.chdir(deep)
    assert project_root() == project.resolve()
    monkeypatch.chdir(project)
    assert project_root() == project.resolve()


def test_project_root_needs_the_config_file_not_just_conf(tmp_path, monkeypatch):
    (tmp_path / "conf").mkdir()
    monkeypatch.chdir(tmp_path)
    if any((p / "conf" / "config.yaml").is_file() for p in tmp_path.resolve().parents):
        pytest.skip("the temporary directory lies inside a project")
    with pytest.raises(ConfigError, match=r"conf/config\.yaml"):
        project_root()


def test_sequence_names_may_hold_dots(tmp_path):
    """``take.001`` is a name, not a stem and a suffix: its file is ``take.001.npz``, whether it
    is given as a name or as the path of that file."""
    stage = StageDir(tmp_path)
    assert stage.sequence("take.001") == tmp_path / "sequences" / "take.001.npz"
    assert (
        stage.sequence(tmp_path / "x" / "take.001.npz") == tmp_path / "sequences" / "take.001.npz"
    )
    assert stage.sequence("take.001") != stage.sequence("take.002")


def test_bench_runs_every_dvc_stage_in_dvc_order(stages, params_file, tmp_path):
    """`dexflow bench pipeline|real` time the pipeline that `dvc repro` runs: the same stages
    (``foreach`` items expanded), in the order dexflow.tools.sweep runs them (dvc.yaml's, a stage
    after those whose outputs it reads); only the report is left out."""
    from dvc.utils.serialize import load_yaml

    from dexflow.config import load_params
    from dexflow.pipeline.registry import load_stages
    from dexflow.tools.bench.pipeline import pipeline_stages

    params = load_params(params_file)  # track=on: every stage
    names = [name for name, _ in pipeline_stages(params, Layout.of("data", root=tmp_path))]
    dvc = yaml.safe_load((Path(__file__).parents[1] / "dvc.yaml").read_text())
    assert next(iter(dvc["stages"])) == "demo"  # ``stages`` leaves the demo out: no sequences
    assert sorted(names) == sorted(["demo", *(name for name in stages if name != "report")])
    root = Path(__file__).parents[1]
    order = [s.name for s in load_stages(root / "dvc.yaml", load_yaml(params_file))]
    assert names == [n.replace("demo@demo", "demo") for n in order if n != "report"]
