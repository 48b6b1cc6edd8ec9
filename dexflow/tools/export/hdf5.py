"""An export as one HDF5 file: the episodes' arrays at full precision, one group per sequence.

::

    /                         attrs: format, format_version, method, hand, skipped (JSON)
    /joint_names              (dof,) str
    /fingers                  (F,) str
    /episodes/<sequence>/     attrs: episode_index, sequence, object, object_mesh, scale, fps,
                              side, mirrored, simulate_success, simulate_success_frame,
                              replay_scored, replay_success, replay_not_scored_reason
        q                     (T, dof) float64
        base_pose             (T, 4, 4) float64
        obj_pose              (T, 4, 4) float64
        contact               (T, F) bool
        penetration_m         (T,) float64
        valid                 (T,) bool

No modification times are stored, so the same export gives the same bytes.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dexflow.io.atomic import atomic_path
from dexflow.tools.export.episodes import Episode, Export, ExportError

__all__ = ["FORMAT", "FORMAT_VERSION", "read_hdf5", "write_hdf5"]

FORMAT = "dexflow-export"
FORMAT_VERSION = 2  # 2: targets
ARRAYS = ("q", "targets", "base_pose", "obj_pose", "contact", "penetration_m", "valid")
ATTRS = ("sequence", "object", "object_mesh", "scale", "fps", "side", "mirrored", "simulate_success",
         "simulate_success_frame", "replay_scored", "replay_success",
         "replay_not_scored_reason")  # fmt: skip
_STRINGS = ("sequence", "object", "object_mesh", "side", "replay_not_scored_reason")
_BOOLS = ("mirrored", "simulate_success", "replay_scored", "replay_success")


def write_hdf5(export: Export, path: str | Path) -> Path:
    """Write ``export`` to the HDF5 file ``path`` (atomically; an existing file is replaced).

    Raises:
        ExportError: ``path`` is a directory.
    """
    import h5py

    path = Path(path)
    if path.is_dir():
        raise ExportError(f"{path}: is a directory; --format hdf5 writes one file (e.g. out.h5)")
    strings = h5py.string_dtype()
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["method"] = export.method
        f.attrs["hand"] = export.hand
        f.attrs["skipped"] = json.dumps(export.skipped, sort_keys=True)
        f.create_dataset("joint_names", data=export.joint_names, dtype=strings, track_times=False)
        f.create_dataset("fingers", data=export.fingers, dtype=strings, track_times=False)
        episodes = f.create_group("episodes")
        for index, episode in enumerate(export.episodes):
            group = episodes.create_group(episode.sequence)
            group.attrs["episode_index"] = index
            for key in ATTRS:
                group.attrs[key] = getattr(episode, key)
            for key in ARRAYS:
                group.create_dataset(key, data=getattr(episode, key), track_times=False)
    return path


def read_hdf5(path: str | Path) -> Export:
    """Read an export written by :func:`write_hdf5`.

    Raises:
        ExportError: the file is not such an export.
    """
    import h5py

    path = Path(path)
    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != FORMAT:
            raise ExportError(f"{path}: not a dexflow export (attribute format is "
                              f"{f.attrs.get('format')!r}, expected {FORMAT!r})")  # fmt: skip
        names = [n.decode() for n in f["joint_names"][()]]
        fingers = [n.decode() for n in f["fingers"][()]]
        groups = sorted(f["episodes"].values(), key=lambda g: int(g.attrs["episode_index"]))
        episodes = []
        for group in groups:
            attrs = {k: group.attrs[k] for k in ATTRS}
            attrs |= {k: str(attrs[k]) for k in _STRINGS}
            attrs |= {k: bool(attrs[k]) for k in _BOOLS}
            attrs |= {k: float(attrs[k]) for k in ("fps", "scale")}
            attrs["simulate_success_frame"] = int(attrs["simulate_success_frame"])
            arrays = {k: np.asarray(group[k][()]) for k in ARRAYS if k in group}
            arrays.setdefault("targets", arrays["q"])  # format 1: the kinematic q
            episodes.append(Episode(**attrs, **arrays))
        return Export(
            method=str(f.attrs["method"]),
            hand=str(f.attrs["hand"]),
            joint_names=names,
            fingers=fingers,
            episodes=episodes,
            skipped=json.loads(f.attrs["skipped"]),
        )
