"""A hand model's kinematic tree as ``dexflow hand init`` walks it: frames, joints, their
parents and children, and the frames' transforms at any configuration (batched), for URDF and
MJCF models alike (an MJCF's root body and its equalities read from the file)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dexflow.errors import HandConfigError
from dexflow.hands.model import (
    KinematicModel,
)

__all__ = ["Kinematics", "mjcf_root", "unit"]


class Kinematics:
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


def unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-12 else np.zeros_like(v)


def mjcf_root(path: Path) -> tuple[str, list[tuple[str, str]]]:
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
