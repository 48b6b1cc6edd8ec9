"""Stage track: refined trajectories the replay carries the object with (physics in the loop).

For every sequence the replay scores (:func:`dexflow.sim.replay_criteria.replay_window`: in
contact, supported, no free fall), :func:`dexflow.sim.track.track_sequence` searches, in the
replay's own MuJoCo scene, for the position targets under which the object follows its recorded
path (contact-guided grip schedules, then a receding-horizon sampling search, the refined
trajectory as the prior, its fingertips and the recorded object pose as the goals;
:mod:`dexflow.sim.track` explains it; grip schedules with the hold ``grasp`` also follow the
human fingertips, read from stage retarget's ``keypoints_human`` on its observed frames). The
output is a trajectory like any other (``data/track/sequences/<name>.npz``, the fourth method
``track`` beside baseline, retarget and refine): ``q`` is where the simulated hand is,
``targets`` the position targets that put it there (stage replay replays those),
``object_pose7`` the simulated object; outside the replay window both are the refined
trajectory, and sequences the replay does not score are passed through unchanged (``tracked``
false, ``not_tracked_reason`` the replay's reason).

**Feasible**: the tracked trajectory's replay succeeds by the replay's criteria (SPIDER's
thresholds and carried). Per sequence: ``tracked``, ``feasible``, ``not_tracked_reason`` and the
replay's summary entry of the tracked trajectory (``success``, ``position_error_mean_m``, ...),
and ``grip_drift_m``: how far the human's fingertips slide over the recorded object while it is
carried (:func:`dexflow.measures.grip_drift` of the scaled fingertips over the valid frames from
the lift to the window's end). A grasp that holds the object, as a carrying one must, and moves
it exactly as recorded misses the human's fingertips on those frames by at least that much, so
it says how much of the tracked trajectory's fingertip error the recording itself demands.
Summary: ``num_tracked``, ``feasible_rate`` (% of the tracked), the means of the object errors
(``position_error_mean_m``, ``rotation_error_mean_rad``, ``position_error_final_m``),
``lost_rate`` and ``grip_drift_mean_m``; the search's CPU time goes to ``reports/timing/track_refine.json``
(``cpu_seconds``, ``cpu_seconds_per_frame`` and ``cpu_seconds_per_70_frames`` of the replay
windows: the search is linear in frames).

Off by default (``dexflow params track=on`` turns it on): on the 24-sequence demo it adds about
5 minutes to ``dvc repro`` on 2 cores.

Deterministic: each sequence's perturbations come from ``np.random.default_rng([seed, crc32 of
its name])``, so results do not depend on the worker count or order.
"""

from __future__ import annotations

import dataclasses
import time
import zlib
from pathlib import Path

import numpy as np
import torch

from dexflow.human.keypoints import FINGERTIPS
from dexflow.io.artifacts import ObjectAssets, Trajectory, read_trajectory, write_trajectory
from dexflow.io.layout import Layout
from dexflow.measures import finite_mean, grip_drift
from dexflow.params import PipelineParams
from dexflow.pipeline.labelled import labelled_hand, load_labelled
from dexflow.pipeline.resume import StageOutput
from dexflow.pipeline.runner import StageSpec
from dexflow.sim.replay_criteria import lift_frame, replay_window
from dexflow.sim.replay_world import replay_world
from dexflow.sim.track import track_sequence

__all__ = ["STAGE", "run_track"]


def _clamp(hand):
    def clamp(x: np.ndarray) -> np.ndarray:
        q = hand.clamp(hand.apply_couplings(hand.as_q(x)))
        return q.cpu().numpy().astype(np.float64)

    return clamp


def run_track(params: PipelineParams, layout: Layout, label: str = "refine") -> dict:
    """Stage runner: track every trajectory labelled ``label`` (module docs).

    Returns:
        The summary (also written to the stage's ``summary.json``), with the wall-clock speed
        under ``timing`` (returned, not written there).
    """
    out, aligned = layout.track, layout.scale_align
    settings = params.track
    world_params = dataclasses.replace(params.replay, squeeze_m=settings.squeeze_m)
    stage = StageOutput(
        out,
        f"track {label}",
        {"hand": params.hand, "replay": params.replay, "track": params.track,
         "seed": params.seed},
        inputs=(layout.trajectory(label), layout.retarget("dexflow"), layout.contact,
                layout.scale_align, layout.hand_files),
    )  # fmt: skip
    files = stage.start()
    if files:  # a hand MuJoCo cannot load fails the stage once (exit 2), not every sequence
        replay_world(labelled_hand(params, layout), world_params, settings.squeeze_reach_m)

    def one(path: Path) -> dict:
        hand, seq, q, found = load_labelled(params, layout, path)
        prior = read_trajectory(path, hand.joint_names, seq.num_frames)
        touching = found.final.any(axis=1)
        world = replay_world(hand, world_params, settings.squeeze_reach_m)
        arrays = dict(prior.arrays)
        entry: dict = {"tracked": False, "feasible": False, "seconds": 0.0}
        window = None
        if touching.any():
            world.set_object(ObjectAssets(aligned.object_of(seq.obj_mesh)).paths.convex)
            window = replay_window(touching, seq, world.lowest_heights(seq.obj_pose), params.replay)
        if window is None or not window.scored:
            reason = "no contact" if window is None else window.not_scored_reason
            arrays.update(targets=q, object_pose7=np.full((len(q), 7), np.nan))
            write_trajectory(out.sequence(path), Trajectory(q, hand.joint_names, arrays))
            return {**entry, "not_tracked_reason": reason, "frames": 0}
        frames = (window.start, window.first_contact, window.end)
        rng = np.random.default_rng([int(params.seed), zlib.crc32(path.stem.encode())])
        tips = None  # the human fingertips: only the hold "grasp" follows them
        if "grasp" in settings.schedule_holds:
            human = read_trajectory(layout.retarget("dexflow").sequence(path), hand.joint_names)
            tips = human["keypoints_human"][:, hand.fingertip_keypoints]  # as fingertip error
            tips = np.where(human["observed"].astype(bool)[:, None, None], tips, np.nan)
        begin = time.process_time()
        result = track_sequence(
            world, q, seq.obj_pose, seq.fps, frames, found.final, settings, rng, _clamp(hand),
            tips,
        )  # fmt: skip
        seconds = time.process_time() - begin
        scored = result["replayed"]  # the replay of its targets, as stage replay's
        carry = np.arange(lift_frame(seq.obj_pose, frames), window.end + 1)
        if seq.valid is not None:
            carry = carry[np.asarray(seq.valid, dtype=bool)[carry]]
        drift = grip_drift(seq.keypoints[carry][:, list(FINGERTIPS)], seq.obj_pose[carry])
        arrays.update(
            targets=result["targets"], object_pose7=result["object_pose7"], cost=result["cost"]
        )
        write_trajectory(out.sequence(path), Trajectory(result["q"], hand.joint_names, arrays))
        return {
            **scored,
            "tracked": True,
            "feasible": bool(scored["success"]),
            "not_tracked_reason": None,
            "grip_drift_m": drift,
            "seconds": seconds,
        }

    torch.set_num_threads(1)
    tally = stage.run(one, files, params.run)
    tracked = [e for e in tally.ok if e["tracked"]]
    seconds = sum(e.pop("seconds") for e in tally.ok)
    frames = sum(e["frames"] for e in tracked)

    def mean(key: str) -> float:
        return float(np.mean([e[key] for e in tracked])) if tracked else float("nan")

    summary = {
        **tally.counts("track"),
        "num_tracked": len(tracked),
        "feasible_rate": 100 * mean("feasible"),
        "position_error_mean_m": mean("position_error_mean_m"),
        "rotation_error_mean_rad": mean("rotation_error_mean_rad"),
        "position_error_final_m": mean("position_error_final_m"),
        "lost_rate": 100 * mean("lost"),
        "grip_drift_mean_m": finite_mean(np.array([e["grip_drift_m"] for e in tracked])),
    }
    summary["sequences"] = dict(sorted(tally.sequences.items()))
    stage.finish(summary)
    return {
        **summary,
        "timing": {
            "cpu_seconds": seconds,
            "cpu_seconds_per_frame": seconds / frames if frames else 0.0,
            "cpu_seconds_per_70_frames": 70 * seconds / frames if frames else 0.0,
        },
    }


STAGE = StageSpec(
    name="track",
    run=run_track,
    metric_keys=None,
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences, {s['num_tracked']} tracked; feasible "
        f"{s['feasible_rate']:.1f} %, lost {s['lost_rate']:.0f} %, mean object error "
        f"{100 * s['position_error_mean_m']:.1f} cm / {s['rotation_error_mean_rad']:.2f} rad; "
        f"{s['timing']['cpu_seconds_per_70_frames']:.1f} CPU-s per 70 frames"
    ),
)  # fmt: skip
