"""Composition of ``conf/`` into ``params.yaml``, and loading it.

``conf/`` (Hydra) is the source of truth. :func:`compose_params` writes ``params.yaml`` with DVC's
own Hydra composition (``dvc.utils.hydra.compose_and_dump``), so the file is byte-identical to
what ``dvc exp run`` writes. Stages call :func:`load_params`, which validates every section
against the schemas of :mod:`dexflow.params` and raises :class:`ConfigError` naming the key that
is wrong.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dexflow.errors import ConfigError
from dexflow.io.layout import project_root
from dexflow.params import PipelineParams, validate

__all__ = ["compose_params", "load_params", "project_root"]


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

    root = project_root() if config_dir is None else Path(config_dir).resolve().parent
    config_dir = Path(config_dir or root / "conf").resolve()
    output = Path(output or root / "params.yaml")
    GlobalHydra.instance().clear()
    try:
        compose_and_dump(output, str(config_dir), None, "config", str(root), list(overrides or []))
    except OmegaConfBaseException as exc:
        raise ConfigError(f"composing {config_dir}: {exc}") from exc
    finally:
        GlobalHydra.instance().clear()
    load_params(output)  # fail now, not in a stage, if the composition breaks a schema
    return output


def load_params(path: str | Path = "params.yaml") -> PipelineParams:
    """Read and validate params.yaml.

    Raises:
        ConfigError: the file is missing, a key is unknown, or a value has the wrong type or range.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file; run `dexflow params` to compose it from conf/")
    try:
        raw = OmegaConf.load(path)
        merged = OmegaConf.merge(OmegaConf.structured(PipelineParams), raw)
        params = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        raise ConfigError(f"{path}: {exc}".strip()) from exc
    assert isinstance(params, PipelineParams)
    return validate(params)
