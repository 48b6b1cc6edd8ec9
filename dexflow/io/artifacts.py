"""Typed readers and writers of the stage artifacts (the ``sequences/<name>.npz`` of each stage).

Each artifact has one writer and one reader here; the reader checks what the next stage relies
on and raises :class:`~dexflow.errors.ArtifactError` naming the file, the field, what was
expected and what was found:

- :class:`Trajectory` (stages retarget and refine): ``q (T, dof)`` with its ``joint_names``;
  readers pass the hand's joint names, so a trajectory of another hand (or an older URDF) is
  refused instead of being read column by column, and columns are mapped by name;
- :class:`ContactResult` (stage contact): per-finger states and the contact map;
- :class:`ObjectAssets` (stage scale_align, per object): signed distance, surface samples,
  convex parts;
- :class:`SimulationResult` (stage simulate): one row per tested frame;
- :class:`ReplayResult` (stage replay): the object's error over the replayed frames;
- :class:`MetricFrames` (stage metrics): per-frame metrics of every trajectory.

Paths come from :mod:`dexflow.io.layout`.
"""

from __future__ import annotations

import zipfile
from collections.abc import Sequence as Names
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dexflow.errors import ArtifactError
from dexflow.io.atomic import save_npz
from dexflow.io.layout import ObjectPaths

if TYPE_CHECKING:
    from dexflow.objects.sdf import SignedDistanceGrid

__all__ = [
    "ENGINE_KEYS",
    "REPLAY_KEYS",
    "SIMULATION_KEYS",
    "ContactResult",
    "MetricFrames",
    "ObjectAssets",
    "ReplayResult",
    "SimulationResult",
    "Trajectory",
    "read_contact",
    "read_metric_frames",
    "read_replay",
    "read_simulation",
    "read_trajectory",
    "write_contact",
    "write_metric_frames",
    "write_replay",
    "write_simulation",
    "write_trajectory",
]


def _load(path: Path, required: Names[str]) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: no such file (has the stage that writes it run?)")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ArtifactError(
            f"{path}: not a readable .npz ({type(exc).__name__}: {exc}); rerun the stage that "
            "writes it"
        ) from exc
    missing = [k for k in required if k not in arrays]
    if missing:
        raise ArtifactError(f"{path}: missing {missing}; found {sorted(arrays)}")
    return arrays


def _names(array: np.ndarray) -> list[str]:
    return [str(n) for n in np.asarray(array).ravel()]


def _check_names(path: Path, what: str, found: list[str], expected: Names[str] | None) -> None:
    if expected is None or list(found) == list(expected):
        return
    expected = list(expected)
    first = next(
        (i for i, (a, b) in enumerate(zip(found, expected, strict=False)) if a != b),
        min(len(found), len(expected)),
    )
    raise ArtifactError(
        f"{path}: {what} do not match the hand: {len(found)} found, {len(expected)} expected; "
        f"first difference at {first}: found {found[first] if first < len(found) else None!r}, "
        f"expected {expected[first] if first < len(expected) else None!r}"
    )


def _check_frames(path: Path, what: str, count: int, frames: int | None) -> None:
    if frames is not None and count != frames:
        raise ArtifactError(
            f"{path}: {what} has {count} frames, expected {frames} (the sequence's)"
        )


# ----------------------------------------------------------------------------- trajectory


@dataclass
class Trajectory:
    """A robot-hand trajectory.

    Attributes:
        q: (T, dof) joint positions, the floating base's six first (``joint_names``).
        joint_names: The names of the columns of ``q``.
        arrays: The stage's other per-sequence arrays (e.g. retarget's ``observed``,
            ``keypoints_human``; refine's energies), saved and read back as they are.
    """

    q: np.ndarray
    joint_names: list[str]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]


def write_trajectory(path: str | Path, trajectory: Trajectory) -> None:
    """Write a trajectory atomically (``q``, ``joint_names`` and its other arrays)."""
    q = np.asarray(trajectory.q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != len(trajectory.joint_names):
        raise ArtifactError(
            f"{path}: q must be (T, {len(trajectory.joint_names)}) for its joint names, "
            f"found {q.shape}"
        )
    clash = {"q", "joint_names"} & set(trajectory.arrays)
    if clash:
        raise ArtifactError(f"{path}: arrays may not be named {sorted(clash)}")
    arrays = {"q": q, "joint_names": np.array(trajectory.joint_names), **trajectory.arrays}
    save_npz(path, arrays)


def read_trajectory(
    path: str | Path, joint_names: Names[str] | None = None, frames: int | None = None
) -> Trajectory:
    """Read a trajectory, checking ``joint_names`` against the hand's and the frame count.

    Columns are mapped by name: a ``q`` stored in another order of the same joints comes back
    in the order of ``joint_names``.

    Args:
        joint_names: The hand's joint names (``RobotHand.joint_names``); None skips the check.
        frames: The sequence's frame count; None skips the check.

    Raises:
        ArtifactError: missing file or key, joints of another hand, wrong shape or frame count,
            non-finite ``q``.
    """
    path = Path(path)
    arrays = _load(path, ("q", "joint_names"))
    q, names = arrays.pop("q"), _names(arrays.pop("joint_names"))
    if q.ndim != 2 or q.shape[1] != len(names):
        raise ArtifactError(
            f"{path}: q must be (T, {len(names)}) for its joint names, found {q.shape}"
        )
    if joint_names is not None and names != list(joint_names):
        if len(set(names)) == len(names) and set(names) == set(joint_names):
            q, names = q[:, [names.index(n) for n in joint_names]], list(joint_names)
        _check_names(path, "joint_names", names, joint_names)
    _check_frames(path, "q", len(q), frames)
    bad = ~np.isfinite(q).all(axis=1)
    if bad.any():
        raise ArtifactError(f"{path}: q is not finite at frame {int(np.argmax(bad))}")
    return Trajectory(q.astype(np.float64), names, arrays)


# -------------------------------------------------------------------------------- contact

_MAP_KEYS = ("map_frame", "map_finger", "map_hand_index", "map_hand_point", "map_object_point",
             "map_object_normal")  # fmt: skip


@dataclass
class ContactResult:
    """Stage contact's result for one sequence.

    Attributes:
        distance_m: (T, F) each finger's nearest surface distance to the object.
        raw: (T, F) dual-threshold states.
        final: (T, F) states after the frame-to-frame smoothing (what later stages use).
        fingers: The F finger names (the hand's order).
        fps: Frame rate.
        contact_map: ``map_*`` arrays: per contact pair its frame, finger, hand point index,
            hand point and the object point and outward normal it maps to (object frame).
    """

    distance_m: np.ndarray
    raw: np.ndarray
    final: np.ndarray
    fingers: list[str]
    fps: float
    contact_map: dict[str, np.ndarray]

    @property
    def first_contact(self) -> int:
        """The first frame with any finger in contact, -1 if none."""
        touching = self.final.any(axis=1)
        return int(np.argmax(touching)) if touching.any() else -1


def write_contact(path: str | Path, result: ContactResult) -> None:
    missing = [k for k in _MAP_KEYS if k not in result.contact_map]
    if missing:
        raise ArtifactError(f"{path}: contact map lacks {missing}")
    save_npz(
        path,
        {
            "distance_m": result.distance_m,
            "raw": result.raw,
            "final": result.final,
            "fingers": np.array(result.fingers),
            "fps": np.array(result.fps),
            **{k: result.contact_map[k] for k in _MAP_KEYS},
        },
    )


def read_contact(
    path: str | Path, fingers: Names[str] | None = None, frames: int | None = None
) -> ContactResult:
    """Read a contact result, checking its fingers against the hand's and its frame count."""
    path = Path(path)
    arrays = _load(path, ("distance_m", "raw", "final", "fingers", "fps", *_MAP_KEYS))
    names = _names(arrays["fingers"])
    _check_names(path, "fingers", names, fingers)
    final = arrays["final"].astype(bool)
    if final.ndim != 2 or final.shape[1] != len(names):
        raise ArtifactError(f"{path}: final must be (T, {len(names)}), found {final.shape}")
    _check_frames(path, "final", len(final), frames)
    return ContactResult(
        distance_m=arrays["distance_m"],
        raw=arrays["raw"].astype(bool),
        final=final,
        fingers=names,
        fps=float(arrays["fps"]),
        contact_map={k: arrays[k] for k in _MAP_KEYS},
    )


# -------------------------------------------------------------------------------- objects


@dataclass(frozen=True)
class ObjectAssets:
    """Readers of one object's precomputation (stage scale_align)."""

    paths: ObjectPaths

    def sdf(self) -> SignedDistanceGrid:
        from dexflow.objects.sdf import SignedDistanceGrid

        if not self.paths.sdf.is_file():
            raise ArtifactError(f"{self.paths.sdf}: no such file (run stage scale_align)")
        return SignedDistanceGrid.load(self.paths.sdf)

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """``points (N, 3)`` and outward ``normals (N, 3)`` on the surface."""
        arrays = _load(self.paths.surface, ("points", "normals"))
        return arrays["points"], arrays["normals"]

    def convex_parts(self) -> list[np.ndarray]:
        """Vertices (V, 3) of every convex part."""
        from dexflow.objects.convex import read_convex_obj

        if not self.paths.convex.is_file():
            raise ArtifactError(f"{self.paths.convex}: no such file (run stage scale_align)")
        return read_convex_obj(self.paths.convex)


# ----------------------------------------------------------------------------- simulation

# The per-tested-frame arrays of a simulation result shared by its engines (see SimulationResult)
SIMULATION_KEYS = ("frame", "penetration_m", "contact_imbalance")
# ... and those of each engine, stored as ``<engine>.<key>``.
ENGINE_KEYS = ("parts_penetration_m", "pushed_links", "imbalance", "closing_displacement_m",
               "closing_rotation_deg", "touching", "held", "displacement_m", "rotation_deg",
               "tested", "contact", "bench", "contact_single", "bench_single")  # fmt: skip


@dataclass
class SimulationResult:
    """Stage simulate's rows for one sequence, one per tested frame (N rows).

    Attributes:
        rows: ``frame (N,)``, ``penetration_m (N,)`` (mesh depth, the penetration rule's),
            ``contact_imbalance (N,)`` (how one-sided stage contact's contacts are at the frame,
            :func:`dexflow.sim.protocol.contact_imbalance`), and
            per engine ``<engine>.<key>``: ``parts_penetration_m (N,)`` (against the convex
            parts), ``pushed_links (N,)``, ``imbalance (N,)`` (how one-sided the pushes are,
            :func:`dexflow.sim.protocol.imbalance`), ``closing_displacement_m (N,)`` and
            ``closing_rotation_deg (N,)`` (the object's motion while the fingers closed, before
            any push; NaN where the engine's test holds it then), ``touching (N, F)``,
            ``held``/``displacement_m``/``rotation_deg``/``tested`` ``(N, 6)`` per push
            direction of the nominal trial, ``contact (N,)`` and ``bench (N,)`` (robust: the
            nominal and every perturbed trial) and ``contact_single``/``bench_single`` (the
            nominal trial alone).
        fingers: The F finger names.
        engines: The engines that tested the frames, the first one the stage's.
    """

    rows: dict[str, np.ndarray]
    fingers: list[str]
    engines: list[str]


def _simulation_keys(engines: Names[str]) -> list[str]:
    return [*SIMULATION_KEYS, *(f"{e}.{k}" for e in engines for k in ENGINE_KEYS)]


def write_simulation(path: str | Path, result: SimulationResult) -> None:
    keys = _simulation_keys(result.engines)
    missing = [k for k in keys if k not in result.rows]
    if missing or not result.engines:
        raise ArtifactError(f"{path}: simulation rows lack {missing or 'an engine'}")
    save_npz(
        path,
        {
            **{k: result.rows[k] for k in keys},
            "fingers": np.array(result.fingers),
            "engines": np.array(result.engines),
        },
    )


def read_simulation(path: str | Path) -> SimulationResult:
    path = Path(path)
    arrays = _load(path, (*SIMULATION_KEYS, "fingers", "engines"))
    engines = _names(arrays["engines"])
    keys = _simulation_keys(engines)
    missing = [k for k in keys if k not in arrays]
    if missing:
        raise ArtifactError(f"{path}: missing {missing}; found {sorted(arrays)}")
    return SimulationResult({k: arrays[k] for k in keys}, _names(arrays["fingers"]), engines)


# --------------------------------------------------------------------------------- replay

# The per-frame arrays of a replay, one row per replayed frame (see ReplayResult).
REPLAY_KEYS = ("frame", "position_error_m", "rotation_error_rad", "object_position",
               "object_quat", "base_error_m", "joint_error_rad")  # fmt: skip


@dataclass
class ReplayResult:
    """Stage replay's rows for one sequence, one per replayed frame (N rows, N may be 0).

    Attributes:
        rows: ``frame (N,)`` (index into the sequence), the simulated object's
            ``position_error_m (N,)`` and ``rotation_error_rad (N,)`` against its recorded pose,
            its ``object_position (N, 3)`` and ``object_quat (N, 4)`` (w, x, y, z) in the world,
            and how well the hand followed q: ``base_error_m (N,)`` (the base's position) and
            ``joint_error_rad (N,)`` (mean over the finger joints).
    """

    rows: dict[str, np.ndarray]


def write_replay(path: str | Path, result: ReplayResult) -> None:
    missing = [k for k in REPLAY_KEYS if k not in result.rows]
    if missing:
        raise ArtifactError(f"{path}: replay rows lack {missing}")
    save_npz(path, {k: np.asarray(result.rows[k]) for k in REPLAY_KEYS})


def read_replay(path: str | Path) -> ReplayResult:
    arrays = _load(Path(path), REPLAY_KEYS)
    return ReplayResult({k: arrays[k] for k in REPLAY_KEYS})


# -------------------------------------------------------------------------------- metrics


@dataclass
class MetricFrames:
    """Stage metrics' per-frame values for one sequence.

    Attributes:
        time: (T,) seconds.
        contact: (T, F) the final contact states.
        methods: Per trajectory label, per metric name, a (T,) array (metres for distances).
    """

    time: np.ndarray
    contact: np.ndarray
    methods: dict[str, dict[str, np.ndarray]]


def write_metric_frames(path: str | Path, frames: MetricFrames) -> None:
    arrays = {"time": frames.time, "contact": frames.contact}
    for method, values in frames.methods.items():
        arrays |= {f"{method}.{k}": v for k, v in values.items()}
    save_npz(path, arrays)


def read_metric_frames(path: str | Path) -> MetricFrames:
    arrays = _load(Path(path), ("time", "contact"))
    time, contact = arrays.pop("time"), arrays.pop("contact")
    methods: dict[str, dict[str, np.ndarray]] = {}
    for key, value in arrays.items():
        method, _, metric = key.partition(".")
        methods.setdefault(method, {})[metric] = value
    return MetricFrames(time, contact, methods)
