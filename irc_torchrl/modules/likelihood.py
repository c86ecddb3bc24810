"""Action likelihood models: how a rational agent's recorded action depends on its belief.

Each model scores ``log p(action | features, nuisance)`` for a frozen policy or value network,
with nuisance parameters (noise of the agent's choices) fitted beside θ. ``log_prob_of_draw``
scores an action drawn from the model itself instead of the recorded one: its gradient in θ is a
sampled score, whose outer product estimates the Fisher information (Fisher scoring).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from tensordict.nn import TensorDictModuleBase
from torch import nn

from irc_torchrl.checks import positive_number, real
from irc_torchrl.envs.belief import symmetrise
from irc_torchrl.envs.model import bounded_box
from irc_torchrl.modules.lapse import lapse_draw

__all__ = [
    "LAPSE_MAX",
    "BoltzmannActionModel",
    "CensoredGaussianActionModel",
    "gaussian_log_prob_of_draw",
]

#: standard deviations beyond which an action's innovation moves the latent's mean no further
#: (a gated update): far outside its predictive, the Gaussian update's step is extrapolation,
#: and iterated it made the outer filter chaotic (gradients of 1e16 and more over 100 steps
#: at 1e-3 motor noise); simulated agents' innovations stay within about 12
_INNOVATION_GATE = 30.0

#: the largest lapse rate a fit may reach (its coordinate is a logit scaled to (0, LAPSE_MAX)):
#: beyond half, lapses would explain the actions better than the belief does
LAPSE_MAX = 0.5


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
    lapse: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """``Σ log p(ã)`` over the (scored) last dim for ``ã ~ N(mean, var)`` drawn and held fixed.

    Its gradient is ``(∂mean)ᵀ ε/σ + (∂var)ᵀ (ε² − 1)/(2 var)`` with ``ε ~ N(0, 1)``: a score
    whose expected outer product is the Gaussian's Fisher information. With ``lapse``
    (``log ε``, ``log(1 − ε)`` broadcasting against ``mean``, and the bounds ``low``,
    ``high``) each dimension is instead drawn, with probability ε, uniformly over the bounds
    widened by half their width on each side, and scored under that mixture (unclipped), so
    the score carries the lapse rate's information too.
    """

    def draw_like(sample: Callable[..., torch.Tensor]) -> torch.Tensor:
        kind = {"dtype": mean.dtype, "generator": generator, "device": generator.device}
        return sample(mean.shape, **kind).to(mean.device)

    draw = mean + var.sqrt() * draw_like(torch.randn)
    if lapse is not None:
        log_lapse, log_keep, low, high = lapse
        width = high - low
        lapsed = draw_like(torch.rand) < log_lapse.detach().exp()
        draw = torch.where(lapsed, lapse_draw(low, high, draw_like(torch.rand)), draw)
    draw = draw.detach()
    logp = -0.5 * (draw - mean) ** 2 / var - 0.5 * var.log() - 0.5 * math.log(2 * math.pi)
    if lapse is not None:
        # the lapse's density is 1/(2 width) on its support only: a Gaussian draw beyond it
        # (a wide predictive at a bound) is scored by the Gaussian alone, so the score's
        # mean stays zero
        inside = (draw >= low - width / 2) & (draw <= high + width / 2)
        uniform = torch.where(inside, log_lapse - torch.log(2 * width), -torch.inf)
        logp = torch.logaddexp(logp + log_keep, uniform)
    return _scored_sum(logp, scored)


class BoltzmannActionModel(nn.Module):
    """Discrete actions drawn from ``softmax(Q(b, ·, θ) / τ)``; the nuisance is ``log τ``.

    Scores by a frozen copy of ``q_network``, taken when it is built."""

    nuisance_names = ("log_temperature",)
    nuisance_bounded = (False,)

    def __init__(self, q_network: nn.Module, temperature: float = 0.5) -> None:
        super().__init__()
        temperature = positive_number("temperature", temperature)
        # a frozen copy: the caller's network stays trainable (and leaves this model as it is)
        self.q_network = copy.deepcopy(q_network).requires_grad_(False)
        self.nuisance_init = torch.tensor(
            [math.log(temperature)], dtype=torch.float32, device="cpu"
        )

    def temperature(self, nuisance: torch.Tensor) -> torch.Tensor:
        """The softmax temperatures ``[*B]`` of nuisance rows ``[*B, 1]``."""
        return nuisance[..., 0].exp()

    def logits(self, features: torch.Tensor, nuisance: torch.Tensor) -> torch.Tensor:
        """Action logits ``Q / τ``, ``[*B, n_actions]``; ``nuisance`` broadcasts against ``*B``."""
        return self.q_network(features) / self.temperature(nuisance).unsqueeze(-1)

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
        # drawn where the generator lives (a fit's is on the CPU), as the Gaussian draws are
        probs = logp.detach().exp().reshape(-1, logp.shape[-1]).to(generator.device)
        draw = torch.multinomial(probs, 1, generator=generator).to(logp.device)
        return logp.gather(-1, draw.view(*logp.shape[:-1], 1)).squeeze(-1)


def _mix_lapse(
    logp: torch.Tensor,
    clipped: torch.Tensor,
    width: torch.Tensor,
    logs: tuple[torch.Tensor, torch.Tensor] | None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``log p`` of the lapse mixture (``logs``: ``log ε``, ``log(1 − ε)``), and the model's
    responsibility for the action (``None`` without lapses: it is responsible for each)."""
    if logs is None:
        return logp, None
    log_lapse, log_keep = logs
    lapse = torch.where(clipped, math.log(0.25), -torch.log(2 * width).expand_as(logp))
    model = logp + log_keep
    mixed = torch.logaddexp(model, lapse + log_lapse)
    return mixed, (model - mixed).exp()


def _tail_where_clipped(clipped: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """``z`` (a bound's distance from the mean, in stds) where the action is ``clipped``,
    0 elsewhere: the tail's terms are read at clipped actions only, and an unbounded box's
    bound (±3e38, the dtype's extreme) puts the others where ``log Φ`` has an infinite slope,
    which the zero gradient of an unread term would turn into NaN (0 × inf)."""
    return torch.where(clipped, z, torch.zeros_like(z))


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
    standard deviation per action dimension (then the lapse rate's logit, when it is fitted).

    With ``lapse`` > 0 each action dimension is, with that probability, unrelated to the
    belief: drawn uniformly over the bounds widened by half their width on each side, then
    clipped (density ``1/(2 width)`` inside, mass 1/4 at each bound). A lapse caps what one
    action can cost, so the few actions a Gaussian approximation of the agent's belief
    cannot explain (near a decision boundary) do not dominate the fit; it costs about
    ``lapse`` nats per scored action dimension where there are none. With ``fit_lapse`` the
    rate is a nuisance parameter too (``lapse`` is where its fit starts): its coordinate is a
    logit scaled to ``(0, LAPSE_MAX)``, bounded in the fit like θ's.

    Args:
        actor: maps belief features ``[*B, df]`` to the noise-free action ``[*B, da]``; the
            model scores actions by a frozen copy of it, taken here.
        low, high: the action bounds, ``[da]``.
        motor_noise: the initial motor-noise standard deviation.
        atol: how close to a bound a recorded action counts as clipped.
        lapse: the lapse probability, in ``[0, 1)`` (in ``(0, LAPSE_MAX)`` when fitted).
        fit_lapse: fit the lapse rate per agent beside the motor noise.
    """

    def __init__(
        self,
        actor: nn.Module,
        low: torch.Tensor,
        high: torch.Tensor,
        motor_noise: float = 0.1,
        atol: float = 1e-6,
        lapse: float = 0.0,
        fit_lapse: bool = False,
    ) -> None:
        super().__init__()
        if isinstance(actor, TensorDictModuleBase):
            raise TypeError(
                f"actor: expected a network of belief features (a tensor in, the action out), "
                f"got a TensorDict module ({type(actor).__name__}, as load_ensemble_policy "
                "returns): wrap it, FeaturePolicy(actor), or build the whole action model "
                "with censored_action_model(actor, model)"
            )
        lapse = real("lapse", lapse)
        if not 0 <= lapse < 1:
            raise ValueError(f"lapse: expected a probability in [0, 1), got {lapse}")
        if not isinstance(fit_lapse, bool):
            raise TypeError(f"fit_lapse: expected a bool, got {fit_lapse!r}")
        if fit_lapse and not 0 < lapse < LAPSE_MAX:
            raise ValueError(
                f"lapse: expected the fitted rate's start in (0, {LAPSE_MAX}), got {lapse}"
            )
        motor_noise = positive_number("motor_noise", motor_noise)
        if isinstance(atol, bool) or not isinstance(atol, (int, float)) or not 0 <= atol < 1:
            raise ValueError(f"atol: expected a tolerance in [0, 1), got {atol!r}")
        self.lapse = lapse
        self.fit_lapse = fit_lapse
        # a frozen copy: the caller's actor stays trainable (and leaves this model as it is)
        self.actor = copy.deepcopy(actor).requires_grad_(False)
        for name, bound in (("low", low), ("high", high)):
            where = bound.device if isinstance(bound, torch.Tensor) else "cpu"
            self.register_buffer(name, torch.as_tensor(bound, dtype=torch.float64, device=where))
        if (
            self.low.ndim != 1
            or self.low.shape != self.high.shape
            or not (torch.isfinite(self.low).all() and torch.isfinite(self.high).all())
            or not (self.low < self.high).all()
        ):
            raise ValueError(
                f"low, high: expected finite action bounds [da] with low < high, got "
                f"{self.low.tolist()} and {self.high.tolist()}"
            )
        if lapse and not bounded_box(self.low, self.high):
            raise ValueError(
                "lapse: a lapse is uniform over the action bounds, and these are an unbounded "
                "spec's (the dtype's extremes); expected lapse=0 for unbounded actions"
            )
        self.atol = atol
        da = self.low.numel()
        names = [f"log_motor_noise_{i}" for i in range(da)]
        init = [math.log(motor_noise)] * da
        if fit_lapse:
            names.append("logit_lapse")
            init.append(math.log(lapse / (LAPSE_MAX - lapse)))
        self.nuisance_names = tuple(names)
        # float32 whatever torch's default dtype: a fit starts from one point
        self.nuisance_init = torch.tensor(init, dtype=torch.float32, device="cpu")
        #: which nuisance coordinates are bounded logits (held within the fit's bounds)
        self.nuisance_bounded = (False,) * da + (True,) * fit_lapse

    def motor_noise(self, nuisance: torch.Tensor) -> torch.Tensor:
        """The motor-noise standard deviations ``[*B, da]`` of nuisance rows ``[*B, dn]``."""
        return nuisance[..., : self.low.numel()].exp()

    def _motor_variance(self, nuisance: torch.Tensor) -> torch.Tensor:
        return (2 * nuisance[..., : self.low.numel()]).exp()

    def lapse_rate(self, nuisance: torch.Tensor) -> torch.Tensor:
        """The lapse rate ``[*B]`` of nuisance rows ``[*B, dn]``."""
        if self.fit_lapse:
            return LAPSE_MAX * torch.sigmoid(nuisance[..., -1])
        return torch.full_like(nuisance[..., 0], self.lapse)

    def _lapse_logs(self, nuisance: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``log ε`` and ``log(1 − ε)``, ``[*B]`` (``None`` where nothing lapses)."""
        if self.fit_lapse:
            u = nuisance[..., -1]
            return math.log(LAPSE_MAX) + F.logsigmoid(u), torch.log1p(-LAPSE_MAX * u.sigmoid())
        if not self.lapse:
            return None
        ones = torch.ones_like(nuisance[..., 0])
        return ones * math.log(self.lapse), ones * math.log1p(-self.lapse)

    def log_prob(
        self,
        features: torch.Tensor,
        action: torch.Tensor,
        nuisance: torch.Tensor,
        scored: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``log p(action)`` summed over the ``scored`` action dimensions (all), ``[*B]``."""
        mean = self.actor(features).to(features.dtype)
        std = self.motor_noise(nuisance)
        low, high = self.low.to(features.dtype), self.high.to(features.dtype)
        z = (action - mean) / std
        density = _standard_log_density(z, std)
        lower, upper = action <= low + self.atol, action >= high - self.atol
        # each tail at its clipped actions only (see _tail_where_clipped)
        below = torch.special.log_ndtr(_tail_where_clipped(lower, (low - mean) / std))
        above = torch.special.log_ndtr(_tail_where_clipped(upper, (mean - high) / std))
        logp = torch.where(upper, above, torch.where(lower, below, density))
        logs = self._lapse_logs(nuisance)
        if logs is not None:
            logs = tuple(x.unsqueeze(-1) for x in logs)
        logp, _ = _mix_lapse(logp, lower | upper, high - low, logs)
        return _scored_sum(logp, scored)

    def log_prob_of_draw(
        self,
        features: torch.Tensor,
        nuisance: torch.Tensor,
        generator: torch.Generator,
        scored: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``log p(ã)`` of an action drawn from the model (held fixed), ``[*B]``: unclipped
        (its score shapes the fit's steps, not θ̂)."""
        mean = self.actor(features).to(features.dtype)
        var = self._motor_variance(nuisance).expand_as(mean)
        return self.log_prob_of_gaussian_draw(mean, var, nuisance, generator, scored)

    def log_prob_of_gaussian_draw(
        self,
        mean: torch.Tensor,
        var: torch.Tensor,
        nuisance: torch.Tensor,
        generator: torch.Generator,
        scored: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """:func:`gaussian_log_prob_of_draw` of a predictive ``N(mean, var)`` ``[*B, da]``,
        with this model's lapses at the rate of ``nuisance`` ``[*B, dn]``."""
        logs = self._lapse_logs(nuisance)
        if logs is not None:
            low, high = self.low.to(mean.dtype), self.high.to(mean.dtype)
            logs = (*(x.unsqueeze(-1) for x in logs), low, high)
        return gaussian_log_prob_of_draw(mean, var, generator, scored, logs)

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
            nuisance: ``[*B, dn]``: log motor-noise standard deviations, then
                ``logit_lapse`` when the rate is fitted.
            scored: which action dimensions to score and condition on, ``[*B, da]``; all
                when ``None``.

        Returns:
            ``log p(action)`` ``[*B]``, the shift of ``z``'s mean ``[*B, dz]`` and its
            covariance ``[*B, dz, dz]`` given the action, and the predictive mean and variance
            of each action dimension (given the dimensions before it), ``[*B, da]`` each.
        """
        low, high = self.low.to(mean.dtype), self.high.to(mean.dtype)
        noise_var = self._motor_variance(nuisance)
        logs = self._lapse_logs(nuisance)
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
            clipped = upper | lower
            alpha = _tail_where_clipped(clipped, torch.where(lower, m - low[i], high[i] - m) / std)
            tail = torch.special.log_ndtr(-alpha)
            ratio = _mills_ratio(alpha)
            keep = torch.ones_like(m) if scored is None else scored[..., i].to(m.dtype)
            step_logp, weight = _mix_lapse(
                torch.where(clipped, tail, interior), clipped, high[i] - low[i], logs
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
            cov = symmetrise(cov)
            if i + 1 < mean.shape[-1]:  # what the next dimensions are conditioned on
                shift_action = shift_action + cov_y * moved
                cross = cross - cov_z.unsqueeze(-1) * cov_y.unsqueeze(-2) * shrink
                cov_action = cov_action - cov_y.unsqueeze(-1) * cov_y.unsqueeze(-2) * shrink
            means.append(m)
            variances.append(var)
        return logp, shift, cov, (torch.stack(means, -1), torch.stack(variances, -1))
