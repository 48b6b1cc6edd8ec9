"""Composition of ``conf/`` into ``params.yaml``, and loading it.

``conf/`` (Hydra) is the source of truth. :func:`compose_params` writes ``params.yaml`` with DVC's
own Hydra composition (``dvc.utils.hydra.compose_and_dump``), so the file is byte-identical to
what ``dvc exp run`` writes; it is composed beside the target and checked before it replaces
it, so a rejected value never reaches ``params.yaml``. ``dexflow params`` writes above it a
comment naming the overrides it was composed with (:func:`params_header`), so that ``dexflow
params --check`` composes ``conf/`` the same way; for a file without one (``dvc exp run``
writes none) :func:`infer_choices` finds the group choices its sections were composed with.
Stages call :func:`load_params`, which validates every section against the schemas of
:mod:`dexflow.params`. Every error is one :class:`ConfigError` line naming the key (with the
keys or options allowed there) or the file, line and column of a YAML syntax error. YAML files
are checked before anything expands their aliases (:func:`dexflow.hands.spec.check_yaml_file`):
a "billion laughs" document in ``conf/`` or ``params.yaml`` is refused in milliseconds instead
of hanging the composition.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import shlex
import typing
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dexflow.errors import ConfigError
from dexflow.hands.spec import check_yaml_file
from dexflow.io.atomic import atomic_path
from dexflow.io.layout import project_root
from dexflow.params import PipelineParams, validate

__all__ = [
    "compose_params",
    "infer_choices",
    "load_params",
    "params_header",
    "project_root",
    "recorded_overrides",
    "without_header",
    "yaml_error_message",
]

_HEADER = re.compile(r"^# Composed from conf/ by `dexflow params(?P<args>[^`]*)`")


def yaml_error_message(exc: yaml.YAMLError) -> str:
    """One line: the file, line and column of a YAML syntax error, and what is wrong there."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    context = getattr(exc, "context", None)
    if mark is None:
        return f"YAML syntax error: {problem}"
    where = f"{mark.name}: line {mark.line + 1}, column {mark.column + 1}"
    return f"{where}: YAML syntax error: {problem}" + (f" ({context})" if context else "")


def _unknown_key(key: str) -> str | None:
    """The message for a dotted key the schemas do not have (None if they have it, or if it
    lies below a free-form mapping such as ``hand.fingertip_offsets``)."""
    node: Any = PipelineParams
    parts = key.lstrip("+~").split(".")
    for i, part in enumerate(parts):
        if not (dataclasses.is_dataclass(node) and isinstance(node, type)):
            return None
        hints = typing.get_type_hints(node)
        known = [f.name for f in dataclasses.fields(node)]
        if part not in known:
            parent = ".".join(parts[:i])
            close = difflib.get_close_matches(part, known, n=1)
            hint = f"did you mean {'.'.join([*parts[:i], close[0]])}? " if close else ""
            return (
                f"{'.'.join(parts)}: unknown key; {hint}the keys of "
                f"{parent or 'params.yaml'} are {', '.join(known)}"
            )
        node = hints[part]
    return None


def _omegaconf_message(exc: OmegaConfBaseException) -> str:
    """One line from an OmegaConf error: the key, then what is wrong."""
    key = getattr(exc, "full_key", None)
    unknown = _unknown_key(key) if key else None
    if unknown and "not in" in str(exc):
        return unknown
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return f"{key}: {first}" if key else first


def _hydra_message(exc: Exception) -> str:
    """One line from a Hydra composition error."""
    from hydra.errors import MissingConfigException, OverrideParseException

    if isinstance(exc, MissingConfigException) and exc.missing_cfg_file:
        group, _, option = exc.missing_cfg_file.rpartition("/")
        if group and exc.options:
            return (
                f"{group}={option}: no option '{option}' in conf/{group}/; available: "
                f"{', '.join(exc.options)}"
            )
    if isinstance(exc, OverrideParseException):
        return (
            f"{exc.override}: not a valid override ({exc.message.splitlines()[0]}); "
            "expected key=value, e.g. retarget.alpha=0.001 or hand=allegro"
        )
    cause = exc.__cause__ or exc.__context__
    if isinstance(cause, OmegaConfBaseException):
        return _omegaconf_message(cause)
    return " ".join(str(exc).split("\n")[0].split()) or type(exc).__name__


def _check_yaml_files(config_dir: Path) -> None:
    """Refuse a yaml file of ``config_dir`` whose aliases would expand without bound, before
    Hydra reads any (it reads only those the composition selects, but which ones is known only
    as it goes). Syntax errors and unreadable files are left to Hydra, which reports them for the
    files it reads."""
    for file in sorted(config_dir.rglob("*.yaml")):
        try:
            check_yaml_file(file)
        except (yaml.YAMLError, UnicodeDecodeError, OSError):
            continue


def compose_params(
    overrides: list[str] | None = None,
    output: str | Path | None = None,
    config_dir: str | Path | None = None,
) -> Path:
    """Compose ``conf/`` with Hydra overrides and write it as DVC's Hydra integration would.

    Args:
        overrides: Hydra overrides, e.g. ``["hand=allegro", "scale_align.sdf_spacing_m=0.003"]``.
        output: File to write; ``params.yaml`` of the project by default.
        config_dir: The ``conf`` directory; the project's by default.

    Returns:
        The path written.
    """
    from dvc.utils.hydra import compose_and_dump
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException

    root = project_root() if config_dir is None else Path(config_dir).resolve().parent
    config_dir = Path(config_dir or root / "conf").resolve()
    output = Path(output or root / "params.yaml")
    overrides = list(overrides or [])
    groups = {p.name for p in config_dir.iterdir() if p.is_dir()}
    for override in overrides:  # a typo'd key, named before Hydra's own message
        key = override.split("=", 1)[0]
        if "=" not in override or key.startswith(("+", "~", "hydra")) or key in groups:
            continue  # added or deleted keys, Hydra's own, group choices: Hydra checks them
        if message := _unknown_key(key):
            raise ConfigError(message)
    _check_yaml_files(config_dir)
    GlobalHydra.instance().clear()
    try:
        # Composed beside the target and checked there: a rejected value never replaces it.
        with atomic_path(output) as tmp:
            compose_and_dump(tmp, str(config_dir), None, "config", str(root), overrides)
            _load(tmp, None)
    except OmegaConfBaseException as exc:
        raise ConfigError(f"composing {config_dir}: {_omegaconf_message(exc)}") from exc
    except HydraException as exc:
        raise ConfigError(_hydra_message(exc)) from exc
    except yaml.YAMLError as exc:
        raise ConfigError(yaml_error_message(exc)) from exc
    finally:
        GlobalHydra.instance().clear()
    return output


def params_header(overrides: list[str]) -> str:
    """The comment ``dexflow params`` writes above the composition: the overrides it was
    composed with (:func:`recorded_overrides` reads them back)."""
    command = shlex.join(["dexflow", "params", *overrides])
    return (
        f"# Composed from conf/ by `{command}`; `dexflow params --check` composes conf/ the same\n"
        "# way. `dvc exp run` recomposes this file with its own -S overrides only (no -S: the\n"
        "# defaults of conf/config.yaml), so set a lasting choice there.\n"
    )


def recorded_overrides(path: str | Path) -> list[str] | None:
    """The overrides :func:`params_header` recorded in ``path``; None if it records none.

    Raises:
        ConfigError: the comment is there but its overrides cannot be split (an edited quote).
    """
    with open(path, encoding="utf-8") as f:
        first = f.readline()
    found = _HEADER.match(first)
    if found is None:
        return None
    try:
        return shlex.split(found["args"])
    except ValueError as exc:
        raise ConfigError(
            f"{path}: line 1: the recorded overrides {found['args'].strip()!r} cannot be read "
            f"({exc}); expected `dexflow params KEY=VALUE ...` as `dexflow params` writes it"
        ) from exc


def without_header(text: str) -> str:
    """``params.yaml``'s text without the comment lines above its first key."""
    lines = text.splitlines(keepends=True)
    while lines and lines[0].startswith("#"):
        lines.pop(0)
    return "".join(lines)


def infer_choices(
    path: str | Path, overrides: list[str] | None = None, config_dir: str | Path | None = None
) -> list[str]:
    """The group choices (``data=generic``) that ``path``'s sections were composed with, for a
    file that records none (:func:`recorded_overrides`; ``dvc exp run -S data=generic`` writes
    none).

    Every section that differs from the composition of ``conf/`` with ``overrides`` is compared
    with the same composition choosing each other option of its group (``experiment``, whose
    files change several sections, is not tried): the option whose section differs in the
    fewest keys is chosen, if fewer than the default's (a section edited by hand, or composed
    from a ``conf/`` edited since, still shows its group's option).

    Args:
        path: A composed ``params.yaml``.
        overrides: Overrides known to apply (given on the command line).
        config_dir: The ``conf`` directory; the project's by default.

    Returns:
        ``overrides`` followed by one ``group=option`` per inferred choice.
    """
    config_dir = Path(config_dir or project_root() / "conf").resolve()
    overrides = list(overrides or [])
    check_yaml_file(path)
    current = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
    given = {o.split("=", 1)[0] for o in overrides}
    groups = sorted(
        p.name for p in config_dir.iterdir()
        if p.is_dir() and p.name != "experiment" and p.name not in given
    )  # fmt: skip
    options = {g: sorted(f.stem for f in (config_dir / g).glob("*.yaml")) for g in groups}
    (default,) = _compose_each(config_dir, [overrides])
    differ = [g for g in groups if len(options[g]) > 1 and current.get(g) != default.get(g)]
    tries = [(g, o) for g in differ for o in options[g]]
    composed = _compose_each(config_dir, [[*overrides, f"{g}={o}"] for g, o in tries])
    misses: dict[str, dict[str, int]] = {g: {} for g in differ}
    for (group, option), trial in zip(tries, composed, strict=True):
        misses[group][option] = _misses(trial.get(group), current.get(group))
    chosen = {}
    for group, by_option in misses.items():
        best = min(by_option, key=by_option.__getitem__)  # ties: the first by name
        if by_option[best] < _misses(default.get(group), current.get(group)):
            chosen[group] = best
    return overrides + [f"{g}={o}" for g, o in chosen.items()]


def _flat(tree, prefix: str = "") -> dict[str, Any]:
    if isinstance(tree, dict):
        return {
            k: v for key, value in tree.items() for k, v in _flat(value, f"{prefix}{key}.").items()
        }
    return {prefix.rstrip("."): tree}


def _misses(found, wanted) -> int:
    """How many leaf keys of two sections differ (present in one only, or with other values)."""
    found, wanted = _flat(found), _flat(wanted)
    absent = object()
    return sum(found.get(k, absent) != wanted.get(k, absent) for k in found.keys() | wanted.keys())


def _compose_each(config_dir: Path, override_sets: list[list[str]]) -> list[dict]:
    """``conf/`` composed with each list of overrides (resolved, as plain containers)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException

    _check_yaml_files(config_dir)
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(str(config_dir), version_base=None):
            return [
                OmegaConf.to_container(compose("config", overrides=o), resolve=True)
                for o in override_sets
            ]
    except OmegaConfBaseException as exc:
        raise ConfigError(f"composing {config_dir}: {_omegaconf_message(exc)}") from exc
    except HydraException as exc:
        raise ConfigError(_hydra_message(exc)) from exc
    finally:
        GlobalHydra.instance().clear()


def load_params(path: str | Path = "params.yaml") -> PipelineParams:
    """Read and validate params.yaml.

    Raises:
        ConfigError: the file is missing, a key is unknown, or a value has the wrong type or range.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file; run `dexflow params` to compose it from conf/")
    return _load(path, str(path))


def _load(path: Path, label: str | None) -> PipelineParams:
    """:func:`load_params` of an existing file; errors start with ``label`` if given."""
    prefix = f"{label}: " if label else ""
    try:
        check_yaml_file(path)
        raw = OmegaConf.load(path)
        merged = OmegaConf.merge(OmegaConf.structured(PipelineParams), raw)
        params = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        raise ConfigError(prefix + _omegaconf_message(exc)) from exc
    except yaml.YAMLError as exc:
        raise ConfigError(yaml_error_message(exc)) from exc
    assert isinstance(params, PipelineParams)
    try:
        return validate(params)
    except ConfigError as exc:
        raise ConfigError(prefix + str(exc)) from exc
