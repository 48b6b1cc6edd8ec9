"""The fingers of a hand model, found and named as ``dexflow hand init`` does (the method: the
docstring of :mod:`dexflow.hands.init`): the chains of the kinematic tree below its branch
points, the points along each, and which finger is the thumb, index, ... little."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dexflow.errors import HandConfigError
from dexflow.hands.tree import Kinematics, unit
from dexflow.human.keypoints import FINGERS

__all__ = [
    "Chain",
    "Naming",
    "find_chains",
    "geometry_points",
    "merged_points",
    "name_fingers",
    "trace_chain",
]

# Joints of one finger closer than this share of the finger's length are one keypoint.
_MERGE_FRACTION = 0.15
# A leaf frame this close to the far end of the distal shapes (share of the last segment, at
# least _TIP_LEAF_MIN_M) is the fingertip.
_TIP_LEAF_FRACTION = 0.3
_TIP_LEAF_MIN_M = 0.01
# A joint turns towards its far limit when that is this many times farther than the near one.
_ONE_SIDED = 1.5
# Opposition scores closer than this leave the thumb a guess.
_THUMB_MARGIN = 0.15


# ---------------------------------------------------------------------------------- chains


@dataclass
class Chain:
    root: str
    frames: list[str]  # the subtree
    joints: list[str]
    path: list[str] = field(default_factory=list)  # root .. distal link
    points: list[tuple[str, np.ndarray]] = field(default_factory=list)  # moving frames, origins
    tip: tuple[str, np.ndarray] = ("", np.zeros(3))  # link, point
    tip_source: str = ""
    length: float = 0.0


def find_chains(kin: Kinematics) -> tuple[list[Chain], list[str], str]:
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
        chains.append(Chain(root, frames, joints))
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


def geometry_points(kin: Kinematics, links, world) -> tuple[np.ndarray | None, np.ndarray]:
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


def trace_chain(kin: Kinematics, chain: Chain, world: dict[str, np.ndarray]) -> None:
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
        along = unit(last - chain.points[-2][1])
    else:
        along = unit(last - world[kin.parents[chain.root][0]][:3, 3])
    rigid = [distal, *kin.fixed_descendants(distal)]
    verts, centre = geometry_points(kin, rigid, world)
    far_end = None
    if verts is not None:
        reach = unit(centre - last)
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


def merged_points(chain: Chain) -> list[tuple[str, np.ndarray]]:
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


def tips_at(kin: Kinematics, chains: list[Chain], q: np.ndarray) -> np.ndarray:
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


def finger_curls(kin: Kinematics, chains: list[Chain]) -> np.ndarray:
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
    tips = tips_at(kin, chains, q)
    return np.stack([tips[i + 1, i] - tips[0, i] for i in range(len(chains))])


def opposition(bases, directions, curls, length: float) -> np.ndarray:
    """(C,) how much each chain opposes the others (the thumb score of the module docstring)."""
    scores = []
    for i in range(len(bases)):
        others = [j for j in range(len(bases)) if j != i]
        score = 1.0 - float(directions[i] @ unit(directions[others].sum(0)))
        mean_curl = unit(np.sum([unit(c) for c in curls[others]], axis=0))
        if np.linalg.norm(curls[i]) > 1e-6 and mean_curl.any():
            score += 1.0 - float(unit(curls[i]) @ mean_curl)
        score += 0.5 * float(np.linalg.norm(bases[i] - bases[others].mean(0))) / length
        scores.append(score)
    return np.asarray(scores)


@dataclass
class Naming:
    names: dict[int, str]  # chain index -> finger
    finger_dir: np.ndarray
    detected_side: str
    palm_sign: float
    scores: np.ndarray
    guesses: list[tuple[str, str]]


def name_fingers(kin: Kinematics, chains: list[Chain], side: str | None) -> Naming:
    """Which chain is the thumb, the order of the others across the palm, the hand's side.

    A mirror-symmetric hand (the thumb midway across the palm) is ordered as a ``side`` hand
    (default right) would be.
    """
    guesses = []
    length = float(np.median([c.length for c in chains]))
    bases = np.array([c.points[0][1] for c in chains])
    directions = np.array([unit(c.tip[1] - b) for c, b in zip(chains, bases, strict=True)])
    curls = finger_curls(kin, chains)
    scores = opposition(bases, directions, curls, length)
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
    finger_dir = unit(directions[others].sum(0))
    thumb_centre = np.mean([p for _, p in chains[thumb].points] + [chains[thumb].tip[1]], axis=0)
    flat = bases[others] - np.outer(bases[others] @ finger_dir, finger_dir)
    if len(others) >= 2:
        across = np.linalg.svd(flat - flat.mean(0))[2][0]
        spread = float(np.ptp((flat - flat.mean(0)) @ across))
    else:
        across = thumb_centre - bases[others[0]]
        across = unit(across - finger_dir * float(across @ finger_dir))
        spread = 0.0
    thumb_offset = float((thumb_centre - bases[others].mean(0)) @ across)
    if thumb_offset < 0:  # across points towards the thumb
        across, thumb_offset = -across, -thumb_offset
    symmetric = thumb_offset < max(0.25 * spread, 0.005)

    normal = unit(np.cross(finger_dir, across))
    curl = np.sum([unit(c) for c in curls[others]], axis=0)
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
    return Naming(names, finger_dir, detected, palm_sign, scores, guesses)
