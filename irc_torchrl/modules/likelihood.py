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

#: standard deviations beyond which an action's innovation moves the latent's mean no further
#: (a gated update): far outside its predictive, the Gaussian update's step is extrapolation,
#: and iterated it made the outer filter chaotic (gradients of 1e16 and more over 100 steps
#: at 1e-3 motor noise); simulated agents' innovations stay within about 12
_INNOVATION_GATE = 30.0


def _scored_sum(logp: torch.Tensor, scored: torch.Tensor | None) -> torch.Tensor:
    """``logp [*B, da]`` summed over the scored action components (all when ``None``)."""
    if scored is not None:
        logp = torch.where(scored, logp, torch.zeros_like(logp))
    return logp.sum(-1)


def _standard_log_density(z: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """``log N(x; m, std²)`` from the standardised ``z = (x − m) / std``."""
    return -0.5 * z**2 - std.log() - 0.5 * math.log(2 * math.pi)


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
    noise = torch.randn(
        mean.shape, dtype=mean.dtype, generator=generator, device=generator.device
    ).to(mean.device)
    draw = (mean + var.sqrt() * noise).detach()
    logp = -0.5 * (draw - mean) ** 2 / var - 0.5 * var.log() - 0.5 * math.log(2 * math.pi)
    return _scored_sum(logp, scored)


class BoltzmannActionModel(nn.Module):
    """Discrete actions drawn from ``softmax(Q(b, ·, θ) / τ)``; the nuisance is ``log τ``."""

    nuisance_names = ("log_temperature",)

    def __init__(self, q_network: nn.Module, temperature: float = 0.5) -> None:
        super().__init__()
        self.q_network = q_network.requires_grad_(False)
        self.nuisance_init = torch.tensor([math.log(temperature)], device="cpu")

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


def _mills_ratio(alpha: torch.Tensor) -> torch.Tensor:
    """``φ(α) / Φ(-α)``, accurate for every ``α``: beyond the mean through ``erfcx``, since
    ``exp(-α²/2 - log Φ(-α))`` loses the digits that the tail's variance factor
    ``ratio · (ratio - α) ∈ (0, 1)`` needs once ``α`` is in the thousands."""
    inside = alpha.clamp_max(0)  # both branches finite, so neither poisons the gradient
    log_tail = torch.special.log_ndtr(-inside)
    near = torch.exp(-0.5 * inside**2 - 0.5 * math.log(2 * math.pi) - log_tail)
    far = math.sqrt(2 / math.pi) / torch.special.erfcx(alpha.clamp_min(0) / math.sqrt(2))
    return torch.where(alpha > 0, far, near)


class CensoredGaussianActionModel(nn.Module):
    """Continuous actions: the actor's output plus Gaussian motor noise, clipped to the bounds.

    A recorded action strictly inside the bounds contributes the Gaussian density; one at a
    bound contributes the probability of the noise carrying it past the bound (a censored
    likelihood), since clipping puts a point mass there. The nuisance is the log motor-noise
    standard deviation per action dimension.

    With ``lapse`` > 0 each action dimension is, with that probability, unrelated to the
    belief: drawn uniformly over the bounds widened by half their width on each side, then
    clipped (density ``1/(2 width)`` inside, mass 1/4 at each bound). A lapse caps what one
    action can cost, so the few actions a Gaussian approximation of the agent's belief
    cannot explain (near a decision boundary) do not dominate the fit; it costs about
    ``lapse`` nats per scored action dimension where there are none.

    Args:
        actor: maps belief features ``[*B, df]`` to the noise-free action ``[*B, da]``.
        low, high: the action bounds, ``[da]``.
        motor_noise: the initial motor-noise standard deviation.
        atol: how close to a bound a recorded action counts as clipped.
        lapse: the lapse probability, in ``[0, 1)``.
    """

    def __init__(
        self,
        actor: nn.Module,
        low: torch.Tensor,
        high: torch.Tensor,
        motor_noise: float = 0.1,
        atol: float = 1e-6,
        lapse: float = 0.0,
    ) -> None:
        super().__init__()
        if not 0 <= lapse < 1:
            raise ValueError(f"lapse: expected a probability in [0, 1), got {lapse}")
        self.lapse = lapse
        self.actor = actor.requires_grad_(False)
        for name, bound in (("low", low), ("high", high)):
            where = bound.device if isinstance(bound, torch.Tensor) else "cpu"
            self.register_buffer(name, torch.as_tensor(bound, dtype=torch.float64, device=where))
        self.atol = atol
        da = self.low.numel()
        self.nuisance_names = tuple(f"log_motor_noise_{i}" for i in range(da))
        self.nuisance_init = torch.full((da,), math.log(motor_noise), device="cpu")

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
        density = _standard_log_density(z, std)
        below = torch.special.log_ndtr((low - mean) / std)
        above = torch.special.log_ndtr((mean - high) / std)
        lower, upper = action <= low + self.atol, action >= high - self.atol
        logp = torch.where(upper, above, torch.where(lower, below, density))
        logp, _ = self._mix_lapse(logp, lower | upper, high - low)
        return _scored_sum(logp, scored)

    def _mix_lapse(
        self, logp: torch.Tensor, clipped: torch.Tensor, width: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``log p`` of the lapse mixture, and the model's responsibility for the action
        (``None`` without a lapse: the model is responsible for every action)."""
        if not self.lapse:
            return logp, None
        lapse = torch.where(clipped, math.log(0.25), -torch.log(2 * width).expand_as(logp))
        model = logp + math.log1p(-self.lapse)
        mixed = torch.logaddexp(model, lapse + math.log(self.lapse))
        return mixed, (model - mixed).exp()

    def log_prob_of_draw(
        self,
        features: torch.Tensor,
        nuisance: torch.Tensor,
        generator: torch.Generator,
        scored: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``log p(ã)`` of an action drawn from the model (held fixed), ``[*B]``: from the
        Gaussian, unclipped and without lapses (its score shapes the fit's steps, not θ̂)."""
        mean = self.actor(features).to(features.dtype)
        var = (2 * nuisance).exp().expand_as(mean)
        return gaussian_log_prob_of_draw(mean, var, generator, scored)

    def assimilate(
        self,
        mean: torch.Tensor,
        cross: torch.Tensor,
        cov_action: torch.Tensor,
        cov: torch.Tensor,
        action: torch.Tensor,
        nuisance: torch.Tensor,
        scored: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """Score an action whose policy input is uncertain, and condition that input on it.

        The policy's input ``z ~ N(ẑ, cov)`` is unseen; its noise-free output ``y`` is taken
        jointly Gaussian with it (``mean``, ``cross`` = Cov(z, y), ``cov_action`` = Cov(y), from
        a linearisation or a cubature rule) and the action is ``clip(y + noise)``. Each action
        dimension is one scalar observation of ``(z, y)`` (the motor noise is independent
        across dimensions): interior values update it as a Kalman step, clipped ones as a
        censored (Tobit) observation whose posterior moments are matched. With a lapse the
        posterior is a mixture (conditioned, weighted by the model's responsibility, and not)
        whose moments are matched.

        Args:
            mean: the policy's predicted output, ``[*B, da]``.
            cross: its covariance with ``z``, ``[*B, dz, da]``.
            cov_action: its covariance, ``[*B, da, da]``.
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
        shift_action = torch.zeros_like(mean)
        logp = torch.zeros_like(mean[..., 0])
        means, variances = [], []
        for i in range(mean.shape[-1]):
            cov_z, cov_y = cross[..., i], cov_action[..., i]  # Cov(z, y_i), Cov(y, y_i)
            var = cov_y[..., i] + noise_var[..., i]
            std = var.sqrt()
            m = mean[..., i] + shift_action[..., i]
            a = action[..., i]
            # interior: a Gaussian observation
            z = (a - m) / std
            interior = _standard_log_density(z, std)
            # clipped: P(u beyond the bound), and the moments of u given that it is beyond
            upper = a >= high[i] - self.atol
            lower = a <= low[i] + self.atol
            sign = torch.where(lower, -torch.ones_like(m), torch.ones_like(m))
            alpha = torch.where(lower, m - low[i], high[i] - m) / std
            tail = torch.special.log_ndtr(-alpha)
            ratio = _mills_ratio(alpha)
            clipped = upper | lower
            keep = torch.ones_like(m) if scored is None else scored[..., i].to(m.dtype)
            step_logp, weight = self._mix_lapse(
                torch.where(clipped, tail, interior), clipped, high[i] - low[i]
            )
            logp = logp + keep * step_logp
            # the innovation in standard deviations (a tail's Mills ratio), gated
            gated = torch.where(
                clipped,
                sign * ratio.clamp_max(_INNOVATION_GATE),
                z.clamp(-_INNOVATION_GATE, _INNOVATION_GATE),
            )
            moved = keep * gated / std
            truncated = (ratio * (ratio - alpha)).clamp(0, 1)  # the variance a tail removes
            shrink = keep * torch.where(clipped, truncated, torch.ones_like(m)) / var
            if weight is not None:
                # a mixture of the conditioned and the unconditioned (lapse) posterior
                shrink = weight * shrink - weight * (1 - weight) * moved**2
                moved = weight * moved
            moved = moved.unsqueeze(-1)
            shift = shift + cov_z * moved
            shrink = shrink[..., None, None]
            cov = cov - cov_z.unsqueeze(-1) * cov_z.unsqueeze(-2) * shrink
            cov = 0.5 * (cov + cov.transpose(-1, -2))
            if i + 1 < mean.shape[-1]:  # what the next dimensions are conditioned on
                shift_action = shift_action + cov_y * moved
                cross = cross - cov_z.unsqueeze(-1) * cov_y.unsqueeze(-2) * shrink
                cov_action = cov_action - cov_y.unsqueeze(-1) * cov_y.unsqueeze(-2) * shrink
            means.append(m)
            variances.append(var)
        return logp, shift, cov, (torch.stack(means, -1), torch.stack(variances, -1))
