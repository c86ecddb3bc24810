"""Algorithm 2: maximum-likelihood θ̂ for many agents at once, with Fisher intervals.

Every (agent, start) pair is an independent row of one batched problem. A damped Newton
(Levenberg–Marquardt) iteration in unconstrained coordinates uses each row's exact gradient and
Hessian, so rows converge at their own pace and the Hessian at θ̂ is the observed Fisher
information used for the intervals.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from irc_torchrl.data.trajectories import validate_trials
from irc_torchrl.objectives.fisher import Intervals, batched_hessian, fisher_intervals
from irc_torchrl.objectives.inverse import InverseRationalLoss

__all__ = ["FitResult", "fit_theta"]

#: the largest move of one Newton step in any unconstrained coordinate
MAX_STEP = 1.5


@dataclass
class FitResult:
    """θ̂ per agent ``[n_agents, d]`` (natural units) with intervals and fit facts."""

    theta_hat: torch.Tensor
    nuisance: torch.Tensor
    log_likelihood: torch.Tensor
    intervals: Intervals
    converged: torch.Tensor
    iterations: int
    names: list[str]

    def agent(self, i: int) -> dict:
        """One agent's result as plain Python values (the ``summary.json`` entry)."""

        def named(row: torch.Tensor) -> dict[str, float]:
            return {n: float(v) for n, v in zip(self.names, row, strict=True)}

        return {
            "theta_hat": named(self.theta_hat[i]),
            "ci_low": named(self.intervals.low[i]),
            "ci_high": named(self.intervals.high[i]),
            "std": named(self.intervals.std[i]),
            "identified": {
                n: bool(v) for n, v in zip(self.names, self.intervals.identified[i], strict=True)
            },
            "log_likelihood": float(self.log_likelihood[i]),
            "converged": bool(self.converged[i]),
        }


def fit_theta(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    n_starts: int = 4,
    n_screen: int = 64,
    max_iter: int = 40,
    tol: float = 1e-6,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> FitResult:
    """Fit θ for every agent in ``trials`` (``[n_agents, n_trials, T]``).

    ``n_screen`` candidates (the prior's default and draws from the prior, the same for every
    agent) are scored by likelihood alone; Newton runs from each agent's best ``n_starts`` of
    them and the best end point per agent is kept. Agents are independent rows: an agent's
    result does not depend on the others in the call. Returns θ̂, 95% intervals from the
    observed Fisher information, identifiability flags, the log-likelihood and whether each
    fit converged.
    """
    trials = validate_trials(trials, loss.model)
    space = loss.theta_space
    n_agents = trials.shape[0]
    free = space.free_mask
    k = int(free.sum())
    params = _screen_starts(loss, trials, n_screen, n_starts, seed)
    rows = (
        trials.unsqueeze(1)
        .expand(n_agents, n_starts, *trials.shape[1:])
        .reshape(n_agents * n_starts, *trials.shape[1:])
    )

    def nll(p: torch.Tensor, data: TensorDictBase) -> torch.Tensor:
        return -loss.log_likelihood(loss.theta(p[:, :k]), p[:, k:], data)

    value, grad, hessian = batched_hessian(lambda p: nll(p, rows), params)
    damping = torch.full((params.shape[0],), 1e-3, dtype=torch.float64)
    eye = torch.eye(params.shape[1], dtype=torch.float64)
    converged = torch.zeros(params.shape[0], dtype=torch.bool)
    stalled = torch.zeros_like(converged)  # no step improves: stop, but do not claim θ̂
    iterations = 0
    for iterations in range(1, max_iter + 1):
        # only rows still moving cost work; a rejected step leaves a row's derivatives valid
        active = (~converged & ~stalled).nonzero().squeeze(-1)
        h, g, d = hessian[active], grad[active], damping[active]
        scale = h.diagonal(dim1=1, dim2=2).abs().clamp_min(1e-6).unsqueeze(-1) * eye
        step = -torch.linalg.solve(h + d.view(-1, 1, 1) * (scale + eye), g.unsqueeze(-1))
        # a trust region in unconstrained units: one long step can land where the logit
        # saturates, the gradient vanishes and the fit would stall far from θ̂
        step = step.squeeze(-1)
        step = step * (MAX_STEP / step.abs().amax(-1, keepdim=True)).clamp(max=1)
        with torch.no_grad():
            accept = nll(params[active] + step, rows[active]) < value[active] - 1e-12
        damping[active] = torch.where(accept, d / 3, d * 8).clamp(1e-9, 1e9)
        # Newton decrement: the decrease a full step promises; tiny means θ̂ is reached
        decrement = -(g * step).sum(-1)
        converged[active] = decrement.abs() < tol
        stalled[active] = damping[active] >= 1e9
        moved = active[accept]
        if len(moved):
            params[moved] += step[accept]
            data = rows[moved]
            value[moved], grad[moved], hessian[moved] = batched_hessian(
                lambda p, data=data: nll(p, data), params[moved]
            )
        if progress is not None:
            progress(iterations, max_iter)
        if (converged | stalled).all():
            break
    best = value.view(n_agents, n_starts).argmin(1)
    pick = torch.arange(n_agents) * n_starts + best
    theta_free_hat = params[pick, :k]
    theta_hat = loss.theta(theta_free_hat).detach()
    intervals = fisher_intervals(space, theta_hat, theta_free_hat, hessian[pick])
    return FitResult(
        theta_hat=theta_hat,
        nuisance=params[pick, k:],
        log_likelihood=-value[pick],
        intervals=intervals,
        converged=converged[pick],
        iterations=iterations,
        names=space.names,
    )


def _screen_starts(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    n_screen: int,
    n_starts: int,
    seed: int,
) -> torch.Tensor:
    """The ``n_starts`` most likely of ``n_screen`` prior draws per agent, ``[A·n_starts, p]``."""
    space = loss.theta_space
    n_agents = trials.shape[0]
    # the same candidates for every agent (an agent's fit depends on its data and the seed
    # alone, not on which other agents share the call), spread evenly by a Sobol sequence
    free = space.free_mask
    low, high = space.low(torch.float64)[free], space.high(torch.float64)[free]
    sobol = torch.quasirandom.SobolEngine(int(free.sum()), scramble=True, seed=seed)
    draws = space.default(torch.float64).expand(n_screen, -1).clone()
    draws[:, free] = low + sobol.draw(n_screen, dtype=torch.float64) * (high - low)
    draws[0] = space.default(torch.float64)
    u = space.to_unconstrained(draws)[:, free]
    nuisance = loss.action_model.nuisance_init.double().expand(n_agents, -1)
    with torch.no_grad():
        scores = torch.stack(
            [
                loss.log_likelihood(loss.theta(u_s.expand(n_agents, -1)), nuisance, trials)
                for u_s in u
            ],
            1,
        )
    best = scores.topk(n_starts, dim=1).indices  # [A, n_starts]
    chosen = u[best]
    return torch.cat([chosen, nuisance.unsqueeze(1).expand(-1, n_starts, -1)], -1).reshape(
        n_agents * n_starts, -1
    )
