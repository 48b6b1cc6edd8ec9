"""The stage registry: the stages of ``dvc.yaml``, each with its command, deps, params and
outputs, listed once.

``dvc.yaml`` is the one list of stages: DVC runs it, and :func:`load_stages` reads it for every
other runner (``dexflow-sweep`` and the ablation suite through
:func:`dexflow.tools.sweep.run_job`, ``dexflow bench pipeline`` and ``dexflow bench real``), so
the order, the deps and the outputs are never written a second time. A stage named ``<name>``
(``<name>@<item>`` for a ``foreach`` one) is run by the script ``stages/<name>.py``, which runs
the :class:`~dexflow.pipeline.runner.StageSpec` ``STAGE`` of the module
``dexflow.stages.<name>`` (:func:`stage_spec`); ``tests/test_registry.py`` checks that every stage
of ``dvc.yaml`` has both and that its deps are the files its script imports
(``tests/test_dvc_deps.py``). :mod:`dexflow.pipeline.executor` runs a registry stage.

A stage comes after the stages whose outputs it depends on; otherwise stages run in file order.
``foreach`` stages expand as DVC expands them (``retarget@dexflow``), ``${...}`` interpolates
from ``params.yaml``.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dvc.utils.serialize import load_yaml  # YAML 1.2 as DVC reads it: `1e-05` is a float

from dexflow.errors import ConfigError

if TYPE_CHECKING:
    from dexflow.pipeline.runner import StageSpec

__all__ = [
    "DVC_YAML",
    "METRICS_DIR",
    "Stage",
    "load_stages",
    "lookup",
    "overlaps",
    "pipeline_file",
    "stage_spec",
    "upstream_stages",
]

DVC_YAML = "dvc.yaml"
METRICS_DIR = "reports/metrics"  # as dexflow.io.layout has it
_INTERPOLATION = re.compile(r"\$\{([^}]+)\}")


def pipeline_file() -> Path:
    """dexflow's own ``dvc.yaml`` (beside the package, in a checkout)."""
    return Path(__file__).resolve().parents[2] / DVC_YAML


def stage_spec(name: str) -> StageSpec:
    """The :class:`~dexflow.pipeline.runner.StageSpec` that runs stage ``name`` of ``dvc.yaml``
    (``name@item`` or ``name``): ``dexflow.stages.<name>.STAGE``.

    Raises:
        ConfigError: no stage module of that name, or its ``STAGE`` is named otherwise.
    """
    base = name.partition("@")[0]
    try:
        module = importlib.import_module(f"dexflow.stages.{base}")
    except ModuleNotFoundError as exc:
        if exc.name != f"dexflow.stages.{base}":
            raise
        raise ConfigError(
            f"{DVC_YAML}: stage {base!r} is run by no module dexflow.stages.{base}"
        ) from None
    spec = getattr(module, "STAGE", None)
    if spec is None or spec.name != base:
        raise ConfigError(f"dexflow.stages.{base} defines no STAGE named {base!r}")
    return spec


@dataclass(frozen=True)
class Stage:
    """One stage of ``dvc.yaml`` (a ``foreach`` stage gives one per item: ``name@key``).

    Attributes:
        name: ``contact``, ``retarget@dexflow``.
        cmd: The command, interpolated.
        deps: Dependency paths, relative to the project.
        params: Dotted keys of ``params.yaml`` the stage reads (``hand``, ``contact.dis_min_m``).
        outs: Cached outputs (``outs``/``metrics``/``plots`` without ``cache: false``).
        copies: ``cache: false`` outputs (reports: small, one copy per job).
        persist: Outputs marked ``persist: true``: not deleted before the stage runs.
    """

    name: str
    cmd: str
    deps: tuple[str, ...] = ()
    params: tuple[str, ...] = ()
    outs: tuple[str, ...] = ()
    copies: tuple[str, ...] = ()
    persist: tuple[str, ...] = ()

    @property
    def outputs(self) -> tuple[str, ...]:
        return self.outs + self.copies

    @property
    def tag(self) -> str:
        """The name of its ``reports/metrics`` and ``reports/timing`` files: its metrics file's
        (``demo@demo`` writes ``demo.json``), else ``name@item`` -> ``name_item``."""
        for path in self.copies:
            rel = Path(path)
            if rel.parent == Path(METRICS_DIR) and rel.suffix == ".json":
                return rel.stem
        return self.name.replace("@", "_")


def lookup(context: Mapping[str, Any], dotted: str) -> Any:
    node: Any = context
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            raise KeyError(dotted)
        node = node[part]
    return node


def _interpolate(value: Any, context: Mapping[str, Any], where: str) -> Any:
    """``${item}``, ``${key}`` and ``${dotted.param}`` in strings, recursively."""
    if isinstance(value, list):
        return [_interpolate(v, context, where) for v in value]
    if isinstance(value, dict):
        return {
            _interpolate(k, context, where): _interpolate(v, context, where)
            for k, v in value.items()
        }
    if not isinstance(value, str):
        return value

    def substitute(match: re.Match) -> str:
        try:
            return str(lookup(context, match.group(1).strip()))
        except KeyError:
            raise ConfigError(
                f"dvc.yaml stage '{where}': cannot interpolate ${{{match.group(1)}}}: "
                "no such key in params.yaml"
            ) from None

    return _INTERPOLATION.sub(substitute, value)


def _paths(entries: list | None, where: str) -> tuple[list[str], list[str], list[str]]:
    """Cached, ``cache: false`` and ``persist: true`` paths of an ``outs``/``metrics``/``plots``
    list."""
    cached, uncached, persist = [], [], []
    for entry in entries or []:
        if isinstance(entry, str):
            entry = {entry: None}
        if not (isinstance(entry, dict) and len(entry) == 1):
            raise ConfigError(f"dvc.yaml stage '{where}': cannot read output entry {entry!r}")
        ((path, options),) = entry.items()
        options = options or {}
        (cached if options.get("cache", True) else uncached).append(str(path))
        if options.get("persist", False):
            persist.append(str(path))
    return cached, uncached, persist


def _param_keys(entries: list | None, where: str) -> tuple[str, ...]:
    keys: list[str] = []
    for entry in entries or []:
        if isinstance(entry, str):
            keys.append(entry)
        elif isinstance(entry, dict) and set(entry) == {"params.yaml"}:
            keys += list(entry["params.yaml"] or [])
        else:
            raise ConfigError(
                f"dvc.yaml stage '{where}': params {entry!r}: dexflow reads only params "
                "from params.yaml"
            )
    return tuple(keys)


def _stage(name: str, body: dict, context: Mapping[str, Any]) -> Stage:
    unsupported = sorted(set(body) - {"cmd", "deps", "params", "outs", "metrics", "plots", "desc",
                                      "meta", "always_changed", "frozen"})  # fmt: skip
    if unsupported:
        raise ConfigError(f"dvc.yaml stage '{name}': dexflow does not support {unsupported}")
    body = _interpolate(body, context, name)
    cmd = body.get("cmd")
    if isinstance(cmd, list):
        cmd = " && ".join(cmd)
    if not isinstance(cmd, str) or not cmd.strip():
        raise ConfigError(f"dvc.yaml stage '{name}': expected a cmd, found {cmd!r}")
    outs, copies, persist = [], [], []
    for key in ("outs", "metrics", "plots"):
        cached, uncached, persisted = _paths(body.get(key), name)
        outs += cached
        copies += uncached
        persist += persisted
    for path in outs + copies:
        if Path(path).is_absolute() or ".." in Path(path).parts:
            raise ConfigError(
                f"dvc.yaml stage '{name}': output {path!r} is outside the project; a sweep job "
                "can only hold outputs relative to it"
            )
    return Stage(
        name=name,
        cmd=cmd,
        deps=tuple(str(d) for d in body.get("deps") or []),
        params=_param_keys(body.get("params"), name),
        outs=tuple(outs),
        copies=tuple(copies),
        persist=tuple(persist),
    )


def load_stages(dvc_yaml: str | Path, params: Mapping[str, Any]) -> list[Stage]:
    """The stages of ``dvc.yaml``, ``foreach`` expanded, interpolated, in the order they run:
    file order, except that a stage waits for the stages whose outputs it depends on (refine
    reads replay@retarget, written by a ``foreach`` stage further down).

    Args:
        dvc_yaml: The pipeline file.
        params: The contents of ``params.yaml`` that ``${...}`` refers to.

    Returns:
        One :class:`Stage` per stage; a ``foreach`` over a list gives ``name@<item>``, over a
        dict ``name@<key>`` (as DVC names them).

    Raises:
        ConfigError: a construct dexflow does not read (``matrix``, ``vars``, ``wdir``,
            params from other files), or an interpolation with no such key.
    """
    spec = load_yaml(dvc_yaml) or {}
    if "vars" in spec:
        raise ConfigError(f"{dvc_yaml}: dexflow does not support top-level 'vars'")
    stages = []
    for name, body in (spec.get("stages") or {}).items():
        if "foreach" in body:
            items = body["foreach"]
            if isinstance(items, str):  # ``foreach: ${dotted.param}``: the list or dict itself
                whole = _INTERPOLATION.fullmatch(items.strip())
                if whole is None:
                    raise ConfigError(
                        f"dvc.yaml stage '{name}': foreach {items!r} is not a list, a dict or "
                        "one ${param}"
                    )
                try:
                    items = lookup(params, whole.group(1).strip())
                except KeyError:
                    raise ConfigError(
                        f"dvc.yaml stage '{name}': cannot interpolate {items}: no such key in "
                        "params.yaml"
                    ) from None
            pairs = items.items() if isinstance(items, dict) else ((i, i) for i in items)
            for key, item in pairs:
                context = {**params, "item": item, "key": key}
                stages.append(_stage(f"{name}@{key}", body["do"], context))
        else:
            stages.append(_stage(name, body, params))
    return _in_dependency_order(stages, dvc_yaml)


def _in_dependency_order(stages: list[Stage], where: str | Path) -> list[Stage]:
    """``stages`` reordered so that every stage comes after those whose outputs it depends on;
    otherwise in file order (the first stage that can run next runs next)."""
    producers = {s.name: {o.name for o in stages if _reads(s, o)} for s in stages}
    ordered: list[Stage] = []
    placed: set[str] = set()
    while len(ordered) < len(stages):
        ready = next((s for s in stages if s.name not in placed and producers[s.name] <= placed),
                     None)  # fmt: skip
        if ready is None:
            cycle = sorted(n for n in producers if n not in placed)
            raise ConfigError(f"{where}: the stages {cycle} depend on each other's outputs")
        ordered.append(ready)
        placed.add(ready.name)
    return ordered


def overlaps(a: str, b: str) -> bool:
    pa, pb = Path(a).parts, Path(b).parts
    n = min(len(pa), len(pb))
    return pa[:n] == pb[:n]


def _reads(stage: Stage, other: Stage) -> bool:
    """Whether ``stage`` depends on an output of ``other`` (a dep equal to, inside or containing
    one of them)."""
    return other is not stage and any(
        overlaps(dep, out) for dep in stage.deps for out in other.outputs
    )


def upstream_stages(stages: list[Stage]) -> dict[str, list[str]]:
    """For each stage, the earlier stages whose outputs it depends on (a dep equal to, inside
    or containing one of their outputs)."""
    upstream: dict[str, list[str]] = {}
    for i, stage in enumerate(stages):
        upstream[stage.name] = [other.name for other in stages[:i] if _reads(stage, other)]
    return upstream
