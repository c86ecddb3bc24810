"""Lapses: actions unrelated to the belief, as psychophysics models inattention."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType, exploration_type

from irc_torchrl.envs.model import bounded_box

__all__ = ["Lapse", "lapse_draw"]


class Lapse(TensorDictModuleBase):
    """Replaces each action dimension, with probability ``lapse``, by a draw unrelated to the
    belief: uniform over the bounds widened by half their width on each side, then clipped.

    This is the lapse that :class:`~irc_torchrl.modules.likelihood.CensoredGaussianActionModel`
    scores (density ``1/(2 width)`` inside the bounds, mass 1/4 at each), so agents simulated
    with it are the agents that model describes. Like TorchRL's exploration modules it acts
    only when exploring (``ExplorationType.RANDOM``); its draws come from torch's global
    generator on the CPU, so a seeded rollout repeats them. ``lapse`` is one rate, or a tensor
    of them broadcasting against the action (e.g. ``[n_agents, 1, 1]``: each agent's own).
    """

    def __init__(
        self, spec: TensorSpec, lapse: float | torch.Tensor, action_key: str = "action"
    ) -> None:
        super().__init__()
        # kept on the CPU, where the draws are made (not a buffer: ``.to`` leaves it there)
        self.lapse = torch.as_tensor(lapse, dtype=torch.float32, device="cpu").detach()
        bad = ~((self.lapse >= 0) & (self.lapse < 1))
        if bad.any():
            raise ValueError(
                f"lapse: expected probabilities in [0, 1), got {self.lapse[bad][0].item():g}"
            )
        self.action_key = action_key
        self.in_keys, self.out_keys = [action_key], [action_key]
        space = getattr(spec, "space", None)
        if not (hasattr(space, "low") and hasattr(space, "high")):
            raise TypeError(f"spec: expected a bounded action spec, got {type(spec).__name__}")
        self.low, self.high = (x.detach().float().cpu() for x in (space.low, space.high))
        if not bounded_box(self.low, self.high):
            raise TypeError(
                "spec: expected a bounded action spec (a lapse is uniform over its bounds), "
                "got an unbounded one"
            )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Replace lapsed action components when exploring (never when acting greedily)."""
        if not self.lapse.any() or exploration_type() not in (ExplorationType.RANDOM, None):
            return tensordict
        action = tensordict.get(self.action_key, None)
        if action is None:
            raise KeyError(f"{self.action_key}: Lapse acts on the policy's action; none is set")
        try:
            fits = torch.broadcast_shapes(self.lapse.shape, action.shape) == action.shape
        except RuntimeError:
            fits = False
        if not fits:
            raise ValueError(
                f"lapse: expected rates broadcasting against the action {list(action.shape)}, "
                f"got shape {list(self.lapse.shape)}"
            )
        lapsed = torch.rand(action.shape, device="cpu") < self.lapse
        draw = lapse_draw(self.low, self.high, torch.rand(action.shape, device="cpu"))
        draw = draw.clamp(self.low, self.high)
        out = torch.where(lapsed.to(action.device), draw.to(action), action)
        tensordict.set(self.action_key, out)
        return tensordict


def lapse_draw(low: torch.Tensor, high: torch.Tensor, uniform: torch.Tensor) -> torch.Tensor:
    """A lapse's action from ``uniform`` draws in [0, 1): uniform over the bounds widened by half
    their width on each side (the simulated agent clips it; the likelihood scores it so)."""
    width = high - low
    return low - width / 2 + 2 * width * uniform
