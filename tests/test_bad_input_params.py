"""`dexflow params` and params.yaml: checked before written, one line naming the key, every
number range-checked by the schemas."""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import shutil
from pathlib import Path

import pytest

from dexflow.config import compose_params, load_params
from dexflow.errors import ConfigError
from dexflow.params import PipelineParams, validate

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def project(tmp_path) -> Path:
    """A copy of the project's conf/ and params.yaml."""
    shutil.copytree(ROOT / "conf", tmp_path / "conf")
    shutil.copy(ROOT / "params.yaml", tmp_path / "params.yaml")
    return tmp_path


@pytest.mark.parametrize(
    ("override", "words"),
    [
        ("retarget.jump_treshold_m=0.1", r"retarget\.jump_treshold_m: unknown key; did you mean "
         r"retarget\.jump_threshold_m\? the keys of retarget are method, alpha, "),
        ("retarget.global_search.mod=off", r"did you mean retarget\.global_search\.mode\?"),
        ("+colour=red", r"colour: unknown key; the keys of params\.yaml are seed, hand, "),
        ("hand=shadw", r"hand=shadw: no option 'shadw' in conf/hand/; available: allegro, shadow"),
        ("retarget.window=[1", r"retarget\.window=\[1: not a valid override .*key=value"),
        ("retarget.alpha=abc", r"retarget\.alpha: Value 'abc' .* could not be converted to Float"),
        ("retarget.jump_threshold_m=-0.08", r"retarget\.jump_threshold_m: expected > 0, found "),
        ("retarget.base_sigma_m=0", r"retarget\.base_sigma_m: expected > 0, found 0\.0"),
        ("contact.alpha=nan", r"contact\.alpha: expected a finite number, found nan"),
        ("demo.release_probability=2", r"demo\.release_probability: expected within \[0, 1\]"),
    ],
)  # fmt: skip
def test_a_rejected_value_is_one_line_and_never_reaches_params_yaml(project, override, words):
    target = project / "params.yaml"
    before = target.read_bytes()
    with pytest.raises(ConfigError, match=words) as info:
        compose_params([override], target, config_dir=project / "conf")
    assert "\n" not in str(info.value)
    assert target.read_bytes() == before
    assert sorted(p.name for p in project.iterdir()) == ["conf", "params.yaml"]  # no leftovers


def test_an_accepted_value_replaces_params_yaml(project):
    target = project / "params.yaml"
    compose_params(["retarget.jump_threshold_m=0.05"], target, config_dir=project / "conf")
    assert load_params(target).retarget.jump_threshold_m == 0.05


def test_a_hand_yaml_with_a_syntax_error_names_its_line(project):
    broken = project / "conf" / "hand" / "broken.yaml"
    broken.write_text((project / "conf" / "hand" / "allegro.yaml").read_text() + "scale: [1\n")
    with pytest.raises(ConfigError, match=rf"{broken}: line \d+, column \d+: YAML syntax error"):
        compose_params(["hand=broken"], project / "params.yaml", config_dir=project / "conf")


def test_a_typo_in_params_yaml_names_the_key(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("retarget:\n  jump_treshold_m: 0.1\n")
    with pytest.raises(ConfigError, match=r"did you mean retarget\.jump_threshold_m\?") as info:
        load_params(path)
    assert "\n" not in str(info.value)


def _numeric_leaves(obj, path: str = ""):
    """Dotted paths (``[i]`` for list items) of every number in the params."""
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            yield from _numeric_leaves(getattr(obj, f.name), f"{path}.{f.name}".lstrip("."))
    elif isinstance(obj, dict):
        for key, value in obj.items():
            yield from _numeric_leaves(value, f"{path}.{key}")
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            yield from _numeric_leaves(value, f"{path}[{i}]")
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield path


def _with(params: PipelineParams, path: str, value) -> PipelineParams:
    """A copy of ``params`` with the number at ``path`` set to ``value``."""
    params = copy.deepcopy(params)
    parts = re.findall(r"[^.\[\]]+|\[\d+\]", path)
    parents, node = [], params
    for part in parts[:-1]:
        parents.append(node)
        node = node[int(part[1:-1])] if part.startswith("[") else (
            node[part] if isinstance(node, dict) else getattr(node, part))  # fmt: skip
    last = parts[-1]
    if last.startswith("[") and isinstance(node, tuple):  # a (lo, hi) pair
        items = list(node)
        items[int(last[1:-1])] = value
        setattr(parents[-1], parts[-2], tuple(items))
    elif last.startswith("["):
        node[int(last[1:-1])] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        setattr(node, last, value)
    return params


# Numbers whose range is checked where their class is built (``__post_init__``), which
# ``validate`` alone does not run; tests/test_scale.py checks them.
CHECKED_ON_CONSTRUCTION = {"run.n_jobs"}


def test_every_numeric_param_is_range_checked_by_the_schemas():
    """Every number of params.yaml (the hand's too) rejects NaN and an absurd value, naming its
    key: a new parameter without a range check fails here."""
    params = load_params(ROOT / "params.yaml")
    leaves = [p for p in _numeric_leaves(params) if p not in CHECKED_ON_CONSTRUCTION]
    assert len(leaves) > 150
    unchecked = []
    for path in leaves:
        key = re.sub(r"\[\d+\]$", "", path)
        for bad in (-1e9, math.nan):
            try:
                validate(_with(params, path, bad))
            except ConfigError as exc:
                if key.split(".")[-1].split("[")[0] not in str(exc):
                    unchecked.append(f"{path}={bad}: the error names another key: {exc}")
            else:
                unchecked.append(f"{path}={bad} accepted")
    assert not unchecked, "\n".join(unchecked)
