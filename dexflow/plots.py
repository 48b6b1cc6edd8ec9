"""Static figures (matplotlib, headless) of sequences: object mesh, hand skeleton, contacts, and
the robot hand posed on the object (:func:`plot_hand_on_object`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from dexflow.geometry import transform_points
from dexflow.human.keypoints import FINGER_KEYPOINTS, FINGERS, FINGERTIPS
from dexflow.io.atomic import atomic_path
from dexflow.io.layout import StageDir
from dexflow.io.sequence import load_sequence
from dexflow.objects.mesh import load_mesh

if TYPE_CHECKING:
    from dexflow.hands.robot import RobotHand

__all__ = ["plot_hand_on_object", "plot_sequence_frames", "posed_hand_triangles"]

_FINGER_COLORS = ("tab:red", "tab:orange", "tab:green", "tab:blue", "tab:purple")


def _draw(ax, seq, mesh, frame: int) -> None:
    vertices = transform_points(seq.obj_pose[frame], mesh.vertices)
    tris = vertices[mesh.faces]
    ax.add_collection3d(Poly3DCollection(tris, facecolor="0.75", edgecolor="none", alpha=0.35))
    kp = seq.keypoints[frame]
    for finger, color in zip(FINGERS, _FINGER_COLORS, strict=True):
        chain = [0, *FINGER_KEYPOINTS[finger]]
        ax.plot(*kp[chain].T, "-o", color=color, markersize=2, linewidth=1.5)
    if seq.gt_contact is not None:
        touching = np.asarray(FINGERTIPS)[seq.gt_contact[frame]]
        ax.scatter(*kp[touching].T, s=40, facecolors="none", edgecolors="k", linewidths=1.2)
    points = np.vstack([vertices, kp])
    centre, radius = points.mean(axis=0), np.ptp(points, axis=0).max() / 2
    for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
        set_lim(c - radius, c + radius)
    ax.set_box_aspect((1, 1, 1))
    ax.set_axis_off()


def plot_sequence_frames(
    data_root: str | Path, names: list[str], out_png: str | Path, columns: int = 3
) -> None:
    """Draw each named sequence at the middle of its ground-truth contact (or its middle frame).

    Fingertips circled in black are in contact according to ``gt_contact``.
    """
    if not names:
        raise ValueError("plot_sequence_frames: no sequence names given")
    data_root = Path(data_root)
    rows = int(np.ceil(len(names) / columns))
    fig = plt.figure(figsize=(4 * columns, 4 * rows))
    for i, name in enumerate(names):
        seq = load_sequence(StageDir(data_root).sequence(name), data_root=data_root)
        mesh = load_mesh(data_root / seq.obj_mesh)
        held = (
            np.flatnonzero(seq.gt_contact.any(axis=1) & seq.valid_mask)
            if seq.gt_contact is not None
            else []
        )
        frame = int(held[len(held) // 2]) if len(held) else seq.num_frames // 2
        ax = fig.add_subplot(rows, columns, i + 1, projection="3d")
        ax.view_init(elev=25, azim=-60)
        _draw(ax, seq, mesh, frame)
        ax.set_title(f"{name}\nframe {frame}", fontsize=9)
    fig.tight_layout()
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=80)
    plt.close(fig)


_HAND_RGB = np.array([0.45, 0.55, 0.78])
_OBJECT_RGB = np.array([0.93, 0.68, 0.35])
_LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])  # world frame, fixed


def posed_hand_triangles(hand: RobotHand, q: np.ndarray) -> np.ndarray:
    """The hand's collision meshes posed by forward kinematics, as world-frame triangles.

    Args:
        hand: The robot hand.
        q: (B, dof) configurations in ``hand.joint_names`` order.

    Returns:
        (B, F, 3, 3) the F triangles of every collision shape, per configuration.
    """
    geometries = hand.model.geometries
    if not geometries:
        raise ValueError(f"hand '{hand.spec.name}': its model has no collision geometry to draw")
    links = list(dict.fromkeys(g.link for g in geometries))
    transforms = hand.link_transforms(q, links).detach().cpu().numpy()  # (B, L, 4, 4)
    index = {link: i for i, link in enumerate(links)}
    posed = []
    for g in geometries:
        t = transforms[:, index[g.link]]  # (B, 4, 4) link to world
        vertices = np.asarray(g.mesh.vertices) @ np.swapaxes(t[:, :3, :3], 1, 2) + t[:, None, :3, 3]
        posed.append(vertices[:, np.asarray(g.mesh.faces)])  # (B, f, 3, 3)
    return np.concatenate(posed, axis=1)


def _shaded(triangles: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """(F, 4) colours of ``triangles (F, 3, 3)`` lit from :data:`_LIGHT` (Lambert, two-sided)."""
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    light = 0.35 + 0.65 * np.abs(normals @ _LIGHT)
    return np.column_stack([np.clip(light[:, None] * rgb, 0, 1), np.ones(len(triangles))])


def plot_hand_on_object(
    hand_triangles: np.ndarray,
    object_triangles: Sequence[np.ndarray],
    focus: Sequence[np.ndarray],
    titles: Sequence[str],
    out_png: str | Path,
    title: str,
    elev: float = 20.0,
    azim: float = -60.0,
) -> None:
    """Draw the posed robot hand and the object side by side at a few frames, one fixed camera.

    Every panel has the same view direction and scale, centred on its own ``focus`` points; hand
    and object triangles are depth-sorted together (one painter's sort, Lambert shading from a
    fixed light).

    Args:
        hand_triangles: (K, F, 3, 3) world-frame hand triangles per panel
            (:func:`posed_hand_triangles`).
        object_triangles: K arrays (O, 3, 3) of world-frame object triangles.
        focus: K arrays (N, 3) of the points each panel must hold (the object's and the
            fingers'); the rest (a forearm) may leave it.
        titles: K panel titles.
        out_png: The PNG to write (atomically).
        title: The figure's title.
    """
    hand_triangles = np.asarray(hand_triangles, dtype=float)
    count = len(hand_triangles)
    if count == 0 or not len(object_triangles) == len(focus) == len(titles) == count:
        raise ValueError(
            f"plot_hand_on_object: expected as many object meshes, focus sets and titles as hand "
            f"poses (>= 1), got {count} poses, {len(object_triangles)} meshes, {len(focus)} "
            f"focus sets, {len(titles)} titles"
        )
    boxes = [np.asarray(f, dtype=float).reshape(-1, 3) for f in focus]
    centres = [(b.min(axis=0) + b.max(axis=0)) / 2 for b in boxes]
    radius = 0.5 * max(float(np.max(b.max(axis=0) - b.min(axis=0))) for b in boxes)
    fig = plt.figure(figsize=(3.2 * count, 3.6))
    for i in range(count):
        ax = fig.add_subplot(1, count, i + 1, projection="3d")
        ax.view_init(elev=elev, azim=azim)
        triangles = np.concatenate([hand_triangles[i], object_triangles[i]])
        colours = np.concatenate(
            [_shaded(hand_triangles[i], _HAND_RGB), _shaded(object_triangles[i], _OBJECT_RGB)]
        )
        ax.add_collection3d(
            Poly3DCollection(triangles, facecolors=colours, edgecolors="none", zsort="average")
        )
        for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centres[i], strict=True):
            set_lim(c - radius, c + radius)
        ax.set_box_aspect((1, 1, 1), zoom=1.4)
        ax.set_axis_off()
        ax.set_title(titles[i], fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.82, wspace=0)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=90, metadata={"Software": None})
    plt.close(fig)
