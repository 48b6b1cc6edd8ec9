"""``dexflow params|validate|demo|convert|view``: the pipeline's inputs, prepared and checked."""

from __future__ import annotations

import argparse
import difflib
import logging
import shlex
import sys
import tempfile
from pathlib import Path

from dexflow.data.formats import ConvertOptions
from dexflow.params import DemoConfig
from dexflow.tools.cli.helptext import HelpFormatter
from dexflow.tools.cli.schema import add_schema_options, options_from, schema_help

__all__ = ["add_commands"]


def _cmd_params(args: argparse.Namespace) -> int:
    """Compose conf/ into params.yaml (``--check``: compare with it), refusing a hand the
    stages would refuse.

    The composition is written to a temporary file and its hand is built as the stages build
    it (:class:`~dexflow.hands.robot.RobotHand`: the model read, every link and joint name the
    hand yaml gives checked against it) before it replaces params.yaml: a hand naming a missing
    link stops here (HandConfigError, exit 2), not in retarget after scale_align ran on every
    sequence. params.yaml starts with a comment naming the overrides
    (:func:`~dexflow.config.params_header`).

    ``--check`` without overrides composes with those params.yaml records, or, if it records
    none (``dvc exp run`` wrote it), with the group choices its sections show
    (:func:`~dexflow.config.infer_choices`), so that its advice keeps a ``data=`` choice.
    """
    from dexflow.config import (
        compose_params,
        infer_choices,
        load_params,
        params_header,
        project_root,
        recorded_overrides,
        without_header,
    )
    from dexflow.hands.robot import RobotHand
    from dexflow.io.atomic import atomic_path
    from dexflow.io.layout import Layout

    root = project_root()
    target = root / "params.yaml"
    overrides, source = list(args.overrides), "given"
    if args.check and not overrides and target.is_file():
        recorded = recorded_overrides(target)
        if recorded is not None:
            overrides, source = recorded, "recorded in its first line"
        else:
            overrides = infer_choices(target, config_dir=root / "conf")
            source = (
                "inferred from its sections; it records no overrides, as `dvc exp run` writes it"
            )
    with tempfile.TemporaryDirectory() as tmp:
        composed = compose_params(overrides, Path(tmp) / "params.yaml")
        RobotHand(load_params(composed).hand, Layout(root=root).hand_dir)
        fresh = composed.read_text()
    if not args.check:
        with atomic_path(target) as out:
            out.write_text(params_header(overrides) + fresh)
        print(f"wrote {target}")
        return 0
    current = without_header(target.read_text()) if target.is_file() else ""
    command = shlex.join(["dexflow", "params", *overrides])
    how = f" with {shlex.join(overrides)} ({source})" if overrides else ""
    if fresh == current:
        print(f"{target} is up to date with conf/ composed{how or ' with its defaults'}")
        return 0
    sys.stdout.writelines(
        difflib.unified_diff(current.splitlines(True), fresh.splitlines(True), str(target), "conf/")
    )
    print(
        f"\n{target} differs from the composition of conf/{how}: run `{command}`", file=sys.stderr
    )
    return 1


def _cmd_validate(args: argparse.Namespace) -> int:
    from dexflow.errors import DexflowError
    from dexflow.io.layout import stray_files, visible_npz
    from dexflow.io.sequence import load_sequence

    paths, strays = [], {}
    for p in args.paths:
        p = Path(p)
        if p.is_dir():  # the files the pipeline reads: <data root>/sequences/*.npz
            folder = p / "sequences" if (p / "sequences").is_dir() else p
            paths += visible_npz(folder)
            strays |= stray_files(folder)
        else:
            paths.append(p)
    for path, why in strays.items():  # the pipeline would leave them out: not valid inputs
        print(f"FAIL {path}: {why}")
    bad = len(strays)
    paths_seen = len(paths) + len(strays)
    meshes: dict[Path, object] = {}
    for path in paths:
        try:
            seq = load_sequence(path, data_root=args.data_root)
            note = _check_mesh(path, seq, Path(args.data_root), meshes) if args.data_root else ""
            print(f"ok   {path}: {seq.num_frames} frames, {seq.obj_name}, {seq.side}{note}")
        except DexflowError as exc:
            bad += 1
            print(f"FAIL {exc}")
    print(f"{paths_seen - bad} valid, {bad} invalid")
    return 1 if bad or not paths else 0


def _check_mesh(path: Path, seq, data_root: Path, meshes: dict) -> str:
    """Load the sequence's mesh as scale_align will (MeshError if empty, unreadable or in
    millimetres); a warning if the fingertips never come near it."""
    from dexflow.data.adapters import fingertip_surface_distance
    from dexflow.errors import MeshError
    from dexflow.io.sequence import NEAR_OBJECT_M, mesh_file
    from dexflow.objects.mesh import load_mesh

    file = mesh_file(seq.obj_mesh, data_root)
    if file not in meshes:
        try:
            meshes[file] = load_mesh(file)
        except MeshError as exc:
            meshes[file] = exc
    if isinstance(meshes[file], MeshError):
        raise MeshError(f"{path}: field 'obj_mesh': {meshes[file]}")
    gap = fingertip_surface_distance(seq, meshes[file], frames=100)
    if len(gap) and gap.min() > NEAR_OBJECT_M:
        return (
            f"; WARNING: the fingertips never come within {NEAR_OBJECT_M * 1000:.0f} mm of "
            f"the object (nearest {gap.min() * 1000:.0f} mm): are obj_pose and the keypoints "
            "in one world frame and unit?"
        )
    return ""


def _cmd_demo(args: argparse.Namespace) -> int:
    """Generate the demo with the ``demo`` and ``run`` sections of conf/ (the project's, else
    dexflow's own) and the overrides."""
    from dexflow.config import compose_params, load_params, project_root
    from dexflow.data.demo import generate_demo
    from dexflow.errors import ConfigError
    from dexflow.params import CONF_DIR

    try:
        conf = project_root() / "conf"
    except ConfigError:  # outside a project: dexflow's own conf/
        conf = CONF_DIR
    with tempfile.TemporaryDirectory() as tmp:
        params = load_params(compose_params(args.overrides, Path(tmp) / "params.yaml", conf))
    manifest = generate_demo(params.demo, args.out, params.run)
    print(f"{manifest['num_sequences']} sequences, {manifest['num_frames']} frames in {args.out}")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from dexflow.data.adapters import ConvertOptions, convert

    options = options_from(args, ConvertOptions)
    report = convert(args.adapter, args.src, args.dst, options)
    for name, entry in report["sequences"].items():
        if entry["status"] == "ok":
            median = entry["fingertip_to_surface_mm_median"]
            print(
                f"ok   {name}: {entry['frames']} frames, {entry['template_frames']} template "
                f"frames, {entry['missing_frames']} without a hand, "
                f"{entry['tracking_lost_frames']} tracking lost, fingertip-to-surface median "
                + ("n/a" if median is None else f"{median:.1f} mm")
                + (" (mirrored left hand)" if entry["mirrored"] else "")
            )
        elif entry["status"] == "skipped":
            print(f"skip {name}: {entry['reason']}")
        else:
            print(f"FAIL {name}: {entry['error']}")
    for folder, table in report["table_frames"].items():
        fit = (
            f"up {[round(x, 3) for x in table['up']]} in the camera's frame, "
            f"{table['captures']} captures, start heights spread "
            f"{table['start_height_mad_m'] * 100:.1f} cm (MAD), "
            f"{table['dip_share'] * 100:.0f} % dip below the table"
        )
        if table["applied"]:
            print(f"table {folder}: written in the table's frame, z up ({fit})")
        else:
            print(f"table {folder}: kept the camera's frame: {table['reason']} ({fit})")
    for folder, check in report["object_rotation"]["sessions"].items():
        better = check["found"] != check["applied"]
        print(
            f"rotations {folder}: read as '{check['applied']}'"
            + (
                f"; fits clearly better: '{check['found']}' (--object-rotation auto)"
                if better
                else ""
            )
        )
    print(
        f"{report['num_ok']}/{report['num_sequences']} sequences written to {args.dst}"
        f" ({report['num_skipped']} skipped, {report['num_failed']} failed)"
    )
    return 0 if report["num_ok"] and not report["num_failed"] else 1


def _cmd_view(args: argparse.Namespace) -> int:
    from dexflow.tools.viz import open_viewer, record_sequence

    out = record_sequence(args.sequence, args.out, trajectory=args.trajectory)
    print(f"wrote {out}")
    if args.open:
        try:
            open_viewer(out)
        except FileNotFoundError:
            logging.error("no `rerun` executable on PATH; open %s with `rerun %s`", out, out)
            return 1
    return 0


def add_commands(sub) -> None:
    """Add this module's subcommands to the ``dexflow`` parser's subparsers."""
    p = sub.add_parser(
        "params",
        help="compose conf/ into params.yaml",
        description="Compose conf/ with Hydra overrides into params.yaml, the file the DVC "
        "stages read, after checking every value and building the hand as the stages will. "
        "The first line of params.yaml records the overrides. --check writes nothing: it "
        "shows how params.yaml differs from conf/ composed with the same overrides (those "
        "given, else those params.yaml records or its sections show) and exits 1 if it does.",
        epilog="examples:\n  dexflow params                       # the defaults of conf/config.yaml\n"
        "  dexflow params data=generic hand=allegro refine.w_pen=2\n"
        "  dexflow params --check               # after editing conf/",
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "overrides", nargs="*", metavar="OVERRIDE",
        help="Hydra overrides: a group choice (hand=allegro, data=generic, experiment=no_temporal) "
        "or a value (refine.w_pen=2)",
    )  # fmt: skip
    p.add_argument(
        "--check", action="store_true", help="only show the drift from conf/ (exit 1 if any)"
    )
    p.set_defaults(func=_cmd_params)

    p = sub.add_parser(
        "validate",
        help="check sequence files (.npz or directories)",
        description="Check sequence files against dexflow's canonical format (the fields, "
        "shapes, units and frames the pipeline reads) and print one line per file: ok, or "
        "FAIL and why. With --data-root, also load each object mesh as scale_align will. "
        "Exit status 1 if any file is invalid.",
        epilog="examples:\n  dexflow validate data/generic --data-root data/generic\n"
        "  dexflow validate data/demo/sequences/025_mug__00_power.npz",
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "paths", nargs="+", metavar="PATH",
        help="sequence .npz files, or data roots / folders holding them (sequences/*.npz)",
    )  # fmt: skip
    p.add_argument("--data-root", default=None, help="check that meshes exist below this root")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser(
        "demo",
        help="generate demo sequences into a directory",
        description="Generate the demo dataset outside the pipeline, with the `demo` and `run` "
        "sections of conf/ and Hydra overrides of them: every option is a field of the schema.",
        epilog=schema_help(DemoConfig, "demo") + "\n\nrun.n_jobs=N: worker processes",
        formatter_class=HelpFormatter,
    )
    p.add_argument("out", help="the data root to write (sequences/, meshes/)")
    p.add_argument(
        "overrides", nargs="*", metavar="KEY=VALUE",
        help="e.g. demo.objects=[025_mug] demo.sequences_per_object=3 run.n_jobs=2",
    )  # fmt: skip
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser(
        "convert",
        help="convert a dataset to dexflow's format",
        description="Convert source folders of a dataset (or its root) into one data root. "
        "Exit status 0 when at least one sequence was written and none failed; sequences "
        "without an object model are skipped (listed), unless --strict.",
        epilog="examples:\n  dexflow convert dexycb ~/DexYCB/20200709-subject-01 data/dexycb\n"
        "  dexflow convert generic my_captures data/generic && dexflow params data=generic",
        formatter_class=HelpFormatter,
    )
    p.add_argument("adapter", choices=["dexycb", "ho3d", "grab", "generic"])
    p.add_argument(
        "src", nargs="+", help="source folder(s): e.g. subject folders or the dataset root"
    )
    p.add_argument("dst", help="output data root (sequences/, meshes/, convert.json)")
    add_schema_options(p, ConvertOptions, {"side": ["right", "left", "both"]})
    p.set_defaults(func=_cmd_convert)

    p = sub.add_parser(
        "view",
        help="write a rerun recording (.rrd) of a sequence",
        description="Write a rerun recording of one sequence of the pipeline's outputs: the "
        "human keypoints, the object and the robot hand of one of its trajectories frame by "
        "frame, fingers coloured by contact; --open starts the rerun viewer on it.",
        epilog="example:\n  dexflow view 025_mug__00_power --trajectory refine --open",
        formatter_class=HelpFormatter,
    )
    p.add_argument("sequence", help="sequence name (e.g. 025_mug__00_power) or a sequence .npz")
    p.add_argument(
        "--trajectory",
        default="refine",
        choices=["refine", "retarget", "baseline", "track"],
        help="data/refine, data/retarget/dexflow or data/retarget/position",
    )
    p.add_argument("--out", default=None, help="the .rrd file (default reports/rerun/<name>.rrd)")
    p.add_argument("--open", action="store_true", help="start the rerun viewer on the file")
    p.set_defaults(func=_cmd_view)
