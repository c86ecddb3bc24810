"""Tutorial: how many trials does an experiment need to pin each parameter of θ?

Before recording anything, simulate agents acting with the policy shipped in the package and
ask how wide the 95% intervals of Algorithm 2 would come out: the Fisher information of their
trials at their own θ predicts it without a fit
(:func:`~irc_torchrl.algorithms.recover2d.predicted_widths`, built on
:func:`~irc_torchrl.algorithms.expected_intervals`). This script prints, for 25, 50, 100 and
200 trials per agent, the median width over the agents of each parameter's interval, and the
fewest of those trial counts that pins it to a tenth of its prior range.

    python examples/plan_an_experiment.py --out runs/plan   # about a minute on one core

The widths fall about as one over the square root of the trials. The gains are read off every
action and are pinned by 25 trials; with the shipped policy σ_ω is too, the other noises need
100, and the goal radius and the effort cost more than 200.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.recover2d import predicted_widths
from irc_torchrl.data.files import write_json

TRIALS = (25, 50, 100, 200)
#: a parameter counts as pinned once its interval spans at most this share of its prior range
PINNED = 0.1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/plan")
    parser.add_argument("--agents", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    widths = predicted_widths(model, actor, TRIALS, args.agents, args.seed)
    span = dict(zip(space.names, (space.high() - space.low()).tolist(), strict=True))
    needed = {
        name: next((n for n in TRIALS if widths[n][name] <= PINNED * span[name]), None)
        for name in space.free_names
    }
    print(f"median width of the 95% intervals over {args.agents} agents, by trials per agent")
    print(f"{'parameter':>12} " + " ".join(f"{n:>7}" for n in TRIALS) + "   pinned from")
    for name in space.free_names:
        pinned = "-" if needed[name] is None else f"{needed[name]} trials"
        print(
            f"{name:>12} " + " ".join(f"{widths[n][name]:>7.3f}" for n in TRIALS) + f"   {pinned}"
        )
    by_trials = {str(n): w for n, w in widths.items()}
    write_json(
        Path(args.out) / "results.json",
        {"trials": list(TRIALS), "widths": by_trials, "pinned": needed},
    )


if __name__ == "__main__":
    main()
