"""A robot hand described as data: the schema of ``conf/hand/<name>.yaml``.

Everything about a hand that dexflow needs and its model file does not say: which links stand
for which human keypoints, the fingers (ordered thumb to little) with their joints and contact
links, joints tied by a tendon, the human-to-robot scale.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from dexflow.errors import HandConfigError
from dexflow.human.keypoints import FINGERS, NUM_KEYPOINTS

__all__ = [
    "CouplingSpec",
    "FingerSpec",
    "HandSpec",
    "KeypointSpec",
    "load_hand_spec",
]


@dataclass
class KeypointSpec:
    """A robot link (or MJCF site) matched to a human keypoint.

    Attributes:
        link: Link, body or site name in the model.
        mano: Index of the human keypoint (MANO order, 0 = wrist).
        offset: Point in the link frame, metres (default: the link origin).
    """

    link: str = ""
    mano: int = 0
    offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])


@dataclass
class FingerSpec:
    """One finger: the joints that move it and the links that may touch an object."""

    joints: list[str] = field(default_factory=list)
    links: list[str] = field(default_factory=list)


@dataclass
class CouplingSpec:
    """A joint tied to another: ``q[joint] = ratio * q[leader] + offset`` (e.g. a tendon)."""

    joint: str = ""
    leader: str = ""
    ratio: float = 1.0
    offset: float = 0.0


@dataclass
class HandSpec:
    """A robot hand (``hand`` in params.yaml; one file per hand in ``conf/hand/``).

    Attributes:
        name: Short name.
        model: URDF or MJCF file: a path (relative to the hand yaml or the working directory)
            or ``pkg://<package>/<path>`` for a file inside an installed Python package.
        root: Body or link where the hand starts (default: the model's root).
        scale: Human-to-robot size factor applied by scale_align.
        fingertip_offsets: Per finger, metres added along the human distal bone.
        keypoints: Robot links matched to human keypoints (retargeting targets).
        fingers: Fingers from thumb to little (a subset for hands with fewer fingers).
        extra_joints: Actuated joints in no finger (e.g. a wrist).
        couplings: Joints tied to others.
        surface_points: Points sampled on the collision geometry of the whole hand.
        surface_exclude: Links left out of the surface points (e.g. a forearm).
        side: The robot hand's side, 'right' or 'left' (scale_align mirrors human hands of
            the other side, with their scene, to the model's).
        mirrored: True if ``model`` is the mirror image (x -> -x) of the robot's own model, so
            of the other side than ``side`` (``dexflow hand init --mirror`` writes a left
            hand's mirror image, a right hand).
    """

    name: str = "hand"
    model: str = ""
    root: str = ""
    scale: float = 1.0
    fingertip_offsets: dict[str, float] = field(default_factory=lambda: dict.fromkeys(FINGERS, 0.0))
    keypoints: list[KeypointSpec] = field(default_factory=list)
    fingers: dict[str, FingerSpec] = field(default_factory=dict)
    extra_joints: list[str] = field(default_factory=list)
    couplings: list[CouplingSpec] = field(default_factory=list)
    surface_points: int = 2048
    surface_exclude: list[str] = field(default_factory=list)
    side: str = "right"
    mirrored: bool = False

    def __post_init__(self) -> None:
        where = f"hand '{self.name}'"
        if self.scale <= 0:
            raise HandConfigError(f"{where}: scale must be > 0, found {self.scale!r}")
        unknown = sorted(set(self.fingertip_offsets) - set(FINGERS))
        if unknown:
            raise HandConfigError(
                f"{where}: fingertip_offsets names unknown fingers {unknown}; known: {list(FINGERS)}"
            )
        order = [f for f in FINGERS if f in self.fingers]
        if list(self.fingers) != order or len(order) != len(self.fingers):
            raise HandConfigError(
                f"{where}: fingers must be named among {list(FINGERS)} and ordered thumb to "
                f"little, found {list(self.fingers)}"
            )
        for kp in self.keypoints:
            if not 0 <= kp.mano < NUM_KEYPOINTS:
                raise HandConfigError(
                    f"{where}: keypoint '{kp.link}' maps to MANO joint {kp.mano}; expected 0..20"
                )
            if len(kp.offset) != 3:
                raise HandConfigError(f"{where}: keypoint '{kp.link}' offset must be [x, y, z]")
        if self.surface_points < 1:
            raise HandConfigError(f"{where}: surface_points must be >= 1")
        if self.side not in ("right", "left"):
            raise HandConfigError(f"{where}: side must be 'right' or 'left', found {self.side!r}")

    @property
    def mano_indices(self) -> list[int]:
        return [kp.mano for kp in self.keypoints]


def load_hand_spec(
    name_or_path: str | Path, conf_dir: str | Path | None = None
) -> tuple[HandSpec, Path]:
    """Load a hand yaml: a name in ``conf/hand/`` or a path to a yaml file.

    Returns:
        The validated spec and the directory relative model paths are resolved against.

    Raises:
        HandConfigError: the file is missing, has unknown keys or wrong types.
    """
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        from dexflow.io.layout import project_root

        conf = Path(conf_dir) if conf_dir else project_root() / "conf"
        path = conf / "hand" / f"{name_or_path}.yaml"
        if not path.is_file():
            known = sorted(p.stem for p in (conf / "hand").glob("*.yaml"))
            raise HandConfigError(f"unknown hand '{name_or_path}'; known: {known} (or a yaml path)")
    if not path.is_file():
        raise HandConfigError(f"{path}: hand yaml not found")
    try:
        merged = OmegaConf.merge(OmegaConf.structured(HandSpec), OmegaConf.load(path))
        spec = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        raise HandConfigError(f"{path}: {exc}") from exc
    assert isinstance(spec, HandSpec)
    return spec, path.parent.resolve()
