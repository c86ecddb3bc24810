"""Action likelihood models: how a rational agent's recorded action depends on its belief.

Each model scores ``log p(action | features, nuisance)`` for a frozen policy or value network,
with nuisance parameters (noise of the agent's choices) fitted beside θ. ``log_prob_of_draw``
scores an action drawn from the model itself instead of the recorded one: its gradient in θ is a
sampled score, whose outer product estimates the Fisher information (Fisher scoring).
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["BoltzmannActionModel", "CensoredGaussianActionModel", "gaussian_log_prob_of_draw"]


def _scored_sum(logp: torch.Tensor, scored: torch.Tensor | None) -> torch.Tensor:
    """``logp [*B, da]`` summed over the scored action components (all when ``None``)."""
    if scored is not None:
        logp = torch.where(scored, logp, torch.zeros_like(logp))
    return logp.sum(-1)


def gaussian_log_prob_of_draw(
    mean: torch.Tensor,
    var: torch.Tensor,
    generator: torch.Generator,
    scored: torch.Tensor | None = None,
) -> torch.Tensor:
    """``Σ log N(ã; mean, var)`` over the (scored) last dim for ``ã`` drawn and held fixed.

    Its gradient is ``(∂mean)ᵀ ε/σ + (∂var)ᵀ (ε² − 1)/(2 var)`` with ``ε ~ N(0, 1)``: a score
    whose expected outer product is the Gaussian's Fisher information.
    """
    noise = torch.randn(mean.shape, dtype=mean.dtype, generator=generator).to(mean.device)
    draw = (mean + var.sqrt() * noise).detach()
    logp = -0.5 * (draw - mean) ** 2 / var - 0.5 * var.log() - 0.5 * math.log(2 * math.pi)
    return _scored_sum(logp, scored)


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

    def log_prob_of_draw(
        self, features: torch.Tensor, nuisance: torch.Tensor, generator: torch.Generator
    ) -> torch.Tensor:
        """``log p(ã)`` of an action ``ã`` drawn from the model (held fixed), ``[*B]``."""
        logp = torch.log_softmax(self.logits(features, nuisance), -1)
        draw = torch.multinomial(
            logp.detach().exp().reshape(-1, logp.shape[-1]), 1, generator=generator
        )
        return logp.gather(-1, draw.view(*logp.shape[:-1], 1)).squeeze(-1)


class CensoredGaussianActionModel(nn.Module):
    """Continuous actions: the actor's output plus Gaussian motor noise, clipped to the bounds.

    A recorded action strictly inside the bounds contributes the Gaussian density; one at a
    bound contributes the probability of the noise carrying it past the bound (a censored
    likelihood), since clipping puts a point mass there. The nuisance is the log motor-noise
    standard deviation per action dimension.

    Args:
        actor: maps belief features ``[*B, df]`` to the noise-free action ``[*B, da]``.
        low, high: the action bounds, ``[da]``.
        motor_noise: the initial motor-noise standard deviation.
        atol: how close to a bound a recorded action counts as clipped.
    """

    def __init__(
        self,
        actor: nn.Module,
        low: torch.Tensor,
        high: torch.Tensor,
        motor_noise: float = 0.1,
        atol: float = 1e-6,
    ) -> None:
        super().__init__()
        self.actor = actor.requires_grad_(False)
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float64))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float64))
        self.atol = atol
        da = self.low.numel()
        self.nuisance_names = tuple(f"log_motor_noise_{i}" for i in range(da))
        self.nuisance_init = torch.full((da,), math.log(motor_noise))

    def log_prob(
        self,
        features: torch.Tensor,
        action: torch.Tensor,
        nuisance: torch.Tensor,
        scored: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``log p(action)`` summed over the ``scored`` action dimensions (all), ``[*B]``."""
        mean = self.actor(features).to(features.dtype)
        std = nuisance.exp()
        low, high = self.low.to(features.dtype), self.high.to(features.dtype)
        z = (action - mean) / std
        density = -0.5 * z**2 - std.log() - 0.5 * math.log(2 * math.pi)
        below = torch.special.log_ndtr((low - mean) / std)
        above = torch.special.log_ndtr((mean - high) / std)
        logp = torch.where(action <= low + self.atol, below, density)
        logp = torch.where(action >= high - self.atol, above, logp)
        return _scored_sum(logp, scored)

    def log_prob_of_draw(
        self,
        features: torch.Tensor,
        nuisance: torch.Tensor,
        generator: torch.Generator,
        scored: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``log p(ã)`` of an action drawn from the model (held fixed), unclipped, ``[*B]``."""
        mean = self.actor(features).to(features.dtype)
        var = (2 * nuisance).exp().expand_as(mean)
        return gaussian_log_prob_of_draw(mean, var, generator, scored)

    def assimilate(
        self,
        mean: torch.Tensor,
        jacobian: torch.Tensor,
        cov: torch.Tensor,
        action: torch.Tensor,
        nuisance: torch.Tensor,
        scored: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Score an action whose policy input is uncertain, and condition that input on it.

        The policy's input ``z ~ N(ẑ, cov)`` is unseen; linearised, the action is
        ``mean + jacobian (z - ẑ) + noise``, clipped. Each action dimension is one scalar
        observation of ``z`` (the motor noise is independent across dimensions): interior
        values update ``z`` as a Kalman step, clipped ones as a censored (Tobit) observation
        whose posterior moments are matched.

        Args:
            mean: the policy's output at ``ẑ``, ``[*B, da]``.
            jacobian: its derivative in ``z``, ``[*B, da, dz]``.
            cov: the covariance of ``z``, ``[*B, dz, dz]``.
            action: the recorded action, ``[*B, da]``.
            nuisance: log motor-noise standard deviations, ``[*B, da]``.
            scored: which action dimensions to score and condition on, ``[*B, da]``; all
                when ``None``.

        Returns:
            ``log p(action)`` ``[*B]``, the shift of ``z``'s mean ``[*B, dz]`` and its
            covariance ``[*B, dz, dz]`` given the action, and the predictive mean and variance
            of each action dimension (given the dimensions before it), ``[*B, da]`` each.
        """
        low, high = self.low.to(mean.dtype), self.high.to(mean.dtype)
        noise_var = (2 * nuisance).exp()
        shift = torch.zeros_like(cov[..., 0])
        logp = torch.zeros_like(mean[..., 0])
        means, variances = [], []
        for i in range(mean.shape[-1]):
            j = jacobian[..., i, :]
            cov_j = (cov @ j.unsqueeze(-1)).squeeze(-1)  # Σ jᵀ
            var = (j * cov_j).sum(-1) + noise_var[..., i]
            std = var.sqrt()
            m = mean[..., i] + (j * shift).sum(-1)
            a = action[..., i]
            # interior: a Gaussian observation
            z = (a - m) / std
            interior = -0.5 * z**2 - std.log() - 0.5 * math.log(2 * math.pi)
            # clipped: P(u beyond the bound), and the moments of u given that it is beyond
            upper = a >= high[i] - self.atol
            lower = a <= low[i] + self.atol
            sign = torch.where(lower, -torch.ones_like(m), torch.ones_like(m))
            alpha = torch.where(lower, m - low[i], high[i] - m) / std
            tail = torch.special.log_ndtr(-alpha)
            ratio = torch.exp(-0.5 * alpha**2 - 0.5 * math.log(2 * math.pi) - tail)
            clipped = upper | lower
            keep = torch.ones_like(m) if scored is None else scored[..., i].to(m.dtype)
            logp = logp + keep * torch.where(clipped, tail, interior)
            moved = keep * torch.where(clipped, sign * std * ratio, a - m)
            shrink = keep * torch.where(clipped, ratio * (ratio - alpha), torch.ones_like(m))
            shift = shift + cov_j * (moved / var).unsqueeze(-1)
            cov = cov - cov_j.unsqueeze(-1) * cov_j.unsqueeze(-2) * (shrink / var)[..., None, None]
            cov = 0.5 * (cov + cov.transpose(-1, -2))
            means.append(m)
            variances.append(var)
        return logp, shift, cov, (torch.stack(means, -1), torch.stack(variances, -1))
