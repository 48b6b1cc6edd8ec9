"""conf/ is the source of truth: params.yaml must equal its composition, and schemas catch typos."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from dexflow.config import (
    compose_params,
    infer_choices,
    load_params,
    params_header,
    recorded_overrides,
    without_header,
)
from dexflow.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (ROOT / "conf" / group).glob("*.yaml"))


def test_committed_params_equal_the_composition_of_conf(tmp_path):
    fresh = compose_params([], tmp_path / "params.yaml", config_dir=ROOT / "conf")
    assert recorded_overrides(ROOT / "params.yaml") in (None, [])
    assert fresh.read_text() == without_header((ROOT / "params.yaml").read_text()), (
        "params.yaml is stale: run `dexflow params` and commit it"
    )


@pytest.mark.parametrize(
    "override",
    [
        f"{group}={option}"
        for group in sorted(p.name for p in (ROOT / "conf").iterdir() if p.is_dir())
        if group != "experiment"
        for option in _options(group)
    ],
)
def test_every_group_option_composes_and_validates(tmp_path, override):
    params = load_params(compose_params([override], tmp_path / "p.yaml", config_dir=ROOT / "conf"))
    group, option = override.split("=")
    if group == "hand":
        assert params.hand.name == option


def test_the_full_demo_differs_from_the_default_only_in_its_size(tmp_path):
    """``demo=full`` keeps every setting of the default demo and makes 3 sequences per object
    (every grasp type each stand-in lists); the default makes 2."""
    import yaml

    from dexflow.data.ycb_standins import STANDINS

    trees = {
        option: _leaves(
            yaml.safe_load(compose_params([f"demo={option}"], tmp_path / f"{option}.yaml",
                                          config_dir=ROOT / "conf").read_text())
        )
        for option in ("default", "full")
    }  # fmt: skip
    changed = {k for k in trees["full"] if trees["full"][k] != trees["default"].get(k)}
    assert changed == {"demo.sequences_per_object"}
    assert trees["default"]["demo.sequences_per_object"] == 2
    assert trees["full"]["demo.sequences_per_object"] == max(
        len(s.grasps) for s in STANDINS.values()
    )


def _leaves(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out |= _leaves(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


@pytest.mark.parametrize("experiment", _options("experiment"))
def test_every_experiment_composes_validates_and_changes_what_it_names(tmp_path, experiment):
    """A named ablation (conf/experiment/*.yaml) composes into valid params that differ from
    the defaults exactly where the experiment file says (a typo'd key would fail to compose, a
    value equal to the default would ablate nothing)."""
    import yaml
    from omegaconf import OmegaConf

    text = (ROOT / "conf" / "experiment" / f"{experiment}.yaml").read_text()
    assert text.startswith("# @package _global_"), "a named experiment overrides global keys"
    path = compose_params(
        [f"experiment={experiment}"], tmp_path / "e.yaml", config_dir=ROOT / "conf"
    )
    load_params(path)  # validates every section
    composed = _leaves(yaml.safe_load(path.read_text()))
    default = _leaves(yaml.safe_load((ROOT / "params.yaml").read_text()))
    overrides = _leaves(OmegaConf.to_container(OmegaConf.create(text)))
    changed = {k for k in composed if composed[k] != default.get(k)}
    expected = {k for k in overrides if not k.startswith("defaults")}
    assert expected <= set(composed), (
        f"{experiment}: keys not in params: {expected - set(composed)}"
    )
    assert {k for k in expected if composed[k] != default[k]} == expected, (
        f"{experiment}: some keys equal the defaults"
    )
    assert changed >= expected
    groups = [next(iter(d)).split("/")[-1] for d in yaml.safe_load(text).get("defaults", [])]
    for group in groups:  # "override /hand: allegro": the hand section is another one
        assert any(k.startswith(f"{group}.") for k in changed), f"{experiment}: {group} unchanged"
    assert expected or groups, f"{experiment}: changes nothing"


def test_sweep_override_reaches_params(tmp_path):
    path = compose_params(
        ["scale_align.sdf_spacing_m=0.003", "seed=7"], tmp_path / "p.yaml", config_dir=ROOT / "conf"
    )
    params = load_params(path)
    assert params.scale_align.sdf_spacing_m == 0.003
    assert params.demo.seed == 7  # ${seed} interpolation resolved as DVC does


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("hand: {scale: -1.0}", "scale must be > 0"),
        ("hand: {fingertip_offsets: {pinky: 0.01}}", "pinky"),
        ("scale_align: {sdf_spacing_m: 0.5}", "scale_align.sdf_spacing_m"),
        ("scale_align: {sdf_spacing: 0.002}", "sdf_spacing"),
        ("run: {backend: slurm}", "run.backend"),
        ("demo: {fps: 0}", "demo.fps"),
        ("demo: {min_frames: 100, max_frames: 50}", "min_frames"),
        ("scale_align: {surface_samples: many}", "surface_samples"),
        ("track: {schedule_holds: [true]}", r"track.schedule_holds: expected .*'grasp'"),
    ],
)
def test_bad_params_name_the_key(tmp_path, text, words):
    path = tmp_path / "params.yaml"
    path.write_text(text + "\n")
    with pytest.raises(ConfigError, match=words):
        load_params(path)


def test_missing_params_file_says_how_to_make_it(tmp_path):
    with pytest.raises(ConfigError, match="dexflow params"):
        load_params(tmp_path / "params.yaml")


def test_dvc_config_enables_hydra_and_disables_analytics():
    text = (ROOT / ".dvc" / "config").read_text()
    assert "enabled = true" in text and "analytics = false" in text and "hardlink" in text


@pytest.mark.parametrize(("overrides", "demo"), [([], True), (["data=custom"], False)])
def test_dvc_has_a_demo_stage_only_where_the_data_is_the_demo(tmp_path, overrides, demo):
    compose_params(overrides, tmp_path / "params.yaml", config_dir=ROOT / "conf")
    shutil.copy(ROOT / "dvc.yaml", tmp_path / "dvc.yaml")
    env = {**os.environ, "DVC_NO_ANALYTICS": "1"}
    subprocess.run(["dvc", "init", "--no-scm", "-q"], cwd=tmp_path, check=True, env=env)
    listed = subprocess.run(
        ["dvc", "stage", "list", "--name-only"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert ("demo@demo" in listed) == demo == any(s.startswith("demo") for s in listed), listed
    assert {"scale_align", "retarget@dexflow", "refine", "report"} <= set(listed)


def test_params_check_keeps_the_choices_params_yaml_was_composed_with(
    tmp_path, monkeypatch, capsys
):
    """After `dexflow params data=generic`, --check composes with data=generic (recorded in
    params.yaml's first line): up to date until conf/data/generic.yaml changes, then its advice
    keeps the choice, and following it brings params.yaml up to date."""
    from dexflow.tools.cli import main

    shutil.copytree(ROOT / "conf", tmp_path / "conf")
    monkeypatch.chdir(tmp_path)
    params = tmp_path / "params.yaml"
    assert main(["params", "data=generic"]) == 0
    assert recorded_overrides(params) == ["data=generic"]
    assert load_params(params).data.name == "generic"
    capsys.readouterr()
    assert main(["params", "--check"]) == 0
    assert "up to date with conf/ composed with data=generic" in capsys.readouterr().out
    generic = tmp_path / "conf" / "data" / "generic.yaml"
    generic.write_text(generic.read_text().replace("root: data/generic", "root: data/mine"))
    assert main(["params", "--check"]) == 1
    out, err = capsys.readouterr()
    assert "+  root: data/mine" in out
    assert "run `dexflow params data=generic`" in err
    assert main(["params", "data=generic"]) == 0
    assert load_params(params).data.root == "data/mine"
    assert main(["params", "--check"]) == 0


def test_params_check_infers_the_choices_of_a_file_dvc_wrote(tmp_path):
    """`dvc exp run -S data=generic -S run=sequential` writes params.yaml without the comment:
    the choices are read from its sections, also once conf/data/generic.yaml has changed."""
    from dvc.utils.hydra import compose_and_dump

    conf = tmp_path / "conf"
    shutil.copytree(ROOT / "conf", conf)
    params = tmp_path / "params.yaml"
    compose_and_dump(
        params, str(conf), None, "config", str(tmp_path), ["data=generic", "run=sequential"]
    )
    assert recorded_overrides(params) is None
    assert infer_choices(params, config_dir=conf) == ["data=generic", "run=sequential"]
    generic = conf / "data" / "generic.yaml"
    generic.write_text(generic.read_text().replace("root: data/generic", "root: data/mine"))
    assert infer_choices(params, ["hand=shadow"], conf) == [
        "hand=shadow", "data=generic", "run=sequential"
    ]  # fmt: skip
    compose_and_dump(params, str(conf), None, "config", str(tmp_path), [])
    assert infer_choices(params, config_dir=conf) == []


def test_params_header_round_trips_its_overrides(tmp_path):
    overrides = ["data=generic", "data.root=my data/x", "+extra='a b'"]
    params = tmp_path / "params.yaml"
    params.write_text(params_header(overrides) + "seed: 0\n")
    assert recorded_overrides(params) == overrides
    assert without_header(params.read_text()) == "seed: 0\n"
    params.write_text("# Composed from conf/ by `dexflow params data.root='x`\nseed: 0\n")
    with pytest.raises(ConfigError, match=r"params.yaml: line 1: the recorded overrides"):
        recorded_overrides(params)


def test_dexflow_help_says_what_the_command_is_for(capsys):
    """`dexflow --help` names the product, says that `dvc repro` runs the pipeline, and lists
    every subcommand."""
    from dexflow.tools.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    text = capsys.readouterr().out
    assert "robot-hand trajectories" in text and "dvc repro" in text
    for command in (
        "params", "validate", "demo", "convert", "hand", "bench", "report", "view", "exp"
    ):  # fmt: skip
        assert command in text


def _subcommands(parser, prefix=()):
    """(command words, parser, its one-line help) of every subcommand, at every depth."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield (*prefix, name), sub, helps.get(name)
                yield from _subcommands(sub, (*prefix, name))


def test_every_subcommand_says_what_it_does():
    """`dexflow SUB --help` opens with a description of at least a sentence, and `dexflow
    --help` (or `dexflow hand --help`) lists each subcommand with a line of help."""
    from dexflow.tools.cli import build_parser

    found = list(_subcommands(build_parser()))
    assert len(found) >= 12, [words for words, _, _ in found]
    for words, parser, line in found:
        command = "dexflow " + " ".join(words)
        assert line, f"{command}: no line in the parent's list of subcommands"
        description = " ".join((parser.description or "").split())
        assert len(description) >= 40 and description.endswith("."), (
            f"{command} --help: no description (a sentence saying what it does): {description!r}"
        )
        shown = " ".join(parser.format_help().split())
        assert description[:60] in shown, f"{command} --help does not show its description"


def test_demo_command_takes_its_options_from_the_schema(tmp_path, capsys):
    """`dexflow demo` has no options of its own: the `demo` section's fields (help listing each
    with its conf/ default) and Hydra overrides of them, validated as params.yaml is."""
    import dataclasses

    from dexflow.params import DemoConfig
    from dexflow.tools.cli import main

    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    shown = capsys.readouterr().out
    for f in dataclasses.fields(DemoConfig):
        assert f"demo.{f.name}={getattr(DemoConfig(), f.name)}" in shown
    out = tmp_path / "demo"
    assert main(["demo", str(out), "demo.objects=[025_mug]", "demo.sequences_per_object=1"]) == 0
    assert [p.name for p in (out / "sequences").iterdir()] == ["025_mug__00_power.npz"]
    assert main(["demo", str(out), "demo.sequences_per_object=0"]) == 2
    assert "demo.sequences_per_object" in capsys.readouterr().err


def test_convert_options_come_from_their_dataclass():
    """Every field of ConvertOptions is an option of `dexflow convert`, described by its
    docstring; options not given keep the dataclass's defaults (written once, there)."""
    import dataclasses

    from dexflow.data.formats import ConvertOptions
    from dexflow.tools.cli import build_parser
    from dexflow.tools.cli.schema import options_from

    parser = build_parser()
    args = parser.parse_args(["convert", "ho3d", "src", "dst"])
    assert options_from(args, ConvertOptions) == ConvertOptions()
    args = parser.parse_args(
        [
            "convert",
            "grab",
            "src",
            "dst",
            "--jump-threshold-m",
            "0.05",
            "--side",
            "both",
            "--strict",
        ]
    )
    assert options_from(args, ConvertOptions) == ConvertOptions(
        jump_threshold_m=0.05, side="both", strict=True
    )
    shown = parser._subparsers._group_actions[0].choices["convert"].format_help()
    for f in dataclasses.fields(ConvertOptions):
        assert "--" + f.name.replace("_", "-") in shown
    shown = " ".join(shown.split())  # argparse wraps the help to the terminal
    assert "marks tracking loss" in shown and "(default: 0.08)" in shown
