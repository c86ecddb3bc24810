"""The inverse's frozen actor in float32 against float64, side by side in one run (2D task).

The 2D marginal likelihood runs in float64; its actor (the shipped MLP, linearised at every
step) need not. This prints the wall time of one gradient pass (values and per-trial scores,
what each BFGS iteration costs) over 1, 2 and 16 rows of 100 trials with each actor, their
ratio, and how far the float32 actor moves the log-likelihood and its gradient.

Run: ``python benchmarks/bench_actor_precision.py [--trials 100] [--threads 2] [--repeats 3]
[--seed 0]``.
"""

from __future__ import annotations

import argparse
import time

import torch
from _common import integer, recorded_agents

from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.fit import _trial_scores
from irc_torchrl.algorithms.simulate import motor_noise_policy
from irc_torchrl.modules.actor_critic import censored_action_model
from irc_torchrl.objectives.inverse import InverseRationalLoss

ROWS = (1, 2, 16)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--trials", type=integer(), default=100)
    parser.add_argument("--threads", type=integer(), default=2)
    parser.add_argument("--repeats", type=integer(), default=3)
    parser.add_argument("--seed", type=integer(0), default=0, help="seed of θ and trials")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    actor, model, _ = load_ensemble_policy("firefly2d")
    spec, space = model.action_spec, model.theta_space
    n = max(ROWS)
    theta = space.sample((n,), generator=torch.Generator().manual_seed(args.seed))
    policy = motor_noise_policy(actor, spec, 0.1)
    trials = recorded_agents(model, policy, theta, args.trials, args.seed)
    free = space.free_mask
    k = int(free.sum())
    losses = {
        name: InverseRationalLoss(
            model, censored_action_model(actor, model, name), n_agents=n, method="marginal"
        )
        for name in ("float64", "float32")
    }
    nuisance = losses["float64"].action_model.nuisance_init.double().expand(n, -1)
    params = torch.cat([space.to_unconstrained(theta.double())[:, free], nuisance], -1)
    value, grad = {}, {}
    for name, loss in losses.items():
        ll, score, _ = _trial_scores(loss, k, params, trials)
        value[name], grad[name] = ll.sum(1), score.sum(1)
    shift = (value["float64"] - value["float32"]).abs()
    error = (grad["float64"] - grad["float32"]).norm(dim=-1) / grad["float64"].norm(dim=-1)
    print(f"firefly2d marginal, {args.trials} trials per row, {args.threads} thread(s), at θ*")
    print(f"|Δ log-likelihood|: median {shift.median():.1e}, max {shift.max():.1e} nats")
    print(f"relative gradient error: median {error.median():.1e}, max {error.max():.1e}")
    for rows in ROWS:
        seconds = {}
        for name, loss in losses.items():
            _trial_scores(loss, k, params[:rows], trials[:rows])  # warm-up
            start = time.perf_counter()
            for _ in range(args.repeats):
                _trial_scores(loss, k, params[:rows], trials[:rows])
            seconds[name] = (time.perf_counter() - start) / args.repeats
        print(
            f"{rows:3d} rows: float64 {seconds['float64']:.2f} s, float32 "
            f"{seconds['float32']:.2f} s per gradient pass, "
            f"speed-up {seconds['float64'] / seconds['float32']:.2f}×"
        )


if __name__ == "__main__":
    main()
