"""An export as a LeRobot dataset, on-disk layout of LeRobot's codebase ``v2.1`` (no videos).

::

    meta/info.json              codebase_version "v2.1", fps, features, data_path, ... and
                                "dexflow": method, hand, skipped sequences, quaternion order
    meta/tasks.jsonl            one task per object: its name
    meta/episodes.jsonl         per episode: episode_index, tasks, length, and dexflow's
                                sequence, object, object_mesh, scale, side, mirrored and
                                success flags
    meta/episodes_stats.jsonl   per episode and feature: min, max, mean, std, count (v2.1)
    meta/stats.json             the same over every frame (what v2.0 readers load)
    data/chunk-XXX/episode_XXXXXX.parquet   one row per frame

Features (float32 unless said): ``observation.state`` = q (dof,), ``action`` = the next frame's
position targets (:attr:`Episode.targets`: q itself but for stage track's, whose targets press
into the object; the last frame repeats its own), ``observation.environment_state`` = the object pose
``[x, y, z, qw, qx, qy, qz]``, ``base_pose`` = the hand root's pose (same order), ``contact``
(F,) bool, ``penetration_m``, ``valid`` bool, and LeRobot's ``timestamp``, ``frame_index``,
``episode_index``, ``index``, ``task_index``. Only ``observation.*`` and ``action`` are what
LeRobot's policies take as inputs and targets; the others ride along as labels.

The dataset has one frame rate, so every episode must share it.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from dexflow.geometry import pose_from_vector, pose_vector
from dexflow.tools.export.episodes import Episode, Export, ExportError
from dexflow.tools.export.hdf5 import FORMAT, FORMAT_VERSION

__all__ = ["CODEBASE_VERSION", "pose_from_vector", "pose_vector", "read_lerobot", "write_lerobot"]

CODEBASE_VERSION = "v2.1"
CHUNKS_SIZE = 1000
DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
POSE_NAMES = ["x", "y", "z", "qw", "qx", "qy", "qz"]
_INDEX = ("timestamp", "frame_index", "episode_index", "index", "task_index")


def _features(export: Export) -> dict[str, dict]:
    dof, fingers = len(export.joint_names), export.fingers

    def feature(dtype: str, shape: int, names: list[str] | None = None) -> dict:
        return {"dtype": dtype, "shape": [shape], "names": names}

    return {
        "observation.state": feature("float32", dof, export.joint_names),
        "action": feature("float32", dof, export.joint_names),
        "observation.environment_state": feature("float32", 7, POSE_NAMES),
        "base_pose": feature("float32", 7, POSE_NAMES),
        "contact": feature("bool", len(fingers), fingers),
        "penetration_m": feature("float32", 1),
        "valid": feature("bool", 1),
        "timestamp": feature("float32", 1),
        "frame_index": feature("int64", 1),
        "episode_index": feature("int64", 1),
        "index": feature("int64", 1),
        "task_index": feature("int64", 1),
    }


def _columns(episode: Episode, index: int, first: int, task: int, fps: float) -> dict:
    """The episode's columns, by feature name (numpy arrays, one row per frame)."""
    frames = np.arange(episode.num_frames)
    q = episode.q.astype(np.float32)
    targets = episode.targets.astype(np.float32)
    return {
        "observation.state": q,
        "action": np.concatenate([targets[1:], targets[-1:]]),
        "observation.environment_state": pose_vector(episode.obj_pose).astype(np.float32),
        "base_pose": pose_vector(episode.base_pose).astype(np.float32),
        "contact": episode.contact.astype(bool),
        "penetration_m": episode.penetration_m.astype(np.float32),
        "valid": episode.valid.astype(bool),
        "timestamp": (frames / fps).astype(np.float32),
        "frame_index": frames.astype(np.int64),
        "episode_index": np.full(len(frames), index, dtype=np.int64),
        "index": (first + frames).astype(np.int64),
        "task_index": np.full(len(frames), task, dtype=np.int64),
    }


def _arrow(values: np.ndarray) -> pa.Array:
    if values.ndim == 1:
        return pa.array(values)
    return pa.FixedSizeListArray.from_arrays(pa.array(values.ravel()), values.shape[1])


def _numpy(column: pa.ChunkedArray) -> np.ndarray:
    """A column as (T,) or, for a list column, (T, n)."""
    array = column.combine_chunks()
    if pa.types.is_fixed_size_list(array.type):
        return array.flatten().to_numpy(zero_copy_only=False).reshape(len(array), -1)
    return array.to_numpy(zero_copy_only=False)


def _stats(values: np.ndarray) -> dict[str, list]:
    """LeRobot's per-feature statistics over the frames (first axis)."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]

    def listed(array: np.ndarray) -> list:
        return [None if not np.isfinite(v) else float(v) for v in array]

    return {
        "min": listed(values.min(axis=0)),
        "max": listed(values.max(axis=0)),
        "mean": listed(values.mean(axis=0)),
        "std": listed(values.std(axis=0)),
        "count": [len(values)],
    }


def _fps(export: Export) -> float | int:
    rates = {e.fps for e in export.episodes}
    if len(rates) > 1:
        by_rate = {r: [e.sequence for e in export.episodes if e.fps == r][:3] for r in rates}
        raise ExportError(
            f"a LeRobot dataset has one frame rate, the sequences have {len(rates)}: "
            + "; ".join(
                f"{r:g} fps ({', '.join(names)}, ...)" for r, names in sorted(by_rate.items())
            )
            + "; export them with --format hdf5, or each rate on its own"
        )
    (fps,) = rates
    return int(fps) if float(fps).is_integer() else fps


def _dump(obj) -> str:
    return json.dumps(obj, sort_keys=True, allow_nan=False)


def write_lerobot(export: Export, path: str | Path) -> Path:
    """Write ``export`` as a LeRobot v2.1 dataset in the directory ``path``.

    The dataset is written beside ``path`` and moved there when complete. An existing ``path``
    is replaced only if it is empty or a previous export (it has ``meta/info.json`` with a
    ``dexflow`` entry).

    Raises:
        ExportError: the episodes have different frame rates, or ``path`` holds something else.
    """
    path = Path(path)
    fps = _fps(export)
    previous = path / "meta" / "info.json"
    if path.is_file() or (path.is_dir() and any(path.iterdir())):
        try:
            ours = "dexflow" in json.loads(previous.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            ours = False
        if not ours:
            raise ExportError(
                f"{path}: exists and is not a previous export (no meta/info.json written by "
                "dexflow export); give a new or empty directory"
            )
    features = _features(export)
    tasks = sorted({e.object for e in export.episodes})
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        (tmp / "meta").mkdir()
        episodes, episode_stats, every = [], [], {k: [] for k in features}
        first = 0
        for index, episode in enumerate(export.episodes):
            columns = _columns(episode, index, first, tasks.index(episode.object), fps)
            file = tmp / DATA_PATH.format(episode_chunk=index // CHUNKS_SIZE, episode_index=index)
            file.parent.mkdir(parents=True, exist_ok=True)
            table = pa.table({k: _arrow(v) for k, v in columns.items()})
            pq.write_table(table, file)
            first += episode.num_frames
            for key, values in columns.items():
                every[key].append(values)
            episode_stats.append({"episode_index": index,
                                  "stats": {k: _stats(v) for k, v in columns.items()}})  # fmt: skip
            episodes.append(
                {
                    "episode_index": index,
                    "tasks": [episode.object],
                    "length": episode.num_frames,
                    "sequence": episode.sequence,
                    "object": episode.object,
                    "object_mesh": episode.object_mesh,
                    "scale": episode.scale,
                    "side": episode.side,
                    "mirrored": episode.mirrored,
                    "simulate_success": episode.simulate_success,
                    "simulate_success_frame": episode.simulate_success_frame,
                    "replay_scored": episode.replay_scored,
                    "replay_success": episode.replay_success,
                    "replay_not_scored_reason": episode.replay_not_scored_reason,
                }
            )
        count = len(export.episodes)
        info = {
            "codebase_version": CODEBASE_VERSION,
            "robot_type": export.hand,
            "total_episodes": count,
            "total_frames": first,
            "total_tasks": len(tasks),
            "total_videos": 0,
            "total_chunks": (count + CHUNKS_SIZE - 1) // CHUNKS_SIZE,
            "chunks_size": CHUNKS_SIZE,
            "fps": fps,
            "splits": {"train": f"0:{count}"},
            "data_path": DATA_PATH,
            "video_path": None,
            "features": features,
            "dexflow": {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "method": export.method,
                "hand": export.hand,
                "pose_order": POSE_NAMES,
                "skipped": export.skipped,
            },
        }
        stats = {k: _stats(np.concatenate(v)) for k, v in every.items()}
        meta = tmp / "meta"
        (meta / "info.json").write_text(json.dumps(info, indent=4, allow_nan=False) + "\n")
        (meta / "stats.json").write_text(json.dumps(stats, indent=4, allow_nan=False) + "\n")
        lines = {
            "tasks.jsonl": [{"task_index": i, "task": t} for i, t in enumerate(tasks)],
            "episodes.jsonl": episodes,
            "episodes_stats.jsonl": episode_stats,
        }
        for name, rows in lines.items():
            (meta / name).write_text("".join(_dump(r) + "\n" for r in rows))
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            path.rename(old / path.name)
            tmp.rename(path)
            shutil.rmtree(old)
        else:
            tmp.rename(path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return path


def read_lerobot(path: str | Path) -> Export:
    """Read a dataset written by :func:`write_lerobot` (q, poses and penetration come back as
    float64 of the stored float32).

    Raises:
        ExportError: ``path`` is not such a dataset.
    """
    path = Path(path)
    try:
        info = json.loads((path / "meta" / "info.json").read_text(encoding="utf-8"))
        ours = info["dexflow"]
    except (OSError, ValueError, KeyError) as exc:
        raise ExportError(
            f"{path}: not a LeRobot dataset written by dexflow export ({exc})"
        ) from exc
    lines = (path / "meta" / "episodes.jsonl").read_text(encoding="utf-8").splitlines()
    entries = sorted((json.loads(line) for line in lines), key=lambda e: e["episode_index"])
    features = info["features"]
    episodes = []
    for entry in entries:
        index = entry["episode_index"]
        file = path / info["data_path"].format(
            episode_chunk=index // info["chunks_size"], episode_index=index
        )
        table = pq.read_table(file)
        columns = {k: _numpy(table.column(k)) for k in features}
        episodes.append(
            Episode(
                sequence=entry["sequence"],
                object=entry["object"],
                object_mesh=entry["object_mesh"],
                scale=float(entry["scale"]),
                fps=float(info["fps"]),
                side=entry["side"],
                mirrored=entry["mirrored"],
                q=columns["observation.state"].astype(np.float64),
                # action[t] is the target of frame t + 1: frame 0's is not stored (its state)
                targets=np.concatenate(
                    [columns["observation.state"][:1], columns["action"][:-1]]
                ).astype(np.float64),
                base_pose=pose_from_vector(columns["base_pose"]),
                obj_pose=pose_from_vector(columns["observation.environment_state"]),
                contact=columns["contact"].astype(bool),
                penetration_m=columns["penetration_m"].astype(np.float64),
                valid=columns["valid"].astype(bool),
                simulate_success=entry["simulate_success"],
                simulate_success_frame=entry["simulate_success_frame"],
                replay_scored=entry["replay_scored"],
                replay_success=entry["replay_success"],
                replay_not_scored_reason=entry["replay_not_scored_reason"],
            )
        )
    return Export(
        method=ours["method"],
        hand=ours["hand"],
        joint_names=list(features["observation.state"]["names"]),
        fingers=list(features["contact"]["names"]),
        episodes=episodes,
        skipped=ours["skipped"],
    )
