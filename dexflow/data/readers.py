"""The dataset readers of ``dexflow convert``: each lists its source sequences and reads one into
a :class:`~dexflow.data.formats.RawSequence`, which :mod:`dexflow.data.adapters` cleans and writes.

Layouts (only the files dexflow reads are listed):

- **DexYCB**: ``<subject>/<sequence>/meta.yml`` (``serials``, ``ycb_ids``, ``ycb_grasp_ind``,
  ``mano_sides``, ``extrinsics``), ``<sequence>/<serial>/labels_%06d.npz`` (``joint_3d
  (1, 21, 3)`` in that camera's frame, ``pose_y (n_obj, 3, 4)``, optional ``pose_m (1, 51)``),
  ``calibration/extrinsics_<name>/extrinsics.yml`` (``extrinsics: {serial: 12 numbers}``, camera
  to world, row-major 3x4; ``apriltag``, the table's tag to world, where given: the sequences are
  written in the tag's frame, z up), models ``models/<ycb name>/textured_simple.obj``. 30 fps.
- **HO-3D** (also DexYCB exported in its layout): ``<sequence>/meta/<frame>.pkl`` below SRC,
  or ``<subject>/<sequence>/meta/<frame>.pkl`` below a dataset root, dicts with
  ``handJoints3D (21, 3)`` (HO-3D order), ``objRot (3,)`` axis-angle, ``objTrans (3,)``,
  ``objName`` (e.g. ``025_mug``); optional ``side``; optional MANO ``handPose (48,)``,
  ``handTrans (3,)``, ``handBeta (10,)`` used with ``--mano`` where the joints are missing.
  Models ``<models>/<objName>/textured_simple.obj``. Poses and joints are in the camera's
  frame; the sequences of one folder (a subject's, as DexYCB exports them: one camera) are one
  session, written in their table's frame (:mod:`dexflow.data.table`).
- **GRAB**: ``*.npz`` (pickled dicts, as GRAB ships them): ``framerate``, ``object`` with
  ``params: {transl (T, 3), global_orient (T, 3)}`` and ``object_mesh`` (path relative to SRC),
  ``rhand`` / ``lhand`` with ``joints (T, 21, 3)`` (MANO order) or, with ``--mano``,
  ``params: {global_orient (T, 3), hand_pose (T, 45 or PCA), transl (T, 3)}`` and ``betas``.
- **generic**: ``<name>.npz`` with ``keypoints (T, 21, 3)``, ``obj_pose (T, 4, 4)`` or
  ``obj_rotvec`` + ``obj_trans (T, 3)``, ``obj_mesh`` (relative to SRC), and optional ``fps``,
  ``side``, ``valid``, ``units`` (m | cm | mm), ``keypoint_order`` (mano | ho3d),
  ``timestamps`` (seconds); or ``<name>.csv`` with columns ``kp<i>_x, kp<i>_y, kp<i>_z``
  (i = 0..20), ``obj_rx, obj_ry, obj_rz`` (axis-angle), ``obj_tx, obj_ty, obj_tz`` (empty cells
  = no hand), optionally ``timestamps``, and a sidecar ``<name>.json`` with ``obj_mesh``, ``fps``
  and the optional fields above. With timestamps, frames are placed on the uniform ``1/fps``
  grid (``fps`` from the timestamps' median step if not given) and the gaps filled with frames
  without a hand: dexflow's stages take time from ``fps``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from dexflow.data.formats import (
    HO3D_TO_DEXFLOW,
    UNITS,
    YCB_CLASSES,
    ConvertOptions,
    DatasetLayoutError,
    RawSequence,
    SourceSequence,
    field,
    frame_number,
    frame_span,
    inside,
    mano_for,
    need,
    reading,
    rotvec_pose,
    visible,
)
from dexflow.geometry import transform_points
from dexflow.io.untrusted import MAX_FRAMES, load_npz, load_pickle

__all__ = ["ADAPTERS"]

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------- DexYCB


def _read_yaml(path: Path):
    import yaml

    with open(need(path, "file")) as handle, reading(path):
        return yaml.safe_load(handle)


def _dexycb(src: Path, options: ConvertOptions) -> Iterator[SourceSequence]:
    metas = sorted(src.glob("*/*/meta.yml"))
    if not metas:
        raise DatasetLayoutError(f"{src}: no <subject>/<sequence>/meta.yml (DexYCB layout)")
    models = Path(options.models) if options.models else src / "models"
    for meta_path in metas:
        seq_dir = meta_path.parent
        yield SourceSequence(
            f"{seq_dir.parent.name}_{seq_dir.name}",
            seq_dir,
            lambda meta_path=meta_path: [_read_dexycb(src, meta_path, models, options)],
        )


def _rigid(numbers, path: Path, name: str) -> np.ndarray:
    """(4, 4) from DexYCB's 12 row-major numbers of a 3x4 rigid transform."""
    try:
        matrix = np.asarray(numbers, dtype=np.float64).reshape(3, 4)
    except (TypeError, ValueError) as exc:
        raise DatasetLayoutError(f"{path}: field {name!r}: expected 12 numbers (3x4)") from exc
    rotation = matrix[:, :3]
    if not np.isfinite(matrix).all() or not np.allclose(
        rotation @ rotation.T, np.eye(3), atol=1e-3
    ):
        raise DatasetLayoutError(
            f"{path}: field {name!r}: expected a rigid transform (a rotation and a translation)"
        )
    return np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])


def _table_frame(extrinsics: dict, path: Path) -> np.ndarray:
    """World to the table's frame, where DexYCB calibrates one: its ``apriltag`` transform (the
    tag lies on the table, +z up, toward the hands and objects, as DexYCB's own toolkit crops
    the scene), else the identity (DexYCB's world, whose z is no vertical).

    The replay stage pulls objects along -z onto a table normal to z: in the tag's frame that is
    gravity; in the calibration's world frame it points along no physical direction."""
    if "apriltag" not in extrinsics:
        return np.eye(4)
    return np.linalg.inv(_rigid(extrinsics["apriltag"], path, "apriltag"))


def _read_dexycb(src: Path, meta_path: Path, models: Path, options: ConvertOptions) -> RawSequence:
    """One DexYCB sequence."""
    meta = _read_yaml(meta_path)
    seq_dir = meta_path.parent
    serials = [str(s) for s in field(meta, "serials", meta_path)]
    serial = options.camera or serials[0]
    cam_dir = inside(seq_dir, serial, meta_path, "serials", name=True)
    ycb_ids = field(meta, "ycb_ids", meta_path)
    grasp = int(field(meta, "ycb_grasp_ind", meta_path))
    side = str(field(meta, "mano_sides", meta_path)[0])
    calib_dir = f"extrinsics_{field(meta, 'extrinsics', meta_path)}"
    inside(src / "calibration", calib_dir, meta_path, "extrinsics", name=True)
    calib = inside(src, f"calibration/{calib_dir}/extrinsics.yml", meta_path, "extrinsics")
    extr = field(_read_yaml(calib), "extrinsics", calib)
    cam_to_world = _table_frame(extr, calib) @ _rigid(field(extr, serial, calib), calib, serial)
    labels = visible(need(cam_dir, f"camera folder of serial {serial}").glob("labels_*.npz"))
    if not labels:
        raise DatasetLayoutError(f"{seq_dir / serial}: no labels_*.npz files")
    frames = [frame_number(p, "labels_<n>.npz") for p in labels]
    n_frames = frame_span(frames, cam_dir, 0)
    kp = np.full((n_frames, 21, 3), np.nan)
    pose = np.full((n_frames, 4, 4), np.nan)
    template = np.zeros(n_frames, dtype=bool)
    for frame, path in zip(frames, labels, strict=True):
        with reading(path):
            data = load_npz(path)
            joints = np.asarray(field(data, "joint_3d", path), dtype=np.float64).reshape(21, 3)
            objects = np.asarray(field(data, "pose_y", path), dtype=np.float64)
            mano = np.asarray(data["pose_m"]) if "pose_m" in data else None
        if np.all(joints == -1):
            pass  # DexYCB's "no hand in this frame"
        elif mano is not None and not mano.any():
            template[frame] = True
        else:
            kp[frame] = transform_points(cam_to_world, joints)
        if len(objects) > grasp and np.isfinite(objects[grasp]).all() and objects[grasp].any():
            pose[frame] = cam_to_world @ np.vstack([objects[grasp], [0, 0, 0, 1]])
    ycb_id = int(ycb_ids[grasp])
    if not 1 <= ycb_id <= len(YCB_CLASSES):
        raise DatasetLayoutError(
            f"{meta_path}: field 'ycb_ids': {ycb_id} is not a YCB-Video id (1..{len(YCB_CLASSES)})"
        )
    name = YCB_CLASSES[ycb_id - 1]
    mesh = inside(models, f"{name}/textured_simple.obj", meta_path, "ycb_ids")
    return RawSequence(
        f"{seq_dir.parent.name}_{seq_dir.name}",
        kp,
        pose,
        mesh,
        name,
        options.fps or 30.0,
        side,
        "dexycb",
        template,
    )


# -------------------------------------------------------------------------------------- HO-3D


def _is_mano_template(meta: dict) -> bool:
    """Whether an HO-3D frame carries the MANO template (all-zero pose and translation)."""
    hand_pose, hand_trans = meta.get("handPose"), meta.get("handTrans")
    return (
        hand_pose is not None
        and hand_trans is not None
        and not np.any(hand_pose)
        and not np.any(hand_trans)
    )


def _ho3d(src: Path, options: ConvertOptions) -> Iterator[SourceSequence]:
    seq_dirs = sorted(p.parent for p in [*src.glob("*/meta"), *src.glob("*/*/meta")] if p.is_dir())
    if not seq_dirs:
        raise DatasetLayoutError(
            f"{src}: no <sequence>/meta/ or <subject>/<sequence>/meta/ folders (HO-3D layout)"
        )
    models = Path(options.models) if options.models else src / "models"
    for seq_dir in seq_dirs:
        yield SourceSequence(
            f"{seq_dir.parent.name}_{seq_dir.name}",
            seq_dir / "meta",
            lambda seq_dir=seq_dir: [_read_ho3d(seq_dir, models, options)],
            session=seq_dir.parent,
        )


def _read_ho3d(seq_dir: Path, models: Path, options: ConvertOptions) -> RawSequence:
    """One HO-3D sequence."""
    files = visible((seq_dir / "meta").glob("*.pkl"))
    if not files:
        raise DatasetLayoutError(f"{seq_dir / 'meta'}: no <frame>.pkl files")
    frames = [frame_number(p, "<n>.pkl") for p in files]
    first = min(frames)
    n_frames = frame_span(frames, seq_dir / "meta", first)
    kp = np.full((n_frames, 21, 3), np.nan)
    pose = np.full((n_frames, 4, 4), np.nan)
    template = np.zeros(n_frames, dtype=bool)
    names: dict[str, Path] = {}  # each object name, with the first file naming it
    side, mano_frames = "right", {}
    for frame, path in zip(frames, files, strict=True):
        with reading(path):  # a frame file that is not what HO-3D writes is named
            meta = load_pickle(path)
            if not isinstance(meta, dict):
                raise DatasetLayoutError(f"{path}: expected a dict, found {type(meta).__name__}")
            t = frame - first
            side = str(meta.get("side", side))
            joints = meta.get("handJoints3D")
            if _is_mano_template(meta):
                template[t] = True  # joints present, but of the template hand far away
            elif joints is not None and np.size(joints) == 63:
                kp[t] = np.asarray(joints, dtype=np.float64).reshape(21, 3)[list(HO3D_TO_DEXFLOW)]
            elif meta.get("handPose") is not None:
                mano_frames[t] = meta
            rot, trans = meta.get("objRot"), meta.get("objTrans")
            if rot is not None and trans is not None:
                pose[t] = rotvec_pose(rot, trans)
            if meta.get("objName") is not None:
                names.setdefault(str(meta["objName"]), path)
    if mano_frames:
        model = mano_for(options, side)
        ts = sorted(mano_frames)
        hand_pose = np.stack([np.asarray(mano_frames[t]["handPose"], dtype=np.float64) for t in ts])
        betas = np.asarray(mano_frames[ts[0]].get("handBeta", np.zeros(10)), dtype=np.float64)
        trans = np.stack([np.asarray(mano_frames[t].get("handTrans", np.zeros(3))) for t in ts])
        kp[ts] = model.joints(hand_pose[:, :3], hand_pose[:, 3:], betas, trans)
    if len(names) != 1:
        raise DatasetLayoutError(
            f"{seq_dir}: expected one 'objName' in the frames, found {sorted(names)}"
        )
    (name, where), *_ = names.items()
    inside(models, name, where, "objName", name=True)
    mesh = inside(models, f"{name}/textured_simple.obj", where, "objName")
    return RawSequence(
        f"{seq_dir.parent.name}_{seq_dir.name}",
        kp,
        pose,
        mesh,
        name,
        options.fps or 30.0,
        side,
        "ho3d",
        template,
    )


# --------------------------------------------------------------------------------------- GRAB


def _grab(src: Path, options: ConvertOptions) -> Iterator[SourceSequence]:
    files = visible(src.rglob("*.npz"))
    if not files:
        raise DatasetLayoutError(f"{src}: no *.npz GRAB sequences")
    for path in files:
        yield SourceSequence(
            f"{path.parent.name}_{path.stem}",
            path,
            lambda path=path: _read_grab(src, path, options),
        )


def _read_grab(src: Path, path: Path, options: ConvertOptions) -> list[RawSequence]:
    """One GRAB file: a sequence per hand side asked for."""
    inside(src, path.relative_to(src).as_posix(), path, "<file>")  # a link out of SRC
    sides = ("right", "left") if options.side == "both" else (options.side,)
    out = []
    with reading(path):
        data = load_npz(path, allow_objects=True)
    raw = {k: v.item() if v.dtype == object and v.shape == () else v for k, v in data.items()}
    fps = float(field(raw, "framerate", path))
    obj = field(raw, "object", path)
    params = field(obj, "params", f"{path}: object")
    transl = np.asarray(field(params, "transl", f"{path}: object.params"), dtype=np.float64)
    orient = np.asarray(field(params, "global_orient", f"{path}: object.params"), dtype=np.float64)
    pose = RigidTransform.from_components(transl, Rotation.from_rotvec(orient)).as_matrix()
    mesh = inside(src, str(field(obj, "object_mesh", f"{path}: object")), path, "object_mesh")
    for side in sides:
        hand = field(raw, "rhand" if side == "right" else "lhand", path)
        if "joints" in hand:
            kp = np.asarray(hand["joints"], dtype=np.float64)
        else:
            hp = field(hand, "params", f"{path}: {side} hand")
            model = mano_for(options, side)
            kp = model.joints(
                field(hp, "global_orient", path),
                field(hp, "hand_pose", path),
                hand.get("betas"),
                field(hp, "transl", path),
            )
        name = f"{path.parent.name}_{path.stem}" + ("" if len(sides) == 1 else f"_{side}")
        out.append(RawSequence(name, kp, pose, mesh, mesh.stem, fps, side, "grab"))
    return out


# ------------------------------------------------------------------------------------ generic


def _generic(src: Path, options: ConvertOptions) -> Iterator[SourceSequence]:
    files = visible([*src.glob("*.npz"), *src.glob("*.csv")])
    if not files:
        raise DatasetLayoutError(f"{src}: no <name>.npz or <name>.csv sequences (generic layout)")
    for path in files:
        yield SourceSequence(path.stem, path, lambda path=path: [_read_generic(src, path, options)])


def _numbers(path: Path, table, columns: list[str]) -> np.ndarray:
    """The CSV ``columns`` as floats (empty cells NaN); a cell that is not a number is named."""
    import pandas as pd

    values = table[columns].apply(pd.to_numeric, errors="coerce")
    bad = (values.isna() & table[columns].notna()).to_numpy()
    if bad.any():
        row, col = (int(i[0]) for i in np.nonzero(bad))
        raise DatasetLayoutError(
            f"{path}: column '{columns[col]}', row {row + 2}: {table[columns[col]].iloc[row]!r} "
            "is not a number (leave the cell empty where there is no hand)"
        )
    return values.to_numpy(dtype=np.float64)


def _read_generic(src: Path, path: Path, options: ConvertOptions) -> RawSequence:
    """One generic sequence (``<name>.npz``, or ``<name>.csv`` and ``<name>.json``)."""
    inside(src, path.relative_to(src).as_posix(), path, "<file>")  # a link out of SRC
    if path.suffix == ".npz":
        with reading(path):
            fields = load_npz(path, max_frames=MAX_FRAMES)
        where = path
        kp = np.asarray(field(fields, "keypoints", path), dtype=np.float64)
    else:
        sidecar = where = need(path.with_suffix(".json"), "sidecar .json (obj_mesh, fps)")
        with reading(sidecar):
            fields = json.loads(sidecar.read_text())
        import pandas as pd

        with reading(path):
            table = pd.read_csv(path)
        cols = [f"kp{i}_{c}" for i in range(21) for c in "xyz"]
        missing = [
            c
            for c in [*cols, "obj_rx", "obj_ry", "obj_rz", "obj_tx", "obj_ty", "obj_tz"]
            if c not in table
        ]
        if missing:
            raise DatasetLayoutError(
                f"{path}: missing columns {missing[:6]}{'...' if len(missing) > 6 else ''}"
            )
        kp = _numbers(path, table, cols).reshape(-1, 21, 3)
        fields["obj_rotvec"] = _numbers(path, table, ["obj_rx", "obj_ry", "obj_rz"])
        fields["obj_trans"] = _numbers(path, table, ["obj_tx", "obj_ty", "obj_tz"])
        if "timestamps" in table:
            fields["timestamps"] = _numbers(path, table, ["timestamps"])[:, 0]
    units = str(fields.get("units", "m"))
    if units not in UNITS:
        raise DatasetLayoutError(f"{path}: units '{units}'; expected one of {list(UNITS)}")
    scale = UNITS[units]
    order = str(fields.get("keypoint_order", "mano"))
    if order not in ("mano", "ho3d"):
        raise DatasetLayoutError(f"{path}: keypoint_order '{order}'; expected 'mano' or 'ho3d'")
    if order == "ho3d":
        kp = kp[:, list(HO3D_TO_DEXFLOW)]
    if "obj_pose" in fields:
        pose = np.asarray(fields["obj_pose"], dtype=np.float64).copy()
    else:
        rotvec = np.asarray(field(fields, "obj_rotvec", path), dtype=np.float64)
        trans = np.asarray(field(fields, "obj_trans", path), dtype=np.float64)
        good = np.isfinite(rotvec).all(axis=1) & np.isfinite(trans).all(axis=1)
        pose = np.full((len(rotvec), 4, 4), np.nan)
        rotation = Rotation.from_rotvec(rotvec[good])
        pose[good] = RigidTransform.from_components(trans[good], rotation).as_matrix()
    pose[:, :3, 3] *= scale
    if "valid" in fields:
        kp[~np.asarray(fields["valid"], dtype=bool)] = np.nan
    fps = float(fields.get("fps", options.fps or 0.0))
    if "timestamps" in fields:
        kp, pose, fps = _on_uniform_grid(path, fields["timestamps"], fps, kp, pose)
    if fps <= 0:
        raise DatasetLayoutError(f"{path}: no 'fps' in the file and no --fps given")
    mesh = inside(src, str(field(fields, "obj_mesh", path)), where, "obj_mesh")
    return RawSequence(
        path.stem,
        kp * scale,
        pose,
        mesh,
        mesh.stem,
        fps,
        str(fields.get("side", "right")),
        "generic",
    )


def _on_uniform_grid(
    path: Path, timestamps, fps: float, kp: np.ndarray, pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Frames placed at their timestamps on the ``1/fps`` grid, gaps filled with frames without
    a hand (NaN keypoints and object pose: masked and held by :func:`write_sequence`).

    ``fps <= 0`` takes the rate from the median step. Returns ``(keypoints, obj_pose, fps)``.
    """
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(ts) != len(kp):
        raise DatasetLayoutError(f"{path}: {len(ts)} timestamps for {len(kp)} frames")
    steps = np.diff(ts)
    bad = np.flatnonzero(~(steps > 0))
    if len(bad):
        raise DatasetLayoutError(
            f"{path}: timestamps must increase; frame {bad[0] + 1} is at {ts[bad[0] + 1]!r} s, "
            f"after {ts[bad[0]]!r} s"
        )
    if fps <= 0:
        fps = 1.0 / float(np.median(steps))
    position = (ts - ts[0]) * fps
    slot = np.round(position).astype(np.int64)
    off = np.flatnonzero(np.abs(position - slot) > 0.25)
    if len(off):
        frame = int(off[0])
        raise DatasetLayoutError(
            f"{path}: frame {frame} (at {ts[frame]:.4g} s) is {position[frame] - slot[frame]:+.2f} "
            f"frames off the 1/fps grid at {fps:g} fps: give the capture's fps, or resample it "
            "to a constant rate first"
        )
    if (np.diff(slot) == 0).any() or slot[-1] + 1 > 10 * len(ts):
        raise DatasetLayoutError(
            f"{path}: the timestamps do not fit {fps:g} fps ({len(ts)} frames over "
            f"{ts[-1] - ts[0]:.4g} s): are they seconds, and is fps the capture's rate?"
        )
    grid_kp = np.full((slot[-1] + 1, *kp.shape[1:]), np.nan)
    grid_pose = np.full((slot[-1] + 1, 4, 4), np.nan)
    grid_kp[slot], grid_pose[slot] = kp, pose
    return grid_kp, grid_pose, fps


ADAPTERS: dict[str, Callable[[Path, ConvertOptions], Iterator[SourceSequence]]] = {
    "dexycb": _dexycb,
    "ho3d": _ho3d,
    "grab": _grab,
    "generic": _generic,
}
