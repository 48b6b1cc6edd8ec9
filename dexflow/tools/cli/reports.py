"""``dexflow bench|report``: benchmarks and reports."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from dexflow.tools.cli.helptext import HelpFormatter

__all__ = ["add_commands"]


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
            overrides=args.set, skip=args.skip,
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
    from dexflow.io.layout import Layout
    from dexflow.stages import report
    from dexflow.tools import experiments as compared

    if args.what == "summary":
        from dexflow.config import load_params

        params = load_params("params.yaml") if Path("params.yaml").is_file() else None
        out = report.write_project_summary(Layout(), out_md=args.out, params=params)
        print(f"wrote {out}")
        return 0
    if args.suite:
        return _ablation_suite(args)
    experiments = _experiments(args)
    if experiments is None:
        return 1
    from dexflow.pipeline import provenance

    out = Path(args.out) if args.out else Layout().reports / "sweep.md"
    machine = None if args.any_machine else provenance.machine_id()
    out = compared.write_ablation(experiments, out, out.parent / "figures", machine=machine)
    print(f"wrote {out} ({len(experiments)} experiments)")
    return 0


def _experiments(args: argparse.Namespace) -> list | None:
    """The experiments of ``dvc exp show`` (``--rev``, ``--all-commits``) and/or ``--multirun``
    directories; None (the reason logged) when there are none or DVC fails."""
    import json
    import subprocess

    from dexflow.io.layout import Layout
    from dexflow.tools import experiments as compared

    experiments = []
    if args.dvc or not args.multirun:
        command = ["dvc", "exp", "show", "--json"]
        command += ["-A"] if args.all_commits else ["--rev", args.rev] if args.rev else []
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            logging.error("%s failed: %s", " ".join(command), done.stderr.strip())
            return None
        show = json.loads(done.stdout or "[]")
        if args.rev:  # the workspace is not derived from that baseline
            show = [node for node in show if node.get("rev") != "workspace"]
        experiments += compared.collect_dvc(show, Layout().reports / "timing")
    for folder in args.multirun or []:
        if not Path(folder).is_dir():
            logging.error("%s: no such multirun directory", folder)
            return None
        experiments += compared.collect_multirun(folder)
    if not experiments:
        logging.error("no experiments found (dvc exp show and --multirun directories are empty)")
        return None
    return experiments


def _cmd_exp(args: argparse.Namespace) -> int:
    """``dexflow exp``: the experiments' headline metrics side by side."""
    import csv
    import sys

    from dexflow.tools.headline import format_table, headline_table

    experiments = _experiments(args)
    if experiments is None:
        return 1
    if args.all:
        metrics = sorted({k for e in experiments for k in e.metrics})
    elif args.metrics:
        metrics = [m.strip() for m in args.metrics.split(",") if m.strip()]
    else:
        metrics = None
    table = headline_table(experiments, metrics)
    if args.csv:
        writer = csv.writer(sys.stdout, lineterminator="\n")
        writer.writerow(table.columns)
        writer.writerows(["" if v is None else v for v in row] for row in table.rows)
        return 0
    if args.all:  # a few hundred metrics: one row each, one column per experiment
        flipped = [[key, *(row[i] for row in table.rows)] for i, key in enumerate(table.columns)]
        head = [["", *(str(row[0]) for row in table.rows)]]
        print(format_table(head, flipped[1:], width=max(map(len, table.columns))))
    else:
        print(format_table(table.header, table.rows))
    for note in table.notes:
        print(f"  {note}")
    return 0


def _ablation_suite(args: argparse.Namespace) -> int:
    """``report ablation --suite NAME``: run (or resume) the suite, then write its report."""
    from dexflow.config import project_root
    from dexflow.tools import ablation

    root = project_root()
    default_out = Path("reports") / (
        "ablation.md" if args.suite == "paper" else f"ablation_{args.suite}.md"
    )
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


def add_commands(sub) -> None:
    """Add this module's subcommands to the ``dexflow`` parser's subparsers."""
    p = sub.add_parser(
        "bench",
        help="throughput benchmarks (frames/s against baselines)",
        description="Time a part of the pipeline and print frames/s: forward kinematics (fk), "
        "one stage on demo sequences (retarget, refine, simulate), the whole pipeline at "
        "several worker counts and data sizes (pipeline, written to reports/bench.md), a "
        "converted dataset (real) or long sequences (long).",
        epilog="examples:\n  dexflow bench retarget --hands shadow allegro --sequences 3\n"
        "  dexflow bench pipeline --workers 1,2 --scales 1,4\n"
        "  dexflow bench real data/dexycb --subset 8 --jobs 2",
        formatter_class=HelpFormatter,
    )
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
    p.add_argument(
        "--skip", action="append", default=[], metavar="STAGE",
        help="real: leave out the stages whose names start with this (repeatable), e.g. "
        "--skip simulate (no grasp tests: no SSR)",
    )  # fmt: skip
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser(
        "report",
        help="write reports/summary.md, reports/ablation.md or reports/sweep.md",
        description="summary: reports/summary.md from reports/metrics (what the `report` "
        "stage runs). ablation --suite paper: run the paper's ablation experiments "
        "(conf/experiment/) and write reports/ablation.md, one table per question (--suite "
        "track: stage track's parts, with track=on, to reports/ablation_track.md). ablation "
        "without --suite: reports/sweep.md, a table and a plot per swept parameter across the "
        "DVC experiments (dvc exp show) and/or Hydra multirun directories.",
        epilog="examples:\n  dexflow report summary\n"
        "  dexflow report ablation --suite paper\n"
        "  dexflow report ablation --suite track\n"
        "  dexflow report ablation --multirun multirun/2024-05-01/12-00-00",
        formatter_class=HelpFormatter,
    )
    p.add_argument("what", choices=["summary", "ablation"])
    p.add_argument(
        "--suite", choices=["paper", "track"],  # dexflow.tools.ablation.SUITES (not imported)
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

    p = sub.add_parser(
        "exp",
        help="the headline metrics of every experiment, side by side",
        description="Print one row per experiment (DVC experiments of the current commit, or "
        "the jobs of Hydra multirun directories): its name, commit, the parameters that differ "
        "between the experiments, then the headline metrics of the refined trajectories (SSR, "
        "PD, CD, fingertip error, RMS acceleration), their replay success and, for multirun "
        "jobs, the retargeting speed. docs/experiments.md has the `dvc exp show` command "
        "that shows the same columns.",
        epilog="examples:\n  dexflow exp\n  dexflow exp --metrics refine.ssr,retarget.keypoint_error_mm\n"
        "  dexflow exp --all                  # every metric, one row each\n"
        "  dexflow exp --csv > experiments.csv\n"
        "  dexflow exp --multirun multirun/2024-05-01/12-00-00",
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "--metrics", metavar="A,B",
        help="these metrics (flat keys of reports/metrics, e.g. refine.ssr,contact.precision) "
        "instead of the headline ones",
    )  # fmt: skip
    p.add_argument(
        "--all", action="store_true",
        help="every metric, one row per metric and one column per experiment",
    )  # fmt: skip
    p.add_argument("--csv", action="store_true", help="comma-separated values, full precision")
    p.add_argument(
        "--multirun", action="append", metavar="DIR",
        help="a Hydra multirun directory (repeatable); then DVC only with --dvc",
    )  # fmt: skip
    p.add_argument("--dvc", action="store_true", help="with --multirun: DVC experiments too")
    p.add_argument("--rev", help="experiments derived from this baseline commit (default HEAD)")
    p.add_argument("-A", "--all-commits", action="store_true", help="experiments of every commit")
    p.set_defaults(func=_cmd_exp)
