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

Each source sequence is read on its own: a file that cannot be read (a corrupt pickle, a frame
file with an unexpected name, a text cell in a CSV) fails that sequence only, with the source
file named in its error, and the others are converted; ``convert.json`` is always written.

Source files are untrusted (:mod:`dexflow.io.untrusted`): pickles (HO-3D frames, GRAB members)
may build plain data only, archive headers are checked before anything is inflated, and every
path or name read from data (an object name, a mesh path, a DexYCB serial) must stay inside its
folder, links followed: the models folder, SRC, or DST for the meshes written.

Layouts (only the files dexflow reads are listed):

- **DexYCB**: ``<subject>/<sequence>/meta.yml`` (``serials``, ``ycb_ids``, ``ycb_grasp_ind``,
  ``mano_sides``, ``extrinsics``), ``<sequence>/<serial>/labels_%06d.npz`` (``joint_3d
  (1, 21, 3)`` in that camera's frame, ``pose_y (n_obj, 3, 4)``, optional ``pose_m (1, 51)``),
  ``calibration/extrinsics_<name>/extrinsics.yml`` (``extrinsics: {serial: 12 numbers}``, camera
  to world, row-major 3x4), models ``models/<ycb name>/textured_simple.obj``. 30 fps.
- **HO-3D** (also DexYCB exported in its layout): ``<sequence>/meta/<frame>.pkl`` below SRC,
  or ``<subject>/<sequence>/meta/<frame>.pkl`` below a dataset root, dicts with
  ``handJoints3D (21, 3)`` (HO-3D order), ``objRot (3,)`` axis-angle, ``objTrans (3,)``,
  ``objName`` (e.g. ``025_mug``); optional ``side``; optional MANO ``handPose (48,)``,
  ``handTrans (3,)``, ``handBeta (10,)`` used with ``--mano`` where the joints are missing.
  Models ``<models>/<objName>/textured_simple.obj``.
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

import contextlib
import json
import logging
from collections.abc import Callable, Iterator
from collections.abc import Sequence as Sequence_
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from dexflow.errors import DexflowError
from dexflow.geometry import transform_points, world_to_object
from dexflow.human.cleaning import detect_bad_frames, nearest_index
from dexflow.human.keypoints import FINGERTIPS
from dexflow.human.mano import MANO_TO_DEXFLOW, ManoModel, load_mano
from dexflow.io.atomic import save_json
from dexflow.io.layout import StageDir
from dexflow.io.mirror import mirror_mesh, mirror_sequence
from dexflow.io.sequence import Sequence, save_sequence
from dexflow.io.untrusted import MAX_FRAMES, load_npz, load_pickle
from dexflow.objects.mesh import load_mesh, write_obj
from dexflow.objects.sdf import signed_distance

__all__ = [
    "ADAPTERS",
    "ConvertOptions",
    "DatasetLayoutError",
    "MissingOptionError",
    "RawSequence",
    "SourceSequence",
    "convert",
]

log = logging.getLogger(__name__)

# YCB-Video's 21 objects, the ids DexYCB's meta.yml uses (1-based).
YCB_CLASSES = (
    "002_master_chef_can", "003_cracker_box", "004_sugar_box", "005_tomato_soup_can",
    "006_mustard_bottle", "007_tuna_fish_can", "008_pudding_box", "009_gelatin_box",
    "010_potted_meat_can", "011_banana", "019_pitcher_base", "021_bleach_cleanser", "024_bowl",
    "025_mug", "035_power_drill", "036_wood_block", "037_scissors", "040_large_marker",
    "051_large_clamp", "052_extra_large_clamp", "061_foam_brick",
)  # fmt: skip
HO3D_TO_DEXFLOW = MANO_TO_DEXFLOW  # HO-3D stores MANO's joint order with tips appended
_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


class DatasetLayoutError(DexflowError, ValueError):
    """A source dataset misses a file or a field the adapter needs (the message names it)."""


class MissingOptionError(DatasetLayoutError):
    """The data needs an option of ``dexflow convert`` that was not given (``--mano``): the
    conversion stops, as no sequence that needs it can be converted."""


@dataclass
class ConvertOptions:
    """Options of ``dexflow convert`` (and ``conf/data/<adapter>.yaml``).

    Attributes:
        models: Directory of object models (DexYCB, HO-3D); default ``SRC/models``.
        mano: MANO model file, or a directory with ``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl``.
        camera: DexYCB camera serial (default: the first in ``meta.yml``).
        fps: Frame rate where the data does not say (HO-3D, generic CSV without it).
        side: GRAB hand(s) to convert: right, left or both.
        jump_threshold_m: Wrist step between tracked frames that marks tracking loss
            (:func:`dexflow.human.cleaning.detect_bad_frames`).
        strict: A missing object model fails its sequence instead of skipping it.
    """

    models: str | None = None
    mano: str | None = None
    camera: str | None = None
    fps: float | None = None
    side: str = "right"
    jump_threshold_m: float = 0.08
    strict: bool = False


@dataclass
class RawSequence:
    """What an adapter reads, before cleaning (world frame of the source, metres).

    ``keypoints (T, 21, 3)`` in dexflow's order with NaN where there is no hand;
    ``obj_pose (T, 4, 4)`` with NaN where the object is not annotated; ``template (T,)`` True
    where the source marks the hand as not annotated (keypoints NaN there too), None if none.
    """

    name: str
    keypoints: np.ndarray
    obj_pose: np.ndarray
    mesh_path: Path
    obj_name: str
    fps: float
    side: str
    source: str
    template: np.ndarray | None = None


@dataclass
class SourceSequence:
    """One source sequence (or one file holding several, GRAB's hands), read on its own.

    Attributes:
        name: Its name in the report if it cannot be read.
        path: The file or folder it is read from (named in errors).
        read: Reads it; raises :class:`DatasetLayoutError` naming the file that is wrong.
    """

    name: str
    path: Path
    read: Callable[[], list[RawSequence]]


def _need(path: Path, what: str) -> Path:
    if not path.exists():
        raise DatasetLayoutError(f"{path}: missing {what}")
    return path


def _inside(root: Path, relative: str, where: Path | str, field: str, name: bool = False) -> Path:
    """``root / relative``, where ``relative`` comes from data: it must stay inside ``root``.

    Links are followed (``Path.resolve``): a link inside ``root`` that leads out of it is refused
    like ``..`` or an absolute path, so that no file outside ``root`` is read or written. Every
    path or name an adapter reads from data goes through here.

    Args:
        root: The folder the path must stay in (the models folder, SRC, or DST).
        relative: The path as the data gives it, relative to ``root``.
        where: The file the path was read from (named in errors).
        field: The field that holds it (named in errors).
        name: ``relative`` must be one plain name (an object's): no separator, ``.`` or ``..``.

    Returns:
        ``root / relative``, as given (not resolved).

    Raises:
        DatasetLayoutError: one line naming ``where``, ``field`` and ``root``.
    """
    rel = Path(relative)
    refused = not relative or "\0" in relative or bool(rel.anchor) or ".." in rel.parts
    if name and (relative in (".", "..") or "/" in relative or "\\" in relative):
        raise DatasetLayoutError(
            f"{where}: field '{field}': {relative!r} does not name one entry of {root} (a name "
            "read from data may hold no path separator, '.' or '..')"
        )
    if not refused:
        try:
            refused = not (root / rel).resolve().is_relative_to(root.resolve())
        except (OSError, RuntimeError):  # a loop of links
            refused = True
    if refused:
        raise DatasetLayoutError(
            f"{where}: field '{field}': {relative!r} leads out of {root} (a path read from data "
            "must be relative to that folder and stay inside it, links followed)"
        )
    return root / rel


@contextlib.contextmanager
def _reading(path: Path) -> Iterator[None]:
    """Name ``path`` in any error reading it raises (a corrupt pickle, an unreadable archive)."""
    try:
        yield
    except DexflowError:
        raise
    except Exception as exc:
        raise DatasetLayoutError(f"{path}: cannot read it ({type(exc).__name__}: {exc})") from exc


def _frame_number(path: Path, pattern: str) -> int:
    """The frame number of a per-frame file named like ``pattern`` (``<n>`` for the number)."""
    prefix, _, suffix = pattern.partition("<n>")
    text = path.name.removeprefix(prefix).removesuffix(suffix)
    if not path.name.startswith(prefix) or not path.name.endswith(suffix) or not text.isdigit():
        raise DatasetLayoutError(
            f"{path}: unexpected file name; frame files are named {pattern} (<n>: the frame "
            "number); move other files out of the folder"
        )
    return int(text)


def _frame_span(frames: list[int], folder: Path, first: int) -> int:
    """How many frames the numbered files from ``first`` to the last one span (missing numbers
    become frames without a hand); at most :data:`~dexflow.io.untrusted.MAX_FRAMES`, so that a
    file numbered 1100000 beside twelve small ones cannot make a 1.1M-frame sequence."""
    span = max(frames) - first + 1
    if span > MAX_FRAMES:
        raise DatasetLayoutError(
            f"{folder}: frame files numbered {first} to {max(frames)} span {span} frames; "
            f"expected at most {MAX_FRAMES} (a stray file with a large number?)"
        )
    return span


def _visible(paths) -> list[Path]:
    """Without hidden files (macOS's ``._*`` resource forks, editors' swap files)."""
    return sorted(p for p in paths if not p.name.startswith("."))


def _field(data, key: str, where: Path | str):
    try:
        return data[key]
    except (KeyError, IndexError, TypeError):
        raise DatasetLayoutError(f"{where}: missing field '{key}'") from None


def _pose(rot, trans) -> np.ndarray:
    """(4, 4) pose from a rotation vector (3,) or a rotation matrix (3, 3) and a translation.

    A matrix is taken as it is: ``RigidTransform`` would re-orthonormalise it, moving the
    annotation by up to its float32 error.
    """
    out = np.eye(4)
    out[:3, :3] = (
        np.asarray(rot, dtype=np.float64).reshape(3, 3)
        if np.size(rot) == 9
        else (Rotation.from_rotvec(np.asarray(rot, dtype=np.float64).reshape(3)).as_matrix())
    )
    out[:3, 3] = np.asarray(trans, dtype=np.float64).reshape(3)
    return out


def _mano_for(options: ConvertOptions, side: str) -> ManoModel:
    if not options.mano:
        raise MissingOptionError(
            "joints are missing and only MANO parameters exist: pass "
            "--mano <your MANO_RIGHT.pkl / MANO_LEFT.pkl or their folder>"
        )
    path = Path(options.mano)
    if path.is_dir():
        path = path / f"MANO_{side.upper()}.pkl"
    return load_mano(path)


# ------------------------------------------------------------------------------------- DexYCB


def _read_yaml(path: Path):
    import yaml

    with open(_need(path, "file")) as handle, _reading(path):
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


def _read_dexycb(src: Path, meta_path: Path, models: Path, options: ConvertOptions) -> RawSequence:
    """One DexYCB sequence."""
    meta = _read_yaml(meta_path)
    seq_dir = meta_path.parent
    serials = [str(s) for s in _field(meta, "serials", meta_path)]
    serial = options.camera or serials[0]
    cam_dir = _inside(seq_dir, serial, meta_path, "serials", name=True)
    ycb_ids = _field(meta, "ycb_ids", meta_path)
    grasp = int(_field(meta, "ycb_grasp_ind", meta_path))
    side = str(_field(meta, "mano_sides", meta_path)[0])
    calib_dir = f"extrinsics_{_field(meta, 'extrinsics', meta_path)}"
    _inside(src / "calibration", calib_dir, meta_path, "extrinsics", name=True)
    calib = _inside(src, f"calibration/{calib_dir}/extrinsics.yml", meta_path, "extrinsics")
    extr = _field(_read_yaml(calib), "extrinsics", calib)
    cam_to_world = np.eye(4)
    cam_to_world[:3] = np.asarray(_field(extr, serial, calib), dtype=np.float64).reshape(3, 4)
    labels = _visible(_need(cam_dir, f"camera folder of serial {serial}").glob("labels_*.npz"))
    if not labels:
        raise DatasetLayoutError(f"{seq_dir / serial}: no labels_*.npz files")
    frames = [_frame_number(p, "labels_<n>.npz") for p in labels]
    n_frames = _frame_span(frames, cam_dir, 0)
    kp = np.full((n_frames, 21, 3), np.nan)
    pose = np.full((n_frames, 4, 4), np.nan)
    template = np.zeros(n_frames, dtype=bool)
    for frame, path in zip(frames, labels, strict=True):
        with _reading(path):
            data = load_npz(path)
            joints = np.asarray(_field(data, "joint_3d", path), dtype=np.float64).reshape(21, 3)
            objects = np.asarray(_field(data, "pose_y", path), dtype=np.float64)
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
    mesh = _inside(models, f"{name}/textured_simple.obj", meta_path, "ycb_ids")
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
        )


def _read_ho3d(seq_dir: Path, models: Path, options: ConvertOptions) -> RawSequence:
    """One HO-3D sequence."""
    files = _visible((seq_dir / "meta").glob("*.pkl"))
    if not files:
        raise DatasetLayoutError(f"{seq_dir / 'meta'}: no <frame>.pkl files")
    frames = [_frame_number(p, "<n>.pkl") for p in files]
    first = min(frames)
    n_frames = _frame_span(frames, seq_dir / "meta", first)
    kp = np.full((n_frames, 21, 3), np.nan)
    pose = np.full((n_frames, 4, 4), np.nan)
    template = np.zeros(n_frames, dtype=bool)
    names: dict[str, Path] = {}  # each object name, with the first file naming it
    side, mano_frames = "right", {}
    for frame, path in zip(frames, files, strict=True):
        with _reading(path):  # a frame file that is not what HO-3D writes is named
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
                pose[t] = _pose(rot, trans)
            if meta.get("objName") is not None:
                names.setdefault(str(meta["objName"]), path)
    if mano_frames:
        model = _mano_for(options, side)
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
    _inside(models, name, where, "objName", name=True)
    mesh = _inside(models, f"{name}/textured_simple.obj", where, "objName")
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
    files = _visible(src.rglob("*.npz"))
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
    _inside(src, path.relative_to(src).as_posix(), path, "<file>")  # a link out of SRC
    sides = ("right", "left") if options.side == "both" else (options.side,)
    out = []
    with _reading(path):
        data = load_npz(path, allow_objects=True)
    raw = {k: v.item() if v.dtype == object and v.shape == () else v for k, v in data.items()}
    fps = float(_field(raw, "framerate", path))
    obj = _field(raw, "object", path)
    params = _field(obj, "params", f"{path}: object")
    transl = np.asarray(_field(params, "transl", f"{path}: object.params"), dtype=np.float64)
    orient = np.asarray(_field(params, "global_orient", f"{path}: object.params"), dtype=np.float64)
    pose = RigidTransform.from_components(transl, Rotation.from_rotvec(orient)).as_matrix()
    mesh = _inside(src, str(_field(obj, "object_mesh", f"{path}: object")), path, "object_mesh")
    for side in sides:
        hand = _field(raw, "rhand" if side == "right" else "lhand", path)
        if "joints" in hand:
            kp = np.asarray(hand["joints"], dtype=np.float64)
        else:
            hp = _field(hand, "params", f"{path}: {side} hand")
            model = _mano_for(options, side)
            kp = model.joints(
                _field(hp, "global_orient", path),
                _field(hp, "hand_pose", path),
                hand.get("betas"),
                _field(hp, "transl", path),
            )
        name = f"{path.parent.name}_{path.stem}" + ("" if len(sides) == 1 else f"_{side}")
        out.append(RawSequence(name, kp, pose, mesh, mesh.stem, fps, side, "grab"))
    return out


# ------------------------------------------------------------------------------------ generic


def _generic(src: Path, options: ConvertOptions) -> Iterator[SourceSequence]:
    files = _visible([*src.glob("*.npz"), *src.glob("*.csv")])
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
    _inside(src, path.relative_to(src).as_posix(), path, "<file>")  # a link out of SRC
    if path.suffix == ".npz":
        with _reading(path):
            fields = load_npz(path, max_frames=MAX_FRAMES)
        where = path
        kp = np.asarray(_field(fields, "keypoints", path), dtype=np.float64)
    else:
        sidecar = where = _need(path.with_suffix(".json"), "sidecar .json (obj_mesh, fps)")
        with _reading(sidecar):
            fields = json.loads(sidecar.read_text())
        import pandas as pd

        with _reading(path):
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
    if units not in _UNITS:
        raise DatasetLayoutError(f"{path}: units '{units}'; expected one of {list(_UNITS)}")
    scale = _UNITS[units]
    order = str(fields.get("keypoint_order", "mano"))
    if order not in ("mano", "ho3d"):
        raise DatasetLayoutError(f"{path}: keypoint_order '{order}'; expected 'mano' or 'ho3d'")
    if order == "ho3d":
        kp = kp[:, list(HO3D_TO_DEXFLOW)]
    if "obj_pose" in fields:
        pose = np.asarray(fields["obj_pose"], dtype=np.float64).copy()
    else:
        rotvec = np.asarray(_field(fields, "obj_rotvec", path), dtype=np.float64)
        trans = np.asarray(_field(fields, "obj_trans", path), dtype=np.float64)
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
    mesh = _inside(src, str(_field(fields, "obj_mesh", path)), where, "obj_mesh")
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


def write_sequence(raw: RawSequence, dst: Path, options: ConvertOptions) -> dict:
    """Clean, mirror (left hands), validate and save one sequence; return its report."""
    kp = np.array(raw.keypoints, dtype=np.float64)
    template = np.zeros(len(kp), dtype=bool) if raw.template is None else np.asarray(raw.template)
    kp[template] = np.nan
    missing = ~np.isfinite(kp).all(axis=(1, 2)) & ~template
    kp[missing] = np.nan
    observed, lost = detect_bad_frames(kp, None, options.jump_threshold_m, fps=raw.fps)
    kp[lost] = np.nan
    valid = observed.copy()
    if not valid.any():
        raise DatasetLayoutError(f"{raw.name}: no frame has a usable hand")
    _inside(dst / "meshes", raw.obj_name, raw.name, "obj_name", name=True)
    mesh = load_mesh(_need(raw.mesh_path, f"object model of '{raw.obj_name}'"))
    mesh_rel = f"meshes/{raw.obj_name}.obj"
    mesh_out = _inside(dst, mesh_rel, raw.name, "obj_name")
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
        mirrored_out = _inside(dst, mirrored_rel, raw.name, "obj_name")
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
        skipped, failed) with its counts or its ``reason``/``error``, and the totals.

    Raises:
        DatasetLayoutError: Unknown adapter, a missing source folder, a source that does not
            have the adapter's layout at all, or data that needs a missing option (``--mano``).
    """
    if adapter not in ADAPTERS:
        raise DatasetLayoutError(f"unknown adapter '{adapter}'; known: {sorted(ADAPTERS)}")
    options = options or ConvertOptions()
    sources = [Path(src)] if isinstance(src, (str, Path)) else [Path(s) for s in src]
    if not sources:
        raise DatasetLayoutError("no source folder given")
    dst = Path(dst)
    for folder in sources:
        _need(folder, "source dataset folder")
    StageDir(dst).sequences_dir.mkdir(parents=True, exist_ok=True)
    sequences: dict[str, dict] = {}
    for folder in sources:
        for source in ADAPTERS[adapter](folder, options):
            try:
                raws = source.read()
            except MissingOptionError:
                raise
            except Exception as exc:  # one unreadable source sequence never stops the others
                sequences[source.name] = {"status": "failed", "error": _reason(exc, source)}
                log.error("%s: %s", source.name, sequences[source.name]["error"])
                continue
            _convert_each(raws, source, folder, dst, options, sequences)
    statuses = [entry["status"] for entry in sequences.values()]
    report = {
        "adapter": adapter,
        "source": [str(folder) for folder in sources],
        "num_sequences": len(sequences),
        "num_ok": statuses.count("ok"),
        "num_skipped": statuses.count("skipped"),
        "num_failed": statuses.count("failed"),
        "sequences": sequences,
    }
    save_json(dst / "convert.json", report)
    return report


def _reason(exc: Exception, source: SourceSequence) -> str:
    """An error's message, naming the source it came from unless it already does."""
    text = str(exc) if isinstance(exc, DexflowError) else f"{type(exc).__name__}: {exc}"
    return text if str(source.path) in text else f"{text} (source: {source.path})"


def _convert_each(
    raws: list[RawSequence],
    source: SourceSequence,
    folder: Path,
    dst: Path,
    options: ConvertOptions,
    sequences: dict[str, dict],
) -> None:
    """Write each sequence read from ``source``, recording its entry in ``sequences``."""
    for raw in raws:
        if raw.name in sequences:
            sequences[f"{raw.name} ({folder})"] = {
                "status": "failed",
                "error": f"{raw.name}: the same name comes from an earlier source; "
                f"convert {folder} into another root",
            }
            log.error("%s: duplicate sequence name from %s", raw.name, folder)
            continue
        if not raw.mesh_path.is_file():
            reason = f"no object model of '{raw.obj_name}': {raw.mesh_path} is missing"
            status = "failed" if options.strict else "skipped"
            key = "error" if options.strict else "reason"
            sequences[raw.name] = {"status": status, key: reason}
            (log.error if options.strict else log.warning)("%s: %s", raw.name, reason)
            continue
        try:
            sequences[raw.name] = {"status": "ok", **write_sequence(raw, dst, options)}
        except MissingOptionError:
            raise
        except Exception as exc:  # reported with its source; the others go on
            sequences[raw.name] = {"status": "failed", "error": _reason(exc, source)}
            log.error("%s: %s", raw.name, sequences[raw.name]["error"])
