"""What a lapse in the action model buys and costs: agents that lapse, and agents that never do.

For each pair (the agents' lapse rate, the fit's: held, or ``fit`` from 0.01), simulates the
same agents (θ* from the prior, motor noise 0.1, 100 trials each) and fits them with the
marginal estimator and ``irc recover``'s fit settings, every parameter free. Prints per pair
the median relative error of each free parameter, the fraction of fits converged, the median
fitted motor noise per action dimension, the fitted lapse rates' range, the agents' mean trial
length (a lapse of the forward control often stops a trial) and the time, side by side.

Run: ``python benchmarks/bench_lapse.py [--quick] [--agents 8] [--trials 100] [--threads 2]
[--seed 0]``
(``--quick``: the three pairs of :data:`QUICK_PAIRS`, 4 agents × 40 trials, a few minutes).
"""

from __future__ import annotations

import argparse
import sys
import time

import torch
from _common import integer, recorded_agents, recover_fit_settings

from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.fit import fit_theta
from irc_torchrl.algorithms.simulate import motor_noise_policy
from irc_torchrl.modules.actor_critic import censored_action_model
from irc_torchrl.objectives.inverse import InverseRationalLoss

#: (the agents' lapse rate, the fit's: a rate held, or "fit")
PAIRS = (
    (0.05, 0.0),
    (0.05, 0.05),
    (0.05, 0.01),
    (0.05, "fit"),
    (0.15, 0.01),
    (0.15, "fit"),
    (0.0, 0.0),
    (0.0, 0.01),
    (0.0, "fit"),
)
#: a lapse unmodelled, fitted, and fitted where there is none
QUICK_PAIRS = ((0.05, 0.0), (0.05, "fit"), (0.0, "fit"))


def main() -> None:
    sys.stdout.reconfigure(line_buffering=True)  # each line shows as it is printed
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 pairs, 4 agents × 40 trials")
    parser.add_argument("--agents", type=integer(), default=None, help="default 8 (4 with --quick)")
    parser.add_argument(
        "--trials",
        type=integer(12),  # the sandwich: more trials than fitted coordinates (8 θ, 3 nuisance)
        default=None,
        help="default 100 (40 with --quick); at least 12",
    )
    parser.add_argument("--threads", type=integer(), default=2)
    parser.add_argument("--seed", type=integer(0), default=0, help="seed of θ, trials and fits")
    args = parser.parse_args()
    if args.agents is None:
        args.agents = 4 if args.quick else 8
    if args.trials is None:
        args.trials = 40 if args.quick else 100
    torch.set_num_threads(args.threads)
    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    free = space.free_mask
    theta = space.sample((args.agents,), generator=torch.Generator().manual_seed(args.seed))
    print(f"{args.agents} agents × {args.trials} trials, marginal, every parameter free")
    print(f"{'agents':>6} {'fit':>5}  median relative error ({', '.join(space.free_names)})")
    for agents_lapse, fit_lapse in QUICK_PAIRS if args.quick else PAIRS:
        policy = motor_noise_policy(actor, model.action_spec, 0.1, agents_lapse)
        held = recorded_agents(model, policy, theta, args.trials, args.seed)
        fitted = fit_lapse == "fit"
        action_model = censored_action_model(
            actor, model, "float32", lapse=0.01 if fitted else fit_lapse, fit_lapse=fitted
        )
        loss = InverseRationalLoss(model, action_model, n_agents=args.agents, method="marginal")
        start = time.perf_counter()
        result = fit_theta(loss, held, seed=args.seed, **recover_fit_settings())
        seconds = time.perf_counter() - start
        truth = theta[:, free].double()
        # the median of an even number of agents is the mean of the middle two
        error = ((result.theta_hat[:, free] - truth).abs() / truth).quantile(0.5, dim=0)
        noise = action_model.motor_noise(result.nuisance).quantile(0.5, dim=0)
        rates = action_model.lapse_rate(result.nuisance)
        print(
            f"{agents_lapse:>6} {fit_lapse:>5}  "
            + " ".join(f"{e:.1%}" for e in error.tolist())
            + f"  converged {result.converged.double().mean():.0%}"
            + f"  motor noise {noise[0]:.3f}, {noise[1]:.3f}"
            + (f"  lapse {rates.min():.4f}–{rates.max():.4f}" if fitted else "")
            + f"  trial {held['mask'].sum(-1).double().mean():.1f} steps  {seconds:.0f} s"
        )


if __name__ == "__main__":
    main()
