"""A robot hand described as data: the schema of ``conf/hand/<name>.yaml``.

Everything about a hand that dexflow needs and its model file does not say: which links stand
for which human keypoints, the fingers (ordered thumb to little) with their joints and contact
links, joints tied by a tendon, the human-to-robot scale.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from dexflow.errors import ConfigError, HandConfigError
from dexflow.human.keypoints import FINGERS, NUM_KEYPOINTS

__all__ = [
    "MAX_YAML_ALIASES",
    "MAX_YAML_NODES",
    "CouplingSpec",
    "FingerSpec",
    "HandSpec",
    "KeypointSpec",
    "check_yaml_file",
    "load_hand_spec",
]

# A YAML file may hold at most this many aliases (``*name``), and expand to at most this many
# nodes with every alias replaced by what it names. Hand yamls and params.yaml use no alias and
# a few hundred nodes; a "billion laughs" document (lists of aliases of lists of aliases) of a
# few hundred bytes expands to billions, which OmegaConf builds one by one.
MAX_YAML_ALIASES = 100
MAX_YAML_NODES = 100_000


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


class _YamlRefused(Exception):
    """What is wrong with a YAML document :func:`check_yaml_file` refuses."""


class _AliasCountingLoader(yaml.SafeLoader):
    """A safe loader used only to compose (never construct) a document, refusing it at its
    :data:`MAX_YAML_ALIASES` + 1st alias."""

    def __init__(self, stream: object) -> None:
        super().__init__(stream)
        self.aliases = 0

    def compose_node(self, parent: yaml.Node | None, index: object) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_YAML_ALIASES:
                raise _YamlRefused(f"more than {MAX_YAML_ALIASES} aliases (*name)")
        return super().compose_node(parent, index)


def _expanded_nodes(node: yaml.Node) -> int:
    """How many nodes ``node`` is with every alias expanded, counted without expanding: each
    node's count is memoised, so shared (aliased) nodes cost one visit.

    Raises:
        _YamlRefused: over :data:`MAX_YAML_NODES`, or an alias inside the node it names.
    """
    counts: dict[int, int] = {}
    open_nodes: set[int] = set()

    def count(current: yaml.Node) -> int:
        key = id(current)
        if key in counts:
            return counts[key]
        if key in open_nodes:
            raise _YamlRefused("an alias inside the node it names (a recursive document)")
        open_nodes.add(key)
        if isinstance(current, yaml.MappingNode):
            children = [child for pair in current.value for child in pair]
        elif isinstance(current, yaml.SequenceNode):
            children = list(current.value)
        else:
            children = []
        total = 1 + sum(count(child) for child in children)
        if total > MAX_YAML_NODES:
            raise _YamlRefused(f"its aliases expand it to more than {MAX_YAML_NODES} nodes")
        open_nodes.discard(key)
        counts[key] = total
        return total

    return count(node)


def check_yaml_file(path: str | Path, error: type[ConfigError] = ConfigError) -> None:
    """Refuse a YAML file whose aliases would make loading it hang or exhaust memory.

    The document is composed (parsed into nodes, an alias pointing at the node it names) and
    never constructed, which takes time linear in the file's size; it is refused if it has
    more than :data:`MAX_YAML_ALIASES` aliases, would expand to more than
    :data:`MAX_YAML_NODES` nodes, names a node inside itself, or nests deeper than Python's
    recursion limit. Call it before ``OmegaConf.load``, which expands every alias. A syntax
    error is raised as the ``yaml.YAMLError`` loading would raise (the file opened the way
    OmegaConf opens it, so the message names the same path).

    Args:
        path: The YAML file.
        error: The exception to raise (:class:`HandConfigError` for a hand yaml).

    Raises:
        ConfigError: (``error``) the document is refused; the message names the file.
        yaml.YAMLError: the file is not valid YAML.
    """
    with open(os.path.abspath(path), encoding="utf-8") as stream:
        loader = _AliasCountingLoader(stream)
        try:
            node = loader.get_single_node()
            if node is not None:
                _expanded_nodes(node)
        except _YamlRefused as exc:
            raise error(f"{path}: YAML document refused: {exc}") from None
        except RecursionError:
            raise error(f"{path}: YAML document refused: nested too deeply") from None
        finally:
            loader.dispose()


def load_hand_spec(
    name_or_path: str | Path, conf_dir: str | Path | None = None
) -> tuple[HandSpec, Path]:
    """Load a hand yaml: a name in ``conf/hand/`` or a path to a yaml file.

    Returns:
        The validated spec and the directory relative model paths are resolved against.

    Raises:
        HandConfigError: the file is missing, has unknown keys or wrong types, or aliases that
            would expand it without bound (:func:`check_yaml_file`).
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
    check_yaml_file(path, HandConfigError)
    try:
        merged = OmegaConf.merge(OmegaConf.structured(HandSpec), OmegaConf.load(path))
        spec = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        raise HandConfigError(f"{path}: {exc}") from exc
    assert isinstance(spec, HandSpec)
    return spec, path.parent.resolve()
