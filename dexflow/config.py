"""Pipeline parameters: dataclass schemas, composition of ``conf/`` into ``params.yaml``, loading.

``conf/`` (Hydra) is the source of truth. :func:`compose_params` writes ``params.yaml`` with DVC's
own Hydra composition (``dvc.utils.hydra.compose_and_dump``), so the file is byte-identical to
what ``dvc exp run`` writes. Stages call :func:`load_params`, which validates every section
against the schemas below and raises :class:`ConfigError` naming the key that is wrong.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dexflow.contact import ContactParams
from dexflow.data.demo import DemoConfig
from dexflow.errors import ConfigError
from dexflow.hands.spec import HandSpec as HandParams
from dexflow.metrics import MetricsParams
from dexflow.refine import RefineParams
from dexflow.retarget import RetargetParams
from dexflow.simulate import SimulateParams

__all__ = [
    "DATA_GENERATORS",
    "ConvexParams",
    "DataParams",
    "HandParams",
    "PipelineParams",
    "RunParams",
    "ScaleAlignParams",
    "compose_params",
    "load_params",
    "project_root",
]

# Stages of dvc.yaml that can write ``data.root`` (``data.generated_by`` names some of them).
DATA_GENERATORS = ("demo",)


def _require(condition: bool, key: str, expected: str, found: Any) -> None:
    if not condition:
        raise ConfigError(f"{key}: expected {expected}, found {found!r}")


@dataclass
class DataParams:
    """Input sequences (``data``): a directory in the canonical format, or the generated demo.

    Attributes:
        name: The data's name (``demo`` for the generated demo; reports say which data they are).
        root: Directory holding ``sequences/*.npz`` and the meshes they reference.
        generated_by: The pipeline stages that write ``root``: ``[demo]`` for the demo, ``[]``
            for your own data (``dvc.yaml``'s ``demo`` stage is a ``foreach`` over this list, so
            plain ``dvc repro`` on your data has no demo stage to run).
    """

    name: str = "demo"
    root: str = "data/demo"
    generated_by: list[str] = field(default_factory=lambda: ["demo"])

    def __post_init__(self) -> None:
        _require(bool(self.root), "data.root", "a directory", self.root)
        unknown = sorted(set(self.generated_by) - set(DATA_GENERATORS))
        _require(not unknown, "data.generated_by", f"stages among {list(DATA_GENERATORS)}", unknown)


def _validate_demo(d: DemoConfig) -> None:
    _require(d.fps > 0, "demo.fps", "> 0", d.fps)
    _require(
        2 <= d.min_frames <= d.max_frames,
        "demo.min_frames/max_frames",
        "2 <= min_frames <= max_frames",
        (d.min_frames, d.max_frames),
    )
    _require(
        d.sequences_per_object >= 1, "demo.sequences_per_object", ">= 1", d.sequences_per_object
    )
    _require(
        0 <= d.inside_fraction + d.hover_fraction <= 1,
        "demo.inside_fraction + hover_fraction",
        "within [0, 1]",
        d.inside_fraction + d.hover_fraction,
    )


def _validate_retarget(r: RetargetParams) -> None:
    _require(
        r.method in ("dexflow", "position"), "retarget.method", "'dexflow' or 'position'", r.method
    )
    modes = ("first_frame", "every_frame", "off")
    _require(
        r.global_search.mode in modes,
        "retarget.global_search.mode",
        " | ".join(modes),
        r.global_search.mode,
    )
    for key in ("alpha", "lambda_diff", "gamma_pred", "robust_delta_m", "lowpass_hz"):
        _require(getattr(r, key) >= 0, f"retarget.{key}", ">= 0", getattr(r, key))
    _require(r.window >= 0, "retarget.window", "0 (all frames) or a window length >= 1", r.window)
    _require(r.iterations >= 1, "retarget.iterations", ">= 1", r.iterations)
    import nlopt

    _require(
        hasattr(nlopt, r.global_search.algorithm),
        "retarget.global_search.algorithm",
        "an nlopt algorithm name such as GN_CRS2_LM",
        r.global_search.algorithm,
    )


@dataclass
class ConvexParams:
    """Convex decomposition of objects for simulation (CoACD)."""

    threshold: float = 0.1
    max_hulls: int = 16
    preprocess_resolution: int = 30
    mcts_iterations: int = 60
    mcts_max_depth: int = 2
    mcts_nodes: int = 10

    def __post_init__(self) -> None:
        _require(
            0 < self.threshold <= 1, "scale_align.convex.threshold", "within (0, 1]", self.threshold
        )


@dataclass
class ScaleAlignParams:
    """Stage ``scale_align`` (``scale_align``)."""

    sdf_spacing_m: float = 0.002
    sdf_padding_m: float = 0.03
    surface_samples: int = 4096
    convex: ConvexParams = field(default_factory=ConvexParams)

    def __post_init__(self) -> None:
        _require(
            0 < self.sdf_spacing_m <= 0.02,
            "scale_align.sdf_spacing_m",
            "a grid spacing in (0, 0.02] metres",
            self.sdf_spacing_m,
        )
        _require(self.sdf_padding_m >= 0, "scale_align.sdf_padding_m", ">= 0", self.sdf_padding_m)
        _require(
            self.surface_samples >= 16, "scale_align.surface_samples", ">= 16", self.surface_samples
        )


@dataclass
class RunParams:
    """How stages map over sequences (``run``; see ``conf/run/*.yaml``). Results do not depend
    on it.

    Attributes:
        backend: ``sequential`` (the stage's process), ``local`` (joblib processes) or ``ray``
            (Ray tasks; the ``ray`` extra).
        n_jobs: Processes (``local``) or Ray tasks in flight (``ray``); -1 = every core.
        address: ``ray`` only: None starts a local Ray with ``n_jobs`` CPUs; ``"auto"`` joins
            the cluster this machine is part of; ``"ray://<head>:10001"`` a remote one.
    """

    backend: str = "local"
    n_jobs: int = -1
    address: str | None = None

    def __post_init__(self) -> None:
        _require(
            self.backend in ("sequential", "local", "ray"),
            "run.backend",
            "'sequential', 'local' or 'ray'",
            self.backend,
        )
        _require(self.n_jobs == -1 or self.n_jobs >= 1, "run.n_jobs", "-1 or >= 1", self.n_jobs)
        _require(
            self.address is None or self.backend == "ray",
            "run.address",
            "null unless run.backend is 'ray'",
            self.address,
        )
        _require(
            self.address is None or bool(str(self.address).strip()),
            "run.address",
            "null (a local Ray), 'auto' or 'ray://<head>:10001'",
            self.address,
        )


@dataclass
class PipelineParams:
    """Everything in params.yaml."""

    seed: int = 0
    hand: HandParams = field(default_factory=HandParams)
    data: DataParams = field(default_factory=DataParams)
    demo: DemoConfig = field(default_factory=DemoConfig)
    scale_align: ScaleAlignParams = field(default_factory=ScaleAlignParams)
    retarget: RetargetParams = field(default_factory=RetargetParams)
    contact: ContactParams = field(default_factory=ContactParams)
    refine: RefineParams = field(default_factory=RefineParams)
    simulate: SimulateParams = field(default_factory=SimulateParams)
    metrics: MetricsParams = field(default_factory=MetricsParams)
    run: RunParams = field(default_factory=RunParams)


def project_root() -> Path:
    """The directory holding ``conf/`` and ``params.yaml`` (the current one, or a parent)."""
    here = Path.cwd().resolve()
    for candidate in (here, *here.parents):
        if (candidate / "conf" / "config.yaml").is_file():
            return candidate
    raise ConfigError(f"no conf/config.yaml in {here} or any parent: run dexflow from the project")


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
    _validate_demo(params.demo)
    _validate_retarget(params.retarget)
    c = params.contact
    _require(
        0 <= c.dis_min_m <= c.dis_max_m,
        "contact.dis_min_m/dis_max_m",
        "0 <= dis_min_m <= dis_max_m",
        (c.dis_min_m, c.dis_max_m),
    )
    _require(c.map_points >= 1, "contact.map_points", ">= 1", c.map_points)
    r = params.refine
    unknown = sorted(set(r.finger_order) - {"thumb", "index", "middle", "ring", "little"})
    _require(not unknown, "refine.finger_order", "finger names thumb..little", unknown)
    for key in ("w_dis", "w_pen", "w_align", "w_spen", "w_joints", "w_smooth", "learning_rate",
                "release_w_pen", "release_w_touch", "release_w_track", "release_w_smooth",
                "release_w_smooth_joints", "release_iterations"):  # fmt: skip
        _require(getattr(r, key) >= 0, f"refine.{key}", ">= 0", getattr(r, key))
    _validate_simulate(params.simulate)
    m = params.metrics
    for key in ("pd_violation_m", "spd_violation_m", "limit_tolerance_rad"):
        _require(getattr(m, key) >= 0, f"metrics.{key}", ">= 0", getattr(m, key))
    _require(m.kl_bins >= 2, "metrics.kl_bins", ">= 2", m.kl_bins)
    return params


def _validate_simulate(s: SimulateParams) -> None:
    for key in ("control_dt_s", "gravity", "object_mass_kg", "motor_force", "base_max_force"):
        _require(getattr(s, key) > 0, f"simulate.{key}", "> 0", getattr(s, key))
    non_negative = ("friction", "position_gain", "velocity_gain", "push_m", "contact_margin_m",
                    "penetration_tol_m", "max_displacement_m", "max_rotation_deg",
                    "drop_distance_m")  # fmt: skip
    for key in non_negative:
        _require(getattr(s, key) >= 0, f"simulate.{key}", ">= 0", getattr(s, key))
    for key in ("substeps", "control_steps", "stride"):
        _require(getattr(s, key) >= 1, f"simulate.{key}", ">= 1", getattr(s, key))
    for key in ("settle_steps", "max_frames"):
        _require(getattr(s, key) >= 0, f"simulate.{key}", ">= 0", getattr(s, key))
