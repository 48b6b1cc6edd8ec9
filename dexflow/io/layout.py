"""Where a project's files are: the one map of ``data/``, ``reports/`` and ``conf/hand``.

Every stage script, ``dexflow bench``, ``dexflow viz`` and the CLI build their paths from a
:class:`Layout`; no other module spells them. ``dvc.yaml`` (declarative, so it cannot import
this) spells the same paths; ``tests/test_layout.py`` checks that the two agree.

A project::

    conf/hand/                   hand yamls; relative model paths in them start here
    data/hand/                   model/ (the hand model's files, copied), hand.json
    <data.root>/sequences/*.npz  the input (canonical format), with the meshes it references
    data/scale_align/            sequences/<name>.npz, objects/<key>/{mesh.obj, sdf.npz, ...}
    data/retarget/<method>/      sequences/<name>.npz (trajectories; methods dexflow, position)
    data/contact/                sequences/<name>.npz (contact states and map)
    data/refine/                 sequences/<name>.npz (refined trajectories)
    data/track/                  sequences/<name>.npz (tracked trajectories; stage track, when on)
    data/simulate/<label>/       sequences/<name>.npz (grasp tests; labels baseline, retarget,
                                 refine)
    data/replay/<label>/         sequences/<name>.npz (trajectories replayed with the object
                                 free; labels as simulate's)
    data/metrics/                sequences/<name>.npz (per-frame metrics), sequences.csv
    reports/metrics/<stage>.json deterministic stage metrics (DVC metrics)
    reports/timing/<stage>.json  wall-clock speeds, kept apart from the metrics
    reports/plots/, reports/figures/, reports/summary.md

Every stage directory also holds ``summary.json`` (per sequence: status, error, statistics).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dexflow.errors import ArtifactError, ConfigError

__all__ = [
    "CORE_TRAJECTORIES",
    "TRAJECTORIES",
    "Layout",
    "NoSequencesError",
    "ObjectPaths",
    "StageDir",
    "project_root",
    "stray_files",
    "visible_npz",
]

# The trajectories the pipeline compares, by label: the baseline, the method before and after
# refinement, and after tracking (stage track, when on: params.yaml's ``methods`` lists those a
# project has; the labels of simulate, replay, metrics and reports).
TRAJECTORIES = ("baseline", "retarget", "refine", "track")
CORE_TRAJECTORIES = TRAJECTORIES[:3]  # those every project has (track only with track=on)
_RETARGET_METHOD = {"baseline": "position", "retarget": "dexflow"}


def project_root() -> Path:
    """The directory holding ``conf/`` and ``params.yaml`` (the current one, or a parent)."""
    here = Path.cwd().resolve()
    for candidate in (here, *here.parents):
        if (candidate / "conf" / "config.yaml").is_file():
            return candidate
    raise ConfigError(f"no conf/config.yaml in {here} or any parent: run dexflow from the project")


@dataclass(frozen=True)
class ObjectPaths:
    """The files stage scale_align precomputes for one object (``objects/<key>/``)."""

    root: Path

    @property
    def mesh(self) -> Path:
        """The scaled mesh (OBJ)."""
        return self.root / "mesh.obj"

    @property
    def sdf(self) -> Path:
        """Its signed distance grid (:class:`dexflow.objects.sdf.SignedDistanceGrid`)."""
        return self.root / "sdf.npz"

    @property
    def surface(self) -> Path:
        """``points (N, 3)`` and outward ``normals (N, 3)`` sampled on the surface."""
        return self.root / "surface.npz"

    @property
    def convex(self) -> Path:
        """Convex decomposition for simulation, one ``o`` group per part."""
        return self.root / "convex.obj"

    @property
    def meta(self) -> Path:
        """Source mesh, scale, bounds, watertightness, part count (JSON)."""
        return self.root / "meta.json"


class NoSequencesError(ArtifactError, FileNotFoundError):
    """A stage directory (or the data root) holds no ``sequences/*.npz``."""


def visible_npz(folder: Path) -> list[Path]:
    """The sequence files of a sequences folder, sorted: ``*.npz`` at its top, hidden ones left
    out (``._name.npz`` resource forks, ``.name.*.tmp.npz`` from an interrupted write)."""
    return sorted(p for p in folder.glob("*.npz") if not p.name.startswith("."))


def stray_files(folder: Path) -> dict[Path, str]:
    """Files below a sequences folder that are no sequence of the pipeline, with the reason.

    The pipeline (and ``dexflow validate``) read ``<folder>/*.npz`` only: an ``.npz`` in a
    sub-folder, or any other visible file, would be silently left out, so every stage's summary
    lists them as dropped by ``data`` and ``dexflow validate`` reports them as invalid. Hidden
    files (``._name.npz`` resource forks, ``.name.tmp.npz`` left by an interrupted write) are
    no inputs of anyone's and are not listed.

    Returns:
        Per file (sorted) why it is not read.
    """
    if not folder.is_dir():
        return {}
    taken = set(visible_npz(folder))
    found = {}
    for path in sorted(folder.rglob("*")):
        parts = path.relative_to(folder).parts
        if not path.is_file() or path in taken or any(s.startswith(".") for s in parts):
            continue
        found[path] = (
            f"in a sub-folder of {folder.name}/: the pipeline reads {folder.name}/*.npz only"
            if len(parts) > 1
            else "not an .npz sequence file"
        )
    return found


@dataclass(frozen=True)
class StageDir:
    """One stage's output directory: ``sequences/<name>.npz`` and ``summary.json``."""

    root: Path

    @property
    def sequences_dir(self) -> Path:
        return self.root / "sequences"

    @property
    def summary(self) -> Path:
        return self.root / "summary.json"

    def sequence(self, name: str | Path) -> Path:
        """The file of sequence ``name``: a name (dots allowed, ``take.001``), or the path of a
        sequence file (``.../take.001.npz``)."""
        base = Path(name).name
        if base.endswith(".npz"):
            base = base[: -len(".npz")]
        return self.sequences_dir / f"{base}.npz"

    def sequence_files(self) -> list[Path]:
        """Every ``sequences/*.npz``, sorted by name (what a stage maps over). Hidden files are
        not sequences: macOS's ``._<name>.npz`` resource forks, the ``.<name>.*.tmp.npz`` an
        interrupted atomic write leaves.

        Raises:
            NoSequencesError: there is none.
        """
        files = visible_npz(self.sequences_dir)
        if not files:
            raise NoSequencesError(
                f"{self.sequences_dir}: no *.npz sequence files (has the stage that writes them "
                "run? is data.root the folder holding sequences/?)"
            )
        return files

    def names(self) -> list[str]:
        """The sequence names present (empty if none)."""
        return [p.stem for p in visible_npz(self.sequences_dir)]

    # Stage scale_align's directory also holds the objects.
    def object_key(self, obj_mesh: str) -> str:
        """The object key of a sequence's ``obj_mesh`` (``objects/<key>/mesh.obj``)."""
        parts = Path(obj_mesh).parts
        if (
            len(parts) != 3
            or parts[0] != "objects"
            or parts[2] != "mesh.obj"
            or parts[1] in ("..", ".")
        ):
            raise ValueError(f"{obj_mesh!r}: expected objects/<key>/mesh.obj (stage scale_align)")
        return parts[1]

    def object(self, key: str) -> ObjectPaths:
        """The precomputed files of object ``key``."""
        return ObjectPaths(self.root / "objects" / key)

    def object_of(self, obj_mesh: str) -> ObjectPaths:
        """The precomputed files of the object a scaled sequence's ``obj_mesh`` points at."""
        return self.object(self.object_key(obj_mesh))


@dataclass(frozen=True)
class Layout:
    """A project's paths, relative to ``root`` (the directory ``dvc repro`` runs in).

    Attributes:
        root: The project directory.
        data_root: The input sequences' directory (``data.root``), relative to ``root`` unless
            absolute.
    """

    root: Path = Path(".")
    data_root: Path = Path("data/demo")

    @classmethod
    def of(cls, data_root: str | Path, root: str | Path = ".") -> Layout:
        return cls(Path(root), Path(data_root))

    # ------------------------------------------------------------------ stage directories
    @property
    def data(self) -> StageDir:
        """The input (``data.root``): ``sequences/*.npz`` and the meshes they reference."""
        return StageDir(self.root / self.data_root)

    @property
    def hand_files(self) -> StageDir:
        """Stage hand's copy of the hand model and every file it reads (``model/``), with
        ``hand.json`` (:mod:`dexflow.hands.files`); the stages load the hand from it."""
        return StageDir(self.root / "data" / "hand")

    @property
    def scale_align(self) -> StageDir:
        return StageDir(self.root / "data" / "scale_align")

    def retarget(self, method: str) -> StageDir:
        """Stage retarget's output for ``method`` (``dexflow`` or ``position``)."""
        return StageDir(self.root / "data" / "retarget" / method)

    @property
    def contact(self) -> StageDir:
        return StageDir(self.root / "data" / "contact")

    @property
    def refine(self) -> StageDir:
        return StageDir(self.root / "data" / "refine")

    def trajectory(self, label: str) -> StageDir:
        """The trajectories labelled ``label`` (one of :data:`TRAJECTORIES`)."""
        if label == "refine":
            return self.refine
        if label == "track":
            return self.track
        if label not in _RETARGET_METHOD:
            raise ValueError(f"trajectory {label!r}: expected one of {list(TRAJECTORIES)}")
        return self.retarget(_RETARGET_METHOD[label])

    @property
    def track(self) -> StageDir:
        return StageDir(self.root / "data" / "track")

    def simulate(self, label: str) -> StageDir:
        """Stage simulate's output for the trajectories labelled ``label``."""
        return StageDir(self.root / "data" / "simulate" / label)

    def replay(self, label: str) -> StageDir:
        """Stage replay's output for the trajectories labelled ``label``."""
        return StageDir(self.root / "data" / "replay" / label)

    @property
    def metrics(self) -> StageDir:
        return StageDir(self.root / "data" / "metrics")

    @property
    def metrics_table(self) -> Path:
        """Per sequence and method, every metric (CSV; stage metrics)."""
        return self.metrics.root / "sequences.csv"

    @property
    def hand_dir(self) -> Path:
        """Where hand yamls live; relative model paths in them are resolved against it."""
        return self.root / "conf" / "hand"

    # ----------------------------------------------------------------------------- reports
    @property
    def reports(self) -> Path:
        return self.root / "reports"

    @property
    def stage_metrics_dir(self) -> Path:
        return self.reports / "metrics"

    def stage_metrics(self, name: str) -> Path:
        """A stage's deterministic metrics (``reports/metrics/<name>.json``, DVC metrics)."""
        return self.stage_metrics_dir / f"{name}.json"

    def timing(self, name: str) -> Path:
        """A stage's wall-clock speeds (``reports/timing/<name>.json``), kept out of metrics."""
        return self.reports / "timing" / f"{name}.json"

    @property
    def plots(self) -> Path:
        return self.reports / "plots"

    @property
    def figures(self) -> Path:
        return self.reports / "figures"

    @property
    def summary_report(self) -> Path:
        return self.reports / "summary.md"

    def summary_table(self, name: str) -> Path:
        """A full table of the summary (``reports/summary_<name>.csv``), linked from it."""
        return self.reports / f"summary_{name}.csv"

    def recording(self, name: str) -> Path:
        """A rerun recording (``reports/rerun/<name>.rrd``, written by ``dexflow view``)."""
        return self.reports / "rerun" / f"{name}.rrd"
