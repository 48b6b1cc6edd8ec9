"""Stage scale_align (paper §III-A): scale human data to the robot hand, precompute objects.

The whole scene (keypoints, object poses and meshes) is scaled by the hand's factor ``s`` about
the world origin: a similarity transform, so every contact and clearance of the human data keeps
its shape, only ``s`` times larger. Then each human fingertip is moved along its distal bone by
the hand's fingertip offset (metres, after scaling). A human hand of the other side than the
robot hand (a ``side: left`` sequence that ``dexflow convert`` did not mirror, for the usual
right robot hand) is first mirrored with its whole scene (:mod:`dexflow.io.mirror`: keypoints,
object poses, and a mirrored copy of the object), so the robot tracks the motion it can
reproduce. A sequence whose fingertips never come within
:data:`~dexflow.io.sequence.NEAR_OBJECT_M` of the object is kept with a warning (its entry's
``warning``): there is no contact to retarget. An object mesh that was inside out is flipped by
:func:`~dexflow.objects.mesh.load_mesh`, and said in the ``warning`` of its ``meta.json`` and of
every sequence using it.

Per object, computed once whatever the number of sequences using it, at the scaled size:

- ``mesh.obj``: the scaled mesh;
- ``sdf.npz``: signed distance grid (winding-number sign, correct for meshes with holes);
- ``surface.npz``: ``points (N, 3)`` and outward ``normals (N, 3)`` sampled on the surface;
- ``convex.obj``: CoACD convex decomposition, one ``o`` group per part, for simulation (the
  unscaled mesh's parts, scaled: they come from the object asset cache of
  :mod:`dexflow.objects.convex` when another run already decomposed the same mesh);
- ``meta.json``: source mesh, scale, bounds, watertightness, part count.

Output layout below the stage directory: ``sequences/<name>.npz`` (canonical format, its
``obj_mesh`` pointing at ``objects/<key>/mesh.obj``, plus ``scale``), ``objects/<key>/...`` and
``summary.json`` listing every sequence and object with its status.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dexflow.errors import DexflowError, MeshError
from dexflow.geometry import world_to_object
from dexflow.human.keypoints import FINGER_KEYPOINTS, FINGERTIPS
from dexflow.io.atomic import save_json, save_npz
from dexflow.io.layout import Layout, ObjectPaths, StageDir
from dexflow.io.mirror import mirror_mesh, mirror_sequence
from dexflow.io.sequence import NEAR_OBJECT_M, Sequence, load_sequence, save_sequence
from dexflow.objects.convex import cached_convex_decomposition, write_convex_obj
from dexflow.objects.mesh import MESH_WARNING, load_mesh, write_obj
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.objects.surface import sample_surface
from dexflow.params import HandParams, PipelineParams
from dexflow.pipeline.resume import StageOutput
from dexflow.pipeline.runner import StageSpec

__all__ = [
    "STAGE",
    "ObjectJob",
    "align_sequence",
    "prepare_object",
    "run_scale_align",
    "scale_sequence",
]

log = logging.getLogger(__name__)


def scale_sequence(seq: Sequence, scale: float, fingertip_offsets: dict[str, float]) -> Sequence:
    """Scale a sequence about the world origin and apply fingertip offsets.

    Args:
        seq: Sequence in metres.
        scale: Human-to-robot size factor.
        fingertip_offsets: Per finger name, metres added along the distal bone (DIP -> tip).

    Returns:
        A new sequence; ``obj_pose`` translations are scaled, rotations kept (the mesh itself
        must be scaled by the same factor). NaN frames stay NaN.
    """
    kp = np.asarray(seq.keypoints, dtype=np.float64) * scale
    for finger, offset in fingertip_offsets.items():
        if offset == 0.0:
            continue
        *_, dip, tip = FINGER_KEYPOINTS[finger]
        bone = kp[:, tip] - kp[:, dip]
        kp[:, tip] += offset * bone / np.linalg.norm(bone, axis=-1, keepdims=True)
    pose = np.array(seq.obj_pose, dtype=np.float64)
    pose[:, :3, 3] *= scale
    extras = {k: v for k, v in seq.extras.items()}
    if "gt_keypoints" in extras:
        extras["gt_keypoints"] = np.asarray(extras["gt_keypoints"]) * scale
    extras["scale"] = np.array(float(scale))
    return replace(seq, keypoints=kp, obj_pose=pose, extras=extras)


def _object_key(mesh_rel: str, mirror: bool = False) -> str:
    stem = Path(mesh_rel).stem
    if mirror:
        stem, mesh_rel = f"{stem}_mirrored", f"{mesh_rel}|mirrored"
    digest = hashlib.sha1(mesh_rel.encode()).hexdigest()[:8]
    return f"{stem}-{digest}"


@dataclass(frozen=True)
class ObjectJob:
    """One object to precompute: its mesh (relative to the data root), output key, and whether
    it is mirrored (the object of a left hand)."""

    mesh_rel: str
    key: str
    mirror: bool = False


def prepare_object(job: ObjectJob, in_root: Path, out: ObjectPaths, params: PipelineParams) -> dict:
    """Scale one object mesh and write its precomputation to ``out`` (``objects/<key>/``).

    A mesh :func:`~dexflow.objects.mesh.load_mesh` repaired (flipped inside out) gets its
    warning in ``meta.json`` and the returned entry (``warning``)."""
    cfg = params.scale_align
    scale = params.hand.scale
    unscaled = load_mesh(in_root / job.mesh_rel)
    warning = unscaled.metadata.get(MESH_WARNING)
    if job.mirror:
        unscaled = mirror_mesh(unscaled)
    mesh = unscaled.copy()
    mesh.apply_scale(scale)
    write_obj(out.mesh, mesh)
    sdf = SignedDistanceGrid.from_mesh(mesh, spacing=cfg.sdf_spacing_m, padding=cfg.sdf_padding_m)
    sdf.save(out.sdf)
    points, normals = sample_surface(mesh, cfg.surface_samples, sdf, seed=params.seed)
    save_npz(out.surface, {"points": points, "normals": normals})
    c = cfg.convex
    # CoACD is scale-equivariant: the unscaled mesh's parts (cached by content, so that another
    # hand's scale or a rerun does not decompose again), scaled
    parts = cached_convex_decomposition(
        unscaled,
        threshold=c.threshold,
        max_hulls=c.max_hulls,
        preprocess_resolution=c.preprocess_resolution,
        mcts_iterations=c.mcts_iterations,
        mcts_max_depth=c.mcts_max_depth,
        mcts_nodes=c.mcts_nodes,
        seed=params.seed,
    )
    for part in parts:
        part.apply_scale(scale)
    write_convex_obj(out.convex, parts)
    meta = {
        "source_mesh": job.mesh_rel,
        "scale": scale,
        "faces": len(mesh.faces),
        "watertight": bool(mesh.is_watertight),
        "bounds_m": np.round(mesh.bounds, 6).tolist(),
        "convex_parts": len(parts),
        "sdf_shape": list(sdf.values.shape),
        "sdf_spacing_m": sdf.spacing,
    }
    if job.mirror:
        meta["mirrored"] = True
    if warning:
        meta["warning"] = warning
    save_json(out.meta, meta)
    return meta


def align_sequence(
    path: Path, in_root: Path, out: StageDir, params: PipelineParams, key: str
) -> dict:
    """Scale one sequence file and write it to ``out`` (stage scale_align's directory)."""
    seq = load_sequence(path, data_root=in_root)
    mesh = out.object(key).mesh.relative_to(out.root).as_posix()
    if _mirror(seq, params.hand):
        seq = replace(mirror_sequence(seq, mesh), mirrored=not seq.mirrored)
    aligned = scale_sequence(seq, params.hand.scale, params.hand.fingertip_offsets)
    aligned = replace(aligned, obj_mesh=mesh)
    save_sequence(out.sequence(path), aligned, data_root=out.root)
    entry = {"frames": aligned.num_frames, "object": key}
    closest, frame = _closest_fingertip(aligned, SignedDistanceGrid.load(out.object(key).sdf))
    entry["closest_fingertip_mm"] = round(closest / params.hand.scale * 1000, 3)
    if closest / params.hand.scale > NEAR_OBJECT_M:
        entry["warning"] = (
            f"the hand never comes within {NEAR_OBJECT_M * 1000:.0f} mm of the object (nearest "
            f"fingertip {entry['closest_fingertip_mm']:.0f} mm, frame {frame}): are obj_pose "
            "and the keypoints in one world frame and unit?"
        )
    return entry


def _mirror(seq: Sequence, hand: HandParams) -> bool:
    """Whether the sequence's hand, as it is stored, is of the other side than the robot hand
    (a ``mirrored`` sequence or hand model is of the other side than its ``side`` says)."""
    other = {"right": "left", "left": "right"}
    human = other[seq.side] if seq.mirrored else seq.side
    side = getattr(hand, "side", "right")
    robot = other[side] if getattr(hand, "mirrored", False) else side
    return human != robot


def _closest_fingertip(seq: Sequence, sdf: SignedDistanceGrid) -> tuple[float, int]:
    """The smallest fingertip-to-surface signed distance over the tracked frames, and its
    frame."""
    frames = np.flatnonzero(seq.valid_mask & np.isfinite(seq.keypoints).all(axis=(1, 2)))
    local = world_to_object(seq.keypoints[frames][:, list(FINGERTIPS)], seq.obj_pose[frames])
    distance = sdf.query(local).min(axis=1)
    best = int(np.argmin(distance))
    return float(distance[best]), int(frames[best])


def _object_of(path: Path, in_root: Path, hand: HandParams) -> ObjectJob:
    """The object a sequence file needs; raises SequenceFormatError for a bad file (its mesh
    missing or outside the data root) before anything reads the mesh."""
    seq = load_sequence(path, data_root=in_root)
    mirror = _mirror(seq, hand)
    return ObjectJob(seq.obj_mesh, _object_key(seq.obj_mesh, mirror), mirror)


def run_scale_align(params: PipelineParams, layout: Layout) -> dict:
    """Run the stage over every sequence of ``layout.data``; never stops at one bad file.

    Returns:
        The summary, also written to ``layout.scale_align.summary``.
    """
    source, out = layout.data, layout.scale_align
    in_root = source.root
    stage = StageOutput(
        out,
        "scale_align",
        {
            "seed": params.seed,
            "hand.scale": params.hand.scale,
            "hand.fingertip_offsets": params.hand.fingertip_offsets,
            "scale_align": params.scale_align,
        },
        inputs=(source,),
    )
    files = stage.start()

    job_of: dict[str, ObjectJob] = {}
    errors: dict[str, str] = {}
    for path in files:
        try:
            job_of[path.stem] = _object_of(path, in_root, params.hand)
        except DexflowError as exc:  # dropped, reported per sequence below
            errors[path.stem] = f"{type(exc).__name__}: {exc}"
    jobs = sorted(set(job_of.values()), key=lambda j: j.key)
    object_results = stage.map(
        lambda job: prepare_object(job, in_root, out.object(job.key), params),
        jobs,
        params.run,
        "objects",
        group="objects",
        name=lambda job: job.key,
        inputs=lambda job: [in_root / job.mesh_rel],
    )
    objects = {r.item.key: r for r in object_results}

    def run_one(path: Path) -> dict:
        obj = objects[job_of[path.stem].key]
        if not obj.ok:  # the object's own failure decides: bad mesh, or the machine (retried)
            error = RuntimeError if obj.retry else MeshError
            raise error(f"object {obj.item.mesh_rel} failed: {obj.error}")
        entry = align_sequence(path, in_root, out, params, obj.item.key)
        if obj.value and obj.value.get("warning"):  # the object's warning is the sequence's
            notes = [f"object {obj.item.mesh_rel}: {obj.value['warning']}", entry.get("warning")]
            entry["warning"] = "; ".join(n for n in notes if n)
        return entry

    todo = [p for p in files if p.stem not in errors]
    seq_results = stage.map(run_one, todo, params.run, "sequences")
    sequences = {stem: {"status": "failed", "error": e} for stem, e in errors.items()}
    for r in seq_results:
        sequences[r.item.stem] = r.entry()
    summary = {
        "stage": "scale_align",
        "hand": params.hand.name,
        "scale": params.hand.scale,
        "num_sequences": len(files),
        "num_ok": sum(s["status"] == "ok" for s in sequences.values()),
        "num_failed": sum(s["status"] != "ok" for s in sequences.values()),
        "num_frames": int(sum(s.get("frames", 0) for s in sequences.values())),
        "num_objects": len(objects),
        "sequences": dict(sorted(sequences.items())),
        "objects": {k: r.entry() for k, r in sorted(objects.items())},
    }
    stage.finish(summary)
    return summary


STAGE = StageSpec(
    name="scale_align",
    run=run_scale_align,
    metric_keys=("num_sequences", "num_ok", "num_failed", "num_frames", "num_objects"),
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences ok, {s['num_frames']} frames, "
        f"{s['num_objects']} objects"
    ),
)
