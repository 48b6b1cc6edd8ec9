"""Dataset adapters: DexYCB, HO-3D, GRAB and a generic format -> dexflow's canonical sequences.

``dexflow convert <adapter> SRC [SRC ...] DST`` writes ``DST/sequences/<adapter>_<name>.npz``
and ``DST/meshes/``; names are unique within a dataset (DexYCB and HO-3D names carry the folder
above the sequence, e.g. the subject: ``ho3d_20201002-subject-08_20201002_104719``). A sequence
whose object model is missing is skipped and listed with the path it looked for. Every adapter
then cleans the same way (:func:`write_sequence`):

- frames without a hand (missing files, ``None`` or all ``-1`` joints, NaN) are kept as frames
  with NaN keypoints and ``valid = False`` (masked, not dropped, so time stays uniform);
- frames whose annotation is the dataset's "not annotated" marker are masked the same way and
  counted apart (``template_frames``): DexYCB and HO-3D leave such frames at the MANO template
  hand (all-zero ``handPose`` and ``handTrans``, or DexYCB's all-zero ``pose_m``), whose joints
  are present but ~0.8 m from the real hand;
- frames whose annotation is a default pose far from the rest of the sequence (an implausible
  wrist jump, :func:`dexflow.human.cleaning.detect_bad_frames`) are masked the same way;
- frames without an object pose hold the nearest annotated pose;
- units are checked (hand size), left hands are mirrored to right ones with their object
  (``mirrored = True``), and a sanity statistic is computed: the distance from the nearest
  fingertip to the object surface, whose median should be a few millimetres for grasping data
  (tens of millimetres mean the object pose and the keypoints are not in the same frame).

Camera-frame data (the HO-3D layout: no extrinsics, no vertical) is written per session, a
folder of sequences from one camera, in the frame of its table (z up, the table at z = 0), the
up vector fitted from where the session's objects rest (:mod:`dexflow.data.table`,
:func:`_convert_session`); ``convert.json`` records each fit under ``table_frames``. Too few
captures (fewer than 8), a fit whose start heights spread over 3 cm, or ``--camera-frame`` keep
the camera's frame.

Each source sequence is read on its own: a file that cannot be read (a corrupt pickle, a frame
file with an unexpected name, a text cell in a CSV) fails that sequence only, with the source
file named in its error, and the others are converted; ``convert.json`` is always written.

Source files are untrusted (:mod:`dexflow.io.untrusted`): pickles (HO-3D frames, GRAB members)
may build plain data only, archive headers are checked before anything is inflated, and every
path or name read from data (an object name, a mesh path, a DexYCB serial) must stay inside its
folder, links followed: the models folder, SRC, or DST for the meshes written.

The datasets' layouts and their readers: :mod:`dexflow.data.readers`; the shared types and
checks: :mod:`dexflow.data.formats`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence as Sequence_
from dataclasses import replace
from pathlib import Path

import numpy as np

from dexflow.data.formats import (
    HO3D_TO_DEXFLOW,
    ConvertOptions,
    DatasetLayoutError,
    MissingOptionError,
    RawSequence,
    SourceSequence,
    inside,
    need,
)
from dexflow.data.readers import ADAPTERS
from dexflow.data.rotation_convention import STANDARD, RotationConvention, check_convention
from dexflow.data.table import DIP_M, MAX_START_MAD_M, MIN_CAPTURES, fit_table, table_frame
from dexflow.errors import DexflowError
from dexflow.geometry import transform_points, world_to_object
from dexflow.human.cleaning import detect_bad_frames, nearest_index
from dexflow.human.keypoints import FINGERTIPS
from dexflow.io.atomic import save_json
from dexflow.io.layout import StageDir
from dexflow.io.mirror import mirror_mesh, mirror_sequence
from dexflow.io.sequence import Sequence, save_sequence
from dexflow.objects.mesh import load_mesh, write_obj
from dexflow.objects.sdf import signed_distance

__all__ = [
    "ADAPTERS",
    "HO3D_TO_DEXFLOW",
    "ConvertOptions",
    "DatasetLayoutError",
    "MissingOptionError",
    "RawSequence",
    "SourceSequence",
    "convert",
]

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------------- cleaning


def _hold_nearest(pose: np.ndarray) -> np.ndarray:
    good = np.isfinite(pose).all(axis=(1, 2))
    if not good.any():
        raise DatasetLayoutError("the object pose is not annotated in any frame")
    idx = np.flatnonzero(good)
    return pose[nearest_index(idx, len(pose))]


def fingertip_surface_distance(seq: Sequence, mesh, frames: int = 40) -> np.ndarray:
    """Per sampled valid frame, the smallest fingertip-to-surface signed distance (metres)."""
    valid = np.flatnonzero(seq.valid_mask & np.isfinite(seq.keypoints).all(axis=(1, 2)))
    if len(valid) == 0:
        return np.zeros(0)
    chosen = valid[np.linspace(0, len(valid) - 1, min(frames, len(valid))).astype(int)]
    local = world_to_object(seq.keypoints[chosen][:, list(FINGERTIPS)], seq.obj_pose[chosen])
    return signed_distance(mesh, local).min(axis=1)


def _clean_hand(
    raw: RawSequence, options: ConvertOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The hand as written: ``(keypoints (T, 21, 3), valid, template, missing, lost)``, the
    masks (T,) bool, keypoints NaN wherever ``valid`` is False."""
    kp = np.array(raw.keypoints, dtype=np.float64)
    template = np.zeros(len(kp), dtype=bool) if raw.template is None else np.asarray(raw.template)
    kp[template] = np.nan
    missing = ~np.isfinite(kp).all(axis=(1, 2)) & ~template
    kp[missing] = np.nan
    observed, lost = detect_bad_frames(kp, None, options.jump_threshold_m, fps=raw.fps)
    kp[lost] = np.nan
    return kp, observed, template, missing, lost


def write_sequence(raw: RawSequence, dst: Path, options: ConvertOptions) -> dict:
    """Clean, mirror (left hands), validate and save one sequence; return its report."""
    kp, valid, template, missing, lost = _clean_hand(raw, options)
    if not valid.any():
        raise DatasetLayoutError(f"{raw.name}: no frame has a usable hand")
    inside(dst / "meshes", raw.obj_name, raw.name, "obj_name", name=True)
    mesh = load_mesh(need(raw.mesh_path, f"object model of '{raw.obj_name}'"))
    mesh_rel = f"meshes/{raw.obj_name}.obj"
    mesh_out = inside(dst, mesh_rel, raw.name, "obj_name")
    if not mesh_out.exists():
        write_obj(mesh_out, mesh)
    seq = Sequence(
        keypoints=kp,
        obj_pose=_hold_nearest(raw.obj_pose),
        obj_mesh=mesh_rel,
        obj_name=raw.obj_name,
        fps=raw.fps,
        side=raw.side,
        source=raw.source,
        valid=valid,
    )
    if raw.side == "left":
        mesh = mirror_mesh(mesh)
        mirrored_rel = f"meshes/{raw.obj_name}_mirrored.obj"
        mirrored_out = inside(dst, mirrored_rel, raw.name, "obj_name")
        if not mirrored_out.exists():
            write_obj(mirrored_out, mesh)
        seq = mirror_sequence(seq, mirrored_rel)
    elif raw.side != "right":
        raise DatasetLayoutError(f"{raw.name}: side '{raw.side}'; expected 'right' or 'left'")
    path = StageDir(dst).sequence(f"{raw.source}_{raw.name}")
    save_sequence(path, seq, data_root=dst)
    gap = fingertip_surface_distance(seq, mesh)
    report = {
        "frames": len(kp),
        "missing_frames": int(missing.sum()),
        "template_frames": int(template.sum()),
        "tracking_lost_frames": int(lost.sum()),
        "mirrored": raw.side == "left",
        "fingertip_to_surface_mm_median": float(np.median(gap) * 1000) if len(gap) else None,
        "fingertip_to_surface_mm_p90": float(np.percentile(gap, 90) * 1000) if len(gap) else None,
    }
    if len(gap) and np.median(gap) > 0.03:
        log.warning(
            "%s: nearest fingertip is %.0f mm from the object surface (median): is the "
            "object pose in the same frame as the keypoints?",
            raw.name,
            np.median(gap) * 1000,
        )
    return report


def convert(
    adapter: str,
    src: str | Path | Sequence_[str | Path],
    dst: str | Path,
    options: ConvertOptions | None = None,
) -> dict:
    """Convert one or several source folders of a dataset into one data root.

    One bad sequence is reported and the others are written. A sequence whose object model is
    missing is ``skipped`` (``failed`` with ``options.strict``); two sources that give the same
    sequence name fail the second one rather than overwrite the first.

    Args:
        adapter: One of :data:`ADAPTERS`.
        src: Source folder(s): what the adapter's layout expects (see the module docstring).
        dst: The data root to write (``sequences/``, ``meshes/``, ``convert.json``).
        options: Adapter options (defaults: :class:`ConvertOptions`).

    Returns:
        The report, also written to ``DST/convert.json``: per sequence its ``status`` (ok,
        skipped, failed) with its counts or its ``reason``/``error``, the totals, and per
        session of camera-frame data (HO-3D: a folder of sequences) its ``table_frames``
        entry and its ``object_rotation`` ``sessions`` entry (:func:`_convert_session`).

    Raises:
        DatasetLayoutError: Unknown adapter, a missing source folder, a source that does not
            have the adapter's layout at all, or data that needs a missing option (``--mano``).
        ConfigError: ``options.object_rotation`` is not a mode or a convention.
    """
    if adapter not in ADAPTERS:
        raise DatasetLayoutError(f"unknown adapter '{adapter}'; known: {sorted(ADAPTERS)}")
    options = options or ConvertOptions()
    sources = [Path(src)] if isinstance(src, (str, Path)) else [Path(s) for s in src]
    if not sources:
        raise DatasetLayoutError("no source folder given")
    dst = Path(dst)
    for folder in sources:
        need(folder, "source dataset folder")
    given = _given_convention(options.object_rotation)
    StageDir(dst).sequences_dir.mkdir(parents=True, exist_ok=True)
    sequences: dict[str, dict] = {}
    tables: dict[str, dict] = {}
    rotations: dict[str, dict] = {}
    for folder in sources:
        sessions: dict[Path, list[SourceSequence]] = {}
        for source in ADAPTERS[adapter](folder, options):
            if source.session is not None:
                sessions.setdefault(source.session, []).append(source)
                continue
            raws = _read(source, sequences)
            for raw in raws:
                if _admit(raw, folder, options, sequences):
                    _write(_rotated(raw, given or STANDARD), source, dst, options, sequences)
        for session, group in sessions.items():
            _convert_session(
                session, group, folder, dst, options, sequences, (tables, rotations), given
            )
    statuses = [entry["status"] for entry in sequences.values()]
    report = {
        "adapter": adapter,
        "source": [str(folder) for folder in sources],
        "num_sequences": len(sequences),
        "num_ok": statuses.count("ok"),
        "num_skipped": statuses.count("skipped"),
        "num_failed": statuses.count("failed"),
        "sequences": sequences,
        "table_frames": tables,
        "object_rotation": {"option": options.object_rotation, "sessions": rotations},
    }
    save_json(dst / "convert.json", report)
    return report


def _reason(exc: Exception, source: SourceSequence) -> str:
    """An error's message, naming the source it came from unless it already does."""
    text = str(exc) if isinstance(exc, DexflowError) else f"{type(exc).__name__}: {exc}"
    return text if str(source.path) in text else f"{text} (source: {source.path})"


def _read(source: SourceSequence, sequences: dict[str, dict]) -> list[RawSequence]:
    """The sequences ``source`` holds; none if it cannot be read (recorded as failed)."""
    try:
        return source.read()
    except MissingOptionError:
        raise
    except Exception as exc:  # one unreadable source sequence never stops the others
        sequences[source.name] = {"status": "failed", "error": _reason(exc, source)}
        log.error("%s: %s", source.name, sequences[source.name]["error"])
        return []


def _admit(
    raw: RawSequence, folder: Path, options: ConvertOptions, sequences: dict[str, dict]
) -> bool:
    """Whether ``raw`` is to be written: not a name an earlier source gave, its object model
    there (else recorded as failed or skipped)."""
    if raw.name in sequences:
        sequences[f"{raw.name} ({folder})"] = {
            "status": "failed",
            "error": f"{raw.name}: the same name comes from an earlier source; "
            f"convert {folder} into another root",
        }
        log.error("%s: duplicate sequence name from %s", raw.name, folder)
        return False
    if not raw.mesh_path.is_file():
        reason = f"no object model of '{raw.obj_name}': {raw.mesh_path} is missing"
        status = "failed" if options.strict else "skipped"
        key = "error" if options.strict else "reason"
        sequences[raw.name] = {"status": status, key: reason}
        (log.error if options.strict else log.warning)("%s: %s", raw.name, reason)
        return False
    return True


def _write(
    raw: RawSequence,
    source: SourceSequence,
    dst: Path,
    options: ConvertOptions,
    sequences: dict[str, dict],
) -> None:
    """Write ``raw``, recording its entry in ``sequences``: ok, or failed with its source."""
    try:
        sequences[raw.name] = {"status": "ok", **write_sequence(raw, dst, options)}
    except MissingOptionError:
        raise
    except Exception as exc:  # reported with its source; the others go on
        sequences[raw.name] = {"status": "failed", "error": _reason(exc, source)}
        log.error("%s: %s", raw.name, sequences[raw.name]["error"])


def _resting_poses(
    raws: list[RawSequence], options: ConvertOptions
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per sequence that will be written with a tracked frame: its object's convex-hull
    vertices and its object poses at its tracked frames, as :func:`write_sequence` cleans them
    (the first: the object at rest)."""
    hulls: dict[Path, np.ndarray] = {}
    out_hulls, out_poses = [], []
    for raw in raws:
        try:
            _, valid, *_ = _clean_hand(raw, options)
            pose = _hold_nearest(raw.obj_pose)[valid]
            if raw.mesh_path not in hulls:
                hulls[raw.mesh_path] = load_mesh(raw.mesh_path).convex_hull.vertices
        except Exception:  # left out of the fit; writing it fails it, saying why
            continue
        if len(pose) and np.isfinite(pose).all():
            out_hulls.append(hulls[raw.mesh_path])
            out_poses.append(pose)
    return out_hulls, out_poses


def _convert_session(
    session: Path,
    group: list[SourceSequence],
    folder: Path,
    dst: Path,
    options: ConvertOptions,
    sequences: dict[str, dict],
    records: tuple[dict[str, dict], dict[str, dict]],
    given: RotationConvention | None,
) -> None:
    """Write one session's sequences (one camera, one table) in their table's frame, their
    object rotations read by ``given`` or, without it, checked (:func:`_session_rotations`).

    The table is fitted from all of them (:func:`dexflow.data.table.fit_table`) in the camera's
    frame, before left hands are mirrored: mirroring (x -> -x) keeps z, so a mirrored sequence
    is z up too. The camera's frame is kept, with a warning, when fewer than
    :data:`~dexflow.data.table.MIN_CAPTURES` sequences can be fitted or their start heights
    spread more than :data:`~dexflow.data.table.MAX_START_MAD_M`; and with
    ``options.camera_frame``. ``records[0][str(session)]`` (``table_frames``) records the fit:
    ``up`` (in the camera's frame), ``table_height_m`` (along it), ``start_height_mad_m``,
    ``dip_share`` (over :data:`~dexflow.data.table.DIP_M`), ``captures``, ``applied``, and
    ``reason`` if not; ``records[1][str(session)]`` the object rotations' check.
    """
    tables, rotations = records
    read = [(source, _read(source, sequences)) for source in group]
    admitted = [
        (source, [raw for raw in raws if _admit(raw, folder, options, sequences)])
        for source, raws in read
    ]
    raws = [raw for _, session_raws in admitted for raw in session_raws]
    hulls, poses = _resting_poses(raws, options)
    convention = given or _session_rotations(session, raws, hulls, poses, options, rotations)
    poses = [convention.poses(pose) for pose in poses]
    admitted = [(source, [_rotated(raw, convention) for raw in raws]) for source, raws in admitted]
    transform = None
    if poses:
        fit = fit_table(hulls, poses)
        if options.camera_frame:
            reason = "--camera-frame given"
        elif fit.num_captures < MIN_CAPTURES:
            reason = f"{fit.num_captures} captures, too few to fit (at least {MIN_CAPTURES})"
        elif fit.start_height_mad_m > MAX_START_MAD_M:
            reason = (
                f"start heights spread {fit.start_height_mad_m * 100:.1f} cm (MAD), over "
                f"{MAX_START_MAD_M * 100:.0f} cm: one camera and one table?"
            )
        else:
            reason = None
        tables[str(session)] = {
            "up": [round(float(x), 6) for x in fit.up],
            "table_height_m": fit.height_m,
            "start_height_mad_m": fit.start_height_mad_m,
            "dip_share": fit.dip_share,
            "captures": fit.num_captures,
            "applied": reason is None,
            **({"reason": reason} if reason else {}),
        }
        numbers = (
            f"up {np.round(fit.up, 3).tolist()} in the camera's frame, start heights spread "
            f"{fit.start_height_mad_m * 100:.1f} cm (MAD), {fit.dip_share * 100:.0f} % of "
            f"{fit.num_captures} captures dip over {DIP_M * 100:.0f} cm"
        )
        if reason is None:
            transform = table_frame(fit)
            log.info("%s: written in its table's frame (%s)", session, numbers)
        else:
            (log.info if options.camera_frame else log.warning)(
                "%s: kept the camera's frame, z not up: %s (%s)", session, reason, numbers
            )
    for source, raws in admitted:
        for raw in raws:
            _write(_moved(raw, transform), source, dst, options, sequences)


def _given_convention(option: str) -> RotationConvention | None:
    """The convention ``--object-rotation`` names; None for ``check`` and ``auto``."""
    return None if option in ("check", "auto") else RotationConvention.parse(option)


def _rotated(raw: RawSequence, convention: RotationConvention) -> RawSequence:
    """``raw`` with its object rotations read by ``convention``."""
    if convention.is_standard:
        return raw
    return replace(raw, obj_pose=convention.poses(raw.obj_pose))


def _session_rotations(
    session: Path,
    raws: list[RawSequence],
    hulls: list[np.ndarray],
    poses: list[np.ndarray],
    options: ConvertOptions,
    rotations: dict[str, dict],
) -> RotationConvention:
    """Check a session's stored object rotations against its hands and its table
    (:func:`~dexflow.data.rotation_convention.check_convention`), record the check in
    ``rotations[str(session)]``, warn when another convention fits clearly better, and return
    the convention to read them by: that one with ``auto``, else the standard one."""
    check = check_convention(
        [raw.keypoints for raw in raws],
        [raw.obj_pose for raw in raws],
        hulls,
        [pose[0] for pose in poses],
    )
    apply = options.object_rotation == "auto"
    rotations[str(session)] = {
        **check.record(),
        "applied": str(check.found if apply else STANDARD),
    }
    if check.found.is_standard:
        log.info("%s: object rotations read as stored (%s)", session, check.summary())
        return STANDARD
    if apply:
        log.info("%s: object rotations read as '%s' (%s)", session, check.found, check.summary())
        return check.found
    log.warning(
        "%s: the stored object rotations fit the hands and the table clearly better read as "
        "'%s' (%s); kept as stored: pass --object-rotation auto (or '%s') to read them so, "
        "--object-rotation as-stored to skip this check",
        session,
        check.found,
        check.summary(),
        check.found,
    )
    return STANDARD


def _moved(raw: RawSequence, transform: np.ndarray | None) -> RawSequence:
    """``raw`` with its keypoints and object poses moved by ``transform`` (4, 4), if any."""
    if transform is None:
        return raw
    return replace(
        raw,
        keypoints=transform_points(transform, np.asarray(raw.keypoints, dtype=np.float64)),
        obj_pose=transform @ np.asarray(raw.obj_pose, dtype=np.float64),
    )
