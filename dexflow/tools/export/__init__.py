"""``dexflow export``: a project's final trajectories as an HDF5 file or a LeRobot dataset.

Per sequence (episode) it carries ``q (T, dof)`` with the joint names, the hand's base pose and
the object's pose per frame, per-frame contact and penetration, the simulate and replay success
flags, the fps, object, sequence and method (:class:`Episode`; docs/export.md describes each
field). :func:`export_project` writes it, :func:`read_export` reads either format back.
"""

from __future__ import annotations

from pathlib import Path

from dexflow.tools.export.episodes import Episode, Export, ExportError, collect_export
from dexflow.tools.export.hdf5 import read_hdf5, write_hdf5
from dexflow.tools.export.lerobot import read_lerobot, write_lerobot

__all__ = [
    "FORMATS",
    "Episode",
    "Export",
    "ExportError",
    "collect_export",
    "export_project",
    "read_export",
]

FORMATS = ("hdf5", "lerobot")


def export_project(
    project_root: str | Path, out: str | Path, fmt: str, method: str = "refine"
) -> Export:
    """Export ``method``'s trajectories of a project to ``out`` in format ``fmt``.

    Args:
        project_root: The project (holding ``params.yaml`` and ``data/``).
        out: The HDF5 file (``hdf5``) or the dataset directory (``lerobot``) to write.
        fmt: ``hdf5`` or ``lerobot``.
        method: ``refine``, ``retarget`` or ``baseline``.

    Returns:
        What was exported, with the sequences skipped and why.

    Raises:
        ExportError: unknown format or method, nothing to export, or ``out`` unusable.
        MissingInputError: an upstream output is missing (names the file and the DVC stage).
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}; expected one of {', '.join(FORMATS)}")
    export = collect_export(project_root, method)
    (write_hdf5 if fmt == "hdf5" else write_lerobot)(export, out)
    return export


def read_export(path: str | Path) -> Export:
    """Read an export back: an HDF5 file, or a LeRobot dataset directory.

    Raises:
        ExportError: ``path`` is neither.
    """
    path = Path(path)
    if path.is_dir():
        return read_lerobot(path)
    if path.is_file():
        return read_hdf5(path)
    raise ExportError(f"{path}: no such file or directory")
