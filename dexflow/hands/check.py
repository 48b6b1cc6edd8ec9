"""``dexflow hand check``: validate a hand config, print its kinematic tree, draw its zero pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dexflow.errors import HandConfigError
from dexflow.hands.robot import RobotHand, load_hand
from dexflow.human.keypoints import FINGERTIPS

__all__ = ["check_hand", "kinematic_tree", "plot_zero_pose"]


def _problems(hand: RobotHand) -> list[str]:
    spec = hand.spec
    problems = []
    if not spec.keypoints:
        problems.append("no keypoints: retargeting needs links matched to human keypoints")
    if not spec.fingers:
        problems.append("no fingers: contact and refinement need fingers with joints and links")
    owners: dict[str, list[str]] = {}
    for finger, fs in spec.fingers.items():
        for joint in fs.joints:
            owners.setdefault(joint, []).append(finger)
    for joint in spec.extra_joints:
        owners.setdefault(joint, []).append("extra_joints")
    shared = {j: o for j, o in owners.items() if len(o) > 1}
    if shared:
        problems.append(f"joints listed more than once: {shared}")
    uncovered = [j for j in hand.hand_joint_names if j not in owners]
    if uncovered:
        problems.append(
            f"actuated joints in no finger (add them to a finger or extra_joints): {uncovered}"
        )

    for k, spec_kp in enumerate(spec.keypoints):
        moved = _moved_by(hand)[k]
        if not np.isfinite(moved).all():
            problems.append(
                f"keypoint '{spec_kp.link}' (MANO {spec_kp.mano}) has no finite position"
            )
        elif spec_kp.mano in FINGERTIPS and not moved.any():
            problems.append(
                f"fingertip keypoint '{spec_kp.link}' (MANO {spec_kp.mano}) is not moved "
                "by any hand joint: it cannot follow the human finger"
            )
    return problems


def _moved_by(hand: RobotHand) -> np.ndarray:
    """(K, J) True where hand joint j moves keypoint k (at mid-range joints)."""
    q = ((hand.lower + hand.upper) / 2).clone()[None]
    q[:, :6] = 0.0
    jac = torch.autograd.functional.jacobian(lambda x: hand.keypoints(x)[0], q)  # (K, 3, 1, dof)
    return (jac[:, :, 0, 6:].abs().amax(dim=1) > 1e-9).numpy()


def kinematic_tree(hand: RobotHand) -> str:
    """The frames of the hand as an indented tree with joints, limits and keypoint roles."""
    children: dict[str | None, list[str]] = {}
    for name, (parent, _) in hand.model.parents.items():
        children.setdefault(parent, []).append(name)
    limits = dict(
        zip(
            hand.hand_joint_names, zip(hand.model.lower, hand.model.upper, strict=True), strict=True
        )
    )
    roles = {kp.link: f"keypoint MANO {kp.mano}" for kp in hand.spec.keypoints}
    finger_of = {link: finger for finger, fs in hand.spec.fingers.items() for link in fs.links}
    lines = []

    def walk(name: str, prefix: str, last: bool, depth: int) -> None:
        _, joint = hand.model.parents[name]
        label = name
        if joint is not None:
            lo, hi = limits[joint]
            label += f"  [{joint}: {lo:+.3f} .. {hi:+.3f}]"
        notes = [
            n for n in (roles.get(name), finger_of.get(name) and f"{finger_of[name]} contact") if n
        ]
        if notes:
            label += "  <- " + ", ".join(notes)
        branch = "" if depth == 0 else ("└─ " if last else "├─ ")
        lines.append(prefix + branch + label)
        kids = children.get(name, [])
        for i, kid in enumerate(kids):
            extension = "" if depth == 0 else ("   " if last else "│  ")
            walk(kid, prefix + extension, i == len(kids) - 1, depth + 1)

    walk(hand.model.root, "", True, 0)
    return "\n".join(lines)


def plot_zero_pose(hand: RobotHand, out_png: str | Path) -> Path:
    """Draw the hand at its zero pose (clamped into limits): surface points and keypoints."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dexflow.io.atomic import atomic_path

    q = hand.zero()
    with torch.no_grad():
        points = hand.surface(q)[0][0].numpy()
        kp = hand.keypoints(q)[0].numpy()
    link_of = hand.surface_point_link_index
    fig = plt.figure(figsize=(12, 4.5))
    views = (("front", 0, -90), ("side", 0, 0), ("top", 89, -90))
    for i, (title, elev, azim) in enumerate(views):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        ax.scatter(*points.T, c=link_of, cmap="tab20", s=2, alpha=0.5)
        ax.scatter(*kp.T, c="red", s=25, depthshade=False)
        for (x, y, z), spec_kp in zip(kp, hand.spec.keypoints, strict=True):
            ax.text(x, y, z, str(spec_kp.mano), color="darkred", fontsize=7)
        allp = np.vstack([points, kp])
        centre, radius = allp.mean(0), np.ptp(allp, 0).max() / 2
        for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            set_lim(c - radius, c + radius)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=6)
    fig.suptitle(
        f"{hand.spec.name}: {len(hand.hand_joint_names)} joints, "
        f"{len(hand.spec.keypoints)} keypoints (red, MANO index), zero pose"
    )
    fig.tight_layout()
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return out_png


def check_hand(
    name_or_path: str | Path, out_png: str | Path | None = None
) -> tuple[RobotHand, str]:
    """Load and validate a hand; return it with a printable report (tree + summary).

    Raises:
        HandConfigError: any problem, all of them listed in the message.
    """
    hand = load_hand(name_or_path)
    problems = _problems(hand)
    if problems:
        listing = "\n  - ".join(problems)
        raise HandConfigError(f"hand '{hand.spec.name}' ({hand.model.path}):\n  - {listing}")
    summary = [
        f"hand '{hand.spec.name}': {hand.model.format.upper()} {hand.model.path}",
        f"  {len(hand.hand_joint_names)} joints (+6 floating-base), {len(hand.model.frames)} frames, "
        f"{len(hand.model.geometries)} collision shapes, {hand.num_surface_points} surface points",
        "  fingers: " + ", ".join(f"{f} ({len(j)} joints)" for f, j in hand.fingers.items()),
        f"  keypoints: {len(hand.spec.keypoints)} -> MANO {hand.mano_indices}",
        "  moved only by the floating base: "
        + (
            ", ".join(
                kp.link
                for kp, m in zip(hand.spec.keypoints, _moved_by(hand), strict=True)
                if not m.any()
            )
            or "none"
        ),
        f"  couplings: {len(hand.spec.couplings)}",
    ]
    if out_png is not None:
        summary.append(f"  zero pose: {plot_zero_pose(hand, out_png)}")
    return hand, "\n".join([kinematic_tree(hand), "", *summary, "ok"])
