"""Algorithm 2: maximum-likelihood θ̂ for many agents at once, with Fisher intervals.

Every (agent, start) pair is an independent row of one batched problem. A damped Newton
(Levenberg–Marquardt) iteration in unconstrained coordinates moves each row with its exact
gradient and a curvature: the exact Hessian (``curvature="hessian"``: one double-backward pass
per parameter), or Fisher scoring (``"fisher"``: the outer product of per-trial scores of data
drawn from the model along the recorded trials, from the same single backward pass as the
gradient; positive semi-definite and, like Gauss–Newton, reliable far from θ̂ where the Hessian
is indefinite), handing over near θ̂ to the exact Hessian (``"fisher"``) or to BFGS updates of
the last Fisher matrix from the gradients alone (``"bfgs"``: no second derivatives until the
intervals, the cheapest where a Hessian costs many gradients). Rows converge at their own pace.
The exact Hessian at θ̂, the observed Fisher information, gives the intervals in every case.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import signal
import threading
import warnings
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from queue import Empty
from typing import Any

import torch
from tensordict import TensorDictBase

from irc_torchrl.algorithms.runtime import check_workers, flushing_denormals
from irc_torchrl.checks import count, first_line, positive_number
from irc_torchrl.checks import seed as check_seed
from irc_torchrl.objectives.fisher import (
    Z95,
    Intervals,
    batched_hessian,
    fisher_intervals,
    narrow,
    observed_covariance,
)
from irc_torchrl.objectives.inverse import InverseRationalLoss
from irc_torchrl.theta import ThetaSpace

__all__ = [
    "COVARIANCES",
    "CURVATURES",
    "INTERVALS",
    "FitResult",
    "check_sandwich",
    "expected_intervals",
    "fit_theta",
    "particle_check",
    "profile_intervals",
    "score_check",
]

#: how the iterations measure curvature (the intervals always use the exact Hessian at θ̂)
CURVATURES = ("hessian", "fisher", "bfgs")
#: how ``fit_theta`` turns curvature into intervals: the inverse observed information, or the
#: sandwich ``H⁻¹ (Σ sᵢ sᵢᵀ) H⁻¹`` over trials' scores (robust to an approximate likelihood)
COVARIANCES = ("hessian", "sandwich")
#: how the 95% intervals are formed: from that covariance (Wald), or where the profile
#: likelihood falls χ²₁(0.95)/2 below its maximum (honest where it is not quadratic)
INTERVALS = ("wald", "profile")

#: the largest move of one Newton step in any unconstrained coordinate
MAX_STEP = 1.5
#: the unconstrained coordinate at which a free θ (or a fitted lapse rate) counts as on its
#: bound (θ within ``1/(1+e^BOUND)`` ≈ 0.25% of its range from the bound)
BOUND = 6.0
#: iterations without a gain of ``tol`` after which a row whose model promises less than
#: ``SWITCH`` nats has converged (a flat top, e.g. θ̂ on a bound)
IDLE = 4
#: rows (agent, candidate pairs) scored together when screening starts
SCREEN_ROWS = 16
#: rows × trials differentiated at once: the exact Hessian's double backward holds ~7 MB per 2D
#: trial of 60 steps, a gradient ~0.7 MB, so 40 agents × 100 trials are taken in pieces
HESSIAN_TRIALS = 400
GRAD_TRIALS = 4000
#: Fisher scoring hands a row to Newton's method once it promises or gains less than this (nats)
SWITCH = 1.0


@dataclass(repr=False)
class FitResult:
    """θ̂ per agent ``[n_agents, d]`` (natural units) with intervals and fit facts.

    Attributes:
        theta_hat: θ̂ ``[n_agents, d]`` in natural units, in the order of ``names``.
        nuisance: the fitted nuisance ``[n_agents, dn]`` (log motor noise, then a lapse's
            logit where fitted).
        log_likelihood: the log-likelihood at θ̂ ``[n_agents]``.
        intervals: standard deviations, 95% intervals and identifiability per parameter.
        converged: whether each agent's fit met the tolerance ``[n_agents]``.
        iterations: the iterations the batched fit ran.
        names: θ's parameter names.
        information: the observed information at θ̂ ``[n_agents, p, p]``: the Hessian of the
            negative log-likelihood in the fit's coordinates (unconstrained free θ, then the
            nuisance).
    """

    theta_hat: torch.Tensor
    nuisance: torch.Tensor
    log_likelihood: torch.Tensor
    intervals: Intervals
    converged: torch.Tensor
    iterations: int
    names: list[str]
    information: torch.Tensor

    #: the fields holding one row per agent (besides ``intervals``)
    _PER_AGENT = ("theta_hat", "nuisance", "log_likelihood", "converged", "information")

    def select(self, rows: torch.Tensor) -> FitResult:
        """The agents ``rows`` (an index or mask) of a batched fit."""
        return dataclasses.replace(
            self,
            **{name: getattr(self, name)[rows] for name in self._PER_AGENT},
            intervals=self.intervals.select(rows),
        )

    def to(self, device: torch.device | str) -> FitResult:
        """This result on ``device``."""
        return dataclasses.replace(
            self,
            **{name: getattr(self, name).to(device) for name in self._PER_AGENT},
            intervals=self.intervals.to(device),
        )

    def cpu(self) -> FitResult:
        """This result on the CPU."""
        return self.to("cpu")

    def state_dict(self) -> dict[str, Any]:
        """This result as tensors and plain values, which ``torch.load(weights_only=True)``
        reads back (:meth:`from_state_dict`)."""
        state = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        state["intervals"] = {
            f.name: getattr(self.intervals, f.name) for f in dataclasses.fields(Intervals)
        }
        state["names"] = list(self.names)
        return state

    @staticmethod
    def from_state_dict(state: Mapping[str, Any]) -> FitResult:
        """The result :meth:`state_dict` gave; a ``KeyError`` or ``TypeError`` if ``state``
        is not one."""
        fields = {**state, "intervals": Intervals(**state["intervals"])}
        return FitResult(**fields)

    @staticmethod
    def cat(parts: Sequence[FitResult]) -> FitResult:
        """The agents of ``parts`` (fits of disjoint agents, in order) as one result."""
        return dataclasses.replace(
            parts[0],
            **{name: torch.cat([getattr(p, name) for p in parts]) for name in FitResult._PER_AGENT},
            intervals=Intervals.cat([p.intervals for p in parts]),
            iterations=max(p.iterations for p in parts),
        )

    def nuisance_intervals(self, bounded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """95% Wald intervals of the nuisance coordinates in the fit's units, ``[n_agents, dn]``
        each, from the observed information (infinite where it does not bound them). A
        ``bounded`` coordinate (``[dn]``) held on its bound reaches past it (±inf) on that
        side: the fit cannot tell how far."""
        cov, unbounded = observed_covariance(self.information)
        dn = self.nuisance.shape[-1]
        sd = cov.diagonal(dim1=-2, dim2=-1)[:, -dn:].clamp_min(0).sqrt()
        reach = torch.where(unbounded[:, -dn:], torch.full_like(sd, torch.inf), Z95 * sd)
        held = bounded.to(sd.device) & _on_bound(self.nuisance)
        low, high = self.nuisance - reach, self.nuisance + reach
        low = torch.where(held & (self.nuisance < 0), -torch.inf, low)
        high = torch.where(held & (self.nuisance > 0), torch.inf, high)
        return low, high

    def check_space(self, space: ThetaSpace) -> None:
        """Refuse a θ space other than the one this fit was made in: other parameters, another
        number of them free, or a parameter it holds fixed at another value than θ̂ has."""
        free = self.information.shape[-1] - self.nuisance.shape[-1]
        same = list(self.names) == list(space.names) and free == len(space.free_names)
        if same:  # and what the space holds fixed, the fit held there too
            same = all(
                bool((self.theta_hat[:, space.index(name)] == value).all())
                for name, value in space.fixed.items()
            )
        if not same:
            raise ValueError(
                f"result: a fit of θ {list(self.names)} with {free} free, not of the space given "
                f"({space.names}, free: {space.free_names})"
            )

    def __repr__(self) -> str:
        """One line per agent: θ̂ with its interval, whether it converged (the dataclass's
        repr printed every tensor in full)."""
        lines = [
            f"FitResult({len(self.theta_hat)} agents, {self.iterations} iterations, "
            f"{int(self.converged.sum())} converged)"
        ]
        for i in range(len(self.theta_hat)):
            fit = self.agent(i)
            values = ", ".join(
                f"{n}={fit['theta_hat'][n]:.4g} [{fit['ci_low'][n]:.4g}, {fit['ci_high'][n]:.4g}]"
                for n in self.names
            )
            lines.append(f"  agent {i}: {values}{'' if fit['converged'] else ' (not converged)'}")
        return "\n".join(lines)

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
            "profiled": {
                n: bool(v) for n, v in zip(self.names, self.intervals.profiled[i], strict=True)
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
    tol: float = 1e-4,
    seed: int = 0,
    curvature: str = "hessian",
    starts: torch.Tensor | None = None,
    covariance: str = "hessian",
    intervals: str = "wald",
    progress: Callable[[int, int], None] | None = None,
    workers: int = 1,
) -> FitResult:
    """Fit θ for every agent in ``trials`` (``[n_agents, n_trials, T]``, or one agent's
    ``[n_trials, T]``): as many agents as the trials hold, whatever ``loss``'s own
    ``n_agents`` (its parameters are not read here).

    ``n_screen`` candidates (the prior's default and draws from the prior, the same for every
    agent) are scored by likelihood alone; Newton runs from each agent's best ``n_starts`` of
    them and the best end point per agent is kept. ``starts`` (natural θ ``[n_agents, d]``,
    e.g. another estimator's θ̂) joins each agent's candidates (with ``n_screen=0`` it is the
    only start). Agents are
    independent rows: an agent's likelihood, starts and steps read its own data alone. The
    others in the call change only the rounding of batched products and, with Fisher scoring,
    which samples its draws get; both move a step by far less than its size, yet where the
    likelihood has cusps (the 2D task's stops) a fit may then end at another point. Returns θ̂,
    95% intervals from the observed Fisher information, identifiability flags, the
    log-likelihood and whether each fit converged. ``covariance="sandwich"`` widens the
    intervals by how much more the trials' scores vary than the curvature says (they agree
    when the likelihood is exact). ``intervals="profile"`` replaces the endpoints by the
    profile likelihood's (:func:`profile_intervals`). ``workers`` > 1 splits the agents into
    that many shards fitted in parallel processes on the CPU, each with its share of torch's
    threads: the iterations' many small operations keep one process's threads mostly idle,
    so processes use the cores better (they are spawned: a script calling this needs the
    ``if __name__ == "__main__":`` guard). The numbers depend on ``workers`` (each shard draws
    its own Fisher-scoring samples) and, where a path crosses a cusp of the likelihood, on
    torch's thread count (its sums round differently), not otherwise on the machine.
    """
    if not isinstance(loss, InverseRationalLoss):
        raise TypeError(f"loss: expected an InverseRationalLoss, got {type(loss).__name__}")
    if curvature not in CURVATURES:
        raise ValueError(f"curvature: expected one of {CURVATURES}, got {curvature!r}")
    if covariance not in COVARIANCES:
        raise ValueError(f"covariance: expected one of {COVARIANCES}, got {covariance!r}")
    if intervals not in INTERVALS:
        raise ValueError(f"intervals: expected one of {INTERVALS}, got {intervals!r}")
    trials = loss.validate(trials)
    space = loss.theta_space
    n_agents, device = trials.shape[0], _trials_device(trials)
    free = space.free_mask
    k = int(free.sum())
    if k == 0:
        raise ValueError(
            "theta_space: every parameter is fixed; expected at least one to fit (ThetaSpace.free)"
        )
    if covariance == "sandwich":
        per_agent = trials[loss.tensor_keys.mask].any(-1).sum(-1)
        check_sandwich(per_agent, k, loss.action_model.nuisance_init.numel())
    bounded = loss.bounded.to(device)
    if starts is not None:
        starts = space.validate(starts, "starts").double()
        if starts.shape != (n_agents, space.dim):
            raise ValueError(
                f"starts: expected one θ per agent, [{n_agents}, {space.dim}], "
                f"got {list(starts.shape)}"
            )
    _check_iterations(max_iter, tol)
    for name, value in (("n_screen", n_screen), ("n_starts", n_starts), ("workers", workers)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{name}: expected an integer, got {value!r}")
    if n_screen < (0 if starts is not None else 1) or n_starts < 1:
        raise ValueError(
            f"n_screen, n_starts: expected n_starts ≥ 1 and n_screen ≥ 1 (≥ 0 with starts), "
            f"got {n_screen}, {n_starts}"
        )
    count("workers", workers)
    check_workers(workers, device)
    check_seed("seed", seed)
    if progress is not None and not callable(progress):
        raise TypeError(f"progress: expected progress(done, total) or None, got {progress!r}")
    if min(workers, n_agents) > 1:
        settings = {
            "n_starts": n_starts, "n_screen": n_screen, "max_iter": max_iter, "tol": tol,
            "seed": seed, "curvature": curvature, "covariance": covariance,
            "intervals": intervals,
        }  # fmt: skip
        return _fit_in_processes(loss, trials, starts, min(workers, n_agents), settings, progress)
    params = _screen_starts(loss, trials, n_screen, n_starts, seed, starts)
    n_starts = params.shape[0] // n_agents
    rows = (
        trials.unsqueeze(1)
        .expand(n_agents, n_starts, *trials.shape[1:])
        .reshape(n_agents * n_starts, *trials.shape[1:])
    )

    def nll(p: torch.Tensor, data: TensorDictBase) -> torch.Tensor:
        return -loss.log_likelihood(loss.theta(p[:, :k]), p[:, k:], data)

    params = params.to(device)
    draws = torch.Generator().manual_seed(seed)

    def hessian_of_nll(p: torch.Tensor, data: TensorDictBase):
        return batched_hessian(lambda x: nll(x, data), p)

    def scores(p: torch.Tensor, data: TensorDictBase):
        return _trial_scores(loss, k, p, data)

    def evaluate(p: torch.Tensor, data: TensorDictBase, with_grad: torch.Tensor):
        """Values of rows ``p`` and, where ``with_grad``, their gradients in the same pass
        (NaN elsewhere)."""
        value, grad = p.new_empty(len(p)), torch.full_like(p, torch.nan)
        if (~with_grad).any():
            with torch.no_grad():
                value[~with_grad] = nll(p[~with_grad], data[~with_grad])
        if with_grad.any():
            ll, score, _ = _by_rows(scores, p[with_grad], data[with_grad], GRAD_TRIALS)
            value[with_grad], grad[with_grad] = -ll.sum(1), -score.sum(1)
        return value, grad

    def derivatives(p: torch.Tensor, data: TensorDictBase, near: torch.Tensor):
        """Value, gradient and curvature of rows ``p``: Fisher scoring far from θ̂; near it the
        exact Hessian, or with ``"bfgs"`` none (NaN: the iteration updates the last one)."""
        n, m = p.shape
        out = (p.new_empty(n), p.new_empty(n, m), p.new_full((n, m, m), torch.nan))
        for rows_, kind in ((near, "near"), (~near, "fisher")):
            if rows_.any():
                q, d = p[rows_], data[rows_]
                if kind == "fisher":
                    parts = _by_rows(
                        lambda q_, d_: _fisher_scoring(loss, k, q_, d_, draws), q, d, GRAD_TRIALS
                    )
                elif curvature == "bfgs":
                    parts = evaluate(q, d, torch.ones_like(rows_[rows_]))
                else:
                    parts = _by_rows(hessian_of_nll, q, d, HESSIAN_TRIALS)
                for o, v in zip(out, parts, strict=False):
                    o[rows_] = v
        return out

    # rows near θ̂ step with the exact Hessian (Newton converges quadratically there);
    # Fisher scoring brings the others near
    near = torch.full((params.shape[0],), curvature == "hessian", device=device)
    value, grad, hessian = derivatives(params, rows, near)
    damping = torch.full((params.shape[0],), 1e-3, dtype=torch.float64, device=device)
    converged = torch.zeros(params.shape[0], dtype=torch.bool, device=device)
    stalled = torch.zeros_like(converged)  # no step improves: stop, but do not claim θ̂
    # iterations in a row without a gain of ``tol``: a flat top (e.g. θ̂ on a bound, where
    # the unconstrained coordinate drifts off with vanishing gradient and curvature)
    idle = torch.zeros(params.shape[0], dtype=torch.long, device=device)
    iterations = 0
    for iterations in range(1, max_iter + 1):
        # only rows still moving cost work; a rejected step leaves a row's derivatives valid
        active = (~converged & ~stalled).nonzero().squeeze(-1)
        h, g = _pin_bounds(params[active], hessian[active], grad[active], bounded)
        d = damping[active]
        # the undamped Newton decrement: the decrease a full step promises (∞ where the
        # curvature is not positive definite); tiny means θ̂ is reached
        decrement = _newton_decrement(h, g)
        # idle counts as a flat top only where the model promises little (a small, finite
        # decrement): idle where the curvature is indefinite, or where steps keep failing
        # while the model promises much, is not θ̂
        flat_top = (idle[active] >= IDLE) & (decrement < SWITCH)
        converged[active] = near[active] & ((decrement < tol) | flat_top)
        # a start below its agent's converged maximum by more than its own model promises to
        # gain is abandoned: it cannot overtake, and the batch would wait for it
        behind = _behind_best(value, converged, n_starts)[active]
        stalled[active] |= ~converged[active] & (behind > decrement.clamp_min(SWITCH))
        step, d = _damped_step(_absolute(h), g, d)
        # θ̂ (or a fitted lapse rate) on its bound: the logit would drift off forever, so it
        # stops at ±BOUND
        to_bound = (params[active] + step).clamp(-BOUND, BOUND) - params[active]
        step = torch.where(bounded, to_bound, step)
        # BFGS rows need the gradient wherever a step lands: it comes with the trial's value
        quasi = near[active] & (curvature == "bfgs")
        trial_value, trial_grad = evaluate(params[active] + step, rows[active], quasi)
        gain = value[active] - trial_value
        accept = (gain > 1e-12) & ~converged[active]
        # Fisher scoring has done its part once it promises or makes little progress
        switch = ~near[active] & ((decrement < SWITCH) | (accept & (gain < SWITCH)))
        # the gain ratio: how much of the decrease the quadratic model promised was made
        quadratic = (step.unsqueeze(-2) @ h @ step.unsqueeze(-1)).view(-1)
        promised = -(g * step).sum(-1) - 0.5 * quadratic
        ratio = gain / promised.clamp_min(1e-300)
        damping[active] = torch.where(
            ~accept, d * 8, torch.where(ratio > 0.75, d / 3, torch.where(ratio < 0.25, d * 2, d))
        ).clamp(1e-9, 1e9)
        stalled[active] |= damping[active] >= 1e9
        idle[active] = torch.where(accept & (gain >= tol), 0, idle[active] + 1)
        params[active[accept]] += step[accept]
        near[active[switch]] = True
        if curvature == "bfgs":
            moved = active[accept]
            before_grad, before_hessian = grad[moved], hessian[moved]
            # a BFGS row's gradient came with its trial value; the others need a pass
            landed = accept & quasi
            value[active[landed]], grad[active[landed]] = trial_value[landed], trial_grad[landed]
            refresh = active[accept & ~quasi]
        else:
            refresh = active[accept | switch]
        if len(refresh):
            value[refresh], grad[refresh], hessian[refresh] = derivatives(
                params[refresh], rows[refresh], near[refresh]
            )
        if curvature == "bfgs":
            # rows near θ̂ update their last curvature (a Fisher matrix for rows switching now)
            update = near[moved]
            hessian[moved[update]] = _bfgs_update(
                before_hessian[update],
                step[accept][update],
                grad[moved[update]] - before_grad[update],
            )
        if progress is not None:
            progress(iterations, max_iter)
        if (converged | stalled).all():
            break
    best = value.view(n_agents, n_starts).argmin(1)
    pick = torch.arange(n_agents, device=device) * n_starts + best
    theta_free_hat = params[pick, :k]
    theta_hat = loss.theta(theta_free_hat).detach()
    # the observed information at θ̂ (rows that did not step with it get it computed now)
    information = hessian[pick]
    missing = ~near[pick] | (curvature == "bfgs")
    if missing.any():
        _, _, information[missing] = _by_rows(
            hessian_of_nll, params[pick][missing], trials[missing], HESSIAN_TRIALS
        )
    # θ̂ is a maximum only where the observed information there is positive definite (BFGS's
    # curvature always is)
    maximum = torch.isfinite(
        _newton_decrement(*_pin_bounds(params[pick], information, grad[pick], bounded))
    )
    meat = None
    if covariance == "sandwich":
        _, score, _ = _by_rows(scores, params[pick], trials, GRAD_TRIALS)
        meat = score.mT @ score
    result = FitResult(
        theta_hat=theta_hat,
        nuisance=params[pick, k:],
        log_likelihood=-value[pick],
        intervals=fisher_intervals(space, theta_hat, theta_free_hat, information, meat),
        converged=converged[pick] & maximum,
        iterations=iterations,
        names=space.names,
        information=information,
    )
    if intervals == "profile":
        result = dataclasses.replace(result, intervals=profile_intervals(loss, trials, result))
    return result


def check_sandwich(
    per_agent: torch.Tensor,
    k: int,
    n_nuisance: int,
    field: str = "covariance",
    agents: Sequence[str] | None = None,
) -> None:
    """Refuse the sandwich covariance where an agent has no more trials (``per_agent``,
    ``[A]``) than fitted coordinates (``k`` of θ, ``n_nuisance``): its middle, one outer
    product of scores per trial, is then singular (at a maximum the trials' scores sum to
    zero, so n trials span n − 1 directions), and the intervals would claim some combination
    of the parameters known exactly. The error names the setting ``field`` and the agent by
    its label in ``agents`` (default ``agent i``)."""
    fewest = int(per_agent.min())
    if fewest <= k + n_nuisance:
        i = int(per_agent.argmin())
        agent = f"agent {i}" if agents is None else agents[i]
        raise ValueError(
            f"{field}: 'sandwich' needs more trials per agent than fitted coordinates "
            f"({k + n_nuisance}: {k} of θ, {n_nuisance} nuisance); {agent} has {fewest}; "
            f"expected {field}=hessian for so few trials"
        )


def expected_intervals(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    theta: torch.Tensor,
    nuisance: torch.Tensor | None = None,
    draws: int = 8,
    seed: int = 0,
) -> Intervals:
    """The 95% intervals that the Fisher information of ``trials`` at ``theta`` predicts.

    No fit: the information is Fisher scoring's, the sum over trials of the outer products of
    the scores of actions drawn from the model along the recorded states, averaged over
    ``draws`` sets of draws (one set has rank at most the number of trials; ``seed`` seeds
    them, and as in :func:`fit_theta` which draws a row gets depends on the rows sharing the
    call). It says how tightly such trials pin each parameter of an agent whose θ is
    ``theta`` (``[n_agents, d]``; fixed parameters take the space's values), e.g. a simulated
    agent's θ*: how much a policy's actions reveal of θ, or how many trials an experiment
    needs. ``nuisance`` (the action model's, ``[n_agents, m]``) defaults to its initial value.
    The draws are unclipped, and lapse at the action model's rate (uniform over the widened
    bounds, scored under the mixture), so lapses lower the information as they lower a fit's.
    """
    trials, theta_free, params = _checked_point(loss, trials, theta, nuisance, draws)
    k = theta_free.shape[-1]
    generator = torch.Generator().manual_seed(seed)
    information = torch.stack(
        [_drawn_information(loss, k, params, trials, generator) for _ in range(draws)]
    ).mean(0)
    # centred as fit_theta's: θ from its free coordinates, the fixed ones the space's
    centre = loss.theta(theta_free).detach()
    return fisher_intervals(loss.theta_space, centre, theta_free, information)


def _checked_point(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    theta: torch.Tensor,
    nuisance: torch.Tensor | None,
    draws: int,
) -> tuple[TensorDictBase, torch.Tensor, torch.Tensor]:
    """Validated trials, θ's free unconstrained coordinates ``[A, k]`` and the fit's
    coordinates there ``[A, k + m]`` (``nuisance`` defaulting to the action model's initial
    value), for the checks made at a given θ rather than a fit's."""
    count("draws", draws)
    trials = loss.checked(theta, nuisance, trials)
    if nuisance is None:
        nuisance = loss.action_model.nuisance_init.expand(trials.shape[0], -1)
    space, device = loss.theta_space, _trials_device(trials)
    theta_free = space.to_unconstrained(theta.detach().double().to(device))[:, space.free_mask]
    return trials, theta_free, torch.cat([theta_free, nuisance.detach().double().to(device)], -1)


def _drawn_information(
    loss: InverseRationalLoss,
    k: int,
    params: torch.Tensor,
    trials: TensorDictBase,
    generator: torch.Generator,
) -> torch.Tensor:
    """One set of drawn actions' sampled Fisher information per row ``[A, p, p]``: the outer
    products of their per-trial scores, summed over the trials."""

    def sampled(p: torch.Tensor, data: TensorDictBase) -> tuple[torch.Tensor]:
        drawn = _trial_scores(loss, k, p, data, generator, data=False)[2]
        return (drawn.mT @ drawn,)

    return _by_rows(sampled, params, trials, GRAD_TRIALS)[0]


def score_check(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    theta: torch.Tensor,
    nuisance: torch.Tensor | None = None,
    draws: int = 4,
    seed: int = 0,
) -> torch.Tensor:
    """How far one Fisher-scoring step from ``theta`` moves each agent, in standard deviations
    of its own Fisher information, ``[A, k + m]`` (the free θ coordinates, unconstrained, then
    the nuisance's).

    At simulated agents' true θ an exact likelihood makes these draws of ``N(0, 1)``: its
    score has mean 0 and covariance the information. Their mean over agents is about the
    approximation's bias of θ̂ in standard deviations, their spread beyond 1 how much too
    narrow its raw intervals are. No fit and no particle filter: one pass of the likelihood
    per set of ``draws`` (the information as in :func:`expected_intervals`), a check of an
    approximation or of a policy in minutes where :func:`particle_check` takes hours.
    """
    trials, theta_free, params = _checked_point(loss, trials, theta, nuisance, draws)
    k = theta_free.shape[-1]
    generator = torch.Generator().manual_seed(seed)

    def scored(p: torch.Tensor, data: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        _, score, drawn = _trial_scores(loss, k, p, data, generator)
        return score.sum(1), drawn.mT @ drawn

    score, information = _by_rows(scored, params, trials, GRAD_TRIALS)
    for _ in range(draws - 1):
        information = information + _drawn_information(loss, k, params, trials, generator)
    covariance = torch.linalg.pinv(information / draws, hermitian=True)
    step = (covariance @ score.unsqueeze(-1)).squeeze(-1)
    return step / covariance.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()


def profile_intervals(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    result: FitResult,
    max_iter: int = 60,
    tol: float = 0.01,
    names: Sequence[str] | None = None,
) -> Intervals:
    """95% profile-likelihood intervals of the free θ of a fit (``names``, all by default):
    where the log-likelihood, maximised over all the other parameters (the nuisance too),
    falls ``Z95²/2`` below its maximum.

    Unlike the Wald interval it follows the likelihood where it is not quadratic, and it does
    not depend on the coordinates. Each (agent, parameter, side) is a row of one batched
    search, started at the Wald endpoint (:func:`_profile_start`: coordinates θ̂ holds on a
    bound left there): the other coordinates are re-maximised by damped BFGS steps (from the
    curvature at θ̂, a unit one for those held), then θ_j takes a Newton step on the profile,
    whose slope is θ_j's own gradient there, inside a bracket of points above and below the
    target (else halfway between them; a point taken as beyond the target before the others
    settled is tested, θ_j moved there, when the step heads past it, and leaves the bracket
    when a settled point there lies inside). A side whose likelihood does not fall that far
    before the parameter's bound ends at the bound. An endpoint found to ``tol`` nats (value
    and the others' remaining decrease) is ``profiled``; the others, and parameters without a
    Wald interval, keep the Wald endpoints.
    """
    _check_iterations(max_iter, tol)
    trials = loss.validate(trials)
    if trials.shape[0] != result.theta_hat.shape[0]:
        raise ValueError(
            f"trials: expected the fit's {result.theta_hat.shape[0]} agent(s), "
            f"got {trials.shape[0]}"
        )
    space = loss.theta_space
    wald = result.intervals
    result.check_space(space)
    if isinstance(names, str):  # one name, not its characters
        names = [names]
    names = space.free_names if names is None else list(names)
    unknown = [n for n in names if n not in space.free_names]
    if unknown:
        raise ValueError(f"names: expected free parameters {space.free_names}, got {unknown}")
    free = space.free_mask.to(result.theta_hat.device)
    k, n_agents, n_named = int(free.sum()), result.theta_hat.shape[0], len(names)
    if n_named == 0:
        return wald
    chosen = torch.tensor([space.free_names.index(n) for n in names], device="cpu")
    centre = torch.cat([space.to_unconstrained(result.theta_hat)[:, free], result.nuisance], -1)
    device = centre.device
    # rows agent-major, then parameter, then side (−1, +1)
    agent = torch.arange(n_agents, device=device).repeat_interleave(2 * n_named)
    which = chosen.to(device).repeat_interleave(2).repeat(n_agents)
    side = torch.tensor([-1.0, 1.0], dtype=centre.dtype, device=device).repeat(n_agents * n_named)
    rows = torch.arange(len(agent), device=device)
    data = trials[agent.to(trials.device)]
    target = (-result.log_likelihood)[agent] + 0.5 * Z95**2
    bounded = loss.bounded.to(device)
    point, fixed, singular = _profile_start(
        centre[agent], _absolute(result.information)[agent], which, side, bounded
    )
    has_wald = torch.isfinite(wald.std[:, free][:, chosen]).reshape(-1).repeat_interleave(2)
    done = ~has_wald.to(device) | (singular != 0) | ~torch.isfinite(point).all(-1)
    found = torch.zeros_like(done)
    # the others' steps start from that curvature, and restart from it after a refused step
    curvature = fixed.clone()

    def evaluate(at: torch.Tensor, i: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        ll, score, _ = _by_rows(lambda q, d: _trial_scores(loss, k, q, d), at, data[i], GRAD_TRIALS)
        return -ll.sum(1), -score.sum(1)

    # the outer search brackets θ_j's endpoint between a point where the profile lies above
    # its target (θ̂ to begin with) and, once one is seen, a point where it lies below
    inside = centre[agent].clone()
    outside = torch.full_like(inside, torch.nan)
    guessed = torch.zeros_like(done)  # the point outside was taken before the others settled
    damping = torch.full_like(target, 1e-3)
    value, grad = evaluate(point, rows)
    for _ in range(max_iter):
        active = (~done).nonzero().squeeze(-1)
        if not len(active):
            break
        x, f, g, h = point[active], value[active], grad[active], curvature[active]
        j, i = which[active], torch.arange(len(active), device=device)
        w, v, decrement = _held_step(x, g, h, j, damping[active], bounded)
        c = x[i, j]
        gap = f - target[active]
        settled = decrement < tol
        on_bound = _on_bound(c)
        # converged: on target, or short of it at the bound of θ (the interval ends there)
        reached = settled & ((gap.abs() < tol) | (on_bound & (gap < 0)))
        found[active[reached]] = done[active[reached]] = True
        # the others settled: move θ_j by Newton's step on the profile, whose slope is θ_j's
        # own gradient there (the envelope theorem), the others along their regression on it.
        # Outside the bracket, go halfway between its points instead (the others stay in the
        # basin both share), or twice as far from θ̂ while no point beyond is known. A value
        # far above the target is taken as beyond the endpoint at once (the profile is far
        # from quadratic there)
        far = ~settled & (gap > Z95**2)
        outer = (settled & ~reached) | far
        below = (gap < 0).unsqueeze(-1)
        inside[active] = torch.where(outer.unsqueeze(-1) & below, x, inside[active])
        outside[active] = torch.where(outer.unsqueeze(-1) & ~below, x, outside[active])
        guessed[active] = torch.where(outer & (gap >= 0), far, guessed[active])
        newton = c - gap / g[i, j]
        # a point taken as beyond the endpoint before the others were re-maximised may not be:
        # a settled point inside at its θ_j shows it is not (it leaves the bracket), and the
        # profile's step from a settled point heading past it tests it first (θ_j goes there)
        guess_j = outside[active][i, j]
        suspect = settled & ~reached & (gap < 0) & guessed[active]
        disproved = suspect & ((c - guess_j) * side[active] >= 0)
        outside[active[disproved]] = torch.nan
        test = (
            suspect & ~disproved & torch.isfinite(newton) & ((newton - guess_j) * side[active] > 0)
        )
        newton = torch.where(test, guess_j, newton)
        lo, hi = inside[active], outside[active]
        known = torch.isfinite(hi[:, 0])
        within = torch.where(
            known,
            (newton - lo[i, j]) * (newton - hi[i, j]) < 0,
            (newton - lo[i, j]) * side[active] > 0,
        )
        direction = v
        direction[i, j] = 1.0
        centre_j = centre[agent[active], j]
        widen = x + (side[active] * (c - centre_j).abs().clamp_min(0.1)).unsqueeze(-1) * direction
        fallback = torch.where(known.unsqueeze(-1), 0.5 * (lo + hi.nan_to_num()), widen)
        newton_x = x + (newton.clamp(-BOUND, BOUND) - c).unsqueeze(-1) * direction
        use_newton = ((within | test) & ~far & torch.isfinite(newton)).unsqueeze(-1)
        step = torch.where(outer.unsqueeze(-1), torch.where(use_newton, newton_x, fallback) - x, w)
        candidate = x + _within_region(step)
        candidate = _clamp_bounded(candidate, bounded)
        moving = ~reached
        f_c, g_c = torch.empty_like(f), torch.empty_like(g)
        if moving.any():
            f_c[moving], g_c[moving] = evaluate(candidate[moving], active[moving])
        # a step of the others is taken only if it lowers the value; θ_j's moves always are
        accept = moving & (outer | (f_c < f))
        taken = active[accept]
        curvature[taken] = _bfgs_update(h[accept], (candidate - x)[accept], g_c[accept] - g[accept])
        # a refused step of the others restarts their curvature from the start's
        curvature[active[moving & ~accept]] = fixed[active[moving & ~accept]]
        point[taken], value[taken], grad[taken] = candidate[accept], f_c[accept], g_c[accept]
        damping[active] = torch.where(
            outer, 1e-3, torch.where(accept, damping[active] / 3, damping[active] * 8)
        ).clamp(1e-9, 1e9)
        done[active] |= damping[active] >= 1e9
    endpoint = point[rows, which]
    # a side that ends on the bound of θ ends on the bound itself, not BOUND's 0.25% short of it
    endpoint = torch.where(_on_bound(endpoint), endpoint.sign() * 40, endpoint)
    endpoint = endpoint.view(n_agents, n_named, 2)
    columns = free.nonzero().squeeze(-1)[chosen.to(device)]
    u = torch.zeros(n_agents, 2, space.dim, dtype=centre.dtype, device=centre.device)
    u[:, :, columns] = endpoint.transpose(1, 2)
    natural = space.from_unconstrained(u.view(-1, space.dim)).view(n_agents, 2, -1)[..., columns]
    profiled = found.view(n_agents, n_named, 2).all(-1)
    low, high = wald.low.clone(), wald.high.clone()
    low[:, columns] = torch.where(profiled, natural[:, 0], wald.low[:, columns])
    high[:, columns] = torch.where(profiled, natural[:, 1], wald.high[:, columns])
    flags = torch.zeros_like(wald.identified)
    flags[:, columns] = profiled
    identified = torch.where(flags, narrow(space, low, high), wald.identified)
    return dataclasses.replace(wald, low=low, high=high, identified=identified, profiled=flags)


def _profile_start(
    centre: torch.Tensor,
    curvature: torch.Tensor,
    which: torch.Tensor,
    side: torch.Tensor,
    bounded: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where each profile search starts, ``(point, curvature, singular)`` per row: the Wald
    endpoint, θ_j moved ``side`` × 1.96 sd, the others along their regression on θ_j.

    The other coordinates θ̂ holds on a bound stay there: their curvature, near 0 in the
    logit, would throw them to the other bound, far from the profile. θ_j's move stops at its
    bound, and from a bound of its own goes at most ``MAX_STEP`` (the same near-0 curvature);
    the others follow the move taken. The curvature returned has the held coordinates
    decoupled, with a unit curvature of their own (the search's steps may take them off the
    bound); ``singular`` is ``torch.linalg.inv_ex``'s flag.
    """
    rows = torch.arange(len(which), device=centre.device)
    held = bounded & _on_bound(centre)
    own = held[rows, which]
    held[rows, which] = False
    eye = torch.eye(centre.shape[-1], dtype=centre.dtype, device=centre.device)
    start = torch.where(~held.unsqueeze(-1) & ~held.unsqueeze(-2), curvature, eye)
    cov, singular = torch.linalg.inv_ex(start)
    column = torch.where(held, 0.0, cov[rows, :, which])
    sd = column[rows, which].clamp_min(1e-300).sqrt()
    move = side * Z95 * sd
    limit = torch.where(own, MAX_STEP, torch.inf)
    taken = centre[rows, which] + move.clamp(-limit, limit)
    taken = torch.where(bounded[which], taken.clamp(-BOUND, BOUND), taken)
    fraction = (taken - centre[rows, which]) / move
    point = centre + (fraction * side * Z95 / sd).unsqueeze(-1) * column
    return _clamp_bounded(point, bounded), start, singular


def particle_check(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    theta: torch.Tensor,
    nuisance: torch.Tensor | None = None,
    n_particles: int = 1000,
    seed: int = 0,
) -> dict[str, torch.Tensor]:
    """How far the loss's likelihood is from the one it approximates, at θ (and ``nuisance``;
    ``None``: the action model's initial one), per agent ``[A]``.

    ``particle_log_likelihood`` is a particle filter's estimate of the likelihood with the
    agent's observations integrated out (:meth:`InverseRationalLoss.particle_log_likelihood`),
    ``approximation_gap`` that minus the loss's own log-likelihood (what its approximation
    loses) and ``min_effective_particles`` the fewest effective particles of any trial (near
    1: too few particles). A gap that differs between θ̂ and nearby θ biases θ̂; on the 2D
    recovery with the shipped policy the marginal intervals of agents with a gap under 10 nats
    at θ̂ covered the truth in 0.82–1.0 of them per parameter, the others' in 0.86–0.97
    (docs/recovery2d.md): the gap says where the approximation is coarse, not by itself that
    the intervals are wrong.
    Both run in float64 (a float32 filter moves the gap by tens of nats).
    """
    trials, theta_free, point = _checked_point(loss, trials, theta, nuisance, 1)
    nuisance = point[:, theta_free.shape[-1] :]
    theta = theta.detach().double().to(_trials_device(trials))
    with torch.no_grad():
        approximate = loss.log_likelihood(theta, nuisance, trials)
    particle, ess = loss.particle_log_likelihood(theta, nuisance, trials, n_particles, seed)
    particle = particle.sum(1)
    return {
        "particle_log_likelihood": particle,
        "approximation_gap": particle - approximate,
        "min_effective_particles": ess.amin(1),
    }


def _fit_in_processes(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    starts: torch.Tensor | None,
    workers: int,
    settings: dict,
    progress: Callable[[int, int], None] | None,
) -> FitResult:
    """:func:`fit_theta` of ``workers`` contiguous shards of the agents, each in a process of
    its own; ``progress`` follows the shard furthest behind. A shard that fails, or an
    interrupt here, ends the other processes at once; a shard's warnings are raised here."""
    sent = _sent(loss)
    shards = torch.arange(trials.shape[0]).tensor_split(workers)
    context = multiprocessing.get_context("spawn")  # fork is unsafe once torch's threads run
    reports = context.Queue()
    setup = (max(1, torch.get_num_threads() // workers), flushing_denormals(), reports)
    reached, reported = [0] * workers, 0

    def advance(upto: int) -> None:
        """Report the iterations up to ``upto`` not yet reported."""
        nonlocal reported
        for iteration in range(reported + 1, upto + 1):
            progress(iteration, settings["max_iter"])
        reported = max(reported, upto)

    report = progress is not None
    pool = ProcessPoolExecutor(
        workers, mp_context=context, initializer=_start_worker, initargs=setup
    )
    try:
        futures = [
            pool.submit(
                _fit_shard,
                i,
                int(rows[0]),
                sent,
                trials[rows],
                _rows_of(starts, rows),
                settings,
                report,
            )
            for i, rows in enumerate(shards)
        ]
        while not all(f.done() for f in futures):
            failed = [f for f in futures if f.done() and f.exception() is not None]
            if failed:  # a failed shard's error is the fit's (the lowest-numbered of several)
                raise failed[0].exception()
            try:
                shard, iteration = reports.get(timeout=0.5)
                reached[shard] = iteration
            except Empty:
                pass
            running = [reached[i] for i, f in enumerate(futures) if not f.done()]
            if report and running:
                advance(min(running))
        done = [f.result() for f in futures]
    except BaseException:
        _end_workers(pool)
        raise
    pool.shutdown()
    for _, caught in done:  # as the shard raised them, so the caller's filters apply alike
        for message, category, filename, lineno in caught:
            warnings.warn_explicit(message, category, filename, lineno)
    result = FitResult.cat([fit for fit, _ in done])
    if report:
        advance(result.iterations)
    return result


def _sent(loss: InverseRationalLoss) -> bytes:
    """``loss`` pickled for the worker processes: refused here, before any process starts,
    where it cannot be (it failed in a worker, as a broken pool)."""
    try:
        return pickle.dumps(loss)
    except Exception as error:
        raise TypeError(
            f"workers: the loss cannot be sent to worker processes ({first_line(error)}); "
            "expected workers=1, or a task and networks whose classes and attributes pickle "
            "(classes at the top level of an importable module)"
        ) from None


def _end_workers(pool: ProcessPoolExecutor) -> None:
    """End a pool's processes now (a shard failed, or the fit was interrupted), not after
    their shards."""
    terminate = getattr(pool, "terminate_workers", None)  # Python 3.14
    if terminate is not None:
        terminate()
    else:
        for process in list((pool._processes or {}).values()):
            if process.is_alive():
                process.terminate()
    pool.shutdown(wait=True, cancel_futures=True)


def _rows_of(starts: torch.Tensor | None, rows: torch.Tensor) -> torch.Tensor | None:
    """The starts of a shard's agents (none where none were given)."""
    return None if starts is None else starts[rows]


#: where a worker process of :func:`_fit_in_processes` reports its iterations
_REPORTS = None
#: the index among all agents of the first agent of a worker's shard (its errors name agents)
_FIRST_AGENT = 0


def _start_worker(threads: int, flush_denormal: bool, reports: Any) -> None:
    """Set up a worker process: its share of the threads, its parent's denormal flushing and
    the queue its progress goes to. Ctrl-C is its parent's to handle (which ends it), and it
    ends itself when its parent dies (``kill -9``) rather than wait forever for work."""
    global _REPORTS
    torch.set_num_threads(threads)
    torch.set_flush_denormal(flush_denormal)
    _REPORTS = reports
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = multiprocessing.parent_process()
    if parent is not None:

        def watch() -> None:
            parent.join()
            os._exit(1)

        threading.Thread(target=watch, daemon=True).start()


def _fit_shard(
    shard: int,
    first_agent: int,
    sent: bytes,
    trials: TensorDictBase,
    starts: torch.Tensor | None,
    settings: dict,
    report: bool,
) -> tuple[FitResult, list[tuple[str, type[Warning], str, int]]]:
    """One shard's :func:`fit_theta` in a worker process, reporting each iteration; returns
    it with the warnings it raised (message, category, file, line: for the parent to raise)."""
    global _FIRST_AGENT
    try:
        loss = pickle.loads(sent)
    except Exception as error:  # the task's module cannot be imported here
        raise ValueError(
            f"workers: a worker process cannot rebuild the loss ({first_line(error)}); "
            "expected workers=1, or a task and networks importable by module name (not "
            "defined in __main__ or in a file loaded by its path)"
        ) from None
    _FIRST_AGENT = first_agent
    progress = (lambda i, _: _REPORTS.put((shard, i))) if report else None
    with warnings.catch_warnings(record=True) as caught:  # the worker's filters apply
        fit = fit_theta(loss, trials, starts=starts, progress=progress, **settings)
    return fit, [(str(w.message), w.category, w.filename, w.lineno) for w in caught]


def _held_step(
    params: torch.Tensor,
    g: torch.Tensor,
    h: torch.Tensor,
    which: torch.Tensor,
    damping: torch.Tensor,
    bounded: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The damped Newton step of every coordinate but ``which`` (held, as are those on a bound),
    how they follow a move of ``which`` at their minimum (``-h⁻¹ h_j``), and the decrease
    still to be had in them (the undamped decrement ``½ gᵀ h⁻¹ g`` over them), per row."""
    n, p = params.shape
    rows = torch.arange(n, device=params.device)
    keep = ~_pinned(params, g, bounded)
    keep[rows, which] = False
    eye = torch.eye(p, dtype=h.dtype, device=h.device)
    inner = torch.where(keep.unsqueeze(-1) & keep.unsqueeze(-2), h, eye)
    g_free = torch.where(keep, g, 0.0)
    follow = torch.linalg.solve(inner, -torch.where(keep, h[rows, :, which], 0.0))
    newton = torch.linalg.solve(inner, -g_free)
    scale = inner.diagonal(dim1=1, dim2=2).abs().clamp_min(1e-6).unsqueeze(-1) * eye + eye
    step = torch.linalg.solve(inner + damping.view(-1, 1, 1) * scale, -g_free)
    return step, follow, -0.5 * (g_free * newton).sum(-1)


def _check_iterations(max_iter: int, tol: float) -> None:
    """An iteration limit ≥ 1 and a positive, finite tolerance, or a one-line error."""
    count("max_iter", max_iter)
    positive_number("tol", tol)


def _by_rows(fn: Callable, params: torch.Tensor, trials: TensorDictBase, budget: int) -> tuple:
    """``fn(params, trials)`` over chunks of rows holding at most ``budget`` trials (at least
    one row), its outputs (tensors or ``None``) joined along the rows."""
    size = max(1, budget // max(1, trials.shape[1]))
    parts = [fn(p, d) for p, d in zip(params.split(size), trials.split(size), strict=True)]
    return tuple(None if x[0] is None else torch.cat(x) for x in zip(*parts, strict=True))


def _behind_best(value: torch.Tensor, converged: torch.Tensor, n_starts: int) -> torch.Tensor:
    """How far each row's negative log-likelihood lies above the best converged row of its
    agent (rows agent-major, ``n_starts`` per agent; ``-inf`` where the agent has none)."""
    reached = torch.where(converged, value, torch.inf).view(-1, n_starts).amin(1)
    return value - reached.repeat_interleave(n_starts)


def _trials_device(trials: TensorDictBase) -> torch.device:
    """Where the trials' tensors live: the TensorDict's device, or (a TensorDict built without
    one, ``TensorDict({...}, batch_size)`` of CUDA tensors) that of its first tensor (the
    loss's keys may have been renamed)."""
    if trials.device is not None:
        return trials.device
    return next(iter(trials.values(include_nested=True, leaves_only=True))).device


def _on_bound(u: torch.Tensor) -> torch.Tensor:
    """Where unconstrained coordinates sit on the fit's bound, ``±BOUND`` (to round-off)."""
    return u.abs() >= BOUND - 1e-9


def _clamp_bounded(params: torch.Tensor, bounded: torch.Tensor) -> torch.Tensor:
    """``params [n, p]`` with the ``bounded`` coordinates ``[p]`` held within ``±BOUND``."""
    return torch.where(bounded, params.clamp(-BOUND, BOUND), params)


def _pin_bounds(
    params: torch.Tensor, h: torch.Tensor, g: torch.Tensor, bounded: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Curvature and gradient with the coordinates held on a bound taken out.

    A coordinate at ``±BOUND`` whose descent direction points further out stays where it is
    (an active bound constraint): its gradient is zeroed and its curvature decoupled, so the
    step and the Newton decrement concern the other coordinates only.
    """
    pinned = _pinned(params, g, bounded)
    keep = ~pinned
    h = torch.where(
        keep.unsqueeze(-1) & keep.unsqueeze(-2), h, torch.diag_embed(pinned.to(h.dtype))
    )
    return h, torch.where(pinned, torch.zeros_like(g), g)


def _pinned(params: torch.Tensor, g: torch.Tensor, bounded: torch.Tensor) -> torch.Tensor:
    """The ``bounded`` coordinates (``[p]``) on a bound whose descent direction points further
    out, ``[n, p]``."""
    return bounded & _on_bound(params) & (params * g < 0)


def _absolute(h: torch.Tensor) -> torch.Tensor:
    """``H`` with its eigenvalues replaced by their absolute values (saddle-free Newton).

    Where the likelihood is not concave a Newton step heads for the saddle or maximum of the
    quadratic model; flipping the negative curvature turns it downhill along those directions
    with a step scaled by how curved they are, instead of leaving it all to the damping.
    """
    eigval, eigvec = torch.linalg.eigh(h)
    return (eigvec * eigval.abs().unsqueeze(-2)) @ eigvec.mT


def _bfgs_update(h: torch.Tensor, s: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """BFGS update of curvatures ``h`` ``[n, p, p]`` after steps ``s`` changed gradients by ``y``.

    Powell's damping moves ``y`` toward ``h s`` where ``sᵀy < 0.2 sᵀhs`` (a step across a
    region of negative curvature), so the update stays positive definite.
    """
    hs = (h @ s.unsqueeze(-1)).squeeze(-1)
    shs = (s * hs).sum(-1, keepdim=True)
    sy = (s * y).sum(-1, keepdim=True)
    mix = torch.where(sy >= 0.2 * shs, torch.ones_like(sy), 0.8 * shs / (shs - sy))
    r = mix * y + (1 - mix) * hs
    return (
        h
        - hs.unsqueeze(-1) * hs.unsqueeze(-2) / shs.unsqueeze(-1)
        + r.unsqueeze(-1) * r.unsqueeze(-2) / (s * r).sum(-1)[:, None, None]
    )


def _newton_decrement(h: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """``½ gᵀ H⁻¹ g`` per row, ``inf`` where ``H`` is not positive definite."""
    chol, info = torch.linalg.cholesky_ex(h)
    ok = info == 0
    eye = torch.eye(h.shape[-1], dtype=h.dtype, device=h.device)
    chol = torch.where(ok[:, None, None], chol, eye)
    half = torch.linalg.solve_triangular(chol, g.unsqueeze(-1), upper=False).squeeze(-1)
    return torch.where(ok, 0.5 * (half**2).sum(-1), torch.full_like(g[:, 0], torch.inf))


def _damped_step(
    h: torch.Tensor, g: torch.Tensor, damping: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The Levenberg–Marquardt step of each row, damped until it lies in the trust region.

    The region (``MAX_STEP`` in every unconstrained coordinate) keeps a long step from landing
    where a logit saturates and the gradient vanishes. Raising the damping, rather than
    shortening the step, turns the step toward the gradient along poorly determined directions
    instead of shrinking the well-determined ones with them.
    """
    eye = torch.eye(h.shape[-1], dtype=h.dtype, device=h.device)
    scale = h.diagonal(dim1=1, dim2=2).abs().clamp_min(1e-6).unsqueeze(-1) * eye + eye
    for _ in range(40):
        step = -torch.linalg.solve(h + damping.view(-1, 1, 1) * scale, g.unsqueeze(-1))
        step = step.squeeze(-1)
        outside = step.abs().amax(-1) > MAX_STEP
        if not outside.any():
            break
        damping = torch.where(outside, damping * 4, damping)
    return _within_region(step), damping


def _within_region(step: torch.Tensor) -> torch.Tensor:
    """Steps ``[n, p]`` shortened, where needed, to ``MAX_STEP`` in every coordinate."""
    return step * (MAX_STEP / step.abs().amax(-1, keepdim=True)).clamp(max=1)


def _trial_scores(
    loss: InverseRationalLoss,
    k: int,
    params: torch.Tensor,
    trials: TensorDictBase,
    generator: torch.Generator | None = None,
    data: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Per-trial log-likelihood ``[n, N]``, scores of the data ``[n, N, p]`` (``None`` without
    ``data``: one backward pass fewer) and, with ``generator``, scores of data drawn from the
    model along the same filter (else ``None``).

    Each trial gets its own copy of the row's parameters, so one backward pass gives every
    trial's score.
    """
    n, n_trials = trials.shape[:2]
    per_trial = params.detach().unsqueeze(1).expand(n, n_trials, -1).clone().requires_grad_(True)
    with torch.enable_grad():
        theta = loss.theta(per_trial[..., :k].reshape(n * n_trials, k)).reshape(n, n_trials, -1)
        ll, drawn = loss.log_likelihood_and_draws(theta, per_trial[..., k:], trials, generator)
        if drawn is None:
            (score,) = torch.autograd.grad(ll.sum(), per_trial)
            return ll.detach(), score, None
        if not data:
            (score,) = torch.autograd.grad(drawn.sum(), per_trial)
            return ll.detach(), None, score
        both = torch.stack([ll.sum(), drawn.sum()])
        eye = torch.eye(2, dtype=both.dtype, device=both.device)
        (scores,) = torch.autograd.grad(both, per_trial, eye, is_grads_batched=True)
    return ll.detach(), scores[0], scores[1]


def _fisher_scoring(
    loss: InverseRationalLoss,
    k: int,
    params: torch.Tensor,
    trials: TensorDictBase,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Values ``[n]``, gradients ``[n, p]`` and a sampled Fisher information ``[n, p, p]``.

    Trials are independent given θ, so the sum of the outer products of their scores of drawn
    data estimates the Fisher information with the draws of all trials.
    """
    ll, score, drawn = _trial_scores(loss, k, params, trials, generator)
    return -ll.sum(1), -score.sum(1), drawn.mT @ drawn


def _skip_undefined(
    loss: InverseRationalLoss, candidates: torch.Tensor, scores: torch.Tensor, n: int
) -> torch.Tensor:
    """``scores [A, c]`` with the NaN ones ranked last (topk ranks NaN first), warning of them
    by the first such θ; an agent left with fewer than ``n`` finite ones is refused."""
    undefined = scores.isnan()
    if not bool(undefined.any()):
        return scores
    agent, row = undefined.nonzero()[0].tolist()
    where = f"θ ({loss.theta_space.format(loss.theta(candidates[agent, row][None])[0].cpu())})"
    cause = "the task's methods (or the trials) give NaN there; expected finite values for "
    short = ((~undefined).sum(1) < n).nonzero().flatten().tolist()
    if short:
        raise ValueError(
            f"fit: agent {short[0] + _FIRST_AGENT}'s log-likelihood is NaN at "
            f"{int(undefined[short[0]].sum())} "
            f"of its {scores.shape[1]} screened θ, fewer than n_starts={n} left to start from "
            f"(one at {where}): {cause}every θ in its space"
        )
    warnings.warn(
        f"fit: the log-likelihood is NaN at {int(undefined.sum())} of {undefined.numel()} "
        f"screened (agent, θ) pairs, the first at {where}: {cause}every θ in its space; those "
        "θ are not started from",
        stacklevel=3,
    )
    return scores.masked_fill(undefined, -torch.inf)


def _screen_starts(
    loss: InverseRationalLoss,
    trials: TensorDictBase,
    n_screen: int,
    n_starts: int,
    seed: int,
    starts: torch.Tensor | None = None,
) -> torch.Tensor:
    """Each agent's ``n_starts`` most likely candidates, ``[A·n, p]``.

    The candidates are ``n_screen`` prior draws (the same for every agent: an agent's fit
    depends on its data and the seed alone, not on which other agents share the call), spread
    evenly by a Sobol sequence, plus the agent's own ``starts`` row (natural θ) if given.
    """
    space = loss.theta_space
    n_agents, device = trials.shape[0], _trials_device(trials)
    free = space.free_mask
    k = int(free.sum())
    low, high = space.low(torch.float64)[free], space.high(torch.float64)[free]
    draws = space.default(torch.float64).expand(n_screen, -1).clone()
    if n_screen:
        with torch.device("cpu"):  # the engine keeps its state on the default device
            sobol = torch.quasirandom.SobolEngine(k, scramble=True, seed=seed)
            draws[:, free] = low + sobol.draw(n_screen, dtype=torch.float64) * (high - low)
        draws[0] = space.default(torch.float64)
    candidates = space.to_unconstrained(draws)[:, free].to(device).expand(n_agents, -1, -1)
    if starts is not None:
        own = space.to_unconstrained(starts.cpu())[:, free].to(device).unsqueeze(1)
        candidates = torch.cat([candidates, own], 1)
    # a candidate past ±BOUND (a draw at the prior's edge, a start on θ's bound) is scored and
    # started where the fit holds its bounded coordinates: from beyond, the first step would
    # drag it back along with the others' step, and a row refusing that step never moves
    candidates = _clamp_bounded(candidates, loss.bounded.to(device)[:k])
    nuisance = loss.action_model.nuisance_init.double().expand(n_agents, -1).to(device)
    # a bounded nuisance (a fitted lapse rate) starts within the fit's bounds
    nuisance = _clamp_bounded(nuisance, loss.bounded.to(device)[k:])
    # every (agent, candidate) pair is a row; rows are scored a chunk at a time
    n_candidates = candidates.shape[1]
    pairs = (
        candidates.reshape(-1, candidates.shape[-1]),
        nuisance.repeat_interleave(n_candidates, 0),
        trials.unsqueeze(1)
        .expand(n_agents, n_candidates, *trials.shape[1:])
        .reshape(-1, *trials.shape[1:]),
    )
    with torch.no_grad():
        scores = torch.cat(
            [
                loss.log_likelihood(loss.theta(u), v, d)
                for u, v, d in zip(*(x.split(SCREEN_ROWS) for x in pairs), strict=True)
            ]
        ).view(n_agents, n_candidates)
    n = min(n_starts, candidates.shape[1])
    scores = _skip_undefined(loss, candidates, scores, n)
    best = scores.topk(n, dim=1).indices  # [A, n]
    chosen = candidates.gather(1, best.unsqueeze(-1).expand(-1, -1, candidates.shape[-1]))
    return torch.cat([chosen, nuisance.unsqueeze(1).expand(-1, n, -1)], -1).reshape(
        n_agents * n, -1
    )
