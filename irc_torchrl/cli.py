"""The ``irc`` command: thin wrappers over the functions in :mod:`irc_torchrl.algorithms`."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> int:
    from irc_torchrl.algorithms.demo import format_summary, run_demo
    from irc_torchrl.config import load_config

    overrides = [*args.overrides, f"seed={args.seed}"] if args.seed is not None else args.overrides
    config = load_config(args.config, overrides)
    summary = run_demo(config, args.out, show_progress=not args.quiet)
    print(format_summary(summary))
    print(
        f"wrote {args.out}/: summary.json, config.yaml, "
        "q_function.png, recovery.png, dp_comparison.png"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="irc",
        description="Inverse Rational Control: what internal model makes behaviour rational?",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = commands.add_parser(
        "demo",
        help="train, simulate agents and recover their θ end to end (the main job)",
        description=(
            "Learn one Q over the θ prior (Algorithm 1), check it against exact DP, simulate "
            "agents with θ* from the prior, fit each agent's θ with 95% intervals (Algorithm 2) "
            "and report coverage. Writes config.yaml, summary.json and figures into --out."
        ),
    )
    demo.add_argument(
        "--task", choices=["firefly1d"], default="firefly1d", help="the task (default firefly1d)"
    )
    demo.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    demo.add_argument(
        "--seed", type=int, default=None, help="seed of every random draw (default 0)"
    )
    demo.add_argument("--config", default=None, help="a YAML config (default: the embedded one)")
    demo.add_argument("--quiet", action="store_true", help="no progress bars")
    demo.add_argument(
        "overrides",
        nargs="*",
        metavar="key=value",
        help="config overrides, e.g. agents.n_agents=30",
    )
    demo.set_defaults(run=_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (KeyError, ValueError, TypeError, FileNotFoundError) as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"irc {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
