"""dexflow: human hand-object captures to robot-hand trajectories (the DexFlow method).

The pipeline itself runs with `dvc repro` (stages in dvc.yaml, parameters composed from conf/
into params.yaml); this command prepares its inputs, checks hands and data, benchmarks and
writes reports. `dexflow SUBCOMMAND --help` describes each.

Subcommands:
  params [OVERRIDE ...] [--check]   compose conf/ into params.yaml (as `dvc exp run` does)
  validate PATH [--data-root DIR]   check sequence files against the canonical format
  demo OUT [--objects ...]          generate (part of) the demo dataset outside the pipeline
  convert ADAPTER SRC [SRC ...] DST [--strict]
                                    dexycb | ho3d | grab | generic -> canonical sequences
  hand init MODEL [--side S] [-o Y] propose a hand yaml from a URDF or MJCF model
  hand check NAME|YAML [--png P]    validate a hand, print its tree, build and step its physics scenes
  hand export NAME|YAML OUT.urdf    write an MJCF hand as a URDF (for pybullet)
  bench fk|retarget|refine|simulate|pipeline|real|long
                                    throughput benchmarks (frames/s against baselines)
  view SEQUENCE [--trajectory T] [--open]
                                    write a rerun recording (.rrd) of a sequence
  report summary                    reports/summary.md from the metrics (the `report` stage)
  report ablation --suite paper [--set KEY=VALUE ...] [--no-run]
                                    run the suite's named experiments, reports/ablation.md
  report ablation [--dvc] [--rev REV | --all-commits] [--multirun DIR ...] [--any-machine]
                                    reports/sweep.md across DVC experiments or a multirun
                                    (runs of this machine only, unless --any-machine)
"""

from __future__ import annotations

import argparse
import difflib
import logging
import sys
import tempfile
from pathlib import Path

__all__ = ["main"]


def _cmd_params(args: argparse.Namespace) -> int:
    """Compose conf/ into params.yaml (``--check``: compare with it), refusing a hand the
    stages would refuse.

    The composition is written to a temporary file and its hand is built as the stages build
    it (:class:`~dexflow.hands.robot.RobotHand`: the model read, every link and joint name the
    hand yaml gives checked against it) before it replaces params.yaml: a hand naming a missing
    link stops here (HandConfigError, exit 2), not in retarget after scale_align ran on every
    sequence.
    """
    from dexflow.config import compose_params, load_params, project_root
    from dexflow.hands.robot import RobotHand
    from dexflow.io.atomic import atomic_path
    from dexflow.io.layout import Layout

    root = project_root()
    target = root / "params.yaml"
    with tempfile.TemporaryDirectory() as tmp:
        composed = compose_params(args.overrides, Path(tmp) / "params.yaml")
        RobotHand(load_params(composed).hand, Layout(root=root).hand_dir)
        if not args.check:
            with atomic_path(target) as out:
                out.write_bytes(composed.read_bytes())
            print(f"wrote {target}")
            return 0
        fresh = composed.read_text()
    current = target.read_text() if target.is_file() else ""
    if fresh == current:
        print(f"{target} is up to date with conf/")
        return 0
    sys.stdout.writelines(
        difflib.unified_diff(current.splitlines(True), fresh.splitlines(True), str(target), "conf/")
    )
    print(
        f"\n{target} differs from the composition of conf/: run `dexflow params`", file=sys.stderr
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
    from dexflow.data.demo import generate_demo
    from dexflow.params import DemoConfig

    cfg = DemoConfig(
        seed=args.seed, objects=args.objects or [], sequences_per_object=args.sequences_per_object
    )
    manifest = generate_demo(cfg, args.out, args.jobs)
    print(f"{manifest['num_sequences']} sequences, {manifest['num_frames']} frames in {args.out}")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from dexflow.data.adapters import ConvertOptions, convert

    options = ConvertOptions(
        models=args.models,
        mano=args.mano,
        camera=args.camera,
        fps=args.fps,
        side=args.side,
        jump_threshold_m=args.jump_threshold_m,
        strict=args.strict,
    )
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
    print(
        f"{report['num_ok']}/{report['num_sequences']} sequences written to {args.dst}"
        f" ({report['num_skipped']} skipped, {report['num_failed']} failed)"
    )
    return 0 if report["num_ok"] and not report["num_failed"] else 1


def _cmd_hand_init(args: argparse.Namespace) -> int:
    from dexflow.hands.check import check_hand
    from dexflow.hands.init import init_hand
    from dexflow.human.keypoints import KEYPOINT_NAMES

    default = Path("conf/hand") if Path("conf/hand").is_dir() else Path()
    out = Path(args.out) if args.out else default / f"{Path(args.model).stem}.yaml"
    proposal = init_hand(
        args.model, out, side=args.side, mirror=args.mirror, name=args.name,
        overwrite=args.force,
    )  # fmt: skip
    spec = proposal.spec
    how = "mirrored to a right hand" if spec.mirrored else "used as it is"
    print(f"{args.model}: a {spec.side} hand ({how}); fingers meet at '{proposal.palm}'")
    written = {kp.mano: kp for kp in spec.keypoints}
    for f in proposal.fingers:
        mapped = [f"{KEYPOINT_NAMES[k]}={written[k].link}" for k in f.keypoints if k in written]
        print(f"  {f.name:<6} {len(f.joints)} joints from '{f.root}': {', '.join(mapped)}")
    print(f"  wrist  {written[0].link} + {written[0].offset}")
    print(
        f"  extra_joints {spec.extra_joints}; {len(spec.couplings)} couplings; "
        f"scale {spec.scale:.3f} ({proposal.notes['scale']})"
    )
    for key, text in proposal.guesses:
        print(f"GUESS ({key}): {text}")
    hand, _ = check_hand(out)
    _check_physics(hand)
    print(f"wrote {out}; `dexflow hand check {out}` passes")
    return 0


def _check_physics(hand) -> list[str]:
    """Build and step every physics scene of the pipeline for ``hand`` with the project's
    simulate and replay params (``params.yaml`` here, else the defaults)."""
    from dexflow.config import load_params
    from dexflow.params import ReplayParams, SimulateParams
    from dexflow.sim.scene_check import check_scenes

    if Path("params.yaml").is_file():
        params = load_params("params.yaml")
        simulate, replay, where = params.simulate, params.replay, "params.yaml"
    else:
        simulate, replay, where = SimulateParams(), ReplayParams(), "default params"
    lines = check_scenes(hand, simulate, replay)
    return [f"  physics ({where}, engines {', '.join(simulate.engines)}):"] + [
        f"    {line}" for line in lines
    ]


def _cmd_hand_check(args: argparse.Namespace) -> int:
    from dexflow.hands.check import check_hand

    hand, report = check_hand(args.hand, out_png=args.png)
    tree, _, summary = report.rpartition("\n")  # the report ends with "ok"
    print("\n".join([tree, *_check_physics(hand), summary]))
    return 0


def _cmd_hand_export(args: argparse.Namespace) -> int:
    from dexflow.hands.export import export_urdf
    from dexflow.hands.robot import load_hand

    print(export_urdf(load_hand(args.hand).model, args.out))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from dexflow.tools.bench import (
        bench_fk,
        bench_long,
        bench_pipeline,
        bench_real,
        bench_refine,
        bench_retarget,
        bench_simulate,
    )

    if args.what == "real":
        if not args.root:
            raise SystemExit("dexflow bench real ROOT: give the converted dataset's root")
        bench_real(
            args.root, args.hands or None, args.jobs, args.subset, args.work, args.out_real,
            overrides=args.set,
        )  # fmt: skip
    elif args.what == "long":
        try:
            lengths = tuple(int(n) for n in args.frames.split(","))
        except ValueError:
            raise SystemExit(f"dexflow bench long --frames: whole numbers, e.g. 600,2400 (got "
                             f"{args.frames!r})") from None  # fmt: skip
        bench_long(lengths, args.out_long)
    elif args.what == "pipeline":
        try:
            workers = tuple(int(w) for w in args.workers.split(","))
            scales = tuple(int(k) for k in args.scales.split(","))
        except ValueError:
            raise SystemExit(f"dexflow bench pipeline --workers/--scales: whole numbers, e.g. 1,2 "
                             f"and 1,4 (got {args.workers!r}, {args.scales!r})") from None  # fmt: skip
        bench_pipeline(args.sequences, workers, args.out, args.root, args.subset, scales)
    elif args.what == "fk":
        bench_fk(args.hands or None, repeats=args.repeats)
    elif args.what == "simulate":
        for hand in args.hands or ["shadow"]:
            bench_simulate(hand, sequences=min(args.sequences, 3))
    elif args.what == "refine":
        for hand in args.hands or ["shadow"]:
            bench_refine(hand, sequences=args.sequences)
    else:
        for hand in args.hands or ["shadow"]:
            bench_retarget(hand, sequences=args.sequences)
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    import json
    import subprocess

    from dexflow.io.layout import Layout
    from dexflow.stages import report
    from dexflow.tools import experiments as compared

    if args.what == "summary":
        out = report.write_project_summary(Layout(), out_md=args.out)
        print(f"wrote {out}")
        return 0
    if args.suite:
        return _ablation_suite(args)
    experiments = []
    use_dvc = args.dvc or not args.multirun
    if use_dvc:
        command = ["dvc", "exp", "show", "--json"]
        command += ["-A"] if args.all_commits else ["--rev", args.rev] if args.rev else []
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            logging.error("%s failed: %s", " ".join(command), done.stderr.strip())
            return 1
        show = json.loads(done.stdout or "[]")
        if args.rev:  # the workspace is not derived from that baseline
            show = [node for node in show if node.get("rev") != "workspace"]
        experiments += compared.collect_dvc(show, Layout().reports / "timing")
    for folder in args.multirun or []:
        if not Path(folder).is_dir():
            logging.error("%s: no such multirun directory", folder)
            return 1
        experiments += compared.collect_multirun(folder)
    if not experiments:
        logging.error("no experiments found (dvc exp show and --multirun directories are empty)")
        return 1
    from dexflow.pipeline import provenance

    out = Path(args.out) if args.out else Layout().reports / "sweep.md"
    machine = None if args.any_machine else provenance.machine_id()
    out = compared.write_ablation(experiments, out, out.parent / "figures", machine=machine)
    print(f"wrote {out} ({len(experiments)} experiments)")
    return 0


def _ablation_suite(args: argparse.Namespace) -> int:
    """``report ablation --suite NAME``: run (or resume) the suite, then write its report."""
    from dexflow.config import project_root
    from dexflow.tools import ablation

    root = project_root()
    default_out = Path("reports") / "ablation.md"
    out = Path(args.out) if args.out else default_out
    jobs = root / "multirun" / out.stem
    results = ablation.run_suite(args.suite, root, jobs, args.set, run=not args.no_run)
    default = results[ablation.DEFAULT]
    data = "data not run yet"
    if default.status == "complete":
        sequences = len({row["sequence"] for row in default.rows})
        frames = int(default.pooled.get("num_frames", 0))
        from dvc.utils.serialize import load_yaml

        given = load_yaml(jobs / ablation.DEFAULT / "params.yaml")
        data = (
            f"`{given['data']['root']}` ({given['data']['name']} data: {sequences} sequences, "
            f"{frames} frames; hand `{given['hand']['name']}` unless the experiment changes it)"
        )
    command = ablation.suite_command(args.suite, args.set, out, default_out)
    path = ablation.write_suite_report(args.suite, results, root / out, command, data)
    counts = {
        s: sum(r.status == s for r in results.values()) for s in ("complete", "failed", "queued")
    }
    print(f"wrote {path} ({', '.join(f'{n} {s}' for s, n in counts.items())}); runs in {jobs}")
    return 0 if counts["failed"] == 0 and counts["queued"] == 0 else 1


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dexflow",
        description="\n\n".join(__doc__.split("\n\n")[:2]),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("params", help="compose conf/ into params.yaml")
    p.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. hand=allegro")
    p.add_argument("--check", action="store_true", help="only report drift (exit 1 if any)")
    p.set_defaults(func=_cmd_params)

    p = sub.add_parser("validate", help="check sequence files (.npz or directories)")
    p.add_argument("paths", nargs="+")
    p.add_argument("--data-root", default=None, help="check that meshes exist below this root")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("demo", help="generate demo sequences into a directory")
    p.add_argument("out")
    p.add_argument("--objects", nargs="*", help="stand-in names (default: all)")
    p.add_argument(
        "--sequences-per-object", type=int, default=2, help="3 = every grasp type (the full demo)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=1)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser(
        "convert",
        help="convert a dataset to dexflow's format",
        description="Convert source folders of a dataset (or its root) into one data root. "
        "Exit status 0 when at least one sequence was written and none failed; sequences "
        "without an object model are skipped (listed), unless --strict.",
    )
    p.add_argument("adapter", choices=["dexycb", "ho3d", "grab", "generic"])
    p.add_argument(
        "src", nargs="+", help="source folder(s): e.g. subject folders or the dataset root"
    )
    p.add_argument("dst", help="output data root (sequences/, meshes/, convert.json)")
    p.add_argument("--models", help="object models folder (default SRC/models)")
    p.add_argument("--mano", help="your MANO model file or folder (only for MANO-only data)")
    p.add_argument("--camera", help="DexYCB camera serial (default: the first)")
    p.add_argument("--fps", type=float, help="frame rate where the data does not give it")
    p.add_argument("--side", default="right", choices=["right", "left", "both"], help="GRAB hands")
    p.add_argument(
        "--jump-threshold-m", type=float, default=0.08, help="wrist jump = tracking lost"
    )
    p.add_argument(
        "--strict", action="store_true", help="a missing object model is an error (exit 1)"
    )
    p.set_defaults(func=_cmd_convert)

    hand = sub.add_parser("hand", help="inspect robot hands").add_subparsers(
        dest="hand_cmd", required=True
    )
    p = hand.add_parser(
        "init",
        help="propose a hand yaml from a URDF or MJCF model",
        description="Find the fingers in the kinematic tree, name them by geometry, map their "
        "joints to human keypoints and write a commented hand yaml; guesses are marked GUESS.",
    )
    p.add_argument("model", help="URDF or MJCF file, or pkg://<package>/<file>")
    p.add_argument(
        "--side", choices=["right", "left"], help="the model's side (default: from its geometry)"
    )
    p.add_argument(
        "--mirror", action="store_true",
        help="write a left hand as its mirror image, a right hand (default: use it as it is)",
    )  # fmt: skip
    p.add_argument("-o", "--out", help="the yaml to write (default: conf/hand/<model stem>.yaml)")
    p.add_argument("--name", default="", help="the hand's name (default: the yaml's stem)")
    p.add_argument("--force", action="store_true", help="replace an existing yaml")
    p.set_defaults(func=_cmd_hand_init)
    p = hand.add_parser(
        "check",
        help="validate a hand, print its tree, build and step every physics scene of the pipeline",
    )
    p.add_argument("hand", help="name in conf/hand/ or a yaml path")
    p.add_argument("--png", default=None, help="also draw its zero pose into this PNG")
    p.set_defaults(func=_cmd_hand_check)
    p = hand.add_parser("export", help="write an MJCF hand as a URDF")
    p.add_argument("hand")
    p.add_argument("out")
    p.set_defaults(func=_cmd_hand_export)

    p = sub.add_parser("bench", help="benchmarks (print frames/s)")
    p.add_argument(
        "what", choices=["fk", "retarget", "refine", "simulate", "pipeline", "real", "long"]
    )
    p.add_argument(
        "root", nargs="?",
        help="real (required), pipeline (optional): root of converted sequences (dexflow convert)",
    )  # fmt: skip
    p.add_argument("--workers", default="1,2", help="pipeline: worker counts, e.g. 1,2")
    p.add_argument(
        "--scales", default="1", help="pipeline (demo): data sizes, e.g. 1,4 (k x the sequences)"
    )
    p.add_argument("--out", default="reports/bench.md", help="pipeline: report file")
    p.add_argument("--hands", nargs="*")
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument(
        "--sequences", type=int, default=6, help="retarget, pipeline: demo sequences to use"
    )
    p.add_argument(
        "--subset",
        type=int,
        default=0,
        help="real, pipeline ROOT: evenly spaced sequences (0: all)",
    )
    p.add_argument("--jobs", type=int, default=2, help="real: worker processes")
    p.add_argument("--work", help="real: keep the stage outputs here (default: a temp dir)")
    p.add_argument("--out-real", default="reports/real.md", help="real: report file")
    p.add_argument("--frames", default="600,2400", help="long: sequence lengths, e.g. 600,2400")
    p.add_argument("--out-long", default="reports/bench_long.md", help="long: report file")
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="real: a Hydra override of the defaults (repeatable), e.g. --set simulate=both",
    )  # fmt: skip
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("report", help="generate reports/summary.md or reports/ablation.md")
    p.add_argument("what", choices=["summary", "ablation"])
    p.add_argument(
        "--suite", choices=["paper"],  # dexflow.tools.ablation.SUITES (not imported at start-up)
        help="ablation: run the suite's named experiments (conf/experiment) in "
        "multirun/<out name>/, resuming finished ones, and write one table per question",
    )  # fmt: skip
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="--suite: a Hydra override for every experiment (repeatable), e.g. --set data=custom",
    )  # fmt: skip
    p.add_argument("--no-run", action="store_true", help="--suite: only write the report")
    p.add_argument("--dvc", action="store_true", help="ablation: read `dvc exp show --json`")
    p.add_argument(
        "--all-commits", action="store_true", help="ablation: experiments of all commits"
    )
    p.add_argument(
        "--rev", help="ablation: experiments derived from this baseline commit (default HEAD)"
    )
    p.add_argument("--multirun", nargs="*", help="ablation: Hydra multirun directories")
    p.add_argument(
        "--any-machine", action="store_true",
        help="ablation without --suite: also compare runs made on other machines or not "
        "recorded where (flagged); by default only runs whose every stage this machine made",
    )  # fmt: skip
    p.add_argument("--out", help="output Markdown file")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("view", help="write a rerun recording (.rrd) of a sequence")
    p.add_argument("sequence", help="sequence name (e.g. 025_mug__00_power) or a sequence .npz")
    p.add_argument(
        "--trajectory",
        default="refine",
        choices=["refine", "retarget", "baseline"],
        help="data/refine, data/retarget/dexflow or data/retarget/position",
    )
    p.add_argument("--out", default=None, help="the .rrd file (default reports/rerun/<name>.rrd)")
    p.add_argument("--open", action="store_true", help="start the rerun viewer on the file")
    p.set_defaults(func=_cmd_view)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    import yaml

    from dexflow.errors import DexflowError

    try:
        return args.func(args)
    except DexflowError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except yaml.YAMLError as exc:  # a hand yaml or config file the user wrote
        from dexflow.config import yaml_error_message

        print(f"error: {yaml_error_message(exc)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
