"""The paper's 1D "catching fireflies" task: walk left or right to a target seen once, then stop.

The agent has no observations, so its Gaussian belief over its position evolves as in the
paper, ``μ' = μ + g_a·a`` and ``σ²' = σ² + σ₀²``. Stopping within the goal radius of the
target pays ``R`` (the agent expects ``R`` times its belief's probability of that); every move
costs ``move_cost``.
Targets are drawn up to ``target_range`` away, so that under some θ the far ones are not worth
the walk.
"""

from __future__ import annotations

import math

import torch
from torchrl.data import Categorical

from irc_torchrl.checks import count, positive_number
from irc_torchrl.envs.model import TaskModel, own_theta_space
from irc_torchrl.envs.task_env import TaskEnv
from irc_torchrl.theta import Parameter, ThetaSpace

__all__ = ["Firefly1DModel", "Firefly1DEnv", "firefly1d_theta_space", "LEFT", "STOP", "RIGHT"]

LEFT, STOP, RIGHT = 0, 1, 2


def firefly1d_theta_space() -> ThetaSpace:
    """θ = (g_a, log σ₀) as in the paper; goal radius and move cost fixed by default."""
    return ThetaSpace(
        [
            Parameter("g_a", 0.5, 1.5, 1.0, "distance/step", "action gain"),
            Parameter(
                "log_sigma0", math.log(0.05), 0.0, math.log(0.3), "log distance", "process noise"
            ),
            Parameter("goal_radius", 0.5, 2.0, 1.0, "distance", "radius rewarded on stopping"),
            Parameter("move_cost", 0.05, 1.0, 0.3, "reward units", "cost of one move"),
        ],
        fixed={"goal_radius": 1.0, "move_cost": 0.3},
    )


def gaussian_interval_probability(
    mean: torch.Tensor, std: torch.Tensor, radius: torch.Tensor
) -> torch.Tensor:
    """``P(|x| < radius)`` for ``x ~ N(mean, std²)``, to an absolute error near the dtype's
    resolution (a tail of ~1e-9 rounds to 0 in float32): the reward it scales needs no more."""
    std = std.clamp_min(1e-4)
    return torch.special.ndtr((radius - mean) / std) - torch.special.ndtr((-radius - mean) / std)


class Firefly1DModel(TaskModel):
    """The 1D task. The state is the agent's position; the target's position is known at start."""

    state_dim = 1
    observation_dim = 0
    target_dim = 1
    #: one step is one time unit: recordings are read with a clock of one step per second
    dt = 1.0
    state_names = ("x",)
    state_units = ("distance",)
    #: the action is an integer index: 0 = left, 1 = stop, 2 = right
    action_names = ("action",)
    target_names = ("target_x",)
    name = "firefly1d"

    def __init__(
        self,
        target_range: float = 12.0,
        max_steps: int = 30,
        reward_value: float = 10.0,
        theta_space: ThetaSpace | None = None,
    ) -> None:
        count("max_steps", max_steps)
        positive_number("target_range", target_range)
        positive_number("reward_value", reward_value)
        self.theta_space = own_theta_space(theta_space, firefly1d_theta_space)
        self.target_range = target_range
        self.max_steps = max_steps
        self.reward_value = reward_value
        self.action_spec = Categorical(3)

    @staticmethod
    def move(action: torch.Tensor) -> torch.Tensor:
        """The step direction ``[*B, 1]`` (-1, 0, +1) of an action index."""
        return (action.long() - STOP).unsqueeze(-1)

    def initial_state(
        self, theta: torch.Tensor, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        batch = theta.shape[:-1]
        u = torch.rand(*batch, 1, generator=generator, device=theta.device, dtype=theta.dtype)
        return torch.zeros_like(u), self.target_range * (2 * u - 1)

    def transition(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        return state + self.parameter(theta, "g_a") * self.move(action).to(state.dtype)

    def transition_jacobian(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        return torch.ones(
            *torch.broadcast_shapes(state.shape[:-1], theta.shape[:-1]),
            1,
            1,
            dtype=state.dtype,
            device=state.device,
        )

    def process_cov(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        var = torch.exp(2 * self.parameter(theta, "log_sigma0"))
        return var.expand(*torch.broadcast_shapes(state.shape[:-1], theta.shape[:-1]), 1).unsqueeze(
            -1
        )

    def stops(self, action: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        return (action == STOP).unsqueeze(-1)

    def reward(
        self,
        state: torch.Tensor,
        target: torch.Tensor,
        action: torch.Tensor,
        stop: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        success = self.succeeded(state, target, stop, theta).to(state.dtype)
        return torch.where(stop, self.reward_value * success, -self.parameter(theta, "move_cost"))

    def succeeded(
        self, state: torch.Tensor, target: torch.Tensor, stop: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        """Stopped inside the goal: what the world rewards."""
        return stop & ((state - target).abs() < self.parameter(theta, "goal_radius"))

    #: the agent knows where it starts, up to this variance (positive, so σ stays differentiable)
    initial_variance = 1e-4

    def initial_belief(
        self, state: torch.Tensor, target: torch.Tensor, theta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        cov = torch.full(
            (*state.shape, 1), self.initial_variance, dtype=state.dtype, device=state.device
        )
        return state.clone(), cov

    def belief_reward(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        target: torch.Tensor,
        action: torch.Tensor,
        stop: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        p = gaussian_interval_probability(
            mean - target, cov[..., 0].sqrt(), self.parameter(theta, "goal_radius")
        )
        return torch.where(stop, self.reward_value * p, -self.parameter(theta, "move_cost"))

    belief_feature_dim = 5

    def belief_features(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        target: torch.Tensor,
        step: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        """Relative position and its size, spread, time, and the belief's goal probability."""
        relative = mean - target
        std = cov[..., 0].clamp_min(0).sqrt()
        p_goal = gaussian_interval_probability(relative, std, self.parameter(theta, "goal_radius"))
        time = step.to(mean.dtype) / self.max_steps
        batch = torch.broadcast_shapes(relative.shape[:-1], theta.shape[:-1])
        relative = relative / self.target_range
        parts = [relative, relative.abs(), std, time, p_goal, self.theta_space.normalise(theta)]
        return torch.cat([p.expand(*batch, p.shape[-1]) for p in parts], -1)


class Firefly1DEnv(TaskEnv):
    """:class:`TaskEnv` over :class:`Firefly1DModel` (see there for the task)."""

    model_class = Firefly1DModel
