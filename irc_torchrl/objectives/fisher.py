"""Observed Fisher information and the intervals it gives.

The Hessian of the negative log-likelihood at θ̂ is taken in the unconstrained coordinates the
fit moves in; its inverse is the covariance there. 95% intervals are formed there and mapped
back through the (monotone) transform, so they respect the bounds of θ. A parameter whose
interval spans more than half of its prior range is flagged as not identified;
one that loads on a direction of zero or negative curvature (e.g. θ̂ on a bound) has no interval
(infinite standard deviation, the whole range), while the others keep theirs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from irc_torchrl.envs.belief import symmetrise
from irc_torchrl.theta import ThetaSpace

__all__ = [
    "Z95",
    "batched_hessian",
    "Intervals",
    "fisher_intervals",
    "narrow",
    "observed_covariance",
]

#: two-sided 95% normal quantile
Z95 = 1.959963984540054


def batched_hessian(
    fn: Callable[[torch.Tensor], torch.Tensor], params: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Values ``[n]``, gradients ``[n, p]`` and Hessians ``[n, p, p]`` of independent rows.

    ``fn`` maps ``[n, p]`` to ``[n]`` and row ``i`` of the output depends only on row ``i``
    of the input, so one double-backward pass per parameter, all ``p`` of them batched
    (``is_grads_batched``), gives every row's Hessian at once.
    """
    params = params.detach().requires_grad_(True)
    n, p = params.shape
    with torch.enable_grad():
        value = fn(params)
        (grad,) = torch.autograd.grad(value.sum(), params, create_graph=True)
        basis = torch.eye(p, dtype=grad.dtype, device=grad.device).unsqueeze(1).expand(p, n, p)
        (columns,) = torch.autograd.grad(grad, params, basis, is_grads_batched=True)
    hessian = columns.movedim(0, 1)
    return value.detach(), grad.detach(), symmetrise(hessian).detach()


@dataclass
class Intervals:
    """θ̂'s standard deviations ``std``, 95% intervals ``low``–``high`` and ``identified``
    flags (the interval spans less than half the prior range), natural units, ``[n, d]`` each
    (a fixed parameter: zero width, identified), and ``covariance`` ``[n, k, k]`` of the ``k``
    free parameters (delta method; infinite in the row and column of a parameter without an
    interval, whose ``std`` is infinite)."""

    std: torch.Tensor
    low: torch.Tensor
    high: torch.Tensor
    identified: torch.Tensor
    covariance: torch.Tensor
    #: where ``low`` and ``high`` are the profile likelihood's endpoints, not the Wald ones
    profiled: torch.Tensor

    def select(self, rows: torch.Tensor) -> Intervals:
        """The agents ``rows`` (an index or mask)."""
        return Intervals(*(getattr(self, f.name)[rows] for f in dataclasses.fields(self)))

    def correlation(self, free: torch.Tensor) -> torch.Tensor:
        """The correlations ``[n, k, k]`` of the ``free`` parameters (``[d]`` bool: how far the
        data trade one off against another); NaN in the rows and columns of a parameter the
        data do not bound."""
        sd = self.covariance.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
        bounded = torch.isfinite(self.std[:, free.to(self.std.device)]) & (sd > 0)
        pair = bounded.unsqueeze(-1) & bounded.unsqueeze(-2)
        scale = (sd.unsqueeze(-1) * sd.unsqueeze(-2)).clamp_min(1e-300)
        r = (self.covariance / scale).clamp(-1, 1)  # |r| ≤ 1 beyond rounding
        return torch.where(pair, r, torch.full_like(scale, torch.nan))

    def to(self, device: torch.device | str) -> Intervals:
        """These intervals on ``device``."""
        return Intervals(*(getattr(self, f.name).to(device) for f in dataclasses.fields(self)))

    def cpu(self) -> Intervals:
        """These intervals on the CPU."""
        return self.to("cpu")

    @staticmethod
    def cat(parts: Sequence[Intervals]) -> Intervals:
        """The agents of ``parts``, in order, as one batch."""
        return Intervals(
            *(torch.cat([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(Intervals))
        )


def observed_covariance(hessian: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The inverse of a Hessian ``[n, p, p]`` over its positive curvature, and which
    coordinates it leaves unbounded ``[n, p]``: a direction of zero or negative curvature
    leaves the coordinates that load on it without an interval (infinite), and only those.
    The Hessian's symmetric part is used (``eigh`` alone would read one triangle)."""
    eigval, eigvec = torch.linalg.eigh(symmetrise(hessian))
    positive = eigval > 1e-10 * eigval.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    loading = eigvec**2  # [n, p coordinates, p directions]
    unbounded = ((loading > 1e-8) & ~positive.unsqueeze(1)).any(-1)
    inv_eig = torch.where(positive, 1 / eigval.clamp_min(1e-300), torch.zeros_like(eigval))
    return (eigvec * inv_eig.unsqueeze(-2)) @ eigvec.transpose(-1, -2), unbounded


def fisher_intervals(
    space: ThetaSpace,
    theta_hat: torch.Tensor,
    theta_free_hat: torch.Tensor,
    hessian: torch.Tensor,
    meat: torch.Tensor | None = None,
) -> Intervals:
    """Intervals for the free parameters from the Hessian over ``[free θ, nuisance]``.

    Fixed parameters get zero width. ``hessian`` is ``[n, p, p]`` with the free θ first. With
    ``meat`` (``Σ sᵢ sᵢᵀ`` over independent trials' scores, ``[n, p, p]``) the covariance is the
    sandwich ``H⁻¹ (Σ sᵢ sᵢᵀ) H⁻¹``, honest where the likelihood is an approximation.
    """
    n, d = theta_hat.shape
    device = theta_hat.device
    free = space.free_mask.to(device)
    k = int(free.sum())
    for name, matrix in (("hessian", hessian), ("meat", meat)):
        if matrix is not None and (
            matrix.ndim != 3 or matrix.shape[0] != n or matrix.shape[1:] != hessian.shape[-2:]
        ):
            raise ValueError(
                f"{name}: expected one [p, p] matrix per agent, [{n}, p, p] with p ≥ {k}, "
                f"got {list(matrix.shape)}"
            )
    if hessian.shape[-1] != hessian.shape[-2] or hessian.shape[-1] < k:
        raise ValueError(f"hessian: expected [{n}, p, p] with p ≥ {k}, got {list(hessian.shape)}")
    cov_u, unbounded = observed_covariance(hessian)
    unbounded = unbounded[:, :k]
    if meat is not None:
        cov_u = cov_u @ meat @ cov_u
    var_u = cov_u.diagonal(dim1=-2, dim2=-1)[:, :k]
    sd_u = torch.where(unbounded, torch.full_like(var_u, torch.inf), var_u.clamp_min(0).sqrt())
    # dθ/du of the scaled logit, for the delta-method standard deviation in natural units
    low, high = (b(theta_hat.dtype, device)[free] for b in (space.low, space.high))
    slope = (theta_hat[:, free] - low) * (high - theta_hat[:, free]) / (high - low)
    std_free = torch.where(unbounded, torch.full_like(sd_u, torch.inf), sd_u * slope)
    ci_low_free = space.from_unconstrained(_embed(space, theta_free_hat - Z95 * sd_u, n))[:, free]
    ci_high_free = space.from_unconstrained(_embed(space, theta_free_hat + Z95 * sd_u, n))[:, free]
    std = torch.zeros(n, d, dtype=theta_hat.dtype, device=device)
    std[:, free] = std_free
    ci_low, ci_high = theta_hat.clone(), theta_hat.clone()
    ci_low[:, free], ci_high[:, free] = ci_low_free, ci_high_free
    # judged by the interval's width, not the delta-method sd, which vanishes on a bound
    identified = narrow(space, ci_low, ci_high) & torch.isfinite(std)
    covariance = cov_u[:, :k, :k] * slope.unsqueeze(-1) * slope.unsqueeze(-2)
    lost = unbounded.unsqueeze(-1) | unbounded.unsqueeze(-2)  # as a calibration's void factor
    covariance = covariance.masked_fill(lost, torch.inf)
    return Intervals(
        std=std,
        low=ci_low,
        high=ci_high,
        identified=identified,
        covariance=covariance,
        profiled=torch.zeros_like(identified),
    )


def narrow(space: ThetaSpace, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """Whether each interval spans less than half of its parameter's prior range."""
    span = space.high(low.dtype, low.device) - space.low(low.dtype, low.device)
    return (high - low) / span < 0.5


def _embed(space: ThetaSpace, u_free: torch.Tensor, n: int) -> torch.Tensor:
    """Unconstrained ``[n, d]`` with the free coordinates set (the rest are irrelevant zeros)."""
    u = torch.zeros(n, space.dim, dtype=u_free.dtype, device=u_free.device)
    u[:, space.free_mask.to(u_free.device)] = u_free.clamp(-40, 40)  # on the bound from ±40
    return u
