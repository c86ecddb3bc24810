"""Batched against sequential fitting, side by side in one run (1D or 2D task).

``fit_theta`` fits every agent as an independent row of one batched problem. This prints the
wall time of one batched call over K agents and of K single-agent calls on the same trials,
their ratio, each single agent's time (the 2D goal: one agent, 100 trials, ≤ 30 s), and how
far apart the θ̂ of both are (the 2D fit's Fisher-scoring phase draws its samples per call,
so there the paths differ and θ̂ agree to the fit's tolerance, not bit for bit). The 2D fit
runs with ``irc recover``'s settings (``--max-iter 80`` for its iteration limit). With
``--workers W`` > 1 the batched call is also timed with its agents shared among W processes
(``fit_theta(workers=W)``), beside the one-process call.

Run: ``python benchmarks/bench_fit.py [--task firefly1d|firefly2d] [--method map|marginal]
[--agents 20] [--trials 100] [--max-iter 40] [--actor-dtype float32|float64] [--workers 2]
[--seed 0]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch
from _common import integer, recorded_agents, recover_fit_settings

from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.fit import fit_theta
from irc_torchrl.algorithms.qiteration import train_factorised_q
from irc_torchrl.algorithms.simulate import boltzmann_policy, motor_noise_policy
from irc_torchrl.envs import Firefly1DModel
from irc_torchrl.modules.actor_critic import ACTOR_DTYPES, censored_action_model
from irc_torchrl.modules.likelihood import BoltzmannActionModel
from irc_torchrl.objectives.inverse import InverseRationalLoss


def _task(name: str, actor_dtype: str, seed: int):
    """``(model, policy, action_model, fit settings)`` of a task (the 2D actor in ``actor_dtype``
    inside the likelihood)."""
    if name == "firefly1d":
        model = Firefly1DModel()
        q = train_factorised_q(model, seed=seed)
        return model, boltzmann_policy(model, q, 0.5), BoltzmannActionModel(q, 0.5), {}
    actor, model, _ = load_ensemble_policy("firefly2d")
    action_model = censored_action_model(actor, model, actor_dtype)
    settings = recover_fit_settings()
    del settings["max_iter"]  # --max-iter's
    return model, motor_noise_policy(actor, model.action_spec, 0.1), action_model, settings


def main() -> None:
    sys.stdout.reconfigure(line_buffering=True)  # each line shows as it is printed
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--task", choices=["firefly1d", "firefly2d"], default="firefly1d")
    parser.add_argument("--method", choices=["map", "marginal"], default="map")
    parser.add_argument("--agents", type=integer(), default=20)
    parser.add_argument("--trials", type=integer(), default=100)
    parser.add_argument("--max-iter", type=integer(), default=40)
    parser.add_argument("--threads", type=integer(), default=1)
    parser.add_argument("--actor-dtype", choices=sorted(ACTOR_DTYPES), default="float32")
    parser.add_argument("--workers", type=integer(), default=1)
    parser.add_argument("--seed", type=integer(0), default=0, help="seed of θ, trials and fits")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model, policy, action_model, settings = _task(args.task, args.actor_dtype, args.seed)
    space = model.theta_space
    theta = space.sample((args.agents,), generator=torch.Generator().manual_seed(args.seed))
    trials = recorded_agents(model, policy, theta, args.trials, args.seed)

    def fit(rows, workers=1):
        loss = InverseRationalLoss(model, action_model, n_agents=rows.shape[0], method=args.method)
        return fit_theta(
            loss, rows, max_iter=args.max_iter, seed=args.seed, workers=workers, **settings
        )

    start = time.perf_counter()
    batched = fit(trials)
    batched_s = time.perf_counter() - start
    if args.workers > 1:
        start = time.perf_counter()
        shared = fit(trials, args.workers)
        shared_s = time.perf_counter() - start
    single, alone_s = [], []
    for i in range(args.agents):
        start = time.perf_counter()
        single.append(fit(trials[i : i + 1]))
        alone_s.append(time.perf_counter() - start)
    sequential_s = sum(alone_s)
    hats = torch.cat([r.theta_hat for r in single])
    gap = ((hats - batched.theta_hat).abs() / (space.high() - space.low()).double()).amax()
    print(
        f"{args.task}, {args.method}: {args.agents} agents × {args.trials} trials, "
        f"{args.threads} thread(s), at most {args.max_iter} iterations"
        + (f", {args.actor_dtype} actor" if args.task == "firefly2d" else "")
    )
    print(f"batched: one call      {batched_s:8.1f} s")
    print(f"sequential: {args.agents} calls  {sequential_s:8.1f} s")
    print(f"speed-up batched/sequential: {sequential_s / batched_s:.1f}×")
    if args.workers > 1:
        print(f"batched: one call, {args.workers} processes {shared_s:8.1f} s")
        ratio = sequential_s / shared_s
        print(f"speed-up batched in {args.workers} processes/sequential: {ratio:.1f}×")
        print(f"speed-up {args.workers} processes/one: {batched_s / shared_s:.2f}×")
    times = sorted(alone_s)
    print(
        f"one agent alone: median {statistics.median(times):.1f} s, fastest {times[0]:.1f} s, "
        f"slowest {times[-1]:.1f} s, {sum(t <= 30 for t in times)} of {len(times)} within 30 s "
        f"({', '.join(f'{t:.1f}' for t in alone_s)})"
    )
    print(f"max |θ̂ batched − θ̂ sequential| / prior range: {gap.item():.2e}")
    alone = torch.cat([r.converged for r in single]).double().mean().item()
    together = batched.converged.double().mean().item()
    print(f"converged: batched {together:.0%}, sequential {alone:.0%}")
    if args.workers > 1:
        print(
            f"converged: batched in {args.workers} processes {shared.converged.double().mean():.0%}"
        )


if __name__ == "__main__":
    main()
