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


def _train(args: argparse.Namespace) -> int:
    from irc_torchrl.algorithms.ensemble import train_ensemble
    from irc_torchrl.config import load_firefly2d_config

    config = load_firefly2d_config(args.config, args.overrides)
    result = train_ensemble(
        config, out=args.out, resume=args.resume, progress=not args.quiet, seed=args.seed
    )
    best = result.best
    print(
        f"best policy: success {best['success_rate']:.1%}, return {best['mean_return']:.2f}, "
        f"trial length {best['mean_length']:.1f} steps (after {best['updates']} updates)"
    )
    print(f"wrote {args.out}/: checkpoint.pt, config.yaml, summary.json, logs/")
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
    train = commands.add_parser(
        "train",
        help="train one θ-conditioned policy over the θ prior (Algorithm 1, 2D task)",
        description=(
            "DDPG over the whole θ prior of the 2D firefly task; writes checkpoint.pt (every "
            "checkpoint_every updates and at the end), config.yaml, summary.json and logs."
        ),
    )
    train.add_argument("--config", default=None, help="a YAML config (default: the embedded one)")
    train.add_argument("--out", default="runs/train", help="output folder (default runs/train)")
    train.add_argument("--resume", default=None, help="a checkpoint to continue from")
    train.add_argument("--seed", type=int, default=None, help="overrides the config's seed")
    train.add_argument("--quiet", action="store_true", help="no progress bar")
    train.add_argument(
        "overrides", nargs="*", metavar="key=value", help="config overrides, e.g. ddpg.n_envs=128"
    )
    train.set_defaults(run=_train)
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
