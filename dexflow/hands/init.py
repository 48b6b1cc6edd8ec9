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
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from dexflow.errors import HandConfigError
from dexflow.hands.model import (
    KinematicModel,
    _origin,
    load_kinematic_model,
    resolve_model_path,
)
from dexflow.hands.spec import CouplingSpec, FingerSpec, HandSpec, KeypointSpec
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

_MIRROR = np.diag([-1.0, 1.0, 1.0])
_MIRROR4 = np.diag([-1.0, 1.0, 1.0, 1.0])
# Joints of one finger closer than this share of the finger's length are one keypoint.
_MERGE_FRACTION = 0.15
# A chain shorter than this share of the median one is no finger (its joints: extra_joints).
_STUB_FRACTION = 0.25
# A leaf frame this close to the far end of the distal shapes (share of the last segment, at
# least _TIP_LEAF_MIN_M) is the fingertip.
_TIP_LEAF_FRACTION = 0.3
_TIP_LEAF_MIN_M = 0.01
# A joint turns towards its far limit when that is this many times farther than the near one.
_ONE_SIDED = 1.5
# Opposition scores closer than this leave the thumb a guess.
_THUMB_MARGIN = 0.15
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


# ------------------------------------------------------------------------------ kinematics


class _Kinematics:
    """A parsed model's tree and its forward kinematics in float64, in the root frame."""

    def __init__(self, model: KinematicModel) -> None:
        self.model = model
        self.chain = model.chain.to(dtype=torch.float64)
        self.joint_names = list(model.joint_names)
        self.frames = list(model.frames)  # parents before children
        self.parents = model.parents
        self.children: dict[str, list[str]] = {f: [] for f in self.frames}
        for name, (parent, _) in self.parents.items():
            if parent is not None:
                self.children[parent].append(name)
        self.frame_of_joint = {j: f for f, (_, j) in self.parents.items() if j is not None}
        self.geometry_links = {g.link for g in model.geometries}
        self.q0 = np.clip(np.zeros(len(self.joint_names)), model.lower, model.upper)
        self._indices = self.chain.get_frame_indices(*self.frames)

    def transforms(self, q: np.ndarray) -> np.ndarray:
        """(B, F, 4, 4) transforms of every frame (:attr:`frames` order) at ``q (B, J)``."""
        q = torch.as_tensor(np.atleast_2d(q), dtype=torch.float64)
        ret = self.chain.forward_kinematics(q, frame_indices=self._indices)
        return torch.stack([ret[f].get_matrix() for f in self.frames], dim=1).numpy()

    def joint(self, joint: str) -> tuple[str, np.ndarray]:
        """The joint's type and its axis in its child frame (which turns about the axis through
        its origin, or slides along it)."""
        j = self.chain.find_frame(self.frame_of_joint[joint]).joint
        return j.joint_type, j.axis.double().numpy()

    def moving(self, frame: str) -> bool:
        return self.parents[frame][1] is not None

    def subtree(self, frame: str) -> list[str]:
        out, stack = [], [frame]
        while stack:
            f = stack.pop()
            out.append(f)
            stack.extend(reversed(self.children[f]))
        return out

    def fixed_descendants(self, frame: str) -> list[str]:
        """Frames attached to ``frame`` through fixed joints only."""
        out, stack = [], list(self.children[frame])
        while stack:
            f = stack.pop()
            if not self.moving(f):
                out.append(f)
                stack.extend(self.children[f])
        return out

    def lineage(self, frame: str) -> list[str]:
        """Frames from the root down to ``frame``."""
        out = [frame]
        while self.parents[out[-1]][0] is not None:
            out.append(self.parents[out[-1]][0])
        return out[::-1]


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-12 else np.zeros_like(v)


def _mjcf_root(path: Path) -> tuple[str, list[tuple[str, str]]]:
    """The MJCF body the hand starts at: the deepest body with every hinge and slide joint
    strictly below it (a body's own joint moves it against its parent)."""
    import mujoco

    try:
        m = mujoco.MjModel.from_xml_path(str(path))
    except Exception as exc:
        raise HandConfigError(f"{path}: MuJoCo cannot compile the MJCF: {exc}") from exc
    joint_bodies = [int(m.jnt_bodyid[j]) for j in range(m.njnt) if m.jnt_type[j] in (2, 3)]
    if not joint_bodies:
        raise HandConfigError(f"{path}: the MJCF has no hinge or slide joint; nothing moves")

    def ancestors(body: int) -> list[int]:
        out = []
        while body != 0:
            body = int(m.body_parentid[body])
            out.append(body)
        return out  # parent first, the world last

    common = set.intersection(*(set(ancestors(b)) for b in joint_bodies))
    root = max(common, key=lambda b: len(ancestors(b)))
    guesses = []
    if root == 0:  # several moving things in the world: the one with the most joints
        counts: dict[int, int] = {}
        for body in joint_bodies:
            top = [body, *ancestors(body)][-2]
            counts[top] = counts.get(top, 0) + 1
        root = max(counts, key=lambda b: counts[b])
        skipped = sorted(m.body(b).name for b in counts if b != root)
        guesses.append(
            (
                "root",
                f"the MJCF holds several moving bodies; the hand is taken to be "
                f"'{m.body(root).name}' (the most joints), not {skipped}",
            )
        )
    return m.body(root).name, guesses


# ---------------------------------------------------------------------------------- chains


@dataclass
class _Chain:
    root: str
    frames: list[str]  # the subtree
    joints: list[str]
    path: list[str] = field(default_factory=list)  # root .. distal link
    points: list[tuple[str, np.ndarray]] = field(default_factory=list)  # moving frames, origins
    tip: tuple[str, np.ndarray] = ("", np.zeros(3))  # link, point
    tip_source: str = ""
    length: float = 0.0


def _find_chains(kin: _Kinematics) -> tuple[list[_Chain], list[str], str]:
    """Fingers (not yet named), joints in no finger, and the palm."""
    below: dict[str, bool] = {}  # a moving joint at or below the frame
    for f in reversed(kin.frames):
        below[f] = kin.moving(f) or any(below[c] for c in kin.children[f])
    roots: dict[str, str] = {}  # finger root -> its branch point
    extra = set()
    for joint in kin.joint_names:
        node = kin.frame_of_joint[joint]
        while True:
            parent = kin.parents[node][0]
            if parent is None:
                extra.add(joint)
                break
            if sum(below[c] for c in kin.children[parent]) >= 2:
                roots[node] = parent
                break
            node = parent
    chains = []
    for root in roots:
        frames = kin.subtree(root)
        inner = [r for r in roots if r != root and r in frames]
        if inner:  # a branch inside a finger: the joints above it are in no finger
            below_inner = {f for r in inner for f in kin.subtree(r)}
            extra |= {kin.parents[f][1] for f in frames if kin.moving(f)} - {
                kin.parents[f][1] for f in below_inner if kin.moving(f)
            }
            continue
        joints = [j for j in kin.joint_names if kin.frame_of_joint[j] in frames]
        chains.append(_Chain(root, frames, joints))
    if len(chains) < 2:
        raise HandConfigError(
            f"{kin.model.path}: found {len(chains)} finger(s) in the kinematic tree; a hand "
            "needs two or more chains of joints branching from a palm"
        )
    lines = [kin.lineage(roots[c.root]) for c in chains]
    palm = lines[0][0]
    for level in zip(*lines, strict=False):
        if len(set(level)) > 1:
            break
        palm = level[0]
    return chains, [j for j in kin.joint_names if j in extra], palm


def _geometry_points(kin: _Kinematics, links, world) -> tuple[np.ndarray | None, np.ndarray]:
    """World vertices and area-weighted centroid of the collision shapes of ``links``."""
    verts, centres, areas = [], [], []
    for g in kin.model.geometries:
        if g.link in links:
            t = world[g.link]
            verts.append(g.mesh.vertices @ t[:3, :3].T + t[:3, 3])
            centres.append(t[:3, :3] @ g.mesh.centroid + t[:3, 3])
            areas.append(g.mesh.area)
    if not verts:
        return None, np.zeros(3)
    return np.vstack(verts), np.average(centres, axis=0, weights=np.asarray(areas) + 1e-12)


def _trace_chain(kin: _Kinematics, chain: _Chain, world: dict[str, np.ndarray]) -> None:
    """The chain's path to its distal link, its joint points and its tip, at the zero pose."""
    depth = {chain.root: 1}
    for f in chain.frames[1:]:
        depth[f] = depth[kin.parents[f][0]] + kin.moving(f)
    first = world[chain.root][:3, 3]
    distal = max(
        (f for f in chain.frames if kin.moving(f)),
        key=lambda f: (depth[f], float(np.linalg.norm(world[f][:3, 3] - first))),
    )
    chain.path = kin.lineage(distal)[len(kin.lineage(chain.root)) - 1 :]
    chain.points = [(f, world[f][:3, 3]) for f in chain.path if kin.moving(f)]

    last = chain.points[-1][1]
    if len(chain.points) >= 2:
        along = _unit(last - chain.points[-2][1])
    else:
        along = _unit(last - world[kin.parents[chain.root][0]][:3, 3])
    rigid = [distal, *kin.fixed_descendants(distal)]
    verts, centre = _geometry_points(kin, rigid, world)
    far_end = None
    if verts is not None:
        reach = _unit(centre - last)
        reach = reach if reach.any() else along
        far_end = centre + reach * float(((verts - centre) @ reach).max())
    else:
        reach = along
    leaves = [f for f in rigid[1:] if not kin.children[f]]
    if leaves:
        leaf = max(leaves, key=lambda f: float((world[f][:3, 3] - last) @ reach))
        point = world[leaf][:3, 3]
        near = _TIP_LEAF_MIN_M
        if far_end is not None:
            near = max(near, _TIP_LEAF_FRACTION * float(np.linalg.norm(far_end - last)))
        if far_end is None or np.linalg.norm(point - far_end) <= near:
            chain.tip, chain.tip_source = (leaf, point), "leaf"
    if not chain.tip_source and far_end is not None:
        chain.tip, chain.tip_source = (distal, far_end), "geometry"
    elif not chain.tip_source:
        step = np.linalg.norm(last - chain.points[-2][1]) if len(chain.points) >= 2 else 0.02
        chain.tip, chain.tip_source = (distal, last + 0.8 * step * along), "guess"
    points = [p for _, p in chain.points] + [chain.tip[1]]
    chain.length = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def _merged_points(chain: _Chain) -> list[tuple[str, np.ndarray]]:
    """Joint points, those closer than a share of the finger's length to the first of their
    group merged into the group's distal one."""
    groups: list[list[tuple[str, np.ndarray]]] = []
    for point in chain.points:
        if groups and np.linalg.norm(point[1] - groups[-1][0][1]) < (
            _MERGE_FRACTION * chain.length
        ):
            groups[-1].append(point)
        else:
            groups.append([point])
    return [g[-1] for g in groups]


# ------------------------------------------------------------------------------------ names


def _tips_at(kin: _Kinematics, chains: list[_Chain], q: np.ndarray) -> np.ndarray:
    """(B, C, 3) every chain's tip point at configurations ``q (B, J)``."""
    index = {f: i for i, f in enumerate(kin.frames)}
    zero = kin.transforms(kin.q0)[0]
    t = kin.transforms(q)
    out = []
    for c in chains:
        link, point = c.tip
        local = np.linalg.inv(zero[index[link]]) @ np.append(point, 1.0)
        out.append(t[:, index[link]] @ local)
    return np.stack(out, axis=1)[..., :3]


def _curls(kin: _Kinematics, chains: list[_Chain]) -> np.ndarray:
    """(C, 3) tip motion of each chain when its one-sided joints turn half way to their far
    limit; zero for a chain without one."""
    lower, upper = kin.model.lower, kin.model.upper
    q = np.tile(kin.q0, (len(chains) + 1, 1))
    for i, c in enumerate(chains):
        for name in c.joints:
            j = kin.joint_names.index(name)
            down, up = kin.q0[j] - lower[j], upper[j] - kin.q0[j]
            if up > _ONE_SIDED * down and up > 0.1:
                q[i + 1, j] += 0.5 * up
            elif down > _ONE_SIDED * up and down > 0.1:
                q[i + 1, j] -= 0.5 * down
    tips = _tips_at(kin, chains, q)
    return np.stack([tips[i + 1, i] - tips[0, i] for i in range(len(chains))])


def _opposition(bases, directions, curls, length: float) -> np.ndarray:
    """(C,) how much each chain opposes the others (the thumb score of the module docstring)."""
    scores = []
    for i in range(len(bases)):
        others = [j for j in range(len(bases)) if j != i]
        score = 1.0 - float(directions[i] @ _unit(directions[others].sum(0)))
        mean_curl = _unit(np.sum([_unit(c) for c in curls[others]], axis=0))
        if np.linalg.norm(curls[i]) > 1e-6 and mean_curl.any():
            score += 1.0 - float(_unit(curls[i]) @ mean_curl)
        score += 0.5 * float(np.linalg.norm(bases[i] - bases[others].mean(0))) / length
        scores.append(score)
    return np.asarray(scores)


@dataclass
class _Naming:
    names: dict[int, str]  # chain index -> finger
    finger_dir: np.ndarray
    detected_side: str
    palm_sign: float
    scores: np.ndarray
    guesses: list[tuple[str, str]]


def _name_fingers(kin: _Kinematics, chains: list[_Chain], side: str | None) -> _Naming:
    """Which chain is the thumb, the order of the others across the palm, the hand's side.

    A mirror-symmetric hand (the thumb midway across the palm) is ordered as a ``side`` hand
    (default right) would be.
    """
    guesses = []
    length = float(np.median([c.length for c in chains]))
    bases = np.array([c.points[0][1] for c in chains])
    directions = np.array([_unit(c.tip[1] - b) for c, b in zip(chains, bases, strict=True)])
    curls = _curls(kin, chains)
    scores = _opposition(bases, directions, curls, length)
    order = np.argsort(-scores, kind="stable")
    thumb = int(order[0])
    if scores[order[0]] - scores[order[1]] < _THUMB_MARGIN:
        listing = {chains[i].root: round(float(scores[i]), 2) for i in order}
        guesses.append(
            (
                "fingers",
                f"no chain clearly opposes the others (opposition {listing}): the thumb is "
                f"guessed to be the chain from '{chains[thumb].root}'",
            )
        )
    others = [i for i in range(len(chains)) if i != thumb]
    finger_dir = _unit(directions[others].sum(0))
    thumb_centre = np.mean([p for _, p in chains[thumb].points] + [chains[thumb].tip[1]], axis=0)
    flat = bases[others] - np.outer(bases[others] @ finger_dir, finger_dir)
    if len(others) >= 2:
        across = np.linalg.svd(flat - flat.mean(0))[2][0]
        spread = float(np.ptp((flat - flat.mean(0)) @ across))
    else:
        across = thumb_centre - bases[others[0]]
        across = _unit(across - finger_dir * float(across @ finger_dir))
        spread = 0.0
    thumb_offset = float((thumb_centre - bases[others].mean(0)) @ across)
    if thumb_offset < 0:  # across points towards the thumb
        across, thumb_offset = -across, -thumb_offset
    symmetric = thumb_offset < max(0.25 * spread, 0.005)

    normal = _unit(np.cross(finger_dir, across))
    curl = np.sum([_unit(c) for c in curls[others]], axis=0)
    if abs(float(curl @ normal)) > 1e-3:
        palm_sign = float(np.sign(curl @ normal))
    else:  # no finger flexes one way only: the thumb sits on the palm side
        palm_sign = float(np.sign((thumb_centre - bases[others].mean(0)) @ normal)) or 1.0
        guesses.append(
            ("side", "no finger joint has a one-sided range: the palm side is taken from the thumb")
        )
    if symmetric:  # a right hand has (u x a) . p < 0
        if (palm_sign < 0) != ((side or "right") == "right"):
            across, palm_sign = -across, -palm_sign
        if len(others) >= 2:
            guesses.append(
                (
                    "fingers",
                    "the thumb sits midway across the palm (the hand is about mirror-symmetric): "
                    f"the index is the finger on the side a {side or 'right'} hand's would be",
                )
            )
    others.sort(key=lambda i: -float(bases[i] @ across))
    names = {thumb: "thumb"} | {i: FINGERS[1 + k] for k, i in enumerate(others)}
    detected = "" if symmetric else ("right" if palm_sign < 0 else "left")
    return _Naming(names, finger_dir, detected, palm_sign, scores, guesses)


# --------------------------------------------------------------------------------- keypoints


def _map_chain(chain: _Chain, finger: str) -> tuple[dict[int, tuple[str, np.ndarray]], list, list]:
    """MANO index -> (link, world point) along a chain; joints left unmapped; guesses.

    The last three joint points are the human base, middle and distal joints; a chain with
    fewer is no human-like finger and only its tip is mapped.
    """
    base, middle, distal, tip = FINGER_KEYPOINTS[finger]
    points = _merged_points(chain)
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
    kin: _Kinematics,
    palm: str,
    chains: list[_Chain],
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
    verts, _ = _geometry_points(kin, rigid, world)
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


def _mjcf_couplings(kin: _Kinematics) -> list[CouplingSpec]:
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
        root, found = _mjcf_root(path)
        guesses += found
    model = load_kinematic_model(path, root or "")
    kin = _Kinematics(model)
    world = dict(zip(kin.frames, kin.transforms(kin.q0)[0], strict=True))

    chains, extra_joints, palm = _find_chains(kin)
    for c in chains:
        _trace_chain(kin, c, world)
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

    naming = _name_fingers(kin, chains, side)
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

    def base_point(chain: _Chain) -> np.ndarray:  # the base joint, or the first one
        points = _merged_points(chain)
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


# ---------------------------------------------------------------------------------- mirror


def _fmt(values) -> str:
    return " ".join(f"{float(v) + 0.0:.9g}" for v in values)


def _urdf_origin(parent: ET.Element, transform: np.ndarray) -> None:
    rpy = Rotation.from_matrix(transform[:3, :3]).as_euler("xyz")  # about the fixed x, y, z
    ET.SubElement(parent, "origin", xyz=_fmt(transform[:3, 3]), rpy=_fmt(rpy))


def _urdf_inertial(inertial: ET.Element) -> tuple[np.ndarray, float, np.ndarray]:
    mass, inertia = inertial.find("mass"), inertial.find("inertia")
    get = {} if inertia is None else inertia.attrib
    xx, xy, xz, yy, yz, zz = (
        float(get.get(k, 0.0)) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    )
    tensor = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    return _origin(inertial), float(0.0 if mass is None else mass.get("value", 0.0)), tensor


def _physics(model: KinematicModel) -> tuple[dict, dict]:
    """What a simulator needs and the kinematic model leaves out, from the model file.

    Returns:
        Per link its inertial ``(pose (4, 4) in the link frame, mass, inertia (3, 3) in that
        pose)`` (links without one are left out), and per joint its ``(effort, velocity)``.
    """
    inertials, limits = {}, {}
    if model.format == "urdf":
        root = ET.parse(model.path).getroot()
        for link in root.iter("link"):
            inertial = link.find("inertial")
            if inertial is not None:
                inertials[link.get("name")] = _urdf_inertial(inertial)
        for joint in root.iter("joint"):
            limit = joint.find("limit")
            if limit is not None:
                limits[joint.get("name")] = (
                    float(limit.get("effort", 10.0)),
                    float(limit.get("velocity", 3.14)),
                )
    else:
        m = model.mj_model
        for b in range(m.nbody):
            if m.body_mass[b] > 0:
                pose = np.eye(4)
                pose[:3, :3] = Rotation.from_quat(m.body_iquat[b], scalar_first=True).as_matrix()
                pose[:3, 3] = m.body_ipos[b]
                inertials[m.body(b).name] = (
                    pose,
                    float(m.body_mass[b]),
                    np.diag(m.body_inertia[b]),
                )
        for a in range(m.nu):
            if m.actuator_trntype[a] == 0 and m.actuator_forcelimited[a]:
                effort = float(np.abs(m.actuator_forcerange[a]).max())
                limits[m.joint(int(m.actuator_trnid[a][0])).name] = (effort, 3.14)
    return inertials, limits


def _inertial(link: ET.Element, pose: np.ndarray, mass: float, tensor: np.ndarray) -> None:
    inertial = ET.SubElement(link, "inertial")
    _urdf_origin(inertial, pose)
    ET.SubElement(inertial, "mass", value=_fmt([mass]))
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    cells = (tensor[0, 0], tensor[0, 1], tensor[0, 2], tensor[1, 1], tensor[1, 2], tensor[2, 2])
    ET.SubElement(inertial, "inertia", {n: _fmt([v]) for n, v in zip(names, cells, strict=True)})


def mirror_model(
    model: KinematicModel, out_path: str | Path, couplings: list[CouplingSpec] | None = None
) -> Path:
    """Write the mirror image (``x -> -x`` in the root frame) of a hand model as a URDF.

    Every frame ``T`` (at zero joints) becomes ``M T M`` with ``M = diag(-1, 1, 1)``, again a
    rigid transform; a revolute axis ``a`` (in its child frame) becomes ``-M a`` and a
    prismatic one ``M a``, so that every joint keeps its name, angle and limits and
    ``FK'(q) = M FK(q) M``. Collision shapes are reflected in their link frames (primitives are
    symmetric; meshes are written as OBJ files in ``<stem>_meshes/``), inertials too (pose
    ``M T M``, inertia ``M I M``); joint efforts and velocities are kept (an MJCF's from its
    joint actuators). Couplings become ``<mimic>`` tags. Visual shapes and joint dynamics are
    not carried over.

    Args:
        model: A parsed URDF or MJCF hand.
        out_path: The URDF to write.
        couplings: Joints tied to others.

    Returns:
        ``out_path``.
    """
    from dexflow.io.atomic import atomic_path

    out_path = Path(out_path)
    mesh_dir = out_path.parent / f"{out_path.stem}_meshes"
    kin = _Kinematics(model)
    zero = kin.transforms(np.zeros(len(kin.joint_names)))[0]
    world = {f: _MIRROR4 @ t @ _MIRROR4 for f, t in zip(kin.frames, zero, strict=True)}
    limits = dict(zip(kin.joint_names, zip(model.lower, model.upper, strict=True), strict=True))
    mimic = {c.joint: c for c in couplings or []}
    inertials, efforts = _physics(model)
    shapes: dict[str, list] = {}
    for g in model.geometries:
        shapes.setdefault(g.link, []).append(g)
    unsafe = re.compile(r"[^A-Za-z0-9_.-]")
    robot = ET.Element("robot", name=f"{model.path.stem}_mirrored")
    for frame in kin.frames:
        link = ET.SubElement(robot, "link", name=frame)
        if frame in inertials:  # mass and inertia reflected too: I' = M I M in M T M
            pose, mass, tensor = inertials[frame]
            _inertial(link, _MIRROR4 @ pose @ _MIRROR4, mass, _MIRROR @ tensor @ _MIRROR)
        elif model.format == "mjcf":  # a site or a massless body: as dexflow hand export
            _inertial(link, np.eye(4), 1e-5, np.eye(3) * 1e-9)
        for k, g in enumerate(shapes.get(frame, [])):
            collision = ET.SubElement(link, "collision")
            geometry = ET.Element("geometry")
            if g.kind == "mesh":  # vertices already in the link frame
                mesh = trimesh.Trimesh(
                    g.mesh.vertices @ _MIRROR, g.mesh.faces[:, ::-1], process=False
                )
                mesh_path = mesh_dir / f"{unsafe.sub('_', frame)}_{k}.obj"
                with atomic_path(mesh_path) as tmp:
                    tmp.write_text(trimesh.exchange.obj.export_obj(mesh, include_normals=False))
                _urdf_origin(collision, np.eye(4))
                ET.SubElement(geometry, "mesh", filename=f"{mesh_dir.name}/{mesh_path.name}")
            else:
                _urdf_origin(collision, _MIRROR4 @ g.transform @ _MIRROR4)
                if g.kind == "box":
                    ET.SubElement(geometry, "box", size=_fmt(2 * np.asarray(g.size)))
                elif g.kind == "sphere":
                    ET.SubElement(geometry, "sphere", radius=_fmt(g.size[:1]))
                else:  # capsule, cylinder: (radius, half-length)
                    ET.SubElement(
                        geometry, g.kind, radius=_fmt(g.size[:1]), length=_fmt([2 * g.size[1]])
                    )
            collision.append(geometry)
        parent, joint = kin.parents[frame]
        if parent is None:
            continue
        if joint is None:
            element = ET.SubElement(robot, "joint", name=f"{frame}_fixed", type="fixed")
        else:
            kind, axis = kin.joint(joint)
            element = ET.SubElement(robot, "joint", name=joint, type=kind)
            ET.SubElement(
                element, "axis", xyz=_fmt(-_MIRROR @ axis if kind == "revolute" else _MIRROR @ axis)
            )
            lower, upper = limits[joint]
            effort, velocity = efforts.get(joint, (10.0, 3.14))
            ET.SubElement(
                element,
                "limit",
                lower=_fmt([lower]),
                upper=_fmt([upper]),
                effort=_fmt([effort]),
                velocity=_fmt([velocity]),
            )
            if joint in mimic:
                c = mimic[joint]
                ET.SubElement(
                    element,
                    "mimic",
                    joint=c.leader,
                    multiplier=_fmt([c.ratio]),
                    offset=_fmt([c.offset]),
                )
        ET.SubElement(element, "parent", link=parent)
        ET.SubElement(element, "child", link=frame)
        _urdf_origin(element, np.linalg.inv(world[parent]) @ world[frame])
    ET.indent(robot)
    header = (
        '<?xml version="1.0"?>\n'
        f"<!-- The mirror image (x -> -x) of {model.path.name} ({model.format.upper()}), written "
        "by dexflow hand init: the same link and joint names, angles and limits; collision "
        "shapes and inertials reflected, no visuals. -->\n"
    )
    with atomic_path(out_path) as tmp:
        tmp.write_text(header + ET.tostring(robot, encoding="unicode") + "\n")
    return out_path


# ------------------------------------------------------------------------------------ yaml


def _scalar(value: str) -> str:
    """A YAML scalar for a name: plain where YAML reads it back as that string, else quoted."""
    import json

    import yaml

    plain = re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.:/-]*", value) is not None
    if plain and not value.endswith(":"):
        try:
            plain = yaml.safe_load(value) == value
        except yaml.YAMLError:
            plain = False
    return value if plain else json.dumps(value)


def _names(values) -> str:
    return "[" + ", ".join(_scalar(v) for v in values) + "]"


def _number(value: float) -> str:
    return repr(round(float(value), 6) + 0.0)


_PARTS = ("base", "middle", "distal", "tip")
_THUMB_PARTS = ("CMC", "MCP", "IP", "tip")
_FINGER_PARTS = ("MCP", "PIP", "DIP", "tip")


def _keypoint_comment(proposal: HandProposal, kp: KeypointSpec) -> str:
    if kp.mano == WRIST:
        return "wrist: " + proposal.notes.get("wrist", "the palm link's origin")
    for f in proposal.fingers:
        chain = FINGER_KEYPOINTS[f.name]
        if kp.mano in chain:
            part = chain.index(kp.mano)
            joint = (_THUMB_PARTS if f.name == "thumb" else _FINGER_PARTS)[part]
            if part == 3:
                source = {
                    "leaf": "a frame at the end of the distal link",
                    "geometry": "far end of the distal collision geometry",
                    "guess": "GUESS: no distal geometry",
                }[f.tip_source]
                return f"{f.name} tip: {source}"
            return f"{f.name} {joint} ({_PARTS[part]} joint of the chain)"
    return ""


def write_hand_yaml(proposal: HandProposal, out_path: str | Path, source: str = "") -> Path:
    """Write a proposal as a commented hand yaml (guesses marked ``GUESS``).

    Args:
        proposal: From :func:`propose_hand`.
        out_path: The yaml file.
        source: The model the proposal was read from, for the header (default: ``spec.model``).

    Returns:
        ``out_path``.
    """
    from dexflow.io.atomic import atomic_path

    spec = proposal.spec
    guesses: dict[str, list[str]] = {}
    for key, text in proposal.guesses:
        guesses.setdefault(key, []).append(text)

    def guess_lines(key: str) -> list[str]:
        return [f"# GUESS ({key}): {text}" for text in guesses.get(key, [])]

    joints = sum(len(f.joints) for f in spec.fingers.values()) + len(spec.extra_joints)
    lines = [
        f"# {spec.name}: a {spec.side} hand, proposed by `dexflow hand init` from "
        f"{source or spec.model}.",
        f"# {joints} joints; {len(spec.fingers)} fingers found in the kinematic tree (chains from "
        f"the palm '{proposal.palm}' to leaf links),",
        "# named by geometry: the thumb opposes the others, the rest are ordered across the palm.",
        (
            f"# Review the {len(proposal.guesses)} GUESS comments, then run `dexflow hand check`."
            if proposal.guesses
            else "# Nothing had to be guessed; `dexflow hand check` shows the tree and zero pose."
        ),
        *guess_lines("root"),
        f"name: {_scalar(spec.name)}",
        f"model: {_scalar(spec.model)}"
        + ("   # a mirrored copy, written beside this file" if spec.mirrored else ""),
        f"root: {_scalar(spec.root) if spec.root else chr(34) * 2}"
        + ("   # the MJCF body the hand starts at" if spec.root else "   # the URDF's root link"),
        *guess_lines("side"),
        f"side: {spec.side}   # {proposal.notes.get('side', '')}",
        f"mirrored: {'true' if spec.mirrored else 'false'}   # "
        + (
            f"model is the mirror image (x -> -x) of {source}, a right hand; left-hand "
            "sequences are mirrored to it"
            if spec.mirrored
            else "the model is used as it is"
            + ("; right-hand sequences are mirrored to it" if spec.side == "left" else "")
        ),
        *guess_lines("scale"),
        f"scale: {_number(spec.scale)}   # proposed (human -> robot size): "
        + proposal.notes.get("scale", ""),
        "fingertip_offsets:   # metres added along each human distal bone (DIP -> tip)",
        *(f"  {finger}: {spec.fingertip_offsets.get(finger, 0.0)!r}" for finger in FINGERS),
        *guess_lines("keypoints"),
        "keypoints:   # robot links (plus offsets in the link frame) matched to MANO joints",
    ]
    for kp in spec.keypoints:
        offset = "" if not any(kp.offset) else f", offset: [{', '.join(map(_number, kp.offset))}]"
        lines.append(
            f"  - {{link: {_scalar(kp.link)}, mano: {kp.mano}{offset}}}   # "
            + _keypoint_comment(proposal, kp)
        )
    lines += [
        *guess_lines("fingers"),
        "fingers:   # thumb -> little: joints, and links that may touch",
    ]
    for f in proposal.fingers:
        fs = spec.fingers[f.name]
        extra = f"; not mapped: {_names(f.unmapped)}" if f.unmapped else ""
        lines += [
            f"  {f.name}:   # the chain from '{f.root}'{extra}",
            f"    joints: {_names(fs.joints)}",
            f"    links: {_names(fs.links)}",
        ]
    lines += [
        *guess_lines("extra_joints"),
        f"extra_joints: {_names(spec.extra_joints)}   # actuated joints in no finger"
        + (" (the wrist: between the root and the palm)" if spec.extra_joints else ""),
    ]
    if spec.couplings:
        lines.append(
            f"couplings:   # q[joint] = ratio * q[leader] + offset; {proposal.notes['couplings']}"
        )
        for c in spec.couplings:
            lines.append(
                f"  - {{joint: {_scalar(c.joint)}, leader: {_scalar(c.leader)}, "
                f"ratio: {float(c.ratio)!r}, offset: {float(c.offset) + 0.0!r}}}"
            )
    else:
        lines.append(f"couplings: []   # none {proposal.notes.get('couplings', '')}")
    lines += [
        f"surface_points: {spec.surface_points}   # points sampled on the collision geometry",
        f"surface_exclude: {_names(spec.surface_exclude)}"
        + (f"   # {proposal.notes['surface_exclude']}" if spec.surface_exclude else ""),
    ]
    out_path = Path(out_path)
    with atomic_path(out_path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return out_path


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
