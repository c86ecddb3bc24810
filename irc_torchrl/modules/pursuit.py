"""A hand-written belief-pursuit controller for the 2D firefly: the floor a learned policy beats.

It turns toward where it believes the target is, drives there, and stops once it believes it
is well inside the goal. It reads only what the agent has (belief mean and θ), so it is a
legitimate policy, but it ignores uncertainty and effort: a rational agent should do better.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from irc_torchrl.envs.belief import BELIEF_MEAN
from irc_torchrl.envs.firefly2d import PHI, Firefly2DModel

__all__ = ["BeliefPursuit"]


class BeliefPursuit(TensorDictModuleBase):
    """Steer to the believed target and stop inside the goal, as a TorchRL policy.

    The belief mean is first pushed one step through the noise-free transition (the current
    velocities still move the agent before a new action acts), then:
    ``a_ω`` turns onto the target's bearing in one step if it can; ``a_v`` covers the remaining
    distance in one step at most, slowed by the cosine of the bearing; the agent stops once the
    believed distance is below ``stop_fraction`` of the goal radius.

    Args:
        model: the 2D task.
        stop_fraction: stop when the believed distance is below this fraction of the radius.
        theta_key: where the agent's θ is read.
    """

    def __init__(
        self, model: Firefly2DModel, stop_fraction: float = 0.5, theta_key: str = "theta"
    ) -> None:
        super().__init__()
        if not 0 < stop_fraction <= 1:
            raise ValueError(f"stop_fraction: expected a value in (0, 1], got {stop_fraction}")
        self.model = model
        self.stop_fraction = stop_fraction
        self.in_keys = [BELIEF_MEAN, "target", theta_key]
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the controller's ``action`` for the believed target."""
        model = self.model
        mean, target, theta = (tensordict[k] for k in self.in_keys)
        space = model.theta_space
        g_v = theta[..., space.index("g_v")].unsqueeze(-1)
        g_w = theta[..., space.index("g_w")].unsqueeze(-1)
        radius = theta[..., space.index("goal_radius")].unsqueeze(-1)
        distance_now = (target - mean[..., :2]).norm(dim=-1, keepdim=True)
        coast = model.transition(mean, torch.zeros_like(mean[..., :2]), theta)
        rel = target - coast[..., :2]
        bearing = torch.atan2(rel[..., 1:], rel[..., :1]) - coast[..., PHI : PHI + 1]
        bearing = torch.atan2(bearing.sin(), bearing.cos())
        distance = rel.norm(dim=-1, keepdim=True)
        dt = model.dt
        a_w = (bearing / (g_w * dt)).clamp(-1, 1)
        go = (distance / (g_v * dt)).clamp(max=1) * bearing.cos().clamp(min=0)
        a_v = go.clamp(min=2 * model.stop_threshold)
        stop = distance_now < self.stop_fraction * radius
        a_v = torch.where(stop, torch.zeros_like(a_v), a_v)
        tensordict.set("action", torch.cat([a_v, a_w], -1).to(mean.dtype))
        return tensordict
