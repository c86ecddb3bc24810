"""Batched against sequential fitting on the 1D task, side by side in one run.

``fit_theta`` fits every agent as an independent row of one batched Newton problem. This
prints the wall time of one batched call over K agents and of K single-agent calls on the same
trials, their ratio, and checks that both give the same θ̂.

Run: ``python benchmarks/bench_fit1d.py [--agents 20] [--trials 100]``.
"""

from __future__ import annotations

import argparse
import time

import torch

from irc_torchrl.algorithms.fit import fit_theta
from irc_torchrl.algorithms.qiteration import train_factorised_q
from irc_torchrl.algorithms.simulate import boltzmann_policy, simulate_agents
from irc_torchrl.envs import Firefly1DModel
from irc_torchrl.modules.likelihood import BoltzmannActionModel
from irc_torchrl.objectives.inverse import InverseRationalLoss


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--agents", type=int, default=20)
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = Firefly1DModel()
    q = train_factorised_q(model, seed=0)
    space = model.theta_space
    theta = space.sample((args.agents,), generator=torch.Generator().manual_seed(0))
    policy = boltzmann_policy(model, q, 0.5)
    trials = simulate_agents(model, policy, theta, args.trials, space.default(), seed=1)

    def fit(rows):
        loss = InverseRationalLoss(model, BoltzmannActionModel(q, 0.5), n_agents=rows.shape[0])
        return fit_theta(loss, rows, seed=0)

    start = time.perf_counter()
    batched = fit(trials)
    batched_s = time.perf_counter() - start
    start = time.perf_counter()
    single = [fit(trials[i : i + 1]) for i in range(args.agents)]
    sequential_s = time.perf_counter() - start
    hats = torch.cat([r.theta_hat for r in single])
    gap = (hats - batched.theta_hat).abs().amax().item()
    print(f"{args.agents} agents × {args.trials} trials, {args.threads} thread(s)")
    print(f"batched: one call      {batched_s:8.1f} s")
    print(f"sequential: {args.agents} calls  {sequential_s:8.1f} s")
    print(f"speed-up batched/sequential: {sequential_s / batched_s:.1f}×")
    print(f"max |θ̂ batched − θ̂ sequential|: {gap:.2e}")


if __name__ == "__main__":
    main()
