"""Stage metrics: every number the reports show, per sequence and aggregated, with its definition.

Methods: ``baseline`` (stage retarget, method ``position``: per-frame keypoint matching),
``retarget`` (DexFlow retargeting) and ``refine`` (DexFlow + contact refinement). All lengths are
reported in millimetres; "frames" are all frames of a sequence unless said otherwise.

Definitions (per sequence; the aggregate is the mean over sequences unless said otherwise):

- ``keypoint_error_mm``: mean over observed frames (valid and not tracking-lost) of the mean
  distance between the robot's keypoints and the human keypoints they are mapped to.
- ``fingertip_error_mm``: the same over the fingertip keypoints only (the keypoints mapped to
  MANO tips 4, 8, 12, 16, 20): how far the robot's fingertips are from the human's.
- ``time_aligned_cd_mm``: per observed frame, the symmetric Chamfer distance between the human
  keypoint set and the robot keypoint set, ``½ (mean_a min_b |a - b| + mean_b min_a |a - b|)``,
  averaged over frames. It compares shapes at the same instant without trusting the
  correspondence; identical trajectories give 0.
- ``velocity_kl``: KL divergence between the histograms of human and robot fingertip speeds
  over consecutive observed frames (:func:`dexflow.measures.velocity_kl`; the aggregate pools
  the speeds of all sequences). Identical trajectories give 0.
- ``rms_acc``: root-mean-square joint acceleration (rad/s²) of the hand joints, central second
  differences at the sequence's fps (:func:`dexflow.measures.rms_acceleration`).
- ``pd_mm`` (penetration depth): per frame the depth of the deepest hand surface point inside
  the object (signed distance grid; 0 if none), averaged over frames
  (:func:`dexflow.measures.penetration_depth`, the same definition stage simulate's
  penetration rule uses). ``pd_max_mm``: the deepest of any frame (the aggregate is the
  largest over sequences, not the mean).
- ``cd_mm`` (contact distance): per frame and finger in contact (stage contact's final
  states), the finger's smallest distance to the object surface clipped at 0, averaged over the
  fingers in contact, then over frames with any contact.
- ``spd_mm`` (self-penetration): per frame the depth of the deepest hand surface point inside the
  collision shape of a non-adjacent link, averaged over frames. Adjacent = a link and its
  nearest ancestor that has collision geometry; pairs already overlapping at the hand's zero
  pose are excluded too (as MoveIt's setup assistant does: they overlap by design).
- ``fvr`` (feasibility violation rate; the paper does not define FVR, this is dexflow's
  definition): fraction of frames with penetration above ``pd_violation_m``, self-penetration
  above ``spd_violation_m`` or a joint outside its limits by more than ``limit_tolerance_rad``.
- ``ssr`` (%): simulation success rate, the share of sequences that stage simulate found to
  hold the object (paper criterion: contact kept in six gravity directions, from a frame within
  the penetration tolerance); ``ssr_bench`` (%): the DexGraspBench criterion (< 5 cm, < 15°).
- ``contact.flicker_raw`` / ``contact.flicker_final``: contact state changes per finger per
  second before and after frame-to-frame inference (method-independent: the contact stage runs
  on the DexFlow trajectory).
- ``contact.precision`` / ``contact.recall``: final contact states against the demo's
  ground-truth contacts (only where the sequence carries ``gt_contact``; pooled over frames).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import ConvexHull

from dexflow.hands.robot import RobotHand
from dexflow.measures import (
    fingertip_speeds,
    penetration_depth,
    rms_acceleration,
    surface_distances,
    velocity_kl,
)
from dexflow.objects.sdf import SignedDistanceGrid

__all__ = [
    "METHODS",
    "MetricsParams",
    "SelfCollision",
    "chamfer_per_frame",
    "contact_distance",
    "run_metrics",
    "state_flicker",
]

METHODS = ("baseline", "retarget", "refine")
TIPS = (4, 8, 12, 16, 20)  # MANO fingertips
# The upstream outputs the stage reads (keys of ``roots``); sequences are listed from the first
STAGE_INPUTS = ("retarget", "baseline", "refine", "contact", "scale_align", "simulate")


@dataclass
class MetricsParams:
    """Stage ``metrics`` (``metrics`` in params.yaml)."""

    pd_violation_m: float = 0.005
    spd_violation_m: float = 0.002
    limit_tolerance_rad: float = 1e-4
    kl_bins: int = 30


# ------------------------------------------------------------------------ hand-object measures


def contact_distance(per_finger: np.ndarray, contact: np.ndarray) -> np.ndarray:
    """Per frame the mean over fingers in contact of their distance clipped at 0 (NaN if none).

    Args:
        per_finger: (T, F) each finger's smallest signed distance to the object.
        contact: (T, F) contact states.
    """
    clipped = np.where(contact, np.clip(per_finger, 0.0, None), 0.0)
    count = contact.sum(axis=1)
    return np.where(count > 0, clipped.sum(axis=1) / np.maximum(count, 1), np.nan)


def chamfer_per_frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Symmetric Chamfer distance per frame between point sets (T, A, 3) and (T, B, 3)."""
    d = np.linalg.norm(a[:, :, None] - b[:, None], axis=-1)  # (T, A, B)
    return 0.5 * (d.min(axis=2).mean(axis=1) + d.min(axis=1).mean(axis=1))


def state_flicker(states: np.ndarray, fps: float) -> float:
    """State changes per finger per second of (T, F) boolean states."""
    states = np.asarray(states, dtype=bool)
    if len(states) < 2:
        return 0.0
    changes = np.count_nonzero(states[1:] != states[:-1])
    return float(changes / states.shape[1] / ((len(states) - 1) / fps))


class SelfCollision:
    """Depth of hand surface points inside the collision shapes of non-adjacent links.

    Boxes, cylinders and meshes are treated as convex polytopes (their convex hull's planes:
    exact depth inside, which is all a penetration depth needs); spheres and capsules exactly.
    """

    def __init__(self, hand: RobotHand) -> None:
        self.hand = hand
        model = hand.model
        has_geometry = {g.link for g in model.geometries}

        def geometric_parent(link: str) -> str | None:
            parent = model.parents.get(link, (None, None))[0]
            while parent is not None and parent not in has_geometry:
                parent = model.parents.get(parent, (None, None))[0]
            return parent

        self.shapes = []  # (link, kind, data)
        for g in model.geometries:
            vertices = np.asarray(g.mesh.vertices)
            center = vertices.mean(axis=0)
            bound = (center, float(np.linalg.norm(vertices - center, axis=1).max()) + 1e-6)
            if g.kind in ("sphere", "capsule"):
                middle = g.transform[:3, 3]
                axis = g.transform[:3, 2] * (g.size[1] if g.kind == "capsule" else 0.0)
                data = (middle - axis, middle + axis, g.size[0])
                self.shapes.append((g.link, "capsule", data, bound))
            else:
                hull = ConvexHull(vertices)
                self.shapes.append((g.link, "polytope", hull.equations, bound))
        self.links = list(dict.fromkeys(shape[0] for shape in self.shapes))
        point_links = np.asarray(hand.surface_point_links)
        parents = {link: geometric_parent(link) for link in has_geometry}
        self.masks = []  # per shape: which surface points may penetrate it
        for link, *_ in self.shapes:
            adjacent = {link, parents.get(link)} | {k for k, p in parents.items() if p == link}
            self.masks.append(~np.isin(point_links, sorted(a for a in adjacent if a)))
        for s in range(len(self.shapes)):  # pairs overlapping at the zero pose
            depth = self._depths(hand.zero().numpy(), s, self.masks[s])[0]
            overlapping = sorted({point_links[i] for i in np.flatnonzero(depth > 1e-6)})
            self.masks[s] &= ~np.isin(point_links, overlapping)

    def _depths(self, q: np.ndarray, s: int, mask: np.ndarray, cache: dict | None = None):
        """(T, N) depth of the surface points in ``mask`` inside shape ``s`` (0 elsewhere)."""
        hand = self.hand
        cache = {} if cache is None else cache
        if "points" not in cache:
            with torch.no_grad():
                qt = torch.as_tensor(q, dtype=hand.dtype)
                cache["points"] = hand.surface(qt)[0].numpy()
                cache["frames"] = hand.link_transforms(qt, self.links).numpy()
        points, frames = cache["points"], cache["frames"]
        link, kind, data, (center, radius) = self.shapes[s]
        t = frames[:, self.links.index(link)]
        rot, pos = t[:, :3, :3], t[:, :3, 3]
        candidates = points[:, mask]  # (T, M, 3)
        center_world = rot @ center + pos  # (T, 3)
        near = np.sum((candidates - center_world[:, None]) ** 2, axis=-1) < radius**2  # cull
        out = np.zeros(points.shape[:2])
        if not near.any():
            return out
        rows, cols = np.nonzero(near)
        # only the points near the shape go to its frame: x = Rᵀ (p - o)
        x = ((candidates[rows, cols] - pos[rows])[:, None, :] @ rot[rows])[:, 0]  # (K, 3)
        if kind == "capsule":
            a, b, r = data
            ab = b - a
            u = np.clip(((x - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
            depth = r - np.linalg.norm(x - (a + u[:, None] * ab), axis=-1)
        else:
            depth = -(x @ data[:, :3].T + data[:, 3]).max(axis=-1)
        inside = np.zeros(near.shape)
        inside[near] = np.clip(depth, 0.0, None)
        out[:, mask] = inside
        return out

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """(T,) self-penetration depth (m) of configurations ``q (T, dof)``."""
        q, cache = np.asarray(q), {}
        out = np.zeros(len(q))
        for s, mask in enumerate(self.masks):
            out = np.maximum(out, self._depths(q, s, mask, cache).max(axis=1))
        return out


_SELF: dict[int, SelfCollision] = {}


def self_collision(hand: RobotHand) -> SelfCollision:
    """One :class:`SelfCollision` per hand and process."""
    if id(hand) not in _SELF:
        _SELF[id(hand)] = SelfCollision(hand)
    return _SELF[id(hand)]


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
) -> tuple[dict, dict[str, np.ndarray]]:
    """Metrics of one trajectory (see the module docstring).

    Args:
        q: (T, dof) robot trajectory.
        human: (T, K, 3) human keypoints matched to the hand's keypoints.
        observed: (T,) frames with a real observation.
        obj_pose: (T, 4, 4) object poses.
        contact: (T, F) contact states (fingers in the hand config's order).

    Returns:
        Scalars per sequence, and per-frame arrays (``keypoint_error_m``, ``pd_m``, ``cd_m``,
        ``spd_m``) plus the fingertip speeds (``tip_speed_robot``, ``tip_speed_human``).
    """
    with torch.no_grad():
        robot = hand.keypoints(torch.as_tensor(q, dtype=hand.dtype)).numpy()
    distance = np.linalg.norm(robot - human, axis=-1)  # (T, K)
    error = np.where(observed, distance.mean(axis=1), np.nan)
    tips = [i for i, m in enumerate(hand.mano_indices) if m in TIPS]
    tip_error = np.where(observed, distance[:, tips].mean(axis=1), np.nan)
    chamfer = np.full(len(q), np.nan)
    if observed.any():
        chamfer[observed] = chamfer_per_frame(human[observed], robot[observed])
    distances, _ = surface_distances(hand, q, obj_pose, sdf)
    masks = list(hand.finger_point_masks.values())
    per_finger = np.stack([np.where(m, distances, np.inf).min(axis=1) for m in masks], axis=1)
    pd = penetration_depth(distances)
    cd = contact_distance(per_finger, contact)
    spd = self_collision(hand)(q)
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
        "time_aligned_cd_mm": _mean_mm(chamfer),
        "velocity_kl": velocity_kl(speed_human, speed_robot, bins=params.kl_bins),
        "rms_acc": rms_acceleration(joints, fps),
        "pd_mm": _mean_mm(pd),
        "pd_max_mm": float(pd.max() * 1000) if len(pd) else float("nan"),
        "cd_mm": _mean_mm(cd),
        "spd_mm": _mean_mm(spd),
        "fvr": float(violation.mean()),
    }
    frames = {"keypoint_error_m": error, "pd_m": pd, "cd_m": cd, "spd_m": spd}
    return scalars, {**frames, "tip_speed_robot": speed_robot, "tip_speed_human": speed_human}


def _mean_mm(values: np.ndarray) -> float:
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(values.mean() * 1000) if len(values) else float("nan")


# ---------------------------------------------------------------------------------- stage


def _simulation(sim_root: Path) -> dict[str, dict]:
    path = sim_root / "summary.json"
    if not path.is_file():
        return {}
    return json.loads(path.read_text())["sequences"]


def run_metrics(params, roots: dict[str, Path], out_root, plots_root) -> dict:
    """Stage runner: metrics of every sequence and method, aggregates and per-frame tables.

    Args:
        params: Pipeline params (``hand``, ``metrics``, ``run``).
        roots: ``scale_align``, ``contact``, ``baseline``, ``retarget``, ``refine`` and
            ``simulate`` (holding ``<method>/summary.json``) directories.
        out_root: Where the per-sequence table goes (``sequences.csv``).
        plots_root: Where the per-frame CSVs go (DVC plots).

    Returns:
        The flat aggregate metrics (``<method>.<metric>``, ``contact.<metric>``) and, under
        ``"sequences"``, every sequence's entry.
    """
    from dexflow.config import project_root
    from dexflow.hands.robot import cached_hand
    from dexflow.io.atomic import atomic_path, save_npz
    from dexflow.io.sequence import load_sequence
    from dexflow.resume import StageOutput

    roots = {k: Path(v) for k, v in roots.items()}
    out_root, plots_root = Path(out_root), Path(plots_root)
    stage = StageOutput(
        out_root,
        "metrics",
        {"hand": params.hand, "metrics": params.metrics},
        inputs=[roots[k] for k in STAGE_INPUTS],
    )
    files = stage.start()
    spec, base_dir, mp = params.hand, project_root() / "conf" / "hand", params.metrics
    simulated = {m: _simulation(roots["simulate"] / m) for m in METHODS}

    def one(path: Path) -> dict:
        torch.set_num_threads(1)
        hand = cached_hand(spec, base_dir)
        name = path.name
        seq = load_sequence(roots["scale_align"] / "sequences" / name, roots["scale_align"])
        with np.load(roots["retarget"] / "sequences" / name) as data:
            human, observed = data["keypoints_human"], data["observed"].astype(bool)
        with np.load(roots["contact"] / "sequences" / name) as data:
            raw, final = data["raw"], data["final"]
            fingers = [str(f) for f in data["fingers"]]
        sdf = SignedDistanceGrid.load((roots["scale_align"] / seq.obj_mesh).parent / "sdf.npz")
        entry = {"object": seq.obj_name, "frames": len(seq.obj_pose), "methods": {}}
        per_frame = {}
        for method in METHODS:
            with np.load(roots[method] / "sequences" / name) as data:
                q = data["q"]
            scalars, frames = trajectory_metrics(
                hand, q, human, observed, seq.obj_pose, sdf, final, seq.fps, mp
            )
            sim = simulated[method].get(path.stem, {})
            if sim.get("status") == "ok":
                scalars["ssr"] = 100.0 * sim["success_contact"]
                scalars["ssr_bench"] = 100.0 * sim["success_bench"]
            entry["methods"][method] = scalars
            per_frame[method] = frames
        entry["contact"] = {
            "flicker_raw": state_flicker(raw, seq.fps),
            "flicker_final": state_flicker(final, seq.fps),
        }
        if seq.gt_contact is not None:
            order = ["thumb", "index", "middle", "ring", "little"]
            truth = np.asarray(seq.gt_contact, dtype=bool)[:, [order.index(f) for f in fingers]]
            entry["contact"]["tp"] = int(np.count_nonzero(final & truth))
            entry["contact"]["fp"] = int(np.count_nonzero(final & ~truth))
            entry["contact"]["fn"] = int(np.count_nonzero(~final & truth))
        arrays = {"time": np.arange(len(seq.obj_pose)) / seq.fps, "contact": final}
        for method in METHODS:
            arrays |= {f"{method}.{k}": v for k, v in per_frame[method].items()}
        save_npz(out_root / "sequences" / name, arrays)
        return entry

    results = stage.map(one, files, params.run)
    entries = {r.item.stem: r for r in results}
    ok = {name: r.value | {"per_frame": _per_frame(out_root, name)}
          for name, r in entries.items() if r.ok}  # fmt: skip
    summary = _aggregate(ok)
    summary["num_sequences"] = len(files)
    summary["num_failed"] = len(files) - len(ok)
    _write_tables(ok, spec.name, out_root, plots_root, atomic_path)
    summary["sequences"] = {
        name: (
            {k: v for k, v in r.value.items() if k != "per_frame"} | {"status": "ok"}
            if r.ok
            else {"status": "failed", "error": r.error}
        )
        for name, r in sorted(entries.items())
    }
    stage.finish(summary)
    return summary


def _per_frame(out_root: Path, name: str) -> dict:
    """A sequence's per-frame arrays as the metrics stage saved them
    (``out_root/sequences/<name>.npz``): ``time``, ``contact`` and one dict per method."""
    with np.load(out_root / "sequences" / f"{name}.npz") as data:
        arrays = {k: data[k] for k in data.files}
    out: dict = {"time": arrays.pop("time"), "contact": arrays.pop("contact")}
    for key, value in arrays.items():
        method, _, metric = key.partition(".")
        out.setdefault(method, {})[metric] = value
    return out


def _aggregate(ok: dict[str, dict]) -> dict:
    out: dict = {}
    for method in METHODS:
        rows = [e["methods"][method] for e in ok.values()]
        keys = sorted({k for row in rows for k in row})
        for key in keys:
            values = np.array([row.get(key, np.nan) for row in rows], dtype=float)
            values = values[np.isfinite(values)]
            reduce = np.max if key.endswith("_max_mm") else np.mean
            out[f"{method}.{key}"] = float(reduce(values)) if len(values) else float("nan")
        human = [e["per_frame"][method]["tip_speed_human"] for e in ok.values()]
        robot = [e["per_frame"][method]["tip_speed_robot"] for e in ok.values()]
        if human:
            out[f"{method}.velocity_kl"] = velocity_kl(np.concatenate(human), np.concatenate(robot))
    contact = [e["contact"] for e in ok.values()]
    for key in ("flicker_raw", "flicker_final"):
        out[f"contact.{key}"] = float(np.mean([c[key] for c in contact])) if contact else 0.0
    tp, fp, fn = (sum(c.get(k, 0) for c in contact) for k in ("tp", "fp", "fn"))
    if tp + fp + fn:
        out["contact.precision"] = tp / (tp + fp) if tp + fp else 0.0
        out["contact.recall"] = tp / (tp + fn) if tp + fn else 0.0
    return out


def _write_tables(ok: dict[str, dict], hand: str, out_root: Path, plots_root: Path, atomic_path):
    """``sequences.csv`` (one row per sequence and method) and the per-frame plot CSVs."""
    out_root.mkdir(parents=True, exist_ok=True)
    plots_root.mkdir(parents=True, exist_ok=True)
    columns = ["sequence", "object", "hand", "method", "frames", "keypoint_error_mm",
               "fingertip_error_mm", "time_aligned_cd_mm", "velocity_kl", "rms_acc", "pd_mm",
               "pd_max_mm", "cd_mm", "spd_mm", "fvr", "ssr", "ssr_bench"]  # fmt: skip
    with atomic_path(out_root / "sequences.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for name, e in sorted(ok.items()):
            for method in METHODS:
                m = e["methods"][method]
                row = [name, e["object"], hand, method, e["frames"]]
                writer.writerow(row + [_fmt(m.get(k, np.nan)) for k in columns[5:]])
    tables = {
        "keypoint_error.csv": ("keypoint_error_m", "keypoint error (mm)"),
        "penetration.csv": ("pd_m", "penetration depth (mm)"),
    }
    for filename, (key, _) in tables.items():
        with atomic_path(plots_root / filename) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["step", "sequence", "frame", "time_s", *METHODS])
            step = 0
            for name, e in sorted(ok.items()):
                pf = e["per_frame"]
                for t in range(len(pf["time"])):
                    values = [_fmt(pf[m][key][t] * 1000) for m in METHODS]
                    writer.writerow([step, name, t, f"{pf['time'][t]:.4f}", *values])
                    step += 1
    with atomic_path(plots_root / "contact_timeline.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["step", "sequence", "frame", "time_s", "fingers_in_contact"])
        step = 0
        for name, e in sorted(ok.items()):
            pf = e["per_frame"]
            for t in range(len(pf["time"])):
                count = int(pf["contact"][t].sum())
                writer.writerow([step, name, t, f"{pf['time'][t]:.4f}", count])
                step += 1


def _fmt(value) -> str:
    value = float(value)
    return "" if not np.isfinite(value) else f"{value:.6g}"
