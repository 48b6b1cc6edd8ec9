"""The hand config yaml that ``dexflow hand init`` writes from a :class:`HandProposal`: every
field of :class:`dexflow.hands.spec.HandSpec`, with a comment per keypoint saying where it
came from and what to check."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

from dexflow.hands.spec import KeypointSpec
from dexflow.human.keypoints import FINGER_KEYPOINTS, FINGERS, WRIST

if TYPE_CHECKING:
    from dexflow.hands.init import HandProposal

__all__ = ["write_hand_yaml"]


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
