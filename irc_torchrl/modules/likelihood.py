"""Action likelihood models: how a rational agent's recorded action depends on its belief.

Each model scores ``log p(action | features, nuisance)`` for a frozen policy or value network,
with nuisance parameters (noise of the agent's choices) fitted beside θ.
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["BoltzmannActionModel"]


class BoltzmannActionModel(nn.Module):
    """Discrete actions drawn from ``softmax(Q(b, ·, θ) / τ)``; the nuisance is ``log τ``."""

    nuisance_names = ("log_temperature",)

    def __init__(self, q_network: nn.Module, temperature: float = 0.5) -> None:
        super().__init__()
        self.q_network = q_network.requires_grad_(False)
        self.nuisance_init = torch.tensor([math.log(temperature)])

    def logits(self, features: torch.Tensor, nuisance: torch.Tensor) -> torch.Tensor:
        """Action logits ``Q / τ``, ``[*B, n_actions]``; ``nuisance`` broadcasts against ``*B``."""
        return self.q_network(features) / nuisance[..., :1].exp()

    def log_prob(
        self, features: torch.Tensor, action: torch.Tensor, nuisance: torch.Tensor
    ) -> torch.Tensor:
        """``log p(action)`` for integer actions ``[*B]``."""
        logp = torch.log_softmax(self.logits(features, nuisance), -1)
        return logp.gather(-1, action.long().unsqueeze(-1)).squeeze(-1)
