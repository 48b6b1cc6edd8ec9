"""Every default is written once, in conf/: the params dataclasses take theirs from it
(dexflow.params.conf_defaults) and stop the import when a default is written twice."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import pytest
import yaml

from dexflow.config import compose_params
from dexflow.params import PipelineParams, conf_defaults


def _plain(value):
    """A dataclass tree as yaml would hold it (tuples as lists)."""
    if dataclasses.is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def test_the_dataclass_defaults_are_the_composed_conf(tmp_path):
    """PipelineParams() equals what `dexflow params` composes from conf/ with no override,
    section by section (the hand has its own yaml loader), values and types."""
    composed = yaml.safe_load(compose_params([], tmp_path / "params.yaml").read_text())
    defaults = _plain(PipelineParams())
    defaults.pop("hand"), composed.pop("hand")
    # keys the yaml leaves to the dataclass: set per stage label, or Ray only
    assert defaults["retarget"].pop("method") == "dexflow"
    assert defaults["run"].pop("address") is None
    assert defaults == composed
    # a float in the yaml stays a float (1.0e-04 is a float; 4 in a float field would be 4.0)
    assert type(PipelineParams().refine.w_joints) is float


def _conf(tmp_path, text: str):
    (tmp_path / "g").mkdir(exist_ok=True)
    (tmp_path / "config.yaml").write_text("seed: 7\n")
    (tmp_path / "g" / "default.yaml").write_text(text)
    return tmp_path


def test_defaults_come_from_the_file_typed_and_fresh(tmp_path):
    conf = _conf(tmp_path, "a: 1\nb: [1, 2]\npair: [1, 2]\nseed: ${seed}\nsub:\n  c: x\n")

    @dataclass
    @conf_defaults("g/default.yaml", "sub", conf_dir=conf)
    class Sub:
        c: str

    @dataclass
    @conf_defaults("g/default.yaml", conf_dir=conf)
    class Section:
        a: float
        b: list[int]
        pair: tuple[float, float]
        seed: int
        sub: Sub = field(default_factory=Sub)
        extra: str = "own"  # not in the yaml: the class's own default

    one, two = Section(), Section()
    assert (one.a, one.pair, one.seed, one.sub.c, one.extra) == (1.0, (1.0, 2.0), 7, "x", "own")
    assert type(one.a) is float and type(one.pair[0]) is float
    one.b.append(3)
    assert two.b == [1, 2]  # a fresh list per instance


@pytest.mark.parametrize(
    "text, fields_, message",
    [
        ("a: 1\n", {"a": 2}, "Section.a: default written twice, in conf/g/default.yaml"),
        (
            "a: 1\nb: 2\n",
            {"a": None},
            "Section: conf/g/default.yaml has keys that are no field: ['b']",
        ),
        (
            "b: 1\n",
            {"a": None, "b": None},
            "Section.a: no default in conf/g/default.yaml or the class",
        ),
        ("a:\n  x: 1\n", {"a": None}, "Section.a: conf/g/default.yaml has a section here"),
    ],
)
def test_a_default_not_written_exactly_once_stops_the_import(tmp_path, text, fields_, message):
    """fields_: name -> the class's own default (None: none)."""
    conf = _conf(tmp_path, text)
    body = {"__annotations__": {name: "int" for name in fields_}}
    body.update({name: value for name, value in fields_.items() if value is not None})
    with pytest.raises(TypeError) as raised:
        dataclass(conf_defaults("g/default.yaml", conf_dir=conf)(type("Section", (), body)))
    assert str(raised.value).startswith(message), raised.value
