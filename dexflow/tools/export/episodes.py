"""The episodes of an export, read from a project's pipeline outputs with the typed readers.

One episode per sequence that every stage the export reads finished; the others are listed as
skipped with the stage and reason the pipeline recorded (a sequence dropped by one stage is
dropped from every later one, and the rest go on).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dexflow.errors import ArtifactError, DexflowError
from dexflow.hands.robot import BASE_JOINT_NAMES, base_transform
from dexflow.io.artifacts import read_contact, read_metric_frames, read_trajectory
from dexflow.io.layout import TRAJECTORIES, Layout, StageDir
from dexflow.io.sequence import load_sequence
from dexflow.tools.viz import TRAJECTORIES as TRAJECTORY_STAGES
from dexflow.tools.viz import MissingInputError

__all__ = ["Episode", "Export", "ExportError", "base_poses", "collect_export"]


class ExportError(DexflowError, ValueError):
    """An export that cannot be made or read: unknown method or format, no sequence to export,
    an output path that holds something else, a file that is no export."""


@dataclass
class Episode:
    """One sequence of an export.

    Attributes:
        sequence: The sequence name (``<object>__<take>``).
        object: The object's name (``obj_name``).
        object_mesh: The mesh ``obj_pose`` places, relative to the project
            (``data/scale_align/objects/<key>/mesh.obj``: scaled, mirrored with the scene).
        scale: The human-to-robot size factor the scene was scaled by about the world origin.
        fps: Frames per second.
        side: The human hand's side, ``'right'`` or ``'left'``.
        mirrored: True if a left hand was mirrored to the right hand (x -> -x in the world).
        q: (T, dof) joint positions, the floating base's six first (radians, metres).
        targets: (T, dof) the position targets that drive the hand to ``q`` (stage track's,
            which press into the object: a position servo grips only that way); ``q`` itself
            for the kinematic methods.
        base_pose: (T, 4, 4) the hand's root (floating base) to world.
        obj_pose: (T, 4, 4) object mesh to world.
        contact: (T, F) finger in contact with the object (stage contact's final states).
        penetration_m: (T,) the deepest point of the hand inside the object (metres, 0 if none).
        valid: (T,) the human hand was tracked (elsewhere ``q`` is bridged).
        simulate_success: A frame's grasp held the object (stage simulate, every criterion).
        simulate_success_frame: That frame, -1 if none.
        replay_scored: Stage replay scored the sequence (see ``replay_not_scored_reason``).
        replay_success: Replaying ``q`` with the object free carried it (False if not scored).
        replay_not_scored_reason: Why replay did not score it, ``""`` if it did.
    """

    sequence: str
    object: str
    object_mesh: str
    scale: float
    fps: float
    side: str
    mirrored: bool
    q: np.ndarray
    targets: np.ndarray
    base_pose: np.ndarray
    obj_pose: np.ndarray
    contact: np.ndarray
    penetration_m: np.ndarray
    valid: np.ndarray
    simulate_success: bool
    simulate_success_frame: int
    replay_scored: bool
    replay_success: bool
    replay_not_scored_reason: str

    @property
    def num_frames(self) -> int:
        return int(self.q.shape[0])


@dataclass
class Export:
    """What an export holds.

    Attributes:
        method: The trajectory exported (``baseline``, ``retarget`` or ``refine``).
        hand: The robot hand's name (``params.yaml`` ``hand.name``).
        joint_names: The dof names of the columns of every episode's ``q``.
        fingers: The F finger names of the columns of every episode's ``contact``.
        episodes: One per exported sequence, sorted by name.
        skipped: Per sequence left out, why (the stage that dropped it and its error).
    """

    method: str
    hand: str
    joint_names: list[str]
    fingers: list[str]
    episodes: list[Episode]
    skipped: dict[str, str] = field(default_factory=dict)


def base_poses(q_base: np.ndarray) -> np.ndarray:
    """(T, 4, 4) the hand's root to world from the six floating-base joints ``q_base (T, 6)``
    (:func:`dexflow.hands.robot.base_transform`: ``T(x, y, z) Rx Ry Rz``)."""
    import torch

    return base_transform(torch.as_tensor(q_base, dtype=torch.float64)).numpy()


def _stages(layout: Layout, method: str) -> list[tuple[str, StageDir]]:
    """The DVC stages an export of ``method`` reads, in pipeline order, with their outputs."""
    return [
        ("scale_align", layout.scale_align),
        (TRAJECTORY_STAGES[method], layout.trajectory(method)),
        ("contact", layout.contact),
        (f"simulate@{method}", layout.simulate(method)),
        (f"replay@{method}", layout.replay(method)),
        ("metrics", layout.metrics),
    ]


def _missing(path: Path, stage: str) -> MissingInputError:
    return MissingInputError(
        f"{path}: no such file; it is written by the DVC stage '{stage}' (run `dvc repro {stage}`)"
    )


def _summary(stage: str, out: StageDir) -> dict:
    """A stage's ``summary.json``, written when the stage completed."""
    if not out.summary.is_file():
        raise _missing(out.summary, stage)
    try:
        summary = json.loads(out.summary.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise ArtifactError(f"{out.summary}: not JSON ({exc}); rerun `dvc repro {stage}`") from exc
    if not isinstance(summary, dict) or not isinstance(summary.get("sequences"), dict):
        raise ArtifactError(f"{out.summary}: no 'sequences' entries; rerun `dvc repro {stage}`")
    return summary


def _skip_reason(name: str, stages: list[tuple[str, StageDir, dict]]) -> str | None:
    """Why sequence ``name`` cannot be exported (the first stage without it), None if it can."""
    for stage, _, summary in stages:
        entry = summary["sequences"].get(name)
        if entry is not None and entry.get("status") == "ok":
            continue
        dropped = summary.get("dropped", {}).get(name)
        if dropped is not None:
            return f"dropped by {dropped.get('stage')}: {dropped.get('error')}"
        if entry is not None:
            return f"{stage} {entry.get('status')}: {entry.get('error')}"
        return f"not in the output of {stage} (run `dvc repro {stage}`)"
    return None


def _flags(name: str, simulate: tuple[str, StageDir, dict], replay: tuple[str, StageDir, dict]):
    """The success flags of sequence ``name`` from stage simulate's and replay's summaries."""

    def value(stage: tuple[str, StageDir, dict], key: str):
        label, out, summary = stage
        entry = summary["sequences"][name]
        if key not in entry:
            raise ArtifactError(
                f"{out.summary}: the entry of {name} has no {key!r}; found {sorted(entry)} "
                f"(rerun `dvc repro {label}`)"
            )
        return entry[key]

    scored = bool(value(replay, "scored"))
    return {
        "simulate_success": bool(value(simulate, "success")),
        "simulate_success_frame": int(value(simulate, "success_frame")),
        "replay_scored": scored,
        "replay_success": bool(value(replay, "success")) if scored else False,
        "replay_not_scored_reason": "" if scored else str(value(replay, "not_scored_reason")),
    }


def _file(out: StageDir, name: str, stage: str) -> Path:
    path = out.sequence(name)
    if not path.is_file():  # its summary says ok: the outputs are out of step
        raise _missing(path, stage)
    return path


def collect_export(project_root: str | Path, method: str = "refine") -> Export:
    """Read the episodes of ``method``'s trajectories from a project's pipeline outputs.

    Args:
        project_root: The project (holding ``params.yaml`` and ``data/``).
        method: ``refine`` (data/refine), ``retarget`` (data/retarget/dexflow), ``baseline``
            (data/retarget/position) or, with track=on, ``track`` (data/track).

    Raises:
        ExportError: unknown method, or no sequence could be exported.
        MissingInputError: a stage's ``summary.json`` (or a sequence file its summary lists as
            done) is missing; the message names the file and the DVC stage that writes it.
        ArtifactError: a file does not hold what its stage writes, or the sequences disagree
            on the joint or finger names.
    """
    if method not in TRAJECTORIES:
        raise ExportError(f"unknown method {method!r}; expected one of {', '.join(TRAJECTORIES)}")
    from dexflow.config import load_params

    root = Path(project_root)
    hand = load_params(root / "params.yaml").hand.name
    layout = Layout(root)
    stages = [(stage, out, _summary(stage, out)) for stage, out in _stages(layout, method)]
    by_label = {stage[0]: stage for stage in stages}
    names = sorted({n for _, _, s in stages for n in (*s["sequences"], *s.get("dropped", {}))})
    episodes, skipped = [], {}
    joint_names: list[str] | None = None
    fingers: list[str] | None = None
    for name in names:
        reason = _skip_reason(name, stages)
        if reason is not None:
            skipped[name] = reason
            continue
        # the stages with a file per sequence (simulate's and replay's flags are in summaries)
        files = {stage: _file(out, name, stage) for stage, out, _ in stages
                 if not stage.startswith(("simulate@", "replay@"))}  # fmt: skip
        seq = load_sequence(files["scale_align"])
        frames = seq.num_frames
        trajectory = read_trajectory(files[TRAJECTORY_STAGES[method]], joint_names, frames)
        found = read_contact(files["contact"], fingers, frames)
        if joint_names is None and tuple(trajectory.joint_names[:6]) != BASE_JOINT_NAMES:
            raise ArtifactError(
                f"{files[TRAJECTORY_STAGES[method]]}: the first six joints are "
                f"{trajectory.joint_names[:6]}, expected the floating base {list(BASE_JOINT_NAMES)}"
            )
        joint_names, fingers = trajectory.joint_names, found.fingers
        per_frame = read_metric_frames(files["metrics"]).methods.get(method, {})
        if "pd_m" not in per_frame:
            raise ArtifactError(
                f"{files['metrics']}: missing '{method}.pd_m' (run `dvc repro metrics`)"
            )
        penetration = np.asarray(per_frame["pd_m"], dtype=np.float64)
        if penetration.shape != (frames,):
            raise ArtifactError(
                f"{files['metrics']}: {method}.pd_m has shape {penetration.shape}, expected "
                f"({frames},) (the sequence's frames)"
            )
        episodes.append(
            Episode(
                sequence=name,
                object=seq.obj_name,
                object_mesh=(Layout().scale_align.root / seq.obj_mesh).as_posix(),
                scale=float(seq.extras.get("scale", 1.0)),
                fps=float(seq.fps),
                side=seq.side,
                mirrored=bool(seq.mirrored),
                q=trajectory.q,
                targets=np.asarray(trajectory.arrays.get("targets", trajectory.q), np.float64),
                base_pose=base_poses(trajectory.q[:, :6]),
                obj_pose=np.asarray(seq.obj_pose, dtype=np.float64),
                contact=found.final,
                penetration_m=penetration,
                valid=seq.valid_mask.copy(),
                **_flags(name, by_label[f"simulate@{method}"], by_label[f"replay@{method}"]),
            )
        )
    if not episodes:
        listed = "; ".join(f"{n}: {why}" for n, why in skipped.items()) or "no sequences"
        raise ExportError(f"{root}: nothing to export for method {method!r} ({listed})")
    return Export(method, hand, list(joint_names), list(fingers), episodes, skipped)
