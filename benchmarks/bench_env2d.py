"""Env-steps/s of the 2D firefly task with its EKF belief, features and an MLP actor.

Three paths over the same math, side by side, for N = 1, 64, 1024, 4096 environments:
``torchrl`` (``env.rollout`` of ``TransformedEnv(Firefly2DEnv, EKFBelief)`` with a
``BeliefFeatures`` + MLP policy), ``plain`` (a torch loop calling the same model functions and
:func:`ekf_step`, keeping the trajectory as the rollout does, no TensorDict), and ``gymnasium``
(``SyncVectorEnv`` over the adapter, the actor called on the stacked features). Each rate is
the best of ``--repeats`` runs, each after a warm-up. Prints a table and, at N = 1024, the
ratios torchrl/plain (goal ≥ 0.6) and torchrl/gymnasium (goal ≥ 10), all measured in the same
run.

Run: ``python benchmarks/bench_env2d.py [--quick] [--threads 1] [--repeats 3] [--seed 0]``
(``--quick``: fewer steps, gymnasium up to N = 1024, one run unless ``--repeats`` says).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from _common import integer
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import TransformedEnv
from torchrl.modules import MLP

from irc_torchrl.envs import (
    BeliefFeatures,
    EKFBelief,
    Firefly2DEnv,
    Firefly2DGymEnv,
    Firefly2DModel,
)
from irc_torchrl.envs.belief import ekf_step


def make_actor(model: Firefly2DModel) -> torch.nn.Module:
    """A θ-conditioned MLP actor (3×64 softplus, tanh output), as in the paper."""
    dim = model.belief_feature_dim + model.theta_space.dim
    net = MLP(
        in_features=dim, out_features=2, num_cells=[64, 64, 64], activation_class=torch.nn.Softplus
    )
    return torch.nn.Sequential(net, torch.nn.Tanh())


def torchrl_rate(
    n: int, steps: int, actor: torch.nn.Module, model: Firefly2DModel, seed: int
) -> float:
    """Env-steps/s of ``env.rollout`` with the EKF transform and a features + MLP policy."""
    env = TransformedEnv(Firefly2DEnv(batch_size=(n,), model=model, seed=seed), EKFBelief(model))
    policy = TensorDictSequential(
        BeliefFeatures(model), TensorDictModule(actor, in_keys=["features"], out_keys=["action"])
    )
    with torch.no_grad():
        env.rollout(3, policy, break_when_any_done=False)
        start = time.perf_counter()
        env.rollout(steps, policy, break_when_any_done=False)
        return n * steps / (time.perf_counter() - start)


def plain_rate(
    n: int, steps: int, actor: torch.nn.Module, model: Firefly2DModel, seed: int
) -> float:
    """Env-steps/s of a torch loop doing the same math: world, noise, filter, features, actor."""
    rng = torch.Generator().manual_seed(seed)

    def noise(cov: torch.Tensor) -> torch.Tensor:
        chol = torch.linalg.cholesky(cov.double()).to(cov.dtype)
        eps = torch.randn(*cov.shape[:-1], 1, generator=rng)
        return (chol @ eps).squeeze(-1)

    def reset(mask: torch.Tensor, carry: tuple) -> tuple:
        theta = model.theta_space.sample((n,), generator=rng)
        state, target = model.initial_state(theta, rng)
        obs = model.observe(state, theta) + noise(model.observation_cov(state, theta))
        mean, cov = model.initial_belief(state, target, theta)
        step = torch.zeros(n, 1, dtype=torch.int64)
        fresh = (theta, state, target, obs, mean, cov, step)
        if carry is None:
            return fresh
        return tuple(
            torch.where(mask.view(-1, *[1] * (f.ndim - 1)), f, c)
            for f, c in zip(fresh, carry, strict=True)
        )

    def run(k: int) -> list[torch.Tensor]:
        theta, state, target, obs, mean, cov, step = reset(None, None)
        carry = (theta, state, target, obs, mean, cov, step)
        trajectory = []
        for _ in range(k):
            theta, state, target, obs, mean, cov, step = carry
            features = model.belief_features(mean, cov, target, step, theta)
            action = actor(features)
            stop = model.stops(action, step)
            reward = model.reward(state, target, action, stop, theta)
            trajectory.append((*carry, features, action, reward))
            state = model.transition(state, action, theta) + noise(
                model.process_cov(state, action, theta)
            )
            obs = model.observe(state, theta) + noise(model.observation_cov(state, theta))
            mean, cov = ekf_step(model, mean, cov, action, obs, theta)
            step = step + 1
            done = (stop | (step >= model.max_steps)).squeeze(-1)
            carry = (theta, state, target, obs, mean, cov, step)
            trajectory[-1] += (*carry, done)
            if done.any():
                carry = reset(done, carry)
        return [torch.stack(column, 1) for column in zip(*trajectory, strict=True)]

    with torch.no_grad():
        run(3)
        start = time.perf_counter()
        run(steps)
        return n * steps / (time.perf_counter() - start)


def gym_rate(n: int, steps: int, actor: torch.nn.Module, model: Firefly2DModel, seed: int) -> float:
    """Env-steps/s of gymnasium's ``SyncVectorEnv`` over the adapter, actor on the batch."""
    envs = gym.vector.SyncVectorEnv([lambda: Firefly2DGymEnv(model=model) for _ in range(n)])
    obs, _ = envs.reset(seed=seed)
    with torch.no_grad():
        obs, *_ = envs.step(actor(torch.from_numpy(obs)).numpy().astype(np.float32))  # warm-up
        start = time.perf_counter()
        for _ in range(steps):
            action = actor(torch.from_numpy(obs)).numpy()
            obs, *_ = envs.step(action.astype(np.float32))
        rate = n * steps / (time.perf_counter() - start)
    envs.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps, gymnasium to N=1024")
    parser.add_argument("--threads", type=integer(), default=1, help="torch threads")
    parser.add_argument(
        "--repeats", type=integer(), default=None, help="best of this many runs (3; 1 with --quick)"
    )
    parser.add_argument("--seed", type=integer(0), default=0, help="seed of the actor, θ and noise")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    torch.manual_seed(args.seed)
    model = Firefly2DModel()
    actor = make_actor(model)
    sizes = [1, 64, 1024, 4096]
    steps = {1: 200, 64: 200, 1024: 100, 4096: 50}
    gym_steps = {1: 200, 64: 20, 1024: 3, 4096: 2}
    if args.quick:
        steps = {k: max(v // 4, 10) for k, v in steps.items()}
        gym_steps = {1: 50, 64: 5, 1024: 2}
    repeats = args.repeats or (1 if args.quick else 3)
    rows = {}
    print(
        f"{'N':>6} {'torchrl':>12} {'plain':>12} {'gymnasium':>12}   env-steps/s "
        f"({args.threads} thread{'s' if args.threads > 1 else ''})"
    )
    for n in sizes:
        t = p = g = 0.0
        for _ in range(repeats):  # interleaved, so that load changes hit every path
            t = max(t, torchrl_rate(n, steps[n], actor, model, args.seed))
            p = max(p, plain_rate(n, steps[n], actor, model, args.seed))
            if n in gym_steps:
                g = max(g, gym_rate(n, gym_steps[n], actor, model, args.seed))
        g = g if n in gym_steps else float("nan")
        rows[n] = (t, p, g)
        print(f"{n:>6} {t:>12,.0f} {p:>12,.0f} {g:>12,.0f}", flush=True)
    t, p, g = rows[1024]
    print(
        f"N=1024: torchrl / plain = {t / p:.2f} (goal >= 0.6); "
        f"torchrl / gymnasium = {t / g:.1f} (goal >= 10)"
    )


if __name__ == "__main__":
    main()
