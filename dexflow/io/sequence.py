"""The canonical sequence format: one ``.npz`` per sequence, validated on load and on save.

Fields:

- ``keypoints (T, 21, 3) float64``: human hand keypoints in metres, MANO joint order, world frame.
  Frames where the tracker lost the hand may hold NaN, but only where ``valid`` is False.
- ``obj_pose (T, 4, 4) float64``: rigid transform from object-mesh coordinates to world.
- ``obj_mesh``: path of the object mesh, relative to the data root and inside it (the data root
  is what DVC tracks: a mesh read from elsewhere could change without any stage rerunning).
- ``obj_name``, ``side`` ('right' | 'left'), ``fps`` (> 0), ``source`` (adapter name).
- optional ``valid (T,) bool``, ``timestamps (T,) float64`` (seconds, strictly increasing, one
  step of ``1/fps`` each: every stage takes time from ``fps``, so a capture with gaps must hold
  its missing frames as invalid ones), ``gt_contact (T, 5) bool`` (ground-truth contact per
  finger, thumb to little), ``mirrored``, and any further arrays (MANO parameters, stage
  outputs), kept as ``extras``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dexflow.errors import DexflowError, SequenceFormatError
from dexflow.human.keypoints import MIDDLE_MCP, NUM_KEYPOINTS, WRIST
from dexflow.io.atomic import save_npz
from dexflow.io.untrusted import MAX_FRAMES, load_npz

__all__ = [
    "HAND_SIZE_RANGE_M",
    "NEAR_OBJECT_M",
    "TIMESTAMP_JITTER",
    "Sequence",
    "load_sequence",
    "mesh_file",
    "save_sequence",
    "validate_sequence",
]

# Wrist to middle-finger MCP, metres. Adults measure about 0.08-0.11 m; the range is wide so
# that children and hands already scaled to a robot's size (x1.7 for Allegro) pass.
HAND_SIZE_RANGE_M = (0.03, 0.25)
# A sequence whose nearest fingertip never comes closer to the object's surface than this is
# suspect (warned about, not refused): the object pose and the keypoints are probably not in
# one world frame or unit.
NEAR_OBJECT_M = 0.03
_RIGID_TOL = 1e-4
# Timestamps: each step may differ from 1/fps by this share of it (camera jitter); a larger
# step is a gap (a dropped frame is a step of 2/fps). Their median must match fps within 2 %.
TIMESTAMP_JITTER = 0.5
_RATE_TOL = 0.02
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
_NPY_MAGIC = b"\x93NUMPY"
_STRING_FIELDS = ("obj_mesh", "obj_name", "side", "source")
_KNOWN_FIELDS = (
    "keypoints",
    "obj_pose",
    "fps",
    "valid",
    "timestamps",
    "gt_contact",
    "mirrored",
    *_STRING_FIELDS,
)


@dataclass
class Sequence:
    """One recorded human hand-object interaction.

    Attributes:
        keypoints: (T, 21, 3) human keypoints in metres, MANO order.
        obj_pose: (T, 4, 4) object-to-world transforms.
        obj_mesh: Mesh path relative to the data root.
        obj_name: Object identifier (e.g. ``025_mug``).
        fps: Frames per second.
        side: ``'right'`` or ``'left'``.
        source: Name of the adapter or generator that produced the sequence.
        valid: (T,) True where the hand was tracked; None means every frame.
        timestamps: (T,) seconds, if the capture was not sampled at a constant rate.
        gt_contact: (T, 5) ground-truth contact per finger (thumb..little), if known.
        mirrored: True if a left hand was mirrored to a right one (x -> -x in the world,
            :mod:`dexflow.io.mirror`).
        extras: Any further named arrays, saved and loaded unchanged.
    """

    keypoints: np.ndarray
    obj_pose: np.ndarray
    obj_mesh: str
    obj_name: str
    fps: float
    side: str = "right"
    source: str = "unknown"
    valid: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    gt_contact: np.ndarray | None = None
    mirrored: bool = False
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def valid_mask(self) -> np.ndarray:
        """(T,) bool, all True when ``valid`` is not given."""
        if self.valid is None:
            return np.ones(self.num_frames, dtype=bool)
        return self.valid

    def to_arrays(self) -> dict[str, Any]:
        arrays: dict[str, Any] = {
            "keypoints": np.asarray(self.keypoints, dtype=np.float64),
            "obj_pose": np.asarray(self.obj_pose, dtype=np.float64),
            "obj_mesh": np.array(self.obj_mesh),
            "obj_name": np.array(self.obj_name),
            "side": np.array(self.side),
            "source": np.array(self.source),
            "fps": np.array(float(self.fps)),
            "mirrored": np.array(bool(self.mirrored)),
        }
        if self.valid is not None:
            arrays["valid"] = np.asarray(self.valid, dtype=bool)
        if self.timestamps is not None:
            arrays["timestamps"] = np.asarray(self.timestamps, dtype=np.float64)
        if self.gt_contact is not None:
            arrays["gt_contact"] = np.asarray(self.gt_contact, dtype=bool)
        for key, value in self.extras.items():
            if key in arrays:
                raise SequenceFormatError(None, key, "an extra field name not reserved", key)
            arrays[key] = np.asarray(value)
        return arrays


def _fail(path: Path | None, name: str, expected: str, found: str, frame: int | None = None):
    raise SequenceFormatError(path, name, expected, found, frame)


def _check_shape(path: Path | None, name: str, array: np.ndarray, shape: tuple) -> None:
    ok = array.ndim == len(shape) and all(
        s is None or s == a for s, a in zip(shape, array.shape, strict=True)
    )
    if not ok:
        want = "(" + ", ".join("T" if s is None else str(s) for s in shape) + ")"
        _fail(path, name, f"shape {want}", f"shape {tuple(array.shape)}")


def _first_bad_frame(bad: np.ndarray) -> int:
    return int(np.flatnonzero(bad.reshape(bad.shape[0], -1).any(axis=1))[0])


def _check_timestamps(path: Path | None, ts: np.ndarray, fps: float, num_frames: int) -> None:
    _check_shape(path, "timestamps", ts, (num_frames,))
    steps = np.diff(ts)
    step_bad = ~(steps > 0)
    if step_bad.any():
        frame = int(np.flatnonzero(step_bad)[0]) + 1
        _fail(
            path,
            "timestamps",
            "strictly increasing seconds",
            f"{ts[frame]!r} after {ts[frame - 1]!r}",
            frame,
        )
    median = float(np.median(steps))
    if abs(median * fps - 1.0) > _RATE_TOL:
        _fail(
            path,
            "timestamps",
            f"steps of 1/fps = {1 / fps:.4g} s (fps {fps:g})",
            f"a median step of {median:.4g} s, i.e. {1 / median:.4g} fps: set fps to the "
            "capture's rate",
        )
    gaps = np.flatnonzero(np.abs(steps * fps - 1.0) > TIMESTAMP_JITTER)
    if len(gaps):
        frame = int(gaps[0]) + 1
        _fail(
            path,
            "timestamps",
            f"a uniform step of 1/fps = {1 / fps:.4g} s (within {TIMESTAMP_JITTER:.0%}), as every "
            "stage takes time from fps: hold each missing frame as an invalid one (NaN "
            "keypoints, valid = False), or let `dexflow convert generic` do it from the "
            "timestamps",
            f"a step of {steps[gaps[0]]:.4g} s ({steps[gaps[0]] * fps:.3g} frames) "
            f"({len(gaps)} such step(s))",
            frame,
        )


def mesh_file(
    obj_mesh: str, data_root: str | Path | None = None, path: str | Path | None = None
) -> Path:
    """The file an ``obj_mesh`` names: relative to the data root and inside it.

    Args:
        obj_mesh: The sequence's ``obj_mesh``.
        data_root: The data root; None checks only the form of the path.
        path: The sequence file (named in errors).

    Returns:
        ``data_root / obj_mesh`` (``obj_mesh`` itself without a data root).

    Raises:
        SequenceFormatError: the path is empty, absolute or climbs out with ``..``. (A link
            inside the data root is followed: linking a mesh folder in is the user's choice.)
    """
    path = None if path is None else Path(path)
    expected = "a mesh path relative to the data root, inside it (only the data root is tracked)"
    if not obj_mesh:
        _fail(path, "obj_mesh", expected, "an empty string")
    rel = Path(obj_mesh)
    if rel.is_absolute() or rel.anchor:
        _fail(path, "obj_mesh", expected, f"the absolute path '{obj_mesh}': copy the mesh into "
              "the data root and name it relative to it")  # fmt: skip
    if ".." in rel.parts:
        _fail(path, "obj_mesh", expected, f"'{obj_mesh}', which climbs out of the data root: "
              "copy the mesh into it")  # fmt: skip
    return rel if data_root is None else Path(data_root) / rel


def validate_sequence(
    seq: Sequence, path: str | Path | None = None, data_root: str | Path | None = None
) -> Sequence:
    """Check every field of ``seq``; raise :class:`SequenceFormatError` at the first problem.

    Args:
        seq: The sequence to check.
        path: File the sequence came from or goes to (named in errors).
        data_root: If given, ``obj_mesh`` must exist below it.

    Returns:
        ``seq`` itself, so that calls can be chained.
    """
    path = None if path is None else Path(path)
    kp = np.asarray(seq.keypoints)
    if not np.issubdtype(kp.dtype, np.floating):
        _fail(path, "keypoints", "a floating-point array", f"dtype {kp.dtype}")
    _check_shape(path, "keypoints", kp, (None, NUM_KEYPOINTS, 3))
    num_frames = kp.shape[0]
    if num_frames < 2:
        _fail(path, "keypoints", "at least 2 frames", f"{num_frames} frame(s)")

    pose = np.asarray(seq.obj_pose)
    _check_shape(path, "obj_pose", pose, (num_frames, 4, 4))

    valid = seq.valid_mask
    if seq.valid is not None:
        valid = np.asarray(seq.valid)
        if valid.dtype != bool:
            _fail(path, "valid", "a bool array", f"dtype {valid.dtype}")
        _check_shape(path, "valid", valid, (num_frames,))
        if not valid.any():
            _fail(path, "valid", "at least one tracked frame", "every frame marked invalid")

    if np.isinf(kp).any():
        _fail(path, "keypoints", "finite values", "inf", _first_bad_frame(np.isinf(kp)))
    nan_in_valid = np.isnan(kp).reshape(num_frames, -1).any(axis=1) & valid
    if nan_in_valid.any():
        _fail(
            path,
            "keypoints",
            "finite values in tracked frames (mark dropouts with valid[t] = False)",
            "NaN",
            int(np.flatnonzero(nan_in_valid)[0]),
        )

    fps = float(np.asarray(seq.fps))
    if not np.isfinite(fps) or fps <= 0:
        _fail(path, "fps", "a finite number > 0", repr(fps))
    if seq.timestamps is not None:
        _check_timestamps(path, np.asarray(seq.timestamps, dtype=np.float64), fps, num_frames)

    if seq.side not in ("right", "left"):
        _fail(path, "side", "'right' or 'left'", repr(seq.side))

    hand_size = np.linalg.norm(kp[valid, MIDDLE_MCP] - kp[valid, WRIST], axis=-1)
    size = float(np.median(hand_size))
    lo, hi = HAND_SIZE_RANGE_M
    if not lo <= size <= hi:
        hint = ""
        if lo * 1000 <= size <= hi * 1000:
            hint = " (this looks like millimetres: divide by 1000)"
        elif lo * 100 <= size <= hi * 100:
            hint = " (this looks like centimetres: divide by 100)"
        _fail(
            path,
            "keypoints",
            f"metres: median wrist-to-middle-MCP distance within [{lo}, {hi}] m",
            f"{size:.4g}{hint}",
        )

    if not np.isfinite(pose).all():
        _fail(path, "obj_pose", "finite values", "NaN or inf", _first_bad_frame(~np.isfinite(pose)))
    bottom_bad = np.abs(pose[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1) > _RIGID_TOL
    if bottom_bad.any():
        frame = int(np.flatnonzero(bottom_bad)[0])
        _fail(
            path,
            "obj_pose",
            "a rigid transform with last row [0, 0, 0, 1]",
            f"last row {pose[frame, 3].tolist()}",
            frame,
        )
    rot = pose[:, :3, :3]
    ortho_err = np.abs(rot.transpose(0, 2, 1) @ rot - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    rot_bad = (ortho_err > _RIGID_TOL) | (np.abs(det - 1.0) > _RIGID_TOL)
    if rot_bad.any():
        frame = int(np.flatnonzero(rot_bad)[0])
        _fail(
            path,
            "obj_pose",
            "a rotation block (R^T R = I, det R = +1, no scale)",
            f"max |R^T R - I| = {ortho_err[frame]:.3g}, det R = {det[frame]:.6g}",
            frame,
        )

    if seq.gt_contact is not None:
        gt = np.asarray(seq.gt_contact)
        _check_shape(path, "gt_contact", gt, (num_frames, 5))
        if gt.dtype != bool:
            _fail(path, "gt_contact", "a bool array", f"dtype {gt.dtype}")

    mesh_path = mesh_file(seq.obj_mesh, data_root, path)
    if data_root is not None and not mesh_path.is_file():
        _fail(
            path,
            "obj_mesh",
            f"an existing mesh file below {data_root}",
            f"'{seq.obj_mesh}' (no file at {mesh_path})",
        )
    return seq


def save_sequence(path: str | Path, seq: Sequence, data_root: str | Path | None = None) -> None:
    """Validate ``seq`` and write it to ``path`` atomically."""
    validate_sequence(seq, path, data_root)
    save_npz(path, seq.to_arrays())


def load_sequence(path: str | Path, data_root: str | Path | None = None) -> Sequence:
    """Read and validate one sequence file.

    Args:
        path: The ``.npz`` file.
        data_root: If given, the object mesh must exist below it.

    Every member's header is checked before any data is inflated (at most
    :data:`~dexflow.io.untrusted.MAX_FRAMES` frames, sizes that match the archive: see
    :mod:`dexflow.io.untrusted`); object arrays are refused unread.

    Raises:
        SequenceFormatError: the file is unreadable, misses a required field, declares more
            frames or bytes than allowed, or fails a check.
    """
    path = Path(path)
    if not path.is_file():
        raise SequenceFormatError(path, "<file>", "an existing .npz file", "no such file")
    with open(path, "rb") as handle:  # an OSError here is the machine's, not the file's
        head = handle.read(len(_NPY_MAGIC))
    if not head.startswith(_ZIP_MAGIC):
        found = (
            "an empty file" if not head
            else "a single .npy array (np.save); save the fields with np.savez"
            if head.startswith(_NPY_MAGIC)
            else f"a file that is not a zip archive (it starts with {head[:4]!r})"
        )  # fmt: skip
        raise SequenceFormatError(path, "<file>", "a readable .npz archive (np.savez)", found)
    try:
        arrays = load_npz(path, max_frames=MAX_FRAMES)
    except (OSError, DexflowError):
        raise
    except Exception as exc:  # zipfile, zlib, header errors: the archive is damaged
        raise SequenceFormatError(
            path, "<file>", "a readable .npz archive", f"a damaged one ({exc!r})"
        ) from exc
    for key in ("keypoints", "obj_pose", "obj_mesh", "obj_name", "fps"):
        if key not in arrays:
            raise SequenceFormatError(path, key, "a required field", f"fields {sorted(arrays)}")

    def text(key: str, default: str) -> str:
        return str(arrays[key]) if key in arrays else default

    try:
        fps = float(arrays["fps"])
    except (TypeError, ValueError):
        found = np.asarray(arrays["fps"])
        raise SequenceFormatError(
            path, "fps", "one number > 0", f"{found.dtype} of shape {found.shape}"
        ) from None
    seq = Sequence(
        keypoints=arrays["keypoints"],
        obj_pose=arrays["obj_pose"],
        obj_mesh=text("obj_mesh", ""),
        obj_name=text("obj_name", ""),
        fps=fps,
        side=text("side", "right"),
        source=text("source", "unknown"),
        valid=arrays.get("valid"),
        timestamps=arrays.get("timestamps"),
        gt_contact=arrays.get("gt_contact"),
        mirrored=bool(arrays.get("mirrored", False)),
        extras={k: v for k, v in arrays.items() if k not in _KNOWN_FIELDS},
    )
    return validate_sequence(seq, path, data_root)
