"""``dexflow hand init``: a complete hand config proposed from a bare URDF or MJCF model.

**Fingers** come from the kinematic tree: walking up from every joint towards the root, the
first frame with two or more moving branches is a branch point, and the subtree below it is a
finger; joints that reach the root without one (a wrist, which every finger passes) are extra
joints, and the palm is the lowest common ancestor of the branch points.

**Names** come from geometry at the zero pose (joints clamped into their limits). Per finger
``i``: its first joint ``b_i``, its tip ``t_i``, the direction ``d_i = (t_i - b_i) / |t_i - b_i|``
and the curl ``c_i``, how the tip moves when every joint with a one-sided range turns half way
to its far limit (the way the finger flexes). The thumb opposes the others most,

    thumb = argmax_i (1 - d_i · d̄_¬i) + (1 - ĉ_i · c̄_¬i) + 0.5 |b_i - b̄_¬i| / L,

with ``x̄_¬i`` the normalised mean over the other fingers and ``L`` the median finger length.
The others are ordered across the palm from the thumb's side: index, middle, ring, little.
With ``u`` the fingers' direction, ``a`` the across-palm direction towards the thumb and ``p``
the way the fingers curl (out of the palm), a right hand has ``(u × a) · p < 0``, as the human
canonical frame of :func:`dexflow.human.keypoints.wrist_frame` (z, y, x) has.

**Keypoints** follow each chain: joints closer together than 15 % of the finger's length are one
point (the distal one is kept); the last three points are the human base (MCP; the thumb's CMC),
middle (PIP; thumb MCP) and distal (DIP; thumb IP) joints. The tip is a leaf frame near the far
end of the distal link's collision geometry, or else that far end. The wrist is the end of the
palm's collision geometry away from the fingers, in line with the finger bases. The config
lists tips, middles, bases and the wrist; a chain with fewer than three joint points is no
human-like finger, and only its tip is listed.

**Scale**: the robot's hand length (wrist to middle fingertip) over the adult human one of
:mod:`dexflow.human.model`. **Couplings**: URDF ``<mimic>`` tags; MJCF joint equalities and
two-joint fixed tendons held at a constant length (by an equality or a tight limit; the proximal
joint leads).

**Left hands** are used as they are by default (``side: left, mirrored: false``): stage
scale_align mirrors every human hand of the other side, with its scene, to the robot's. With
``mirror=True`` a left model is written as its mirror image instead, a right hand
(:func:`mirror_model`, a URDF beside the yaml; ``side: left, mirrored: true``).

**One file** (about 550 lines): the method (its first paragraphs) and the proposal it describes, step by
step; the tree walk, the fingers, the mirror and the yaml each have their own module.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dexflow.errors import HandConfigError
from dexflow.hands.config_file import write_hand_yaml
from dexflow.hands.fingers import (
    Chain,
    find_chains,
    geometry_points,
    merged_points,
    name_fingers,
    trace_chain,
)
from dexflow.hands.mirror import mirror_model
from dexflow.hands.model import (
    load_kinematic_model,
    resolve_model_path,
)
from dexflow.hands.spec import CouplingSpec, FingerSpec, HandSpec, KeypointSpec
from dexflow.hands.tree import Kinematics, mjcf_root
from dexflow.human.keypoints import FINGER_KEYPOINTS, FINGERS, WRIST
from dexflow.human.model import forward_keypoints

__all__ = [
    "FingerProposal",
    "HandProposal",
    "init_hand",
    "mirror_model",
    "propose_hand",
    "write_hand_yaml",
]

# A chain shorter than this share of the median one is no finger (its joints: extra_joints).
_STUB_FRACTION = 0.25
# Slack of a limited two-joint MJCF tendon, in radians of its follower, below which it couples.
_TENDON_SLACK_RAD = 0.35


@dataclass
class FingerProposal:
    """One finger found in the tree.

    Attributes:
        name: thumb, index, middle, ring or little.
        root: First frame below the branch point.
        path: Frames from ``root`` to the distal link.
        joints: Actuated joints of the finger, in chain order.
        links: Links that may touch an object: those with collision geometry from the base
            keypoint's link on.
        keypoints: MANO index -> (link, offset in the link frame): every mapped point, the
            distal joint too, which the config leaves out.
        unmapped: Links of joint points not mapped: those proximal of the last three (e.g. a
            metacarpal joint), or all of them in a chain of fewer than three.
        tip_source: 'leaf' (a frame of the model), 'geometry' (the far end of the distal
            shapes) or 'guess' (no shape, no leaf).
    """

    name: str
    root: str
    path: list[str]
    joints: list[str]
    links: list[str]
    keypoints: dict[int, tuple[str, np.ndarray]]
    unmapped: list[str] = field(default_factory=list)
    tip_source: str = "leaf"


@dataclass
class HandProposal:
    """What ``hand init`` proposes for a model.

    Attributes:
        spec: The hand config.
        detected_side: The side the geometry shows: 'right', 'left', or '' for a
            mirror-symmetric hand.
        fingers: The fingers, thumb to little.
        palm: The link where the fingers meet.
        hand_length_m: Wrist to middle (or longest) fingertip at the zero pose.
        opposition: Per finger, its thumb score (the module docstring).
        guesses: (yaml section, sentence) for everything the model does not say.
        notes: Per yaml section, how it was derived.
    """

    spec: HandSpec
    detected_side: str
    fingers: list[FingerProposal]
    palm: str
    hand_length_m: float
    opposition: dict[str, float] = field(default_factory=dict)
    guesses: list[tuple[str, str]] = field(default_factory=list)
    notes: dict[str, str] = field(default_factory=dict)


# --------------------------------------------------------------------------------- keypoints


def _map_chain(chain: Chain, finger: str) -> tuple[dict[int, tuple[str, np.ndarray]], list, list]:
    """MANO index -> (link, world point) along a chain; joints left unmapped; guesses.

    The last three joint points are the human base, middle and distal joints; a chain with
    fewer is no human-like finger and only its tip is mapped.
    """
    base, middle, distal, tip = FINGER_KEYPOINTS[finger]
    points = merged_points(chain)
    mapped: dict[int, tuple[str, np.ndarray]] = {tip: chain.tip}
    guesses = []
    if len(points) >= 3:
        mapped |= dict(zip((base, middle, distal), points[-3:], strict=True))
        unmapped = [f for f, _ in points[:-3]]
    else:
        unmapped = [f for f, _ in points]
        guesses.append(
            (
                "keypoints",
                f"{finger}: {len(points)} joint point(s) along the chain, not a human finger's "
                f"three: only its tip is mapped ({unmapped} could stand for several human joints)",
            )
        )
    if chain.tip_source == "guess":
        guesses.append(
            (
                "keypoints",
                f"{finger}: '{chain.tip[0]}' has no collision geometry and no tip frame: the "
                "fingertip is guessed 0.8 x the previous segment beyond the last joint",
            )
        )
    return mapped, unmapped, guesses


def _written(finger: str, mapped) -> list[int]:
    """The MANO indices the config lists for a finger: base, middle and tip (not the distal
    joint: the tip and the middle already pose the last phalanges)."""
    base, middle, _, tip = FINGER_KEYPOINTS[finger]
    return [k for k in (base, middle, tip) if k in mapped]


def _wrist(
    kin: Kinematics,
    palm: str,
    chains: list[Chain],
    finger_bases: np.ndarray,
    finger_dir: np.ndarray,
    world: dict[str, np.ndarray],
) -> tuple[np.ndarray, str]:
    """The wrist point: where the palm's shapes end away from the fingers, in line with the
    centre of the finger bases (else the palm's origin, marked as a guess)."""
    rigid = {palm}
    if not kin.moving(palm):  # links fixed above the palm are palm too
        for f in reversed(kin.lineage(palm)[:-1]):
            rigid.add(f)
            if kin.moving(f):  # it turns against its parent: the palm ends here
                break
    in_fingers = {f for c in chains for f in c.frames}
    for f in list(rigid):
        rigid |= {d for d in kin.fixed_descendants(f) if d not in in_fingers}
    centre = finger_bases.mean(0)
    verts, _ = geometry_points(kin, rigid, world)
    reach = None if verts is None else float(((verts - centre) @ finger_dir).min())
    if reach is not None and reach < 0:
        return centre + reach * finger_dir, (
            f"the end of the palm's collision shapes away from the fingers, "
            f"{-reach * 1000:.0f} mm behind the finger bases"
        )
    return world[palm][:3, 3], ""


# -------------------------------------------------------------------------------- couplings


def _mimic_couplings(path: Path, joint_names: list[str]) -> list[CouplingSpec]:
    """Couplings from the ``<mimic>`` tags of a URDF."""
    found = {}
    for joint in ET.parse(path).getroot().iter("joint"):
        mimic = joint.find("mimic")
        if mimic is not None and joint.get("name") in joint_names:
            found[joint.get("name")] = CouplingSpec(
                joint.get("name"),
                mimic.get("joint"),
                float(mimic.get("multiplier", 1.0)),
                float(mimic.get("offset", 0.0)),
            )
    return [found[j] for j in joint_names if j in found]


def _mjcf_couplings(kin: Kinematics) -> list[CouplingSpec]:
    """Couplings from an MJCF: active joint equalities (their linear part), and fixed tendons of
    two joints held at a constant length by an equality or a tight limit (the proximal joint
    leads: ``c_f q_f + c_l q_l = L`` gives ``q_f = -c_l / c_f q_l + L / c_f``)."""
    m = kin.model.mj_model
    names = set(kin.joint_names)
    depth = {j: len(kin.lineage(kin.frame_of_joint[j])) for j in kin.joint_names}
    found: dict[str, CouplingSpec] = {}
    held: dict[int, float] = {}
    for e in range(m.neq):
        if not m.eq_active0[e]:
            continue
        if m.eq_type[e] == 2 and m.eq_obj2id[e] >= 0:  # q1 - q1_ref = c0 + c1 (q2 - q2_ref)
            j1, j2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
            follower, leader = m.joint(j1).name, m.joint(j2).name
            if follower in names and leader in names:
                c0, c1 = float(m.eq_data[e][0]), float(m.eq_data[e][1])
                ref1, ref2 = float(m.qpos0[m.jnt_qposadr[j1]]), float(m.qpos0[m.jnt_qposadr[j2]])
                found[follower] = CouplingSpec(follower, leader, c1, c0 + ref1 - c1 * ref2)
        elif m.eq_type[e] == 3 and m.eq_obj2id[e] < 0:  # a tendon's length held
            t = int(m.eq_obj1id[e])
            held[t] = float(m.eq_data[e][0]) + float(m.tendon_length0[t])
    for t in range(m.ntendon):
        adr, num = int(m.tendon_adr[t]), int(m.tendon_num[t])
        if num != 2 or any(int(m.wrap_type[adr + k]) != 1 for k in (0, 1)):  # fixed, 2 joints
            continue
        coef = {
            m.joint(int(m.wrap_objid[adr + k])).name: float(m.wrap_prm[adr + k]) for k in (0, 1)
        }
        if len(coef) != 2 or not set(coef) <= names:
            continue
        leader, follower = sorted(coef, key=lambda j: depth[j])
        if t in held:
            length = held[t]
        elif m.tendon_limited[t]:
            lo, hi = (float(v) for v in m.tendon_range[t])
            j = kin.joint_names.index(follower)
            span = float(kin.model.upper[j] - kin.model.lower[j])
            if (hi - lo) / abs(coef[follower]) > min(_TENDON_SLACK_RAD, 0.25 * span):
                continue
            length = (lo + hi) / 2
        else:
            continue
        found.setdefault(
            follower,
            CouplingSpec(follower, leader, -coef[leader] / coef[follower], length / coef[follower]),
        )
    return [found[j] for j in kin.joint_names if j in found]


# --------------------------------------------------------------------------------- propose


def propose_hand(
    model_path: str | Path,
    side: str | None = None,
    name: str = "",
    model_ref: str = "",
    root: str | None = None,
) -> HandProposal:
    """Read a model and propose its hand config, the model used as it is.

    Args:
        model_path: URDF (``.urdf``) or MJCF (``.xml``, ``.mjcf``) file.
        side: 'right' or 'left' if known; None to take the side the geometry shows.
        name: The hand's name (default: the model file's stem).
        model_ref: What the config's ``model`` says (default: ``model_path``).
        root: MJCF body the hand starts at (default: the deepest body above every joint).

    Returns:
        The proposal (``spec.mirrored`` False).

    Raises:
        HandConfigError: the model cannot be read, or does not hold 2 to 5 fingers.
    """
    if side not in (None, "right", "left"):
        raise HandConfigError(f"hand init: side must be 'right' or 'left', found {side!r}")
    path = Path(model_path)
    guesses: list[tuple[str, str]] = []
    notes: dict[str, str] = {}
    if path.suffix.lower() in (".xml", ".mjcf") and root is None:
        root, found = mjcf_root(path)
        guesses += found
    model = load_kinematic_model(path, root or "")
    kin = Kinematics(model)
    world = dict(zip(kin.frames, kin.transforms(kin.q0)[0], strict=True))

    chains, extra_joints, palm = find_chains(kin)
    for c in chains:
        trace_chain(kin, c, world)
    median = float(np.median([c.length for c in chains]))
    for c in [c for c in chains if c.length < _STUB_FRACTION * median]:
        guesses.append(
            (
                "extra_joints",
                f"the chain from '{c.root}' ({c.length * 1000:.0f} mm; {c.joints}) is too "
                "short for a finger: its joints are extra joints",
            )
        )
        extra_joints += c.joints
        chains.remove(c)
    if not 2 <= len(chains) <= len(FINGERS):
        raise HandConfigError(
            f"{path}: found {len(chains)} fingers (chains from {[c.root for c in chains]}); "
            f"a hand config has 2 to {len(FINGERS)}"
        )

    naming = name_fingers(kin, chains, side)
    guesses += naming.guesses
    detected = naming.detected_side
    if side is None:
        side = detected or "right"
        if not detected:
            guesses.append(("side", "the hand is about mirror-symmetric: taken as a right hand"))
    elif detected and detected != side:
        guesses.append(
            (
                "side",
                f"you said the model is a {side} hand, but its geometry shows a {detected} hand "
                f"(palm towards you, thumb on the {detected}); the config follows what you said",
            )
        )
    notes["side"] = f"geometry: {detected or 'mirror-symmetric'} hand" + (
        "" if side == detected else f"; taken as {side}"
    )

    inverse = {f: np.linalg.inv(world[f]) for f in kin.frames}

    def local(link: str, point: np.ndarray) -> np.ndarray:
        return np.round((inverse[link] @ np.append(point, 1.0))[:3], 6) + 0.0

    fingers = []
    for i, finger in sorted(naming.names.items(), key=lambda item: FINGERS.index(item[1])):
        c = chains[i]
        mapped, unmapped, found = _map_chain(c, finger)
        guesses += found
        base_link = mapped.get(FINGER_KEYPOINTS[finger][0], (c.points[0][0],))[0]
        before = set(c.path[: c.path.index(base_link)])
        links = [f for f in c.frames if f in kin.geometry_links and f not in before]
        fingers.append(
            FingerProposal(
                name=finger,
                root=c.root,
                path=c.path,
                joints=c.joints,
                links=links,
                keypoints={k: (link, local(link, p)) for k, (link, p) in sorted(mapped.items())},
                unmapped=unmapped,
                tip_source=c.tip_source,
            )
        )

    def world_point(link: str, offset: np.ndarray) -> np.ndarray:
        return (world[link] @ np.append(offset, 1.0))[:3]

    def base_point(chain: Chain) -> np.ndarray:  # the base joint, or the first one
        points = merged_points(chain)
        return points[-3 if len(points) >= 3 else 0][1]

    finger_bases = np.array(
        [base_point(c) for i, c in enumerate(chains) if naming.names[i] != "thumb"]
    )
    wrist, how = _wrist(kin, palm, chains, finger_bases, naming.finger_dir, world)
    if how:
        notes["wrist"] = how
    else:
        guesses.append(
            (
                "keypoints",
                f"the palm '{palm}' has no collision geometry behind the fingers: the wrist "
                "(MANO 0) is guessed at the palm link's origin",
            )
        )

    # Scale: hand length (wrist to the middle fingertip, or the longest finger's) vs a human's.
    reference = next((f for f in fingers if f.name == "middle"), None) or max(
        fingers[1:],
        key=lambda f: np.linalg.norm(world_point(*f.keypoints[max(f.keypoints)]) - wrist),
    )
    tip_k = FINGER_KEYPOINTS[reference.name][3]
    hand_length = float(np.linalg.norm(world_point(*reference.keypoints[tip_k]) - wrist))
    human = forward_keypoints(np.zeros(20))
    human_length = float(np.linalg.norm(human[tip_k] - human[WRIST]))
    notes["scale"] = (
        f"robot wrist to {reference.name} tip {hand_length * 1000:.0f} mm / adult human "
        f"{human_length * 1000:.0f} mm"
    )

    if model.format == "urdf":
        couplings = _mimic_couplings(path, kin.joint_names)
        notes["couplings"] = "from the URDF's <mimic> tags"
    else:
        couplings = _mjcf_couplings(kin)
        notes["couplings"] = (
            "from the MJCF: joint equalities, and two-joint fixed tendons held at a constant "
            "length (the proximal joint leads)"
        )

    keypoints = [
        KeypointSpec(f.keypoints[k][0], k, [float(v) for v in f.keypoints[k][1]])
        for f in fingers
        for k in _written(f.name, f.keypoints)
    ]
    keypoints.append(KeypointSpec(palm, WRIST, [float(v) for v in local(palm, wrist)]))
    keypoints.sort(key=lambda kp: _KEYPOINT_ORDER.index(kp.mano))

    # Links above the first wrist joint (a forearm, a mount) are no part of the hand's surface.
    trunk = kin.lineage(palm)
    first_moving = next((i for i, f in enumerate(trunk) if kin.moving(f)), None)
    surface_exclude = []
    if first_moving is not None:
        above = set(trunk[:first_moving])
        for f in trunk[:first_moving]:
            above |= set(kin.fixed_descendants(f))
        surface_exclude = [f for f in kin.frames if f in above and f in kin.geometry_links]
        if surface_exclude:
            notes["surface_exclude"] = "links above the wrist joints"

    spec = HandSpec(
        name=name or path.stem,
        model=model_ref or str(model_path),
        root=model.root if model.format == "mjcf" else "",
        scale=hand_length / human_length,
        keypoints=keypoints,
        fingers={f.name: FingerSpec(list(f.joints), list(f.links)) for f in fingers},
        extra_joints=[j for j in kin.joint_names if j in extra_joints],
        couplings=couplings,
        surface_exclude=surface_exclude,
        side=side,
        mirrored=False,
    )
    return HandProposal(
        spec=spec,
        detected_side=detected,
        fingers=fingers,
        palm=palm,
        hand_length_m=hand_length,
        opposition={naming.names[i]: float(s) for i, s in enumerate(naming.scores)},
        guesses=guesses,
        notes=notes,
    )


# Order of the config's keypoints: tips, middles, distals, bases, wrist (as conf/hand/*.yaml).
_KEYPOINT_ORDER = [
    *(ks[part] for part in (3, 1, 2, 0) for ks in FINGER_KEYPOINTS.values()),
    WRIST,
]


# ------------------------------------------------------------------------------------ init


def _model_ref(model: str, path: Path, out_dir: Path) -> str:
    """What the yaml's ``model`` says: ``pkg://`` kept; a path relative to the yaml when the
    model lies below the yaml's directory or both lie in the working directory; else absolute."""
    if model.startswith("pkg://"):
        return model
    cwd = Path.cwd().resolve()
    if path.is_relative_to(out_dir) or (path.is_relative_to(cwd) and out_dir.is_relative_to(cwd)):
        return Path(os.path.relpath(path, out_dir)).as_posix()
    return path.as_posix()


def init_hand(
    model: str | Path,
    out_path: str | Path,
    side: str | None = None,
    mirror: bool = False,
    name: str = "",
    overwrite: bool = False,
) -> HandProposal:
    """Propose a hand config for a model and write it (and, asked to, a left hand's mirror).

    Args:
        model: URDF or MJCF file, or ``pkg://<package>/<path>``.
        out_path: The hand yaml to write.
        side: 'right' or 'left' if known; None to take the side the geometry shows.
        mirror: Write a left hand as its mirror image, a right hand, beside the yaml (by
            default it is used as it is: scale_align mirrors right-hand sequences to it).
        name: The hand's name (default: the yaml's stem).
        overwrite: Replace an existing yaml.

    Returns:
        The proposal written (``spec.mirrored`` says whether the model was mirrored).

    Raises:
        HandConfigError: the model cannot be read, or the yaml exists and ``overwrite`` is off.
    """
    out_path = Path(out_path)
    if out_path.exists() and not overwrite:
        raise HandConfigError(f"{out_path} exists; pass --force to replace it")
    model = str(model)
    path = resolve_model_path(model)
    out_dir = out_path.parent.resolve()
    name = name or out_path.stem
    proposal = propose_hand(path, side, name, _model_ref(model, path, out_dir))
    if proposal.spec.side == "left" and mirror:
        source = proposal
        mirrored_path = mirror_model(
            load_kinematic_model(path, source.spec.root),
            out_dir / f"{name}_mirrored.urdf",
            source.spec.couplings,
        )
        proposal = propose_hand(mirrored_path, None, name, mirrored_path.name, root="")
        flipped = {"right": "left", "left": "right", "": ""}[source.detected_side]
        found = {f.name: f.joints for f in proposal.fingers}
        expected = {f.name: f.joints for f in source.fingers}
        if found != expected or proposal.detected_side != flipped:
            raise HandConfigError(
                f"{mirrored_path}: the mirror image of {path} reads differently: fingers "
                f"{found} vs {expected}, side {proposal.detected_side!r} vs {flipped!r}"
            )
        proposal.spec.side, proposal.spec.mirrored = "left", True
        proposal.spec.couplings = source.spec.couplings
        proposal.detected_side, proposal.guesses = source.detected_side, source.guesses
        proposal.notes["side"] = source.notes["side"]
        proposal.notes["couplings"] = source.notes["couplings"]
    write_hand_yaml(proposal, out_path, source=model)
    return proposal
