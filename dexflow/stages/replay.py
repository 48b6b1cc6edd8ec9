"""Stage replay: does the robot trajectory carry the object along its recorded path?

Stage simulate tests frames one at a time with the object held still; this stage plays a whole
grasp back in MuJoCo with the object free under gravity, as a dataset user (imitation learning,
RL from demonstrations) would, and measures how far the object ends up from where the human took
it. **Success** needs two things: SPIDER's criterion (the object's mean position error below
10 cm and its mean rotation error below 0.5 rad; ``replay.max_position_error_m``,
``max_rotation_error_rad``) and **carried**: its final position error below
``max_position_error_m`` and below ``carried_fraction`` (0.5) of the final error an object left
where it was at the first contact would have (the recorded object's net displacement over the
grasp). SPIDER's criterion alone cannot tell carrying from leaving: demo objects travel about
20 cm, and one that never moves has a mean error of about 8 cm. Both are reported
(``spider_success``, ``carried``); a recorded object that barely moves cannot be carried.

The scene is :class:`dexflow.sim.replay_world.ReplayWorld` (stage simulate's MuJoCo scene with
a driven base, gravity and a table; its docstring has the details).

**The scored window.** The replay runs from ``lead_frames`` before the first contact (stage
contact's final states; the hand approaches) to ``end``; frames first contact..``end`` are
scored. The object starts at rest at its recorded pose at the first contact; each recorded frame
is ``substeps`` physics steps of ``1 / (fps * substeps)`` seconds, the targets moving linearly
between frames. ``end`` is the last frame in contact before the **release**, else the last frame
in contact. The release is the first frame ``r`` after the first contact where

- no finger is in contact,
- the recorded object is more than ``release_distance_m`` from its position at ``a``, the last
  frame in contact before ``r``, and
- it is also more than ``release_distance_m`` from where it would be had it moved rigidly with
  the recorded human hand since ``a`` (its position in the wrist frame of the human keypoints,
  :func:`dexflow.human.keypoints.wrist_frame`, moved that far), the hand tracked at ``r`` and
  ``a``.

After its release the recorded object is carried off by someone else or falls, and the replayed
one, with nothing holding it, falls: on GRAB "pass" sequences scored to the last contact, mean
errors of 188-291 cm. The object must leave the hand, not only contact: on 83 DexYCB captures the
robot's fingers lose contact for 1-14 frames mid-carry in 6; in 5 the object moves 4-26 cm
meanwhile but at most 2.3 cm in the wrist's frame, in the sixth it does not move. An object put
down and let go does not move either, so putting it down and grasping it again is no release.

**Not scored** (``scored`` false, ``not_scored_reason``; not replayed, left out of every rate and
mean of the summary), the first that applies of:

- ``"no contact"``: no finger is ever in contact.
- ``"no support"``: the replay's table stands for a static support under the object at the first
  contact, and the recording must agree: from its first frame to the first contact the lowest
  point of the object's convex parts (at the recorded poses) stays within
  ``support_tolerance_m`` of its height at the first contact. Sliding or tipping over on a table
  keeps it there; lifted by the other hand, handed over by someone else or falling does not. A
  first contact at frame 0 leaves nothing to judge (scored); an object that hangs perfectly
  still in the air until the grasp cannot be told from one on a table this way. On the 83 DexYCB
  captures (z along their camera's axis) it changes by at most 2.3 cm.
- ``"free fall"``: within first contact..``end`` the recorded object falls freely, away from the
  hand: ``k = max(1, round(free_fall_s * fps))`` frames ``t..t+k-1`` there over which its mean
  vertical acceleration ``(v(t+k-1) - v(t-1)) * fps / k``, ``v(s) = (z(s+1) - z(s)) * fps``, is
  within ``free_fall_tolerance_mps2`` of ``-gravity``, and over which it moves more than
  ``release_distance_m`` in the wrist's frame (from frame ``t-1`` to ``t+k``, the hand tracked at
  both). A finger is in contact with an object falling off the hand (contact late to see a drop,
  or a tracking error): no replay reproduces that. Away from the hand, because hands move
  objects that fast: the demo's put objects down at a mean -9.2 m/s² over 0.2 s.

Vertical is world z, as for the replay's gravity and table.

**Targets.** A trajectory is replayed on its ``q``: the base's servos and the fingers' actuators
aim at it. A trajectory that also holds ``targets`` (stage track's: ``q`` is where the simulated
hand got to, ``targets`` the position targets that took it there, pressing into the object) is
replayed on those, base and fingers, and ``replay.squeeze_m`` does not apply to it.

Per sequence: the object's position and rotation error against its recorded pose at every replayed
frame; from the first contact on, their means (SPIDER's success), maxima and final values, SPIDER's
success, carried and success (both), the frame where the object was **lost** (its error first
beyond ``lost_position_m`` or ``lost_rotation_rad``; -1: never) and the **time held** before it;
also the error an object left where it started would have (``static_error_mean_m`` over the grasp,
the bar SPIDER's success sets; ``static_error_final_m`` at its end, the bar carried sets). Every
sequence has ``replayed``, ``scored`` and ``not_scored_reason`` (null when scored); one with
contact also ``start`` (first frame replayed), ``first_contact``, ``end``, ``last_contact``,
``release_frame`` (-1: none), ``support_drift_m`` (the largest change of the lowest point's
height before the first contact, m) and ``free_fall_frame`` (first frame of a free fall in the
window; -1: none), :class:`ReplayWindow`.

Two diagnostics per scored sequence say what bounds its success whatever the fingers do:

- **Rigid ceiling** (``ceiling_success``, ``ceiling_spider_success``,
  ``ceiling_position_error_mean_m``, ``ceiling_rotation_error_mean_rad``;
  :func:`dexflow.sim.replay_criteria.rigid_ceiling`): the object welded to the trajectory's base
  from the recorded **lift** (the first frame it is 1 cm from where it was at the first contact),
  scored by the same criteria, no physics. No grip carries the object closer to its recording
  than that hand path allows. On the demo 83-92 %; on 28 real DexYCB captures 61-86 % (both
  hands, every method; 7-14 % with their object rotations misread, the recorded object turning
  about 1 rad in the hand).
- **Unstable rest** (``unstable_rest``, ``rest_drift_m``, ``rest_drift_rad``;
  :meth:`ReplayWorld.rest_drift`): the object left alone on the replay's table at its recorded
  pose at the first contact, for the frames from ``start`` to the lift, is *lost* (beyond
  ``lost_position_m`` or ``lost_rotation_rad``). It rests on an edge: its annotation, or the
  table's frame, is tilted (or its rotations are misread), and it topples whatever the hand
  does. The demo 0 % (33 % with its misread-rotation artefacts on); the 28 real captures 4 %
  (Shadow's windows) and 7 % (Allegro's), 64-71 % with their rotations misread.

The summary's rates and means (``success_rate``, ``spider_success_rate``, ``carried_rate``,
``lost_rate`` in %, ``position_error_mean_m``, ``rotation_error_mean_rad``,
``position_error_final_m``, ``held_fraction``, ``static_error_*``, ``base_error_mean_m``,
``joint_error_mean_rad``, ``ceiling_success_rate``, ``ceiling_rotation_error_mean_rad``,
``unstable_rest_rate``, ``rest_drift_mean_m``) are over the scored sequences only. Counts: ``num_scored`` (=
``num_replayed``: only scored sequences are replayed), ``num_not_scored`` and, per reason,
``num_not_scored_no_contact``, ``num_not_scored_no_support``, ``num_not_scored_free_fall``;
``num_ended_at_release``: scored sequences whose window ends at a release before their last
contact.

Deterministic: one single-threaded MuJoCo run per sequence from a reset state; nothing random.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path

import numpy as np

from dexflow.io.artifacts import (
    ObjectAssets,
    ReplayResult,
    read_trajectory,
    write_replay,
)
from dexflow.io.layout import Layout
from dexflow.io.sequence import Sequence
from dexflow.params import PipelineParams
from dexflow.pipeline.labelled import labelled_hand, labelled_output, load_labelled
from dexflow.pipeline.runner import StageSpec
from dexflow.sim.replay_criteria import (
    ReplayWindow,
    grasp_window,
    lift_frame,
    replay_window,
    rigid_ceiling,
    sequence_result,
)
from dexflow.sim.replay_world import ReplayWorld, replay_world

__all__ = [
    "NOT_SCORED_REASONS",
    "STAGE",
    "ReplayWindow",
    "aggregate",
    "grasp_window",
    "replay_sequence",
    "replay_window",
    "run_replay",
]

NOT_SCORED_REASONS = ("no contact", "no support", "free fall")

logger = logging.getLogger(__name__)


def _empty_rows() -> dict[str, np.ndarray]:
    return {
        "frame": np.zeros(0, dtype=np.int64),
        "position_error_m": np.zeros(0),
        "rotation_error_rad": np.zeros(0),
        "object_position": np.zeros((0, 3)),
        "object_quat": np.zeros((0, 4)),
        "base_error_m": np.zeros(0),
        "joint_error_rad": np.zeros(0),
    }


def replay_sequence(
    world: ReplayWorld,
    seq: Sequence,
    q: np.ndarray,
    touching: np.ndarray,
    targets: np.ndarray | None = None,
) -> tuple[dict[str, np.ndarray], dict]:
    """Replay one sequence over its window, if it can be scored (module docs).

    Args:
        world: The scene, its object set (:meth:`ReplayWorld.set_object`) where ``touching``
            has a contact.
        seq: The recorded sequence (object poses, human keypoints, fps).
        q: (T, dof) the trajectory.
        touching: (T,) frames with a finger in contact (stage contact's final states).
        targets: (T, dof) the position targets of base and fingers, where the trajectory has
            them (stage track's: ``q`` is where they put the hand); replayed as they are.

    Returns:
        The rows of :class:`~dexflow.io.artifacts.ReplayResult` (none where not scored) and the
        sequence's summary entry.
    """
    p = world.replay_params
    touching = np.asarray(touching, dtype=bool)
    not_scored = {"replayed": False, "scored": False, "frames": 0}
    if not touching.any():
        return _empty_rows(), {**not_scored, "not_scored_reason": "no contact"}
    window = replay_window(touching, seq, world.lowest_heights(seq.obj_pose), p)
    if not window.scored:
        return _empty_rows(), {**not_scored, **window.entry()}
    frames = (window.start, window.first_contact, window.end)
    if targets is not None:
        rows = world.replay(targets, seq.obj_pose, seq.fps, frames)
    else:
        squeezed = world.squeezed(q, seq.obj_pose, touching)
        rows = world.replay(q, seq.obj_pose, seq.fps, frames, squeezed)
    result = sequence_result(rows, window.first_contact, seq.obj_pose, seq.fps, p)
    ceiling = rigid_ceiling(q, seq.obj_pose, seq.fps, frames, p)
    rest = lift_frame(seq.obj_pose, frames) - window.start
    drift_m, drift_rad = world.rest_drift(seq.obj_pose[window.first_contact], seq.fps, rest)
    unstable = drift_m > p.lost_position_m or drift_rad > p.lost_rotation_rad
    diagnostics = {"rest_drift_m": drift_m, "rest_drift_rad": drift_rad, "unstable_rest": unstable}
    return rows, {**result, **ceiling, **diagnostics, **window.entry()}


def aggregate(entries: list[dict]) -> dict:
    """The summary's counts, rates (%) and means from the sequences' entries: over the scored
    sequences only (module docs)."""
    scored = [e for e in entries if e["scored"]]
    reasons = Counter(e["not_scored_reason"] for e in entries if not e["scored"])

    def mean(key: str) -> float:
        return float(np.mean([e[key] for e in scored])) if scored else float("nan")

    return {
        "num_replayed": sum(e["replayed"] for e in entries),
        "num_scored": len(scored),
        "num_not_scored": len(entries) - len(scored),
        **{f"num_not_scored_{r.replace(' ', '_')}": reasons[r] for r in NOT_SCORED_REASONS},
        "num_ended_at_release": sum(e["end"] < e["last_contact"] for e in scored),
        "success_rate": 100 * mean("success"),
        "spider_success_rate": 100 * mean("spider_success"),
        "carried_rate": 100 * mean("carried"),
        "position_error_mean_m": mean("position_error_mean_m"),
        "rotation_error_mean_rad": mean("rotation_error_mean_rad"),
        "position_error_final_m": mean("position_error_final_m"),
        "held_fraction": mean("held_fraction"),
        "lost_rate": 100 * mean("lost"),
        "static_error_mean_m": mean("static_error_mean_m"),
        "static_error_final_m": mean("static_error_final_m"),
        "base_error_mean_m": mean("base_error_mean_m"),
        "joint_error_mean_rad": mean("joint_error_mean_rad"),
        "ceiling_success_rate": 100 * mean("ceiling_success"),
        "ceiling_rotation_error_mean_rad": mean("ceiling_rotation_error_mean_rad"),
        "unstable_rest_rate": 100 * mean("unstable_rest"),
        "rest_drift_mean_m": mean("rest_drift_m"),
    }


def run_replay(params: PipelineParams, layout: Layout, label: str) -> dict:
    """Stage runner: replay every trajectory labelled ``label`` with the object free.

    Args:
        params: Pipeline params (``hand``, ``replay``, ``run``).
        layout: The project's paths; the trajectories are ``layout.trajectory(label)``.
        label: One of :data:`~dexflow.io.layout.TRAJECTORIES` (baseline, retarget, refine,
            track); a trajectory with ``targets`` (stage track's) is replayed on those.

    Returns:
        The summary (also written to the stage's ``summary.json``), with the wall-clock speed
        under ``timing`` (returned, not written there).
    """
    out, aligned = layout.replay(label), layout.scale_align
    stage = labelled_output("replay", params, layout, label, out)
    files = stage.start()
    rp = params.replay
    if files:  # a hand MuJoCo cannot load fails the stage once (exit 2), not every sequence
        replay_world(labelled_hand(params, layout), rp)

    def one(path: Path) -> dict:
        hand, seq, q, found = load_labelled(params, layout, path)
        touching = found.final.any(axis=1)
        world = replay_world(hand, rp)
        if touching.any():
            world.set_object(ObjectAssets(aligned.object_of(seq.obj_mesh)).paths.convex)
        targets = read_trajectory(path, hand.joint_names, seq.num_frames).arrays.get("targets")
        begin = time.perf_counter()
        rows, entry = replay_sequence(world, seq, q, touching, targets)
        seconds = time.perf_counter() - begin
        write_replay(out.sequence(path), ReplayResult(rows))
        return {**entry, "seconds": seconds}

    tally = stage.run(one, files, params.run)
    seconds = sum(s.pop("seconds") for s in tally.ok)
    summary = {**tally.counts("replay"), "method": label, **aggregate(tally.ok)}
    summary["sequences"] = dict(sorted(tally.sequences.items()))
    stage.finish(summary)
    frames = summary["num_frames"]
    return {
        **summary,
        "timing": {"frames_per_second_one_core": frames / seconds if seconds else 0.0},
    }


STAGE = StageSpec(
    name="replay",
    run=run_replay,
    metric_keys=None,  # every aggregate
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences, {s['num_scored']} scored "
        f"({s['num_ended_at_release']} up to the release; not scored: "
        f"{s['num_not_scored_no_contact']} no contact, {s['num_not_scored_no_support']} no "
        f"support, {s['num_not_scored_free_fall']} free fall); success "
        f"{s['success_rate']:.1f} % (SPIDER's {s['spider_success_rate']:.1f} % and carried "
        f"{s['carried_rate']:.1f} %), lost {s['lost_rate']:.0f} %, mean object error "
        f"{100 * s['position_error_mean_m']:.1f} cm / {s['rotation_error_mean_rad']:.2f} rad, "
        f"held {100 * s['held_fraction']:.0f} % of the grasp; {s['num_frames']} frames, "
        f"{s['timing']['frames_per_second_one_core']:.0f} frames/s per core"
    ),
)  # fmt: skip
