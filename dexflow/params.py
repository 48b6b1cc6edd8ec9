"""The pipeline's parameters: one dataclass schema per ``params.yaml`` section, and their checks.

A leaf module: it imports no stage, so every stage module, :mod:`dexflow.config` (which composes
``conf/`` into ``params.yaml`` and loads it) and the tools can import the schemas they need
without importing each other. Each attribute is documented in ``conf/<group>/*.yaml``, next to
its default; :func:`validate` raises :class:`~dexflow.errors.ConfigError` naming the key whose
value is out of range.

**Every default is written once**, in ``conf/`` (what ``dvc exp run`` and ``dexflow params``
compose): :func:`conf_defaults` gives each dataclass the values of its group's default file, so
``RefineParams()`` is ``conf/refine/default.yaml`` whatever the caller. A dataclass writes a
default itself only for a key its file does not have (``retarget.method``, set per stage
label; ``run.address``, for Ray only), and a key written in both places, a yaml key with no
field or a field with no default anywhere stops the import, naming it.

**One file** (about 880 lines): the schema of every conf/ group in one place, a dataclass per group in the
order of conf/, so that a reader finds every parameter, its type and its range where the stages read
them; the defaults themselves are only in conf/.
"""

from __future__ import annotations

import copy
import functools
import inspect
import math
import re
from dataclasses import Field, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import yaml

from dexflow.errors import ConfigError
from dexflow.hands.spec import HandSpec as HandParams
from dexflow.hands.spec import check_yaml_file

__all__ = [
    "DATA_GENERATORS",
    "ENGINES",
    "TRACK_HOLDS",
    "ContactParams",
    "ConvexParams",
    "DataParams",
    "DemoConfig",
    "GlobalSearchParams",
    "HandParams",
    "MetricsParams",
    "MujocoParams",
    "PerturbationParams",
    "PipelineParams",
    "RefineParams",
    "ReplayParams",
    "RetargetParams",
    "RunParams",
    "ScaleAlignParams",
    "SimulateParams",
    "validate",
]

# Stages of dvc.yaml that can write ``data.root`` (``data.generated_by`` names some of them).
DATA_GENERATORS = ("demo",)


def _require(condition: bool, key: str, expected: str, found: Any) -> None:
    if not condition:
        raise ConfigError(f"{key}: expected {expected}, found {found!r}")


def _check_numbers(section: Any, prefix: str, signed: tuple[str, ...] = ()) -> None:
    """Every number of a params section (nested sections, lists and pairs included) is finite
    and, unless its key is in ``signed``, >= 0: weights, distances, counts, rates and seeds
    all are. Stricter ranges are checked by name."""
    values = (
        {f.name: getattr(section, f.name) for f in fields(section)}
        if is_dataclass(section)
        else dict(section)
    )
    for name, value in values.items():
        key = f"{prefix}.{name}"
        if is_dataclass(value) or isinstance(value, dict):
            _check_numbers(value, key, signed)
            continue
        items = value if isinstance(value, (list, tuple)) else [value]
        for i, item in enumerate(items):
            if is_dataclass(item):  # e.g. the hand's keypoints and couplings
                _check_numbers(item, f"{key}[{i}]", signed)
            elif isinstance(item, (int, float)) and not isinstance(item, bool):
                _require(math.isfinite(item), key, "a finite number", value)
                _require(name in signed or item >= 0, key, ">= 0", value)


def _require_pair(pair: Any, key: str, positive: bool = False) -> None:
    """A ``[lo, hi]`` range: two numbers, ``lo <= hi`` (and ``lo > 0`` if ``positive``)."""
    ok = len(pair) == 2 and pair[0] <= pair[1] and (pair[0] > 0 or not positive)
    _require(ok, key, f"[lo, hi] with {'0 <' if positive else '0 <='} lo <= hi", list(pair))


CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
_REFERENCE = re.compile(r"\$\{(\w+)\}")


@functools.cache
def _conf_values(conf_dir: Path, relative: str) -> dict[str, Any]:
    """The keys of one ``conf/`` file, its Hydra ``defaults`` list left out and ``${key}``
    references to ``config.yaml``'s top level (the master ``seed``) resolved."""
    path = conf_dir / relative
    if not path.is_file():
        raise ImportError(
            f"{path}: missing; dexflow's defaults live in the project's conf/ (install dexflow "
            "from its source folder: pip install -e .)"
        )
    check_yaml_file(path)  # no alias bomb, as for every yaml dexflow reads
    values = yaml.safe_load(path.read_text()) or {}
    values.pop("defaults", None)
    top = values if relative == "config.yaml" else _conf_values(conf_dir, "config.yaml")

    def resolve(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: resolve(v) for k, v in value.items()}
        if isinstance(value, list):
            return [resolve(v) for v in value]
        whole = _REFERENCE.fullmatch(value) if isinstance(value, str) else None
        return top[whole.group(1)] if whole else value

    return resolve(values)


def _typed(value: Any, annotation: str) -> Any:
    """``value`` as the field's annotation has it: a float field's ``1`` is ``1.0``, a
    ``tuple[...]`` field's yaml list a tuple of its element types."""
    if annotation == "float" and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if annotation.startswith("tuple[") and isinstance(value, list):
        kinds = [k.strip() for k in annotation[len("tuple[") : -1].split(",")]
        return tuple(_typed(v, k) for v, k in zip(value, kinds, strict=True))
    return value


def conf_defaults(relative: str, key: str | None = None, conf_dir: Path | None = None):
    """Class decorator, under ``@dataclass``: the fields' defaults from ``conf/<relative>``
    (its sub-mapping ``key`` for a nested section), so that each default is written once.

    A field with a mapping there (a nested section) keeps its own ``field(default_factory=...)``
    of a dataclass decorated the same way; a list gets a fresh copy per instance.

    Raises:
        TypeError: at import, naming the class and key: a default written both in the file and
            in the class, a key of the file that is no field, or a field with no default.
    """

    def apply(cls: type) -> type:
        where = f"conf/{relative}" + (f" [{key}]" if key else "")
        values = _conf_values(conf_dir or CONF_DIR, relative)
        if key:
            values = values[key]
        annotations = inspect.get_annotations(cls)
        unknown = sorted(set(values) - set(annotations))
        if unknown:
            raise TypeError(f"{cls.__name__}: {where} has keys that are no field: {unknown}")
        for name, annotation in annotations.items():
            own = cls.__dict__.get(name, Field)  # Field: a sentinel for "none"
            nested = isinstance(own, Field) and callable(own.default_factory)
            if name not in values:
                if own is Field:
                    raise TypeError(f"{cls.__name__}.{name}: no default in {where} or the class")
                continue
            value = values[name]
            if isinstance(value, dict):
                if not nested:
                    raise TypeError(f"{cls.__name__}.{name}: {where} has a section here; the "
                                    "field needs field(default_factory=<its dataclass>)")  # fmt: skip
                continue
            if own is not Field:
                raise TypeError(f"{cls.__name__}.{name}: default written twice, in {where} "
                                "and in the class; keep the yaml's")  # fmt: skip
            value = _typed(value, str(annotation))
            if isinstance(value, list):
                value = field(default_factory=functools.partial(copy.deepcopy, value))
            setattr(cls, name, value)
        return cls

    return apply


@dataclass
@conf_defaults("data/demo.yaml")
class DataParams:
    """Input sequences (``data``): a directory in the canonical format, or the generated demo.

    Attributes:
        name: The data's name (``demo`` for the generated demo; reports say which data they are).
        root: Directory holding ``sequences/*.npz`` and the meshes they reference.
        generated_by: The pipeline stages that write ``root``: ``[demo]`` for the demo, ``[]``
            for your own data (``dvc.yaml``'s ``demo`` stage is a ``foreach`` over this list, so
            plain ``dvc repro`` on your data has no demo stage to run).
    """

    name: str
    root: str
    generated_by: list[str]

    def __post_init__(self) -> None:
        _require(bool(self.root), "data.root", "a directory", self.root)
        unknown = sorted(set(self.generated_by) - set(DATA_GENERATORS))
        _require(not unknown, "data.generated_by", f"stages among {list(DATA_GENERATORS)}", unknown)


@dataclass
@conf_defaults("demo/default.yaml")
class DemoConfig:
    """Size and realism of the demo dataset (``data.demo`` in params.yaml).

    Attributes:
        seed: Seed of everything random.
        objects: Stand-in names (keys of ``STANDINS``); empty means all.
        sequences_per_object: Sequences per object, cycling through its grasp types.
        fps: Frame rate, Hz.
        min_frames: Fewest frames in a sequence.
        max_frames: Most frames in a sequence.
        release_probability: Chance that a sequence ends by putting the object down.
        noise_std_m: Tracker noise per coordinate (white and drifting parts each), metres.
        inside_fraction: Share of contacting fingers annotated inside the object.
        inside_depth_m: Range of that penetration, metres.
        hover_fraction: Share of contacting fingers annotated hovering off the surface.
        hover_gap_m: Range of the hover gap, metres.
        hover_wobble_m: Amplitude of the slow wobble of a hovering finger, metres.
        dropout_bursts: Mean number of NaN bursts per sequence (Poisson).
        dropout_length: Range of frames per dropout burst.
        tracking_loss_probability: Chance of a burst of "teleported" frames in a sequence.
        tracking_loss_length: Range of frames per tracking-loss burst.
        tracking_loss_distance_m: Range of how far away the lost hand is reported.
        template_start_probability: Chance that a sequence starts with template frames.
        template_start_length: Range of frames of that run.
        template_end_probability: Chance that a sequence ends with template frames.
        template_end_length: Range of frames of that run.
        template_distance_m: Range of how far the template hand is from the real one.
        template_max_fraction: Most of a sequence that template runs may take together.
        hold_penetration_probability: Chance that the annotated hand sits too deep while holding.
        hold_penetration_m: Range of how far it is shifted into the object along its approach.
        hold_penetration_wobble_m: Amplitude of the slow wobble of that shift and of tip depths.
        tip_inside_probability: Chance that pressing fingertips are annotated inside the object.
        tip_depth_mean_m: Mean depth of the deepest fingertip keypoint (exponential), metres.
        tip_depth_max_m: Largest such depth, metres.
        rest_tilt_probability: Chance that a sequence's whole scene is recorded tilted, so that
            its object rests on an edge on a level table (as object rotations read by the
            wrong convention look; 0 by default: read right, real captures rest).
        rest_tilt_deg: Range of that tilt, degrees.
        spin_probability: Chance that a stand-in symmetric about an axis (the cans, the bowl) is
            annotated spinning about it while held (as a wrong rotation convention shows
            them; 0 by default).
        spin_rad: Range of that spin by the end of the hold, radians.
        hand_scale: Range of hand sizes (1 = average adult).
        contact_tolerance_m: Skin-to-surface distance that counts as ground-truth contact.
        sdf_spacing_m: Grid spacing of the signed distance used for synthesis.
    """

    seed: int
    objects: list[str]
    sequences_per_object: int
    fps: float
    min_frames: int
    max_frames: int
    release_probability: float
    noise_std_m: float
    inside_fraction: float
    inside_depth_m: tuple[float, float]
    hover_fraction: float
    hover_gap_m: tuple[float, float]
    hover_wobble_m: float
    dropout_bursts: float
    dropout_length: tuple[int, int]
    tracking_loss_probability: float
    tracking_loss_length: tuple[int, int]
    tracking_loss_distance_m: tuple[float, float]
    template_start_probability: float
    template_start_length: tuple[int, int]
    template_end_probability: float
    template_end_length: tuple[int, int]
    template_distance_m: tuple[float, float]
    template_max_fraction: float
    hold_penetration_probability: float
    hold_penetration_m: tuple[float, float]
    hold_penetration_wobble_m: float
    tip_inside_probability: float
    tip_depth_mean_m: float
    tip_depth_max_m: float

    def __post_init__(self) -> None:
        from dexflow.errors import ConfigError

        for key in ("template_start_probability", "template_end_probability",
                    "hold_penetration_probability", "tip_inside_probability",
                    "template_max_fraction"):  # fmt: skip
            value = getattr(self, key)
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"demo.{key}: expected within [0, 1], found {value!r}")
        for key in ("template_start_length", "template_end_length", "template_distance_m",
                    "hold_penetration_m"):  # fmt: skip
            lo, hi = getattr(self, key)
            if not 0 <= lo <= hi:
                raise ConfigError(f"demo.{key}: expected [lo, hi] with 0 <= lo <= hi, "
                                  f"found {[lo, hi]!r}")  # fmt: skip
        for key in ("tip_depth_mean_m", "tip_depth_max_m", "hold_penetration_wobble_m"):
            if getattr(self, key) < 0:
                raise ConfigError(f"demo.{key}: expected >= 0, found {getattr(self, key)!r}")

    rest_tilt_probability: float
    rest_tilt_deg: tuple[float, float]
    spin_probability: float
    spin_rad: tuple[float, float]
    hand_scale: tuple[float, float]
    contact_tolerance_m: float
    sdf_spacing_m: float


def _validate_demo(d: DemoConfig) -> None:
    _check_numbers(d, "demo")
    for key in ("release_probability", "inside_fraction", "hover_fraction",
                "tracking_loss_probability", "rest_tilt_probability",
                "spin_probability"):  # fmt: skip
        _require(getattr(d, key) <= 1, f"demo.{key}", "within [0, 1]", getattr(d, key))
    for key in ("inside_depth_m", "hover_gap_m", "dropout_length", "tracking_loss_length",
                "tracking_loss_distance_m", "rest_tilt_deg", "spin_rad"):  # fmt: skip
        _require_pair(getattr(d, key), f"demo.{key}")
    _require_pair(d.hand_scale, "demo.hand_scale", positive=True)
    _require(0 < d.sdf_spacing_m <= 0.02, "demo.sdf_spacing_m", "within (0, 0.02] metres",
             d.sdf_spacing_m)  # fmt: skip
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


@dataclass
@conf_defaults("scale_align/default.yaml", "convex")
class ConvexParams:
    """Convex decomposition of objects for simulation (CoACD)."""

    threshold: float
    max_hulls: int
    preprocess_resolution: int
    mcts_iterations: int
    mcts_max_depth: int
    mcts_nodes: int

    def __post_init__(self) -> None:
        _require(
            0 < self.threshold <= 1, "scale_align.convex.threshold", "within (0, 1]", self.threshold
        )


@dataclass
@conf_defaults("scale_align/default.yaml")
class ScaleAlignParams:
    """Stage ``scale_align`` (``scale_align``)."""

    sdf_spacing_m: float
    sdf_padding_m: float
    surface_samples: int
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
@conf_defaults("retarget/default.yaml", "global_search")
class GlobalSearchParams:
    """nlopt global search used for initialisation (paper: GN_CRS2_LM)."""

    mode: str
    algorithm: str
    max_evals: int
    seed: int


@dataclass
@conf_defaults("retarget/default.yaml")
class RetargetParams:
    """Stage ``retarget`` (``retarget`` in params.yaml). Weights are relative to metres²."""

    method: str = "dexflow"
    alpha: float
    lambda_diff: float
    gamma_pred: float
    window: int
    chunk_frames: int
    chunk_overlap: int
    base_sigma_m: float
    base_sigma_rad: float
    robust_delta_m: float
    iterations: int
    tolerance: float
    global_search: GlobalSearchParams = field(default_factory=GlobalSearchParams)
    recover_error_m: float
    recover_factor: float
    max_recoveries: int
    jump_threshold_m: float
    lowpass_hz: float


def _validate_retarget(r: RetargetParams) -> None:
    _require(
        r.method in ("dexflow", "position"), "retarget.method", "'dexflow' or 'position'", r.method
    )
    for key in ("base_sigma_m", "base_sigma_rad", "jump_threshold_m"):  # divisors, thresholds
        _require(getattr(r, key) > 0, f"retarget.{key}", "> 0", getattr(r, key))
    _require(r.global_search.max_evals >= 1, "retarget.global_search.max_evals", ">= 1",
             r.global_search.max_evals)  # fmt: skip
    _check_numbers(r, "retarget")
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
    _require(r.chunk_frames >= 0, "retarget.chunk_frames", ">= 0 (0: no chunks)", r.chunk_frames)
    if r.chunk_frames:
        _require(
            3 <= r.chunk_overlap < r.chunk_frames,
            "retarget.chunk_overlap",
            f"3 to chunk_frames - 1 = {r.chunk_frames - 1}",
            r.chunk_overlap,
        )
    _require(r.iterations >= 1, "retarget.iterations", ">= 1", r.iterations)
    import nlopt

    _require(
        hasattr(nlopt, r.global_search.algorithm),
        "retarget.global_search.algorithm",
        "an nlopt algorithm name such as GN_CRS2_LM",
        r.global_search.algorithm,
    )


@dataclass
@conf_defaults("contact/default.yaml")
class ContactParams:
    """Stage ``contact`` (``contact`` in params.yaml)."""

    dis_min_m: float
    dis_max_m: float
    alpha: float
    finger_speed_mps: float
    tau_c: float
    smoothing: bool
    guard: bool
    spline_tolerance_m: float
    beta1: float
    accel_tolerance_mps2: float
    v_max_mps: float
    map_points: int


# Stage refine's dvc.yaml dep ``${refine.grip_input}``: replay@retarget's folder when the grip
# reads it, else a folder refine depends on anyway (so that refine waits on no replay).
GRIP_INPUT = "data/replay/retarget"
# The trajectories the later stages compare (``methods`` in params.yaml: label -> folder, the
# ``foreach`` of stages simulate and replay); ``track=on`` adds ``track``: TRACK_OUTPUT.
METHODS = {
    "baseline": "data/retarget/position",
    "retarget": "data/retarget/dexflow",
    "refine": "data/refine",
}
TRACK_OUTPUT = "data/track"
NO_GRIP_INPUT = "data/contact"


@dataclass
@conf_defaults("refine/default.yaml")
class RefineParams:
    """Stage ``refine`` (``refine`` in params.yaml)."""

    finger_order: list[str]
    w_dis: float
    w_pen: float
    w_align: float
    w_spen: float
    w_joints: float
    w_tip: float
    w_smooth: float
    spen_delta_m: float
    pen_margin_m: float
    spen_points: int
    iterations: int
    learning_rate: float
    blend_frames: float
    refine_base: bool
    surface_tips: bool
    release: bool
    release_w_pen: float
    release_w_touch: float
    release_w_track: float
    release_tip_weight: float
    release_w_smooth: float
    release_w_smooth_joints: float
    release_w_joints: float
    release_iterations: int
    release_first_iterations: int
    release_rounds: int
    release_depth_m: float
    release_reach_m: float
    window_frames: int
    window_overlap: int
    grip_m: float
    grip_lead_frames: int
    grip_input: str


ENGINES = ("pybullet", "mujoco")


@dataclass
@conf_defaults("simulate/default.yaml", "mujoco")
class MujocoParams:
    """The MuJoCo grasp test (``simulate.mujoco``): DexGraspBench's published settings.

    Attributes:
        timestep_s: Physics time step (DexGraspBench: 0.004 s).
        impratio: Ratio of frictional to normal constraint impedance (10).
        kp: Position gain of every hand joint's actuator, N·m/rad (5).
        joint_damping: Damping of every hand joint, N·m·s/rad (added to the model's own).
        object_mass_kg: Object mass, uniform density over its convex parts (0.1 kg).
        friction: Sliding and torsional friction of every geom (0.6, 0.02), elliptic cones.
        force_scale: The pushes: a force of ``force_scale * object_mass_kg`` newtons along each
            of ±x, ±y, ±z (10, about the object's weight), gravity off.
        close_steps: Control steps from the pre-grasp to the grasp and from the grasp to the
            squeeze pose (10 each), ...
        steps_per_control: ... each this many physics steps (10).
        hold_checks: Checks of the object's pose while a force acts (10), ...
        steps_per_check: ... each after this many physics steps (50): 2 s per direction.
    """

    timestep_s: float
    impratio: float
    kp: float
    joint_damping: float
    object_mass_kg: float
    friction: tuple[float, float]
    force_scale: float
    close_steps: int
    steps_per_control: int
    hold_checks: int
    steps_per_check: int


@dataclass
@conf_defaults("simulate/default.yaml", "perturbations")
class PerturbationParams:
    """Robust success (``simulate.perturbations``): a frame succeeds only if it succeeds in the
    nominal test and under every one of ``count`` perturbed copies of it.

    Attributes:
        count: Perturbed trials per frame (0: the single nominal trial).
        position_m: Object offset of each trial, uniform in a ball of this radius.
        rotation_deg: Object rotation of each trial, about a random axis, up to this angle.
        friction_rel: Friction of each trial scaled by a factor within 1 ± this.
        seed: Seed of the perturbations (per frame: the same frame gets the same trials).
    """

    count: int
    position_m: float
    rotation_deg: float
    friction_rel: float
    seed: int


@dataclass
@conf_defaults("simulate/default.yaml")
class SimulateParams:
    """Stage ``simulate`` (``simulate`` in params.yaml).

    ``engines`` lists the physics engines that test every frame (the first one's result is the
    stage's SSR; with two, the report shows their per-frame agreement); ``mujoco`` holds the
    MuJoCo protocol's settings, the other fields pybullet's (``penetration_tol_m``, ``stride``,
    ``early_stop``, ``max_frames``, ``push_m``, ``contact_margin_m``, ``max_displacement_m``,
    ``max_rotation_deg`` apply to both).
    """

    engines: list[str]
    mujoco: MujocoParams = field(default_factory=MujocoParams)
    perturbations: PerturbationParams = field(default_factory=PerturbationParams)

    control_dt_s: float
    substeps: int
    control_steps: int
    gravity: float
    object_mass_kg: float
    friction: float
    motor_force: float
    position_gain: float
    velocity_gain: float
    base_max_force: float
    push_m: float
    contact_margin_m: float
    penetration_tol_m: float
    test_over_tolerance: bool
    max_displacement_m: float
    max_rotation_deg: float
    drop_distance_m: float
    early_exit: bool
    settle_steps: int
    stride: int
    early_stop: bool
    max_frames: int
    massless_link_mass_kg: float
    massless_link_inertia_kgm2: float


@dataclass
@conf_defaults("replay/default.yaml")
class ReplayParams:
    """Stage ``replay`` (``replay`` in params.yaml): the trajectory played back in MuJoCo with
    the object free under gravity (see :mod:`dexflow.stages.replay`).

    Attributes:
        lead_frames: Frames before the first contact the replay starts at (the hand approaches).
        substeps: Physics steps per recorded frame (time step ``1 / (fps * substeps)``).
        base_frequency_hz: Natural frequency of the base's six position servos (critically
            damped, velocity fed forward), from each axis's inertia.
        base_force_n: Force limit of each of the base's three translation servos.
        base_torque_nm: Torque limit of each of its three rotation servos.
        kp: Position gain of every finger joint's actuator, N·m/rad.
        joint_damping: Damping of every finger joint, N·m·s/rad (added to the model's own).
        joint_torque_nm: Torque limit of every finger actuator (0: unlimited).
        squeeze_m: Fingers in contact (stage contact's final states) get targets pushed this far
            into the object at the recorded pose (0: the recorded q as it is).
        object_mass_kg: Object mass, uniform density over its convex parts.
        friction: Sliding and torsional friction of every geom, elliptic cones.
        gravity: m/s², along -z of the world.
        max_position_error_m: SPIDER's success: the object's mean position error below this ...
        max_rotation_error_rad: ... and its mean rotation error below this.
        carried_fraction: The object is *carried* when its final position error is below
            ``max_position_error_m`` and below this fraction of the final error an object left
            where it was at the first contact would have (the recorded object's net
            displacement over the grasp); *success* needs SPIDER's criterion and carried.
        lost_position_m: The object is *lost* from the first frame its position error exceeds
            this (or its rotation error ``lost_rotation_rad``); time held is the time before.
        lost_rotation_rad: See ``lost_position_m``.
        release_distance_m: The scored window ends at the release: the first frame after the
            first contact out of contact where the recorded object is this far from where it
            was at the last contact, both in the world and in the recorded wrist's frame.
        support_tolerance_m: Not scored ("no support") when the lowest point of the recorded
            object moves up or down by more than this between the first frame and the first
            contact (nothing static held it where the replay's table is).
        free_fall_s: Not scored ("free fall") when, in the scored window, the recorded object's
            mean vertical acceleration over this long (s) ...
        free_fall_tolerance_mps2: ... is within this of ``-gravity`` (m/s²), and it moves
            ``release_distance_m`` away from the recorded hand meanwhile.
    """

    lead_frames: int
    substeps: int
    base_frequency_hz: float
    base_force_n: float
    base_torque_nm: float
    kp: float
    joint_damping: float
    joint_torque_nm: float
    squeeze_m: float
    object_mass_kg: float
    friction: tuple[float, float]
    gravity: float
    max_position_error_m: float
    max_rotation_error_rad: float
    carried_fraction: float
    lost_position_m: float
    lost_rotation_rad: float
    release_distance_m: float
    support_tolerance_m: float
    free_fall_s: float
    free_fall_tolerance_mps2: float


def _validate_replay(r: ReplayParams) -> None:
    _check_numbers(r, "replay")
    _require(r.substeps >= 1, "replay.substeps", ">= 1", r.substeps)
    for key in ("base_frequency_hz", "base_force_n", "base_torque_nm", "kp", "object_mass_kg",
                "max_position_error_m", "max_rotation_error_rad", "lost_position_m",
                "lost_rotation_rad", "release_distance_m", "support_tolerance_m", "free_fall_s",
                "free_fall_tolerance_mps2"):  # fmt: skip
        _require(getattr(r, key) > 0, f"replay.{key}", "> 0", getattr(r, key))
    _require(0 < r.carried_fraction <= 1, "replay.carried_fraction", "within (0, 1]",
             r.carried_fraction)  # fmt: skip
    _require(r.squeeze_m <= 0.02, "replay.squeeze_m", "within [0, 0.02] metres", r.squeeze_m)
    _require(len(r.friction) == 2, "replay.friction", "[sliding, torsional], both >= 0",
             r.friction)  # fmt: skip


# What stage track's grip schedules do from the lift on (TrackParams.schedule_holds).
TRACK_HOLDS = ("follow", "fingers", "grasp")


@dataclass
@conf_defaults("track/default.yaml")
class TrackParams:
    """Stage ``track`` (``track`` in params.yaml; off unless ``enabled``): the sampling MPC that
    makes the replay carry the object (see :mod:`dexflow.sim.track`).

    Attributes:
        after: The trajectories the stage starts from: ``[]`` (off: dvc.yaml has no stage
            track) or ``["refine"]`` (``track=on``: stage ``track@refine``).
        trajectories: The folder stage metrics reads for it: ``data/track`` when on, else
            ``data/refine`` (a dep of stage metrics anyway; dvc.yaml's deps cannot be optional).
        squeeze_m: Grip schedules: fingers in contact (stage contact) pushed this far into the
            object ...
        squeeze_reach_m: ... every hand link within this of it at its recorded pose.
        schedule_scales: Grid of schedules: times ``squeeze_m`` the fingers press, ...
        schedule_ramps: ... frames the press ramps in over, ...
        schedule_leads: ... ending this many frames before the lift, ...
        schedule_backoffs: ... the fingers held this times ``squeeze_m`` back until then, ...
        schedule_holds: ... and from the lift on (:data:`TRACK_HOLDS`): ``follow`` (the
            targets follow the refined trajectory), ``fingers`` (the fingers' targets kept as
            they are at the lift, the base following the refined trajectory) or ``grasp``
            (the fingers kept so and the base moved with the human fingertips' rigid motion:
            the grasp carried as one body, :func:`dexflow.sim.carry.grasp_carry`).
        carry_smooth_frames: The hold ``grasp``: the fingertips' rigid motion smoothed by a
            Gaussian of this many frames (0: as fitted).
        mpc: Run the receding-horizon search around the best schedule.
        horizon_frames: Frames each candidate is rolled out ahead.
        samples: Random perturbations of the plan per round and frame.
        iterations: Rounds per frame, each around the best so far with its spread halved.
        noise_base_m: Standard deviation of the base's translation offsets (m).
        noise_base_rad: ... of its rotation offsets (rad, each Euler angle).
        noise_finger_rad: ... of every finger joint's offsets (rad).
        prior_weight: Cost of leaving the schedule's targets per metre of base translation
            (base rotation counted 0.1 m/rad, the fingers' mean 0.05 m/rad).
        rotation_weight_m_per_rad: Object rotation error counted as this many metres per rad.
        contact_weight: Cost (m) of a frame where none of stage contact's fingers touch.
        tip_weight: Cost per metre the simulated fingertips are from the refined trajectory's
            (mean over fingertips and frames), in the search's rollouts and in the ranking of
            replays that are equal in success and carrying.
        object_guidance: Candidates with the base shifted by the object's position error.
    """

    after: list[str]
    trajectories: str
    squeeze_m: float
    squeeze_reach_m: float
    schedule_scales: list[float]
    schedule_ramps: list[int]
    schedule_leads: list[int]
    schedule_backoffs: list[float]
    schedule_holds: list[str]
    carry_smooth_frames: float
    mpc: bool
    horizon_frames: int
    samples: int
    iterations: int
    noise_base_m: float
    noise_base_rad: float
    noise_finger_rad: float
    prior_weight: float
    rotation_weight_m_per_rad: float
    contact_weight: float
    tip_weight: float
    object_guidance: bool

    @property
    def enabled(self) -> bool:
        return bool(self.after)


def _validate_track(t: TrackParams, methods: dict) -> None:
    _check_numbers(t, "track")
    for key in ("horizon_frames", "iterations"):
        _require(getattr(t, key) >= 1, f"track.{key}", ">= 1", getattr(t, key))
    for key in ("samples", "noise_base_m", "noise_base_rad", "noise_finger_rad", "prior_weight",
                "rotation_weight_m_per_rad", "contact_weight", "tip_weight", "squeeze_reach_m",
                "carry_smooth_frames"):  # fmt: skip
        _require(getattr(t, key) >= 0, f"track.{key}", ">= 0", getattr(t, key))
    holds = list(t.schedule_holds)
    _require(bool(holds) and set(holds) <= set(TRACK_HOLDS), "track.schedule_holds",
             f"a non-empty list of {list(TRACK_HOLDS)}", holds)  # fmt: skip
    for key in ("schedule_scales", "schedule_ramps", "schedule_leads", "schedule_backoffs"):
        values = list(getattr(t, key))
        _require(bool(values) and min(values) >= 0, f"track.{key}", "a non-empty list, >= 0",
                 values)  # fmt: skip
    _require(min(t.schedule_ramps) >= 1, "track.schedule_ramps", "frames >= 1", t.schedule_ramps)
    _require(0 <= t.squeeze_m <= 0.02, "track.squeeze_m", "within [0, 0.02] metres", t.squeeze_m)
    _require(list(t.after) in ([], ["refine"]), "track.after", "[] (off) or [refine]", t.after)
    on = {"trajectories": TRACK_OUTPUT, "methods": {**METHODS, "track": TRACK_OUTPUT}}
    off = {"trajectories": METHODS["refine"], "methods": dict(METHODS)}
    expected = on if t.enabled else off
    found = {"trajectories": t.trajectories, "methods": dict(methods)}
    for key, value in expected.items():
        _require(
            found[key] == value,
            "track.trajectories" if key == "trajectories" else "methods",
            f"{value} with track.after {list(t.after)} (`dexflow params track=on` or "
            "track=default sets all three)",
            found[key],
        )


def _validate_simulate(s: SimulateParams) -> None:
    unknown = [e for e in s.engines if e not in ENGINES]
    _require(bool(s.engines) and not unknown, "simulate.engines", f"engines among {list(ENGINES)}",
             s.engines)  # fmt: skip
    _require(len(set(s.engines)) == len(s.engines), "simulate.engines", "no repeats", s.engines)
    m = s.mujoco
    for key in ("timestep_s", "impratio", "kp", "object_mass_kg", "force_scale"):
        _require(getattr(m, key) > 0, f"simulate.mujoco.{key}", "> 0", getattr(m, key))
    _require(m.joint_damping >= 0, "simulate.mujoco.joint_damping", ">= 0", m.joint_damping)
    _require(len(m.friction) == 2 and min(m.friction) >= 0, "simulate.mujoco.friction",
             "[sliding, torsional], both >= 0", m.friction)  # fmt: skip
    for key in ("close_steps", "steps_per_control", "hold_checks", "steps_per_check"):
        _require(getattr(m, key) >= 1, f"simulate.mujoco.{key}", ">= 1", getattr(m, key))
    pt = s.perturbations
    _require(pt.count >= 0, "simulate.perturbations.count", ">= 0", pt.count)
    for key in ("position_m", "rotation_deg"):
        _require(getattr(pt, key) >= 0, f"simulate.perturbations.{key}", ">= 0", getattr(pt, key))
    _require(0 <= pt.friction_rel < 1, "simulate.perturbations.friction_rel", "within [0, 1)",
             pt.friction_rel)  # fmt: skip
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


@dataclass
@conf_defaults("metrics/default.yaml")
class MetricsParams:
    """Stage ``metrics`` (``metrics`` in params.yaml)."""

    pd_violation_m: float
    spd_violation_m: float
    limit_tolerance_rad: float
    kl_bins: int


@dataclass
@conf_defaults("run/local.yaml")
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

    backend: str
    n_jobs: int
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
@conf_defaults("config.yaml")
class PipelineParams:
    """Everything in params.yaml."""

    seed: int
    hand: HandParams = field(default_factory=HandParams)
    data: DataParams = field(default_factory=DataParams)
    demo: DemoConfig = field(default_factory=DemoConfig)
    scale_align: ScaleAlignParams = field(default_factory=ScaleAlignParams)
    retarget: RetargetParams = field(default_factory=RetargetParams)
    contact: ContactParams = field(default_factory=ContactParams)
    refine: RefineParams = field(default_factory=RefineParams)
    simulate: SimulateParams = field(default_factory=SimulateParams)
    replay: ReplayParams = field(default_factory=ReplayParams)
    metrics: MetricsParams = field(default_factory=MetricsParams)
    run: RunParams = field(default_factory=RunParams)
    track: TrackParams = field(default_factory=TrackParams)
    methods: dict[str, str] = field(default_factory=lambda: dict(METHODS))


def validate(params: PipelineParams) -> PipelineParams:
    """Check the ranges and cross-field rules the types cannot express.

    Raises:
        ConfigError: naming the first key whose value is wrong, what was expected and found.
    """
    _require(params.seed >= 0, "seed", ">= 0", params.seed)
    _check_numbers(params.hand, "hand", signed=("fingertip_offsets", "offset", "ratio"))
    for finger, offset in params.hand.fingertip_offsets.items():
        _require(abs(offset) <= 0.05, f"hand.fingertip_offsets.{finger}",
                 "within [-0.05, 0.05] metres", offset)  # fmt: skip
    for i, kp in enumerate(params.hand.keypoints):  # a point on a link: centimetres from it
        _require(max(map(abs, kp.offset)) <= 0.2, f"hand.keypoints[{i}].offset",
                 "[x, y, z] within [-0.2, 0.2] metres", kp.offset)  # fmt: skip
    for i, c in enumerate(params.hand.couplings):
        _require(abs(c.ratio) <= 10, f"hand.couplings[{i}].ratio", "within [-10, 10]", c.ratio)
        _require(abs(c.offset) <= 2 * math.pi, f"hand.couplings[{i}].offset",
                 "within [-2 pi, 2 pi] rad", c.offset)  # fmt: skip
    _validate_demo(params.demo)
    sa = params.scale_align
    _check_numbers(sa, "scale_align")
    for key in ("max_hulls", "preprocess_resolution", "mcts_iterations", "mcts_max_depth",
                "mcts_nodes"):  # fmt: skip
        value = getattr(sa.convex, key)
        _require(value >= 1, f"scale_align.convex.{key}", ">= 1", value)
    _validate_retarget(params.retarget)
    c = params.contact
    _check_numbers(c, "contact")
    _require(c.beta1 > 0, "contact.beta1", "> 0 (at 0 the contact probability is 0.5: never "
             "likely)", c.beta1)  # fmt: skip
    _require(
        0 <= c.dis_min_m <= c.dis_max_m,
        "contact.dis_min_m/dis_max_m",
        "0 <= dis_min_m <= dis_max_m",
        (c.dis_min_m, c.dis_max_m),
    )
    _require(c.map_points >= 1, "contact.map_points", ">= 1", c.map_points)
    r = params.refine
    _check_numbers(r, "refine")
    unknown = sorted(set(r.finger_order) - {"thumb", "index", "middle", "ring", "little"})
    _require(not unknown, "refine.finger_order", "finger names thumb..little", unknown)
    _require(r.spen_points >= 1, "refine.spen_points", ">= 1", r.spen_points)
    for key in ("w_dis", "w_pen", "w_align", "w_spen", "w_joints", "w_smooth", "learning_rate",
                "release_w_pen", "release_w_touch", "release_w_track", "release_tip_weight",
                "release_w_smooth", "release_w_smooth_joints", "release_w_joints",
                "release_iterations", "release_first_iterations",
                "release_depth_m", "release_reach_m"):  # fmt: skip
        _require(getattr(r, key) >= 0, f"refine.{key}", ">= 0", getattr(r, key))
    _require(r.release_rounds >= 1, "refine.release_rounds", ">= 1", r.release_rounds)
    _require(0 <= r.grip_m <= 0.02, "refine.grip_m", "within [0, 0.02] metres", r.grip_m)
    _require(r.grip_lead_frames >= 0, "refine.grip_lead_frames", ">= 0", r.grip_lead_frames)
    grip_input = GRIP_INPUT if r.grip_m > 0 else NO_GRIP_INPUT
    _require(
        r.grip_input == grip_input,
        "refine.grip_input",
        f"'{grip_input}' with refine.grip_m {r.grip_m:g} (stage refine's dvc.yaml dep: it waits on "
        "replay@retarget only when it reads it)",
        r.grip_input,
    )
    _require(
        r.release_reach_m > r.pen_margin_m,
        "refine.release_reach_m",
        f"> refine.pen_margin_m = {r.pen_margin_m} (points beyond it must add nothing)",
        r.release_reach_m,
    )
    _require(r.window_frames >= 0, "refine.window_frames", ">= 0 (0: no windows)", r.window_frames)
    if r.window_frames:
        _require(
            2 <= r.window_overlap <= r.window_frames // 2,
            "refine.window_overlap",
            f"2 to window_frames / 2 = {r.window_frames // 2}",
            r.window_overlap,
        )
    _check_numbers(params.simulate, "simulate")
    _validate_simulate(params.simulate)
    _validate_replay(params.replay)
    _validate_track(params.track, params.methods)
    m = params.metrics
    _check_numbers(m, "metrics")
    for key in ("pd_violation_m", "spd_violation_m", "limit_tolerance_rad"):
        _require(getattr(m, key) >= 0, f"metrics.{key}", ">= 0", getattr(m, key))
    _require(m.kl_bins >= 2, "metrics.kl_bins", ">= 2", m.kl_bins)
    return params
