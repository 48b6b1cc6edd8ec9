"""The embedded demo dataset: human grasp sequences on YCB stand-ins, generated from a seed.

Each sequence is reach -> close the fingers until they touch -> lift and move the object with the
hand -> optionally put it down and release. Contacts come from the geometry (see
:mod:`dexflow.data.grasps`), and the ground truth (``gt_contact``: a finger's skin within
``contact_tolerance_m`` of the surface) is computed from the clean hand before the recording is
made realistic the way real captures are:

- annotation error at contacts: per finger in contact, its skin sits 3-10 mm inside the object
  (``inside_fraction`` of fingers), hovers a few mm off it with a slow wobble
  (``hover_fraction``), or touches it;
- tracker noise on every keypoint (white plus slowly drifting, ``noise_std_m`` each);
- the annotated hand sits a few millimetres too deep into the object while holding it: the
  whole hand (palm included) is shifted along its approach during the hold
  (``hold_penetration_*``), so, as in DexYCB, fingertip keypoints are inside the object in most
  held frames (a median of a few mm, over 10 mm in about a quarter of them);
- dropouts: short bursts of NaN frames, marked ``valid = False``;
- tracking loss: short bursts where the tracker reports a default flat hand tens of cm away
  (still ``valid = True``, as a tracker would; ``gt_tracking_lost`` marks them);
- unannotated frames at the MANO-like template: most sequences START with a run of frames
  where the hand is a fixed flat default hand ~0.7 m away, identical every frame, and some END
  with one (``template_*``; ``valid = True`` as in an uncleaned capture, ``gt_tracking_lost``
  and ``gt_template`` mark them);
- a tilted rest: the whole recorded scene (object and hand) turned ``rest_tilt_deg`` about a
  horizontal axis through the resting object (``rest_tilt_probability``), so that on a level
  table the object rests on an edge and topples left alone, as most of a DexYCB export's do
  when its rotations are read by the wrong convention (off by default: :mod:`dexflow.data.
  rotation_convention` finds the right one, and real captures so read rest);
- an annotation that spins: a stand-in symmetric about an axis (the cans, the bowl:
  ``Standin.symmetry_axis``) turns about it by up to ``spin_rad`` while held
  (``spin_probability``), its surface where it was, as that misread export's annotations of
  such objects do (off by default). No hand following the human's can turn the object so
  (stage replay's rigid ceiling).

Everything is a deterministic function of the configuration: the same seed gives byte-identical
files.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from dexflow.data.annotation import (
    annotation_spin,
    hold_penetration,
    rest_tilt,
    rigid_motion,
    tip_penetration,
)
from dexflow.data.grasps import GRASP_TYPES, Grasp, synthesize_grasp
from dexflow.data.ycb_standins import STANDINS, build_standin
from dexflow.geometry import transform_points, world_to_object
from dexflow.human.model import HandShape, finger_capsules, forward_keypoints
from dexflow.io.atomic import save_json
from dexflow.io.layout import StageDir
from dexflow.io.sequence import Sequence, save_sequence
from dexflow.objects.mesh import write_obj
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import DemoConfig

if TYPE_CHECKING:
    from dexflow.params import RunParams

__all__ = ["generate_demo", "generate_object"]

log = logging.getLogger(__name__)


def _min_jerk(n: int) -> np.ndarray:
    """Minimum-jerk time scaling from 0 to 1 over ``n`` samples."""
    tau = np.linspace(0.0, 1.0, n)
    return 10 * tau**3 - 15 * tau**4 + 6 * tau**5


def _interp_poses(a: np.ndarray, b: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(len(weights), 4, 4) poses from ``a`` to ``b``: lerp of position, slerp of rotation."""
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))
    out = np.repeat(np.eye(4)[None], len(weights), axis=0)
    out[:, :3, :3] = slerp(np.clip(weights, 0.0, 1.0)).as_matrix()
    out[:, :3, 3] = a[:3, 3] + weights[:, None] * (b[:3, 3] - a[:3, 3])
    return out


def _bursts(rng, num_frames, count, length, lo=0) -> np.ndarray:
    mask = np.zeros(num_frames, dtype=bool)
    for _ in range(count):
        n = int(rng.integers(length[0], length[1] + 1))
        start = int(rng.integers(max(lo, 1), num_frames - n - 1))
        mask[start : start + n] = True
    return mask


def _plan_phases(rng, cfg: DemoConfig, release: bool) -> tuple[int, int, int, int]:
    num_frames = int(rng.integers(cfg.min_frames, cfg.max_frames + 1))
    n_reach = round(0.28 * num_frames)
    n_close = max(6, round(0.12 * num_frames))
    n_release = round(0.22 * num_frames) if release else 0
    return num_frames, n_reach, n_close, n_release


def _make_sequence(
    name: str,
    grasp: Grasp,
    sdf: SignedDistanceGrid,
    rng: np.random.Generator,
    cfg: DemoConfig,
    shape: HandShape,
    symmetry_axis: tuple[float, float, float] | None = None,
) -> tuple[Sequence, dict]:
    release = bool(rng.random() < cfg.release_probability)
    num_frames, n_reach, n_close, n_release = _plan_phases(rng, cfg, release)
    n_hold = num_frames - n_reach - n_close - n_release
    t_close, t_hold, t_release = n_reach, n_reach + n_close, num_frames - n_release

    # Where the object rests in the world, and how it moves once held.
    rest = rigid_motion(
        [0.0, 0.0, rng.uniform(-np.pi, np.pi)],
        [rng.uniform(0.3, 0.5), rng.uniform(-0.15, 0.15), rng.uniform(0.05, 0.15)],
    )
    centre = rest[:3, 3]
    axis = rng.normal(size=3)
    lift = rigid_motion(
        axis / np.linalg.norm(axis) * rng.uniform(0.2, 0.6),
        [rng.uniform(-0.12, 0.12), rng.uniform(-0.12, 0.12), rng.uniform(0.1, 0.2)],
        centre,
    )
    motion = np.repeat(np.eye(4)[None], num_frames, axis=0)
    if release:
        n_up = n_hold * 2 // 3
        place = rigid_motion(
            [0.0, 0.0, rng.uniform(-0.5, 0.5)],
            [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.0],
            centre,
        )
        motion[t_hold : t_hold + n_up] = _interp_poses(np.eye(4), lift, _min_jerk(n_up))
        motion[t_hold + n_up : t_release] = _interp_poses(lift, place, _min_jerk(n_hold - n_up))
        motion[t_release:] = place
    else:
        motion[t_hold:] = _interp_poses(np.eye(4), lift, _min_jerk(n_hold))
    obj_pose = motion @ rest

    # The wrist: reach from a random start, ride with the object, retreat after release.
    grasp_wrist = rest @ grasp.wrist_pose
    approach_world = rest[:3, :3] @ grasp.approach
    start = (
        rigid_motion(
            rng.normal(size=3) * 0.3,
            -approach_world * rng.uniform(0.2, 0.3) + [0.0, 0.0, rng.uniform(0.05, 0.15)],
            grasp_wrist[:3, 3],
        )
        @ grasp_wrist
    )
    wrist = motion @ grasp_wrist
    wrist[:t_close] = _interp_poses(start, grasp_wrist, _min_jerk(n_reach))
    if release:
        n_open = n_release // 2
        retreat = rigid_motion([0.0, 0.0, 0.0], -approach_world * 0.2) @ wrist[t_release]
        wrist[t_release + n_open :] = _interp_poses(
            wrist[t_release], retreat, _min_jerk(n_release - n_open)
        )

    # Finger closure over time: clean (ground truth) and as annotated.
    clean_target = grasp.stop_closure
    annotated = np.tile(clean_target, (num_frames, 1))
    in_contact = ~np.isnan(grasp.contact_closure)
    modes = []
    times = np.arange(num_frames) / cfg.fps
    for f in range(5):
        if not in_contact[f]:
            modes.append("none")
            continue
        u = rng.random()
        if u < cfg.inside_fraction:
            depth = rng.uniform(*cfg.inside_depth_m)
            annotated[:, f] = grasp.closure_for_distance(f, -depth)
            modes.append("inside")
        elif u < cfg.inside_fraction + cfg.hover_fraction:
            gap = rng.uniform(*cfg.hover_gap_m)
            period, phase = rng.uniform(0.6, 1.5), rng.uniform(0, 2 * np.pi)
            gaps = gap + cfg.hover_wobble_m * np.sin(2 * np.pi * times / period + phase)
            annotated[:, f] = [grasp.closure_for_distance(f, g) for g in gaps]
            modes.append("hover")
        else:
            modes.append("touch")
    ramp = np.zeros(num_frames)
    ramp[t_close:t_hold] = _min_jerk(n_close)
    ramp[t_hold:] = 1.0
    if release:
        n_open = n_release // 2
        ramp[t_release : t_release + n_open] = 1.0 - _min_jerk(n_open)
        ramp[t_release + n_open :] = 0.0
    clean_closure = ramp[:, None] * clean_target[None]
    annotated_closure = ramp[:, None] * annotated

    template = grasp.template
    clean_kp = forward_keypoints(template.angles(clean_closure), wrist, shape)
    keypoints = forward_keypoints(template.angles(annotated_closure), wrist, shape)

    # Ground truth contact from the clean hand's skin, in the object's frame.
    kp_obj = world_to_object(clean_kp, obj_pose)
    skin, radii = finger_capsules(kp_obj, shape)
    skin_dist = (sdf.query(skin) - radii).min(axis=-1)  # (T, 5)
    gt_contact = skin_dist <= cfg.contact_tolerance_m

    # Penetrating annotation while holding: the whole hand a few mm too deep (palm included),
    # fingertips inside the object (a stream of its own: one draw from the sequence's).
    extra = np.random.default_rng(rng.integers(2**63))
    approach_world = obj_pose[:, :3, :3] @ grasp.approach
    shift = hold_penetration(extra, cfg, ramp, times, approach_world)
    keypoints = keypoints + shift[:, None]
    pressing = [f for f in range(5) if in_contact[f] and modes[f] != "hover"]
    keypoints = keypoints + tip_penetration(
        extra, cfg, keypoints, obj_pose, sdf, ramp, times, pressing
    )

    # Tracker artefacts.
    white = rng.normal(scale=cfg.noise_std_m, size=keypoints.shape)
    drift = np.cumsum(rng.normal(size=keypoints.shape), axis=0)
    drift -= drift.mean(axis=0)
    drift *= cfg.noise_std_m / max(drift.std(), 1e-12)
    keypoints = keypoints + white + drift

    lost = np.zeros(num_frames, dtype=bool)
    if rng.random() < cfg.tracking_loss_probability:
        lost = _bursts(rng, num_frames, 1, cfg.tracking_loss_length)
        direction = rng.normal(size=3)
        direction *= rng.uniform(*cfg.tracking_loss_distance_m) / np.linalg.norm(direction)
        far = wrist[lost].copy()
        far[:, :3, 3] += direction
        keypoints[lost] = forward_keypoints(np.zeros((lost.sum(), 20)), far, shape)
    dropped = _bursts(rng, num_frames, int(rng.poisson(cfg.dropout_bursts)), cfg.dropout_length)
    dropped &= ~lost

    unannotated = _template_frames(extra, cfg, num_frames)
    if unannotated.any():
        keypoints[unannotated] = _template_hand(extra, cfg, wrist[~unannotated][0, :3, 3])
    lost |= unannotated
    dropped &= ~unannotated
    keypoints[dropped] = np.nan

    # The object's annotation as real captures have it (a stream of its own).
    quirks = np.random.default_rng(extra.integers(2**63))
    spin = annotation_spin(quirks, cfg, symmetry_axis, ramp, t_hold)
    obj_pose = obj_pose @ spin
    tilt = rest_tilt(quirks, cfg, rest)
    obj_pose = tilt @ obj_pose
    keypoints, clean_kp = transform_points(tilt, keypoints), transform_points(tilt, clean_kp)

    seq = Sequence(
        keypoints=keypoints,
        obj_pose=obj_pose,
        obj_mesh=f"meshes/{name.split('__')[0]}.obj",
        obj_name=name.split("__")[0],
        fps=cfg.fps,
        side="right",
        source="demo",
        valid=~dropped,
        gt_contact=gt_contact,
        extras={
            "gt_keypoints": clean_kp,
            "gt_tracking_lost": lost,
            "gt_template": unannotated,
            "grasp_type": np.array(template.name),
            "hand_scale": np.array(shape.scale),
        },
    )
    info = {
        "name": name,
        "object": seq.obj_name,
        "grasp": template.name,
        "frames": num_frames,
        "release": release,
        "fingers_in_contact": int(in_contact.sum()),
        "annotation": modes,
        "dropout_frames": int(dropped.sum()),
        "tracking_lost_frames": int(lost.sum()),
        "template_frames": int(unannotated.sum()),
        "hold_penetration_mm": float(1000 * np.linalg.norm(shift, axis=-1).max()),
        "rest_tilt_deg": float(np.degrees(Rotation.from_matrix(tilt[:3, :3]).magnitude())),
        "spin_rad": float(Rotation.from_matrix(spin[-1, :3, :3]).magnitude()),
    }
    return seq, info


def _template_frames(rng: np.random.Generator, cfg: DemoConfig, num_frames: int) -> np.ndarray:
    """(T,) runs of unannotated frames at the start and at the end of a sequence."""
    budget = int(cfg.template_max_fraction * num_frames)
    n_start = n_end = 0
    if rng.random() < cfg.template_start_probability:
        n_start = min(
            int(rng.integers(cfg.template_start_length[0], cfg.template_start_length[1] + 1)),
            budget,
        )
    if rng.random() < cfg.template_end_probability:
        n_end = min(
            int(rng.integers(cfg.template_end_length[0], cfg.template_end_length[1] + 1)),
            budget - n_start,
        )
    mask = np.zeros(num_frames, dtype=bool)
    mask[:n_start] = True
    mask[num_frames - n_end :] = True
    return mask


def _template_hand(rng: np.random.Generator, cfg: DemoConfig, near: np.ndarray) -> np.ndarray:
    """(21, 3) a flat average hand in a fixed pose ``template_distance_m`` from ``near``."""
    direction = rng.normal(size=3)
    direction *= rng.uniform(*cfg.template_distance_m) / np.linalg.norm(direction)
    pose = np.eye(4)
    pose[:3, 3] = near + direction
    return forward_keypoints(np.zeros((1, 20)), pose[None], HandShape())[0]


def _grasp_with_fallback(sdf, grasp_types, first, rng, shape) -> Grasp:
    """Try the object's grasp types from ``first`` on; keep the first that holds (thumb + one)."""
    best = None
    for k in range(len(grasp_types)):
        grasp = synthesize_grasp(sdf, grasp_types[(first + k) % len(grasp_types)], rng, shape)
        if best is None or grasp.score > best.score:
            best = grasp
        if grasp.score >= 3:
            return grasp
    return best


def generate_object(name: str, cfg: DemoConfig, out_dir: str | Path) -> list[dict]:
    """Write the mesh and every sequence of one object; return their manifest entries."""
    out_dir = Path(out_dir)
    index = sorted(STANDINS).index(name)
    seeds = np.random.SeedSequence([cfg.seed, index]).spawn(cfg.sequences_per_object + 1)
    mesh = build_standin(name, seed=int(seeds[0].generate_state(1)[0]))
    write_obj(out_dir / "meshes" / f"{name}.obj", mesh)
    sdf = SignedDistanceGrid.from_mesh(mesh, spacing=cfg.sdf_spacing_m, padding=0.03)
    grasp_types = [g for g in STANDINS[name].grasps if g in GRASP_TYPES]
    entries = []
    for k in range(cfg.sequences_per_object):
        rng = np.random.default_rng(seeds[k + 1])
        shape = HandShape(scale=float(rng.uniform(*cfg.hand_scale)))
        grasp = _grasp_with_fallback(sdf, grasp_types, k, rng, shape)
        seq_name = f"{name}__{k:02d}_{grasp.template.name}"
        symmetry = STANDINS[name].symmetry_axis
        seq, info = _make_sequence(seq_name, grasp, sdf, rng, cfg, shape, symmetry)
        save_sequence(StageDir(out_dir).sequence(seq_name), seq, data_root=out_dir)
        info["grasp_score"] = grasp.score
        entries.append(info)
    return entries


def generate_demo(cfg: DemoConfig, out_dir: str | Path, run: int | RunParams = 1) -> dict:
    """Generate the whole demo dataset into ``out_dir`` (``sequences/``, ``meshes/``).

    Args:
        cfg: What to generate (seeded: the same config gives the same bytes).
        out_dir: The data root to write.
        run: The ``run`` params (backend, n_jobs) or an int n_jobs; objects map over it.

    Returns:
        The manifest, also written to ``out_dir/index.json``.
    """
    from dexflow.pipeline.parallel import map_items, raise_first_error

    names = list(cfg.objects) or sorted(STANDINS)
    unknown = sorted(set(names) - set(STANDINS))
    if unknown:
        from dexflow.errors import ConfigError

        raise ConfigError(f"data.demo.objects: unknown {unknown}; known: {sorted(STANDINS)}")
    results = map_items(
        lambda name: generate_object(name, cfg, out_dir), names, run, desc="demo objects"
    )
    raise_first_error(results)
    entries = [e for r in results for e in r.value]
    manifest = {
        "objects": names,
        "sequences": entries,
        "num_sequences": len(entries),
        "num_frames": int(sum(e["frames"] for e in entries)),
    }
    save_json(Path(out_dir) / "index.json", manifest)
    return manifest


# Objects shown in reports/figures/demo.png (when the demo has them): one per kind of shape.
FIGURE_OBJECTS = (
    "025_mug",
    "024_bowl",
    "011_banana",
    "005_tomato_soup_can",
    "051_large_clamp",
    "006_mustard_bottle",
)
