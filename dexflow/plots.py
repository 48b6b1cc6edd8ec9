"""Static figures (matplotlib, headless) of sequences: object mesh, hand skeleton, contacts."""

from __future__ import annotations

from pathlib import Path

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

__all__ = ["plot_sequence_frames"]

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
