"""Observed Fisher information and the intervals it gives.

The Hessian of the negative log-likelihood at θ̂ is taken in the unconstrained coordinates the
fit moves in; its inverse is the covariance there. 95% intervals are formed there and mapped
back through the (monotone) transform, so they respect the bounds of θ. A parameter whose
standard deviation spans more than a quarter of its prior range is flagged as not identified.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from irc_torchrl.theta import ThetaSpace

__all__ = ["batched_hessian", "Intervals", "fisher_intervals"]

#: two-sided 95% normal quantile
Z95 = 1.959963984540054


def batched_hessian(
    fn: Callable[[torch.Tensor], torch.Tensor], params: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Values ``[n]``, gradients ``[n, p]`` and Hessians ``[n, p, p]`` of independent rows.

    ``fn`` maps ``[n, p]`` to ``[n]`` and row ``i`` of the output depends only on row ``i``
    of the input, so ``p`` double-backward passes give every row's Hessian at once.
    """
    params = params.detach().requires_grad_(True)
    with torch.enable_grad():
        value = fn(params)
        (grad,) = torch.autograd.grad(value.sum(), params, create_graph=True)
        rows = [
            torch.autograd.grad(grad[:, j].sum(), params, retain_graph=j + 1 < params.shape[1])[0]
            for j in range(params.shape[1])
        ]
    hessian = torch.stack(rows, 1)
    return value.detach(), grad.detach(), 0.5 * (hessian + hessian.transpose(1, 2)).detach()


@dataclass
class Intervals:
    """θ̂ with standard deviations and 95% intervals, natural units, ``[n, d]`` each."""

    std: torch.Tensor
    low: torch.Tensor
    high: torch.Tensor
    identified: torch.Tensor
    covariance: torch.Tensor


def fisher_intervals(
    space: ThetaSpace, theta_hat: torch.Tensor, theta_free_hat: torch.Tensor, hessian: torch.Tensor
) -> Intervals:
    """Intervals for the free parameters from the Hessian over ``[free θ, nuisance]``.

    Fixed parameters get zero width. ``hessian`` is ``[n, p, p]`` with the free θ first.
    """
    n, d = theta_hat.shape
    free = space.free_mask
    k = int(free.sum())
    eigval, eigvec = torch.linalg.eigh(hessian)
    positive = eigval > 1e-10 * eigval.abs().amax(-1, keepdim=True).clamp_min(1e-300)
    inv_eig = torch.where(
        positive, 1 / eigval.clamp_min(1e-300), torch.full_like(eigval, torch.inf)
    )
    cov_u = (eigvec * inv_eig.nan_to_num(posinf=1e12).unsqueeze(-2)) @ eigvec.transpose(-1, -2)
    var_u = cov_u.diagonal(dim1=-2, dim2=-1)[:, :k]
    degenerate = ~positive.all(-1, keepdim=True)
    sd_u = torch.where(degenerate, torch.full_like(var_u, torch.inf), var_u.clamp_min(0).sqrt())
    # dθ/du of the scaled logit, for the delta-method standard deviation in natural units
    low, high = space.low(theta_hat.dtype)[free], space.high(theta_hat.dtype)[free]
    slope = (theta_hat[:, free] - low) * (high - theta_hat[:, free]) / (high - low)
    std_free = (sd_u * slope).nan_to_num(posinf=torch.inf)
    ci_low_free = space.from_unconstrained(_embed(space, theta_free_hat - Z95 * sd_u, n))[:, free]
    ci_high_free = space.from_unconstrained(_embed(space, theta_free_hat + Z95 * sd_u, n))[:, free]
    std = torch.zeros(n, d, dtype=theta_hat.dtype)
    std[:, free] = std_free
    ci_low, ci_high = theta_hat.clone(), theta_hat.clone()
    ci_low[:, free], ci_high[:, free] = ci_low_free, ci_high_free
    normalised_sd = 2 * std / (space.high(theta_hat.dtype) - space.low(theta_hat.dtype))
    identified = (normalised_sd < 0.5) & ~degenerate
    covariance = cov_u[:, :k, :k] * slope.unsqueeze(-1) * slope.unsqueeze(-2)
    return Intervals(
        std=std, low=ci_low, high=ci_high, identified=identified, covariance=covariance
    )


def _embed(space: ThetaSpace, u_free: torch.Tensor, n: int) -> torch.Tensor:
    """Unconstrained ``[n, d]`` with the free coordinates set (the rest are irrelevant zeros)."""
    u = torch.zeros(n, space.dim, dtype=u_free.dtype)
    u[:, space.free_mask] = u_free.clamp(-40, 40)
    return u
