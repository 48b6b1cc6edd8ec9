"""Optional MANO: the 21 hand joints from MANO parameters, with the user's own model file.

dexflow never ships or downloads MANO (its licence forbids it). Point ``load_mano`` at your
``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl`` (or an ``.npz`` with the same arrays). Official files
pickle some arrays as ``chumpy`` objects; they are read without chumpy installed.

Joints: the 16 skeleton joints ``J_regressor @ v_shaped`` posed by forward kinematics along
``kintree_table`` (Rodrigues rotations), then the five fingertips taken from posed vertices
(linear blend skinning), as in the common MANO layers. The output is in MANO order with tips,
dexflow's keypoint order: the wrist, then thumb to little finger four keypoints each from the
palm outwards, the tip last (:data:`dexflow.human.keypoints.KEYPOINT_NAMES`).
"""

from __future__ import annotations

import copyreg
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.errors import DexflowError
from dexflow.io.untrusted import RestrictedUnpickler, load_npz, load_pickle

__all__ = ["FINGERTIP_VERTICES", "MANO_TO_DEXFLOW", "ManoModel", "load_mano"]

# Vertex ids of the fingertips on the MANO mesh: thumb, index, middle, ring, little.
FINGERTIP_VERTICES = (745, 317, 444, 556, 673)
# MANO's 16 joints + tips (0 wrist, index 1-3, middle 4-6, little 7-9, ring 10-12, thumb 13-15,
# tips thumb..little 16-20) -> dexflow/MANO-21 order. HO-3D uses the same 21-joint order.
MANO_TO_DEXFLOW = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)
_REQUIRED = ("v_template", "shapedirs", "J_regressor", "weights", "kintree_table")


class _Tolerant:
    """Stands in for chumpy classes while unpickling; keeps the array in its state."""

    def __init__(self, *args, **kwargs):
        self.state = None

    def __setstate__(self, state):
        self.state = state

    def __array__(self, dtype=None, copy=None):
        state = self.state if isinstance(self.state, dict) else {}
        for key in ("x", "a", "r"):
            if key in state:
                return np.asarray(state[key], dtype=dtype)
        raise DexflowError("a chumpy object in the MANO file holds no array ('x')")


def _sparse_class(name: str) -> type | None:
    """The scipy.sparse matrix class ``name`` (MANO's ``J_regressor``), None for anything else."""
    import scipy.sparse

    found = getattr(scipy.sparse, name, None)
    bases = (scipy.sparse.spmatrix, scipy.sparse.sparray)
    return found if isinstance(found, type) and issubclass(found, bases) else None


class _ManoUnpickler(RestrictedUnpickler):
    """Plain data, plus chumpy classes as :class:`_Tolerant`, scipy.sparse matrix classes, and
    ``copy_reg._reconstructor(cls, object, state)``, which protocol 0-1 pickles use to build
    them (it can only build classes this unpickler admits)."""

    def find_extra(self, module: str, name: str) -> Any | None:
        if module.startswith("chumpy"):
            return _Tolerant
        if module.startswith("scipy.sparse"):
            return _sparse_class(name)
        if (module, name) == ("copyreg", "_reconstructor"):
            return copyreg._reconstructor
        if (module, name) == ("builtins", "object"):
            return object
        return None


@dataclass
class ManoModel:
    """Arrays of a MANO hand model (any side)."""

    v_template: np.ndarray  # (V, 3)
    shapedirs: np.ndarray  # (V, 3, S)
    posedirs: np.ndarray | None  # (V, 3, 135)
    J_regressor: np.ndarray  # (16, V)
    weights: np.ndarray  # (V, 16)
    parents: np.ndarray  # (16,), -1 for the root
    hands_components: np.ndarray | None = None  # (C, 45) PCA basis of the hand pose
    hands_mean: np.ndarray | None = None  # (45,)

    def joints(
        self,
        global_orient: np.ndarray,
        hand_pose: np.ndarray,
        betas: np.ndarray | None = None,
        transl: np.ndarray | None = None,
    ) -> np.ndarray:
        """21 keypoints (T, 21, 3), dexflow/MANO order, in the model's units (metres).

        Args:
            global_orient: (T, 3) axis-angle of the wrist.
            hand_pose: (T, 45) axis-angle of the 15 finger joints, or (T, C) PCA coefficients
                when the model has ``hands_components`` (``hands_mean`` is added either way
                when it is present and the pose is given as PCA).
            betas: (S,) or (T, S) shape coefficients; zeros if None.
            transl: (T, 3) translation; zeros if None.
        """
        global_orient = np.atleast_2d(np.asarray(global_orient, dtype=np.float64))
        hand_pose = np.atleast_2d(np.asarray(hand_pose, dtype=np.float64))
        n_frames = len(global_orient)
        if hand_pose.shape[1] != 45:
            if self.hands_components is None:
                raise DexflowError(
                    f"hand_pose has {hand_pose.shape[1]} values; expected 45 "
                    "(this MANO model has no PCA components)"
                )
            hand_pose = hand_pose @ self.hands_components[: hand_pose.shape[1]]
            if self.hands_mean is not None:
                hand_pose = hand_pose + self.hands_mean
        n_shape = self.shapedirs.shape[-1]
        betas = np.zeros(n_shape) if betas is None else np.asarray(betas, dtype=np.float64)
        betas = np.broadcast_to(betas[..., :n_shape], (n_frames, n_shape))
        v_shaped = self.v_template + np.einsum("vcs,ts->tvc", self.shapedirs, betas)  # (T,V,3)
        rest_joints = np.einsum("jv,tvc->tjc", self.J_regressor, v_shaped)  # (T,16,3)
        pose = np.concatenate([global_orient, hand_pose], axis=1).reshape(n_frames, 16, 3)
        rot = Rotation.from_rotvec(pose.reshape(-1, 3)).as_matrix().reshape(n_frames, 16, 3, 3)
        if self.posedirs is not None:
            feature = (rot[:, 1:] - np.eye(3)).reshape(n_frames, -1)
            v_shaped = v_shaped + np.einsum("vcp,tp->tvc", self.posedirs, feature)
        world = np.zeros((n_frames, 16, 4, 4))
        for j, parent in enumerate(self.parents):
            local = np.zeros((n_frames, 4, 4))
            local[:, :3, :3] = rot[:, j]
            offset = rest_joints[:, j] - (rest_joints[:, parent] if parent >= 0 else 0.0)
            local[:, :3, 3] = offset
            local[:, 3, 3] = 1.0
            world[:, j] = local if parent < 0 else world[:, parent] @ local
        joints = world[:, :, :3, 3]
        # Skinning for the fingertip vertices only: remove each joint's rest position first.
        skin = world.copy()
        skin[:, :, :3, 3] -= np.einsum("tjab,tjb->tja", world[:, :, :3, :3], rest_joints)
        tips = np.asarray(FINGERTIP_VERTICES)
        blend = np.einsum("vj,tjab->tvab", self.weights[tips], skin)
        tip_pos = (
            np.einsum("tvab,tvb->tva", blend[..., :3, :3], v_shaped[:, tips]) + blend[..., :3, 3]
        )
        out = np.concatenate([joints, tip_pos], axis=1)[:, list(MANO_TO_DEXFLOW)]
        if transl is not None:
            out = out + np.asarray(transl, dtype=np.float64)[:, None]
        return out


def load_mano(path: str | Path) -> ManoModel:
    """Read a MANO model file (.pkl, with or without chumpy arrays, or .npz).

    The file is read as untrusted data (:mod:`dexflow.io.untrusted`): a pickle may name numpy,
    chumpy (kept as inert holders of their arrays) and scipy.sparse matrix classes only.

    Raises:
        DexflowError: missing file or arrays, with the names that are missing.
        UnsafePickleError: the pickle names any other global (it could run code).
    """
    path = Path(path)
    if not path.is_file():
        raise DexflowError(
            f"{path}: MANO model file not found (dexflow does not ship MANO; "
            "download it from the MANO website under its licence)"
        )
    if path.suffix == ".npz":
        raw = load_npz(path)
    else:
        raw = load_pickle(path, unpickler=_ManoUnpickler)
    if not isinstance(raw, dict):
        raise DexflowError(f"{path}: not a MANO model; expected a dict, found {type(raw).__name__}")
    missing = [k for k in _REQUIRED if k not in raw]
    if missing:
        raise DexflowError(f"{path}: not a MANO model; missing arrays {missing}")

    def arr(key):
        value = raw.get(key)
        if value is None:
            return None
        if hasattr(value, "toarray"):
            value = value.toarray()
        return np.asarray(value, dtype=np.float64)

    parents = np.asarray(arr("kintree_table")[0], dtype=np.int64)
    parents[0] = -1
    return ManoModel(
        v_template=arr("v_template"),
        shapedirs=arr("shapedirs"),
        posedirs=arr("posedirs"),
        J_regressor=arr("J_regressor"),
        weights=arr("weights"),
        parents=parents,
        hands_components=arr("hands_components"),
        hands_mean=arr("hands_mean"),
    )
