"""Stage metrics: every number the reports show, per sequence and aggregated, with its definition.

Methods: ``baseline`` (stage retarget, method ``position``: per-frame keypoint matching),
``retarget`` (DexFlow retargeting) and ``refine`` (DexFlow + contact refinement). All lengths are
reported in millimetres; "frames" are all frames of a sequence unless said otherwise.

Definitions (per sequence; the aggregate is the mean over sequences unless said otherwise):

- ``keypoint_error_mm``: mean over observed frames (valid and not tracking-lost) of the mean
  distance between the robot's keypoints and the human keypoints they are mapped to.
- ``fingertip_error_mm``: the same over the fingertip keypoints only (the keypoints mapped to
  MANO tips 4, 8, 12, 16, 20): how far the robot's fingertips are from the human's.
- ``fingertip_error_surface_mm``: the same against the human fingertips pushed out to the
  object's surface (:func:`dexflow.human.surface_tips.surface_corrected_tips`; tips outside
  the object stay): on real captures the annotated tips lie millimetres inside the scanned
  object, so a hand that does not penetrate cannot reach them, and this is the error against
  the physically possible target. The raw ``fingertip_error_mm`` stays beside it.
- ``time_aligned_cd_mm``: per observed frame, the symmetric Chamfer distance between the human
  keypoint set and the robot keypoint set, ``½ (mean_a min_b |a - b| + mean_b min_a |a - b|)``,
  averaged over frames. dexflow's own measure, not the paper's "time-aligned CD" (whose
  definition is not published): wherever the robot's keypoints are nearer to their own human
  keypoints than to any other (errors below half the keypoint spacing, which holds on every
  dataset tried), each nearest neighbour is the matched keypoint and it equals
  ``keypoint_error_mm``. It differs only where the keypoints are confused.
- ``velocity_kl``: KL divergence between the histograms of human and robot fingertip speeds
  over consecutive observed frames (:func:`dexflow.measures.velocity_kl`; the aggregate pools
  the speeds of all sequences). Identical trajectories give 0.
- ``rms_acc``: root-mean-square joint acceleration (rad/s²) of the hand joints, central second
  differences at the sequence's fps (:func:`dexflow.measures.rms_acceleration`).
- ``pd_mm`` (penetration depth, BODex's ``ho_pene`` per frame): per frame the depth of the
  deepest point of the hand's collision geometry inside the object (every collision shape,
  forearm and palm included, sampled densely: :func:`dexflow.hands.robot.measurement_hand`;
  signed distance to the object's mesh; 0 if none), averaged over frames
  (:func:`dexflow.measures.penetration_depth`, the same definition stage simulate's
  penetration rule uses). ``pd_max_mm``: the deepest of any frame (the aggregate is the
  largest over sequences, not the mean). Always against the recorded object.
- ``pd_own_object_mm``: the same against the object where the trajectory itself puts it. A
  trajectory that carries the object in physics (stage track) comes with its own object poses
  (``object_pose7``, the simulated object, in the replay window): its hand holds that object,
  which is centimetres from the recorded one, so ``pd_mm`` measures mostly that distance and
  this one the hand inside the object it holds. For the others (their object is the recorded
  one) it equals ``pd_mm``.
- ``cd_mm`` (contact distance, BODex's ``contact_dist``): per grasp frame (stage contact finds
  any finger in contact), **every** finger's smallest distance to the object surface clipped
  to [0, 10 mm], averaged over the fingers, then over the grasp frames
  (:func:`dexflow.measures.capped_contact_distance`). ``cd_contact_mm`` (dexflow's variant):
  the same averaged over the fingers in contact only, unclipped above
  (:func:`dexflow.measures.contact_distance`).
- ``spd_mm`` (self-penetration, BODex's ``self_pene`` per frame): per frame the depth of the
  deepest point of the hand's collision geometry (every shape, as for PD) inside the collision
  shape of a non-adjacent link, averaged over frames. Adjacent = a link and its nearest
  ancestor that has collision geometry (MuJoCo, where BODex measures it, excludes
  parent-child pairs likewise); pairs already overlapping at the hand's zero pose are excluded
  too (as MoveIt's setup assistant does: they overlap by design).
- ``fvr`` (feasibility violation rate; **dexflow's definition**: the paper does not define
  FVR, so this number is not the paper's and the reports do not print the two side by side):
  fraction of frames with penetration above ``pd_violation_m``, self-penetration above
  ``spd_violation_m`` or a joint outside its limits by more than ``limit_tolerance_rad``.
- ``ssr_paper`` (%): simulation success rate by the paper's protocol, the share of sequences
  with a frame (from the first contact on, within the penetration tolerance, robust under
  ``simulate.perturbations``) that stage simulate found held under the object's weight along
  each of the six axis directions in turn (contact kept to the end of each), in every engine
  run. ``ssr_bench`` (%): the same with DexGraspBench's push test and criterion (< 5 cm,
  < 15° under all six pushes). ``ssr`` (%), the headline: the conservative one, a frame must
  pass both tests in every engine. The per-frame agreement of the two tests is in
  ``reports/metrics/simulate_<method>.json`` (``criteria_agree_*``), with each engine's SSRs.
- ``contact.flicker_raw`` / ``contact.flicker_final``: contact state changes per finger per
  second before and after frame-to-frame inference (method-independent: the contact stage runs
  on the DexFlow trajectory).
- ``contact.precision`` / ``contact.recall``: final contact states against the demo's
  ground-truth contacts (only where the sequence carries ``gt_contact``; pooled over frames).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import torch

from dexflow.geometry import pose_from_vector
from dexflow.hands.files import staged_spec
from dexflow.hands.robot import RobotHand, cached_hand, measurement_hand
from dexflow.human.keypoints import FINGERS
from dexflow.human.surface_tips import surface_corrected_tips
from dexflow.io.artifacts import (
    MetricFrames,
    ObjectAssets,
    read_contact,
    read_metric_frames,
    read_trajectory,
    write_metric_frames,
)
from dexflow.io.atomic import atomic_path
from dexflow.io.layout import CORE_TRAJECTORIES, TRAJECTORIES, Layout
from dexflow.io.sequence import load_sequence
from dexflow.measures import (
    capped_contact_distance,
    chamfer_per_frame,
    contact_counts,
    contact_distance,
    fingertip_speeds,
    finite_mean,
    hand_object_depths,
    precision_recall,
    rms_acceleration,
    self_collision,
    state_flicker,
    velocity_kl,
)
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import MetricsParams, PipelineParams
from dexflow.pipeline.resume import StageOutput
from dexflow.pipeline.runner import StageSpec

__all__ = [
    "METHODS",
    "STAGE",
    "run_metrics",
    "trajectory_metrics",
]

METHODS = CORE_TRAJECTORIES  # the methods every project has; track's with track=on


# ------------------------------------------------------------------------------ per sequence


def trajectory_metrics(
    hand: RobotHand,
    q: np.ndarray,
    human: np.ndarray,
    observed: np.ndarray,
    obj_pose: np.ndarray,
    sdf: SignedDistanceGrid,
    contact: np.ndarray,
    fps: float,
    params: MetricsParams,
    own_pose: np.ndarray | None = None,
) -> tuple[dict, dict[str, np.ndarray]]:
    """Metrics of one trajectory (see the module docstring).

    Args:
        q: (T, dof) robot trajectory.
        human: (T, K, 3) human keypoints matched to the hand's keypoints.
        observed: (T,) frames with a real observation.
        obj_pose: (T, 4, 4) object poses.
        contact: (T, F) contact states (fingers in the hand config's order).
        own_pose: (T, 4, 4) the object's poses in the trajectory itself, where it has its own
            (stage track's simulated object); None: ``obj_pose``.

    Returns:
        Scalars per sequence, and per-frame arrays (``keypoint_error_m``, ``pd_m``, ``cd_m``,
        ``spd_m``) plus the fingertip speeds (``tip_speed_robot``, ``tip_speed_human``).
    """
    with torch.no_grad():
        robot = hand.keypoints(torch.as_tensor(q, dtype=hand.dtype)).numpy()
    distance = np.linalg.norm(robot - human, axis=-1)  # (T, K)
    error = np.where(observed, distance.mean(axis=1), np.nan)
    tips = hand.fingertip_keypoints
    tip_error = np.where(observed, distance[:, tips].mean(axis=1), np.nan)
    surface_tips = surface_corrected_tips(human[:, tips], obj_pose, sdf)
    tip_error_surface = np.where(
        observed, np.linalg.norm(robot[:, tips] - surface_tips, axis=-1).mean(axis=1), np.nan
    )
    chamfer = np.full(len(q), np.nan)
    if observed.any():
        chamfer[observed] = chamfer_per_frame(human[observed], robot[observed])
    measured = measurement_hand(hand)  # every collision shape, forearm and palm included
    pd, per_finger = hand_object_depths(measured, q, obj_pose, sdf)
    pd_own = pd if own_pose is None else hand_object_depths(measured, q, own_pose, sdf)[0]
    cd = capped_contact_distance(per_finger, np.asarray(contact, dtype=bool).any(axis=1))
    cd_contact = contact_distance(per_finger, contact)
    spd = self_collision(measured)(q)
    joints = q[:, 6:]
    lower, upper = hand.lower.numpy()[6:], hand.upper.numpy()[6:]
    tol = params.limit_tolerance_rad
    off_limits = ((joints < lower - tol) | (joints > upper + tol)).any(axis=1)
    violation = (pd > params.pd_violation_m) | (spd > params.spd_violation_m) | off_limits
    speed_robot = fingertip_speeds(robot[:, tips], fps, observed)
    speed_human = fingertip_speeds(human[:, tips], fps, observed)
    scalars = {
        "keypoint_error_mm": _mean_mm(error),
        "fingertip_error_mm": _mean_mm(tip_error),
        "fingertip_error_surface_mm": _mean_mm(tip_error_surface),
        "time_aligned_cd_mm": _mean_mm(chamfer),
        "velocity_kl": velocity_kl(speed_human, speed_robot, bins=params.kl_bins),
        "rms_acc": rms_acceleration(joints, fps),
        "pd_mm": _mean_mm(pd),
        "pd_max_mm": float(pd.max() * 1000) if len(pd) else float("nan"),
        "pd_own_object_mm": _mean_mm(pd_own),
        "cd_mm": _mean_mm(cd),
        "cd_contact_mm": _mean_mm(cd_contact),
        "spd_mm": _mean_mm(spd),
        "fvr": float(violation.mean()),
    }
    frames = {"keypoint_error_m": error, "pd_m": pd, "cd_m": cd, "spd_m": spd}
    return scalars, {**frames, "tip_speed_robot": speed_robot, "tip_speed_human": speed_human}


def _own_poses(pose7: np.ndarray | None, recorded: np.ndarray) -> np.ndarray | None:
    """(T, 4, 4) the object's poses of a trajectory with its own (``object_pose7 (T, 7)``,
    NaN where it has none: the recorded pose there); None for one without."""
    if pose7 is None:
        return None
    pose7 = np.asarray(pose7, dtype=np.float64)
    own = np.array(recorded, dtype=np.float64)
    rows = np.isfinite(pose7).all(axis=1)
    own[rows] = pose_from_vector(pose7[rows])
    return own


def _mean_mm(values: np.ndarray) -> float:
    return finite_mean(values) * 1000


# ---------------------------------------------------------------------------------- stage


def _simulation(summary: Path) -> dict[str, dict]:
    """Per sequence, stage simulate's entry (empty if that stage has not written its summary)."""
    if not summary.is_file():
        return {}
    return json.loads(summary.read_text())["sequences"]


def run_metrics(params: PipelineParams, layout: Layout) -> dict:
    """Stage runner: metrics of every sequence and method, aggregates and per-frame tables.

    Reads every trajectory (params.yaml's ``methods``: :data:`METHODS`, and ``track`` with
    track=on), stage contact's states, stage scale_align's
    sequences and objects and stage simulate's summaries; writes the per-frame arrays
    (``layout.metrics``), ``sequences.csv`` and the per-frame plot CSVs (``layout.plots``).

    Returns:
        The flat aggregate metrics (``<method>.<metric>``, ``contact.<metric>``), the sequence
        counts and, under ``"sequences"``, every sequence's entry.
    """
    aligned, contacts, out = layout.scale_align, layout.contact, layout.metrics
    methods = list(params.methods)
    stage = StageOutput(
        out,
        "metrics",
        # simulate's params too: its summaries (ssr) are read, and a resumed run must not reuse
        # entries made from another simulation's
        {"hand": params.hand, "metrics": params.metrics, "simulate": params.simulate},
        inputs=[layout.trajectory(m) for m in methods]
        + [contacts, aligned]
        + [layout.simulate(m) for m in methods]
        + [layout.hand_files],
    )
    files = stage.start()
    spec, mp = staged_spec(params.hand, layout.hand_files.root), params.metrics
    simulated = {m: _simulation(layout.simulate(m).summary) for m in methods}

    def one(path: Path) -> dict:
        torch.set_num_threads(1)
        hand = cached_hand(spec, None)
        seq = load_sequence(aligned.sequence(path), aligned.root)
        frames, fingers = seq.num_frames, list(hand.spec.fingers)
        retargeted = read_trajectory(layout.retarget("dexflow").sequence(path), hand.joint_names)
        human, observed = retargeted["keypoints_human"], retargeted["observed"].astype(bool)
        found = read_contact(contacts.sequence(path), fingers, frames)
        sdf = ObjectAssets(aligned.object_of(seq.obj_mesh)).sdf()
        entry = {"object": seq.obj_name, "frames": frames, "methods": {}}
        per_frame = {}
        for method in methods:
            trajectory = read_trajectory(
                layout.trajectory(method).sequence(path), hand.joint_names, frames
            )
            scalars, values = trajectory_metrics(
                hand, trajectory.q, human, observed, seq.obj_pose, sdf, found.final, seq.fps,
                mp, _own_poses(trajectory.arrays.get("object_pose7"), seq.obj_pose),
            )  # fmt: skip
            sim = simulated[method].get(path.stem, {})
            if sim.get("status") == "ok":
                scalars["ssr"] = 100.0 * sim["success"]
                scalars["ssr_paper"] = 100.0 * sim["success_contact"]
                scalars["ssr_bench"] = 100.0 * sim["success_bench"]
            entry["methods"][method] = scalars
            per_frame[method] = values
        entry["contact"] = {
            "flicker_raw": state_flicker(found.raw, seq.fps),
            "flicker_final": state_flicker(found.final, seq.fps),
        }
        if seq.gt_contact is not None:
            truth = np.asarray(seq.gt_contact, dtype=bool)[:, [FINGERS.index(f) for f in fingers]]
            entry["contact"] |= contact_counts(found.final, truth)
        time_s = np.arange(frames) / seq.fps
        write_metric_frames(out.sequence(path), MetricFrames(time_s, found.final, per_frame))
        return entry

    tally = stage.run(one, files, params.run)
    ok = {
        name: entry | {"per_frame": read_metric_frames(out.sequence(name))}
        for name, entry in sorted(tally.sequences.items())
        if entry["status"] == "ok"
    }
    counts = tally.counts("metrics")
    summary = {
        **_aggregate(ok, mp.kl_bins),
        **{k: counts[k] for k in ("num_sequences", "num_ok", "num_failed", "num_frames")},
    }
    _write_tables(ok, spec.name, layout.metrics_table, layout.plots, methods)
    summary["sequences"] = dict(sorted(tally.sequences.items()))
    stage.finish(summary)
    return summary


def _aggregate(ok: dict[str, dict], kl_bins: int) -> dict:
    """Aggregates over sequences (see the module docstring): means, except ``*_max_mm`` (the
    largest), ``velocity_kl`` (the speeds of all sequences pooled, ``kl_bins`` bins) and
    contact precision/recall (counts pooled)."""
    out: dict = {}
    methods = list(next(iter(ok.values()))["methods"]) if ok else []
    for method in methods:
        rows = [e["methods"][method] for e in ok.values()]
        keys = sorted({k for row in rows for k in row})
        for key in keys:
            values = np.array([row.get(key, np.nan) for row in rows], dtype=float)
            values = values[np.isfinite(values)]
            reduce = np.max if key.endswith("_max_mm") else np.mean
            out[f"{method}.{key}"] = float(reduce(values)) if len(values) else float("nan")
        human = [e["per_frame"].methods[method]["tip_speed_human"] for e in ok.values()]
        robot = [e["per_frame"].methods[method]["tip_speed_robot"] for e in ok.values()]
        if human:
            out[f"{method}.velocity_kl"] = velocity_kl(
                np.concatenate(human), np.concatenate(robot), bins=kl_bins
            )
    contact = [e["contact"] for e in ok.values()]
    for key in ("flicker_raw", "flicker_final"):
        out[f"contact.{key}"] = float(np.mean([c[key] for c in contact])) if contact else 0.0
    tp, fp, fn = (sum(c.get(k, 0) for c in contact) for k in ("tp", "fp", "fn"))
    if tp + fp + fn:
        scores = precision_recall(tp, fp, fn)
        out["contact.precision"], out["contact.recall"] = scores["precision"], scores["recall"]
    return out


def _write_tables(
    ok: dict[str, dict], hand: str, table: Path, plots: Path, methods: list[str]
) -> None:
    """``table`` (``sequences.csv``: one row per sequence and method) and the per-frame plot
    CSVs in ``plots`` (a column per method)."""
    table.parent.mkdir(parents=True, exist_ok=True)
    plots.mkdir(parents=True, exist_ok=True)
    columns = ["sequence", "object", "hand", "method", "frames", "keypoint_error_mm",
               "fingertip_error_mm", "fingertip_error_surface_mm", "time_aligned_cd_mm",
               "velocity_kl", "rms_acc", "pd_mm", "pd_max_mm", "pd_own_object_mm", "cd_mm",
               "cd_contact_mm", "spd_mm", "fvr", "ssr", "ssr_paper", "ssr_bench"]  # fmt: skip
    with atomic_path(table) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for name, e in sorted(ok.items()):
            for method in methods:
                m = e["methods"][method]
                row = [name, e["object"], hand, method, e["frames"]]
                writer.writerow(row + [_fmt(m.get(k, np.nan)) for k in columns[5:]])

    def frame_rows(name: str, frames: MetricFrames, values):
        for t in range(len(frames.time)):
            yield [name, t, f"{frames.time[t]:.4f}", *values(frames, t)]

    tables = {
        "keypoint_error.csv": (methods, lambda f, t: _in_mm(f, methods, "keypoint_error_m", t)),
        "penetration.csv": (methods, lambda f, t: _in_mm(f, methods, "pd_m", t)),
        "contact_timeline.csv": (["fingers_in_contact"], lambda f, t: [int(f.contact[t].sum())]),
    }
    for filename, (header, values) in tables.items():
        with atomic_path(plots / filename) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["step", "sequence", "frame", "time_s", *header])
            rows = (r for name, e in sorted(ok.items())
                    for r in frame_rows(name, e["per_frame"], values))  # fmt: skip
            for step, row in enumerate(rows):
                writer.writerow([step, *row])


def _in_mm(frames: MetricFrames, methods: list[str], key: str, t: int) -> list[str]:
    return [_fmt(frames.methods[m][key][t] * 1000) for m in methods]


def _fmt(value) -> str:
    value = float(value)
    return "" if not np.isfinite(value) else f"{value:.6g}"


def _describe(s: dict) -> str:
    def line(method: str) -> str:
        values = (s.get(f"{method}.{k}", float("nan")) for k in (
            "keypoint_error_mm", "ssr", "pd_mm", "cd_mm", "spd_mm", "fvr", "velocity_kl",
            "rms_acc", "time_aligned_cd_mm"))  # fmt: skip
        return (
            "{}: error {:.2f} mm, SSR {:.1f} %, PD {:.2f} mm, CD {:.2f} mm, SPD {:.2f} mm, "
            "FVR {:.3f}, velocity KL {:.3f}, RMS acc {:.2f} rad/s^2, time-aligned CD {:.2f} mm"
        ).format(method, *values)

    counts = f"{s['num_ok']}/{s['num_sequences']} sequences"
    methods = [m for m in TRAJECTORIES if f"{m}.keypoint_error_mm" in s]
    return "; ".join([counts, *(line(m) for m in methods)])


STAGE = StageSpec(
    name="metrics",
    run=run_metrics,
    metric_keys=None,  # every aggregate
    describe=_describe,
)
