"""The paper's factorised θ-conditioned Q: ``Q(b, a, θ) = Σ_km w[a,k,m] φ_k(b) ψ_m(θ)``.

``φ`` and ``ψ`` are random shallow networks (fixed after construction); only the weights ``w``
are learned, by least squares, which makes the fit a linear problem (fitted Q-iteration).
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["RandomBasis", "FactorisedQ"]


class RandomBasis(nn.Module):
    """A fixed random one-layer network ``tanh(x W + c)``, plus a constant feature."""

    def __init__(
        self, in_features: int, n_basis: int, scale: float, generator: torch.Generator
    ) -> None:
        super().__init__()
        # drawn where the generator is (the CPU), whatever the default device
        weight = scale * torch.randn(
            in_features, n_basis - 1, generator=generator, device=generator.device
        )
        bias = scale * (
            2 * torch.rand(n_basis - 1, generator=generator, device=generator.device) - 1
        )
        self.register_buffer("weight", weight)
        self.register_buffer("bias", bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The basis ``[1, tanh(x W + b)]``: a constant, then the random features."""
        h = torch.tanh(x @ self.weight.to(x.dtype) + self.bias.to(x.dtype))
        return torch.cat([h.new_ones(*h.shape[:-1], 1), h], -1)


def regressors(phi: torch.Tensor, psi: torch.Tensor) -> torch.Tensor:
    """``φ ⊗ ψ`` per row, ``[*B, K·M]``, from the bases ``[*B, K]`` and ``[*B, M]``."""
    return (phi.unsqueeze(-1) * psi.unsqueeze(-2)).flatten(-2)


class FactorisedQ(nn.Module):
    """Q values ``[*B, n_actions]`` from ``features = [belief features, normalised θ]``.

    Args:
        belief_dim: how many leading feature entries describe the belief (input of ``φ``).
        theta_dim: how many trailing entries are normalised θ (input of ``ψ``).
        n_actions: number of discrete actions.
        n_belief_basis, n_theta_basis: sizes of ``φ`` and ``ψ`` (constant feature included).
        belief_scale, theta_scale: spread of the random input weights.
        seed: seed of the random bases.
    """

    def __init__(
        self,
        belief_dim: int,
        theta_dim: int,
        n_actions: int,
        n_belief_basis: int = 64,
        n_theta_basis: int = 16,
        belief_scale: float = 3.0,
        theta_scale: float = 1.5,
        seed: int = 0,
    ) -> None:
        super().__init__()
        generator = torch.Generator().manual_seed(seed)
        self.belief_dim = belief_dim
        self.phi = RandomBasis(belief_dim, n_belief_basis, belief_scale, generator)
        self.psi = RandomBasis(theta_dim, n_theta_basis, theta_scale, generator)
        self.weight = nn.Parameter(
            torch.zeros(n_actions, n_belief_basis, n_theta_basis, device=generator.device)
        )

    @property
    def n_actions(self) -> int:
        """How many discrete actions Q scores."""
        return self.weight.shape[0]

    def design(self, features: torch.Tensor) -> torch.Tensor:
        """The regressors ``φ(b) ⊗ ψ(θ)``, ``[*B, K·M]``: Q is linear in them for each action."""
        phi = self.phi(features[..., : self.belief_dim])
        return regressors(phi, self.psi(features[..., self.belief_dim :]))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """``Q(b, a; θ)`` of every action, ``[*B, n_actions]``."""
        phi = self.phi(features[..., : self.belief_dim])
        psi = self.psi(features[..., self.belief_dim :])
        # contract ψ first: never materialise the [*B, a, k, m] outer product
        weighted = torch.einsum("akm,...m->...ak", self.weight.to(features.dtype), psi)
        return (weighted * phi.unsqueeze(-2)).sum(-1)
