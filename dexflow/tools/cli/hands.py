"""``dexflow hand init|check|export``: bring a robot hand and check it before the pipeline runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from dexflow.tools.cli.helptext import HelpFormatter

__all__ = ["add_commands"]


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


def add_commands(sub) -> None:
    """Add this module's subcommands to the ``dexflow`` parser's subparsers."""
    hand = sub.add_parser(
        "hand",
        help="bring a robot hand: propose its yaml, check it, export it",
        description="Bring a robot hand to the pipeline: `hand init` proposes a hand yaml from "
        "a URDF or MJCF model, `hand check` validates a hand and steps its physics scenes, "
        "`hand export` writes an MJCF hand as a URDF. `dexflow hand SUBCOMMAND --help` "
        "describes each.",
        epilog="example:\n  dexflow hand init models/myhand.urdf && dexflow hand check myhand",
        formatter_class=HelpFormatter,
    ).add_subparsers(dest="hand_cmd", required=True)
    p = hand.add_parser(
        "init",
        help="propose a hand yaml from a URDF or MJCF model",
        description="Find the fingers in the kinematic tree, name them by geometry, map their "
        "joints to human keypoints and write a commented hand yaml; guesses are marked GUESS.",
        epilog="example:\n  dexflow hand init models/myhand.urdf -o conf/hand/myhand.yaml",
        formatter_class=HelpFormatter,
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
        description="Load a hand as the stages do (its model, every link and joint its yaml "
        "names), print its kinematic tree with the human keypoints mapped to it, and build and "
        "step every physics scene of the pipeline with the project's simulate and replay "
        "params. Exit status 2 with the reason if the stages would refuse it.",
        epilog="examples:\n  dexflow hand check allegro\n"
        "  dexflow hand check conf/hand/myhand.yaml --png myhand.png",
        formatter_class=HelpFormatter,
    )
    p.add_argument("hand", help="name in conf/hand/ or a yaml path")
    p.add_argument("--png", default=None, help="also draw its zero pose into this PNG")
    p.set_defaults(func=_cmd_hand_check)
    p = hand.add_parser(
        "export",
        help="write an MJCF hand as a URDF",
        description="Write the model of a hand given as MJCF as a URDF (links, joints, limits, "
        "meshes), for tools that read only URDF such as pybullet.",
        epilog="example:\n  dexflow hand export shadow shadow.urdf",
        formatter_class=HelpFormatter,
    )
    p.add_argument("hand", help="name in conf/hand/ or a yaml path")
    p.add_argument("out", help="the URDF file to write")
    p.set_defaults(func=_cmd_hand_export)
