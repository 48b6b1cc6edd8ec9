"""Composition of ``conf/`` into ``params.yaml``, and loading it.

``conf/`` (Hydra) is the source of truth. :func:`compose_params` writes ``params.yaml`` with DVC's
own Hydra composition (``dvc.utils.hydra.compose_and_dump``), so the file is byte-identical to
what ``dvc exp run`` writes; it is composed beside the target and checked before it replaces
it, so a rejected value never reaches ``params.yaml``. Stages call :func:`load_params`, which
validates every section against the schemas of :mod:`dexflow.params`. Every error is one
:class:`ConfigError` line naming the key (with the keys or options allowed there) or the file,
line and column of a YAML syntax error. YAML files are checked before anything expands their
aliases (:func:`dexflow.hands.spec.check_yaml_file`): a "billion laughs" document in ``conf/``
or ``params.yaml`` is refused in milliseconds instead of hanging the composition.
"""

from __future__ import annotations

import dataclasses
import difflib
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

__all__ = ["compose_params", "load_params", "project_root", "yaml_error_message"]


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
