"""Exact dynamic programming on the 1D task's belief MDP, the yardstick for Algorithm 1.

Without observations the 1D belief is deterministic: after ``t`` steps and ``k`` net moves the
mean sits at ``μ₀ + g_a·k`` and the variance is ``σ²_init + t·σ₀²``. Backward induction over
that lattice gives the optimal value for any θ and start exactly, with no grid interpolation.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from irc_torchrl.envs.belief import ekf_predict
from irc_torchrl.envs.firefly1d import STOP, Firefly1DModel, gaussian_interval_probability

__all__ = ["optimal_values", "greedy_returns"]


def _inputs(
    model: Firefly1DModel, theta: torch.Tensor, relative_start: torch.Tensor, gamma: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """θ ``[n_theta, d]`` and the starts ``[n_start]`` in float64, each checked first, and
    the discount ``gamma``."""
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma: expected a discount in (0, 1], got {gamma}")
    space = model.theta_space
    theta = space.validate(theta.to(torch.float64))
    if theta.ndim != 2:
        raise ValueError(f"theta: expected [n_theta, {space.dim}], got {list(theta.shape)}")
    start = torch.as_tensor(relative_start, dtype=torch.float64)
    if start.ndim != 1:
        raise ValueError(
            f"relative_start: expected a 1-D tensor [n_start], got {list(start.shape)}"
        )
    if not torch.isfinite(start).all():
        raise ValueError(f"relative_start: expected finite values [n_start], got {start.tolist()}")
    return theta, start


def optimal_values(
    model: Firefly1DModel, theta: torch.Tensor, relative_start: torch.Tensor, gamma: float = 1.0
) -> torch.Tensor:
    """Optimal ``Q(b₀, a, θ)`` at the start of a trial, ``[n_theta, n_start, 3]``.

    Args:
        theta: agent θ, ``[n_theta, d]``.
        relative_start: initial agent position minus target, ``[n_start]``.
    """
    theta, relative_start = _inputs(model, theta, relative_start, gamma)
    horizon = model.max_steps
    k = torch.arange(-horizon, horizon + 1, dtype=torch.float64)
    gain = theta[:, model.theta_space.index("g_a")].view(-1, 1, 1)
    sigma0 = theta[:, model.theta_space.index("log_sigma0")].exp().view(-1, 1, 1)
    radius = theta[:, model.theta_space.index("goal_radius")].view(-1, 1, 1)
    cost = theta[:, model.theta_space.index("move_cost")].view(-1, 1, 1)
    offset = relative_start.view(1, -1, 1) + gain * k
    value = torch.zeros_like(offset)
    blocked = torch.full_like(offset[..., :1], -torch.inf)
    for t in range(horizon - 1, -1, -1):
        stop = model.reward_value * gaussian_interval_probability(
            offset, (model.initial_variance + t * sigma0**2).sqrt(), radius
        )
        left = -cost + gamma * torch.cat([blocked, value[..., :-1]], -1)
        right = -cost + gamma * torch.cat([value[..., 1:], blocked], -1)
        q = torch.stack([left, stop, right], -1)  # the order of LEFT, STOP, RIGHT
        value = q.max(-1).values
    return q[..., horizon, :]


def greedy_returns(
    model: Firefly1DModel,
    q_values: Callable[[torch.Tensor], torch.Tensor],
    theta: torch.Tensor,
    relative_start: torch.Tensor,
    gamma: float = 1.0,
) -> torch.Tensor:
    """Expected return ``[n_theta, n_start]`` of acting greedily on ``q_values(features)``,
    each reward at step ``t`` counted ``γᵗ`` (as :func:`optimal_values` counts it).

    The belief is deterministic, so the return (under the agent's own model) is exact.
    """
    theta, relative_start = _inputs(model, theta, relative_start, gamma)
    n_theta, n_start = theta.shape[0], relative_start.shape[0]
    theta = theta.unsqueeze(1).expand(n_theta, n_start, -1)
    target = -relative_start.view(1, -1, 1).expand(n_theta, n_start, 1)
    mean, cov = model.initial_belief(torch.zeros_like(target), target, theta)
    total = torch.zeros(n_theta, n_start, dtype=torch.float64)
    alive = torch.ones(n_theta, n_start, dtype=torch.bool)
    for t in range(model.max_steps):
        step = torch.full((n_theta, n_start, 1), t)
        with torch.no_grad():
            q = q_values(model.belief_features(mean, cov, target, step, theta).float())
        if q.shape[-1] != model.action_spec.n:
            raise ValueError(
                f"q_values: expected one value per action [..., {model.action_spec.n}], "
                f"got [..., {q.shape[-1]}]"
            )
        action = q.argmax(-1)
        stop = model.stops(action, step)
        reward = model.belief_reward(mean, cov, target, action, stop, theta)[..., 0]
        total += gamma**t * torch.where(alive, reward, torch.zeros_like(reward))
        alive &= action != STOP
        mean, cov = ekf_predict(model, mean, cov, action, theta)
    return total
