"""What every dataset reader shares: the convert options, a read sequence before cleaning, the
errors of a dataset's layout, and the checks on untrusted paths, frame files and fields."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.errors import DexflowError
from dexflow.human.mano import MANO_TO_DEXFLOW, ManoModel, load_mano
from dexflow.io.untrusted import MAX_FRAMES

__all__ = [
    "HO3D_TO_DEXFLOW",
    "UNITS",
    "YCB_CLASSES",
    "ConvertOptions",
    "DatasetLayoutError",
    "MissingOptionError",
    "RawSequence",
    "SourceSequence",
    "field",
    "frame_number",
    "frame_span",
    "inside",
    "mano_for",
    "need",
    "reading",
    "rotvec_pose",
    "visible",
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
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


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
        camera_frame: HO-3D: keep the camera's frame instead of writing each folder's captures
            in the frame of their table (z up), fitted from where the objects rest
            (:mod:`dexflow.data.table`).
        object_rotation: How the stored object rotations are read
            (:mod:`dexflow.data.rotation_convention`): ``check`` (read as stored, and each
            camera-frame session is checked against its hands and its table: a warning names
            the convention the data fits clearly better), ``auto`` (read by that convention),
            ``as-stored`` (no check), or a convention such as ``"-z+y+x R^T +z-y+x"`` (every
            sequence, every adapter).
    """

    models: str | None = None
    mano: str | None = None
    camera: str | None = None
    fps: float | None = None
    side: str = "right"
    jump_threshold_m: float = 0.08
    strict: bool = False
    camera_frame: bool = False
    object_rotation: str = "check"


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
        session: The capture session it belongs to (one camera, one table) where the data is
            in a camera's frame: the folder whose sequences are written in their table's frame
            together (HO-3D); None where the data has a world frame of its own.
    """

    name: str
    path: Path
    read: Callable[[], list[RawSequence]]
    session: Path | None = None


def need(path: Path, what: str) -> Path:
    if not path.exists():
        raise DatasetLayoutError(f"{path}: missing {what}")
    return path


def inside(root: Path, relative: str, where: Path | str, field: str, name: bool = False) -> Path:
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
def reading(path: Path) -> Iterator[None]:
    """Name ``path`` in any error reading it raises (a corrupt pickle, an unreadable archive)."""
    try:
        yield
    except DexflowError:
        raise
    except Exception as exc:
        raise DatasetLayoutError(f"{path}: cannot read it ({type(exc).__name__}: {exc})") from exc


def frame_number(path: Path, pattern: str) -> int:
    """The frame number of a per-frame file named like ``pattern`` (``<n>`` for the number)."""
    prefix, _, suffix = pattern.partition("<n>")
    text = path.name.removeprefix(prefix).removesuffix(suffix)
    if not path.name.startswith(prefix) or not path.name.endswith(suffix) or not text.isdigit():
        raise DatasetLayoutError(
            f"{path}: unexpected file name; frame files are named {pattern} (<n>: the frame "
            "number); move other files out of the folder"
        )
    return int(text)


def frame_span(frames: list[int], folder: Path, first: int) -> int:
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


def visible(paths) -> list[Path]:
    """Without hidden files (macOS's ``._*`` resource forks, editors' swap files)."""
    return sorted(p for p in paths if not p.name.startswith("."))


def field(data, key: str, where: Path | str):
    try:
        return data[key]
    except (KeyError, IndexError, TypeError):
        raise DatasetLayoutError(f"{where}: missing field '{key}'") from None


def rotvec_pose(rot, trans) -> np.ndarray:
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


def mano_for(options: ConvertOptions, side: str) -> ManoModel:
    if not options.mano:
        raise MissingOptionError(
            "joints are missing and only MANO parameters exist: pass "
            "--mano <your MANO_RIGHT.pkl / MANO_LEFT.pkl or their folder>"
        )
    path = Path(options.mano)
    if path.is_dir():
        path = path / f"MANO_{side.upper()}.pkl"
    return load_mano(path)
