"""``dexflow export``: a project's final trajectories as an HDF5 file or a LeRobot dataset."""

from __future__ import annotations

import argparse
import logging

__all__ = ["add_commands"]

log = logging.getLogger(__name__)


def _cmd_export(args: argparse.Namespace) -> int:
    from dexflow.tools.export import export_project

    export = export_project(args.project, args.out, args.format, args.method)
    for name, why in export.skipped.items():
        print(f"skip {name}: {why}")
    frames = sum(e.num_frames for e in export.episodes)
    print(
        f"wrote {args.out} ({args.format}): {len(export.episodes)} episodes, {frames} frames of "
        f"{export.method} ({export.hand}); {len(export.skipped)} skipped"
    )
    return 0


def add_commands(sub) -> None:
    """Add this module's subcommands to the ``dexflow`` parser's subparsers."""
    p = sub.add_parser(
        "export",
        help="write a project's trajectories as HDF5 or a LeRobot dataset",
        description="Write the trajectories of one method of a project's pipeline outputs, with "
        "per-frame base and object poses, contact and penetration and per-sequence success "
        "flags, as one HDF5 file or a LeRobot (v2.1 layout) dataset directory. Sequences some "
        "stage dropped are listed as skipped; the exit status is 2 if nothing was exported. "
        "docs/export.md describes the fields.",
    )
    p.add_argument("project", nargs="?", default=".", help="the project directory (default .)")
    p.add_argument("out", help="the .h5 file (hdf5) or the dataset directory (lerobot)")
    p.add_argument("--format", required=True, choices=["hdf5", "lerobot"])
    p.add_argument(
        "--method",
        default="refine",
        choices=["refine", "retarget", "baseline", "track"],
        help="data/refine (default), data/retarget/dexflow or data/retarget/position",
    )
    p.set_defaults(func=_cmd_export)
