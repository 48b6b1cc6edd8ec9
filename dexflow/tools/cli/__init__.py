"""dexflow: human hand-object captures to robot-hand trajectories (the DexFlow method).

The pipeline itself runs with `dvc repro` (stages in dvc.yaml, parameters composed from conf/
into params.yaml); this command prepares its inputs, checks hands and data, benchmarks and
writes reports. `dexflow SUBCOMMAND --help` describes each.

Subcommands:
  params [OVERRIDE ...] [--check]   compose conf/ into params.yaml (as `dvc exp run` does)
  validate PATH [--data-root DIR]   check sequence files against the canonical format
  demo OUT [KEY=VALUE ...]          generate (part of) the demo dataset outside the pipeline
  convert ADAPTER SRC [SRC ...] DST [--strict]
                                    dexycb | ho3d | grab | generic -> canonical sequences
  hand init MODEL [--side S] [-o Y] propose a hand yaml from a URDF or MJCF model
  hand check NAME|YAML [--png P]    validate a hand, print its tree, build and step its physics scenes
  hand export NAME|YAML OUT.urdf    write an MJCF hand as a URDF (for pybullet)
  bench fk|retarget|refine|simulate|pipeline|real|long
                                    throughput benchmarks (frames/s against baselines)
  view SEQUENCE [--trajectory T] [--open]
                                    write a rerun recording (.rrd) of a sequence
  exp [--metrics A,B | --all] [--csv] [--multirun DIR]
                                    the headline metrics of every experiment, side by side
  export [PROJECT] OUT --format hdf5|lerobot [--method M]
                                    a project's trajectories as HDF5 or a LeRobot dataset
  report summary                    reports/summary.md from the metrics (the `report` stage)
  report ablation --suite paper [--set KEY=VALUE ...] [--no-run]
                                    run the suite's named experiments, reports/ablation.md
  report ablation [--dvc] [--rev REV | --all-commits] [--multirun DIR ...] [--any-machine]
                                    reports/sweep.md across DVC experiments or a multirun
                                    (runs of this machine only, unless --any-machine)
"""

from __future__ import annotations

import argparse
import logging
import sys

from dexflow.tools.cli import data, export, hands, reports
from dexflow.tools.cli.helptext import HelpFormatter

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dexflow",
        description="\n\n".join(__doc__.split("\n\n")[:2]),
        epilog="examples:\n"
        "  dexflow params data=generic && dvc repro   # run the pipeline on converted data\n"
        "  dexflow hand check allegro                 # check a hand before a run\n"
        "  dexflow exp                                # compare the DVC experiments",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in (data, hands, export, reports):
        module.add_commands(sub)
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
