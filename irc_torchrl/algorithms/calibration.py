"""Intervals calibrated by simulation: the parametric bootstrap of the interval's pivot.

Where the likelihood is an approximation, or not quadratic at the scale of its intervals (the
2D task's stops make it a cusp), the intervals of :func:`~irc_torchrl.algorithms.fit.fit_theta`
can be too narrow for some parameters, and no local curvature says by how much. Datasets
simulated from every agent's fitted model and refitted the same way show it: how far each
refit lands from the θ̂ that generated its data, in units of its own interval's half-width,
is the pivot whose 95% quantile over agents and datasets is the factor that makes the
intervals cover (bootstrap-t, one factor per parameter pooled over agents). Applied to the
real fits it calibrates them to the extent the pivot's spread at θ̂ is its spread at the
truth, which is what a simulation of the recovery can check.

Each factor is read off its parameter's own refits, at the rank a new pivot exceeds 5% of the
time whatever their number (:func:`_quantile_and_scale`): on 80 refits (40 agents × 2
datasets) it rests on the few largest, so it is noisy (one parameter's ranged 1.27–2.12 over
three draws of the 2D recovery), yet on average right for every parameter. ``tail="shrunk"``
(the default until 2026-12-07) reads it as its median size times its tail (the 95% quantile
over the median) shrunk toward the tail all parameters share by as much as the refits say it
is imprecise (empirical Bayes over a bootstrap of the agents). That steadies the factors
where every parameter's pivots have one shape, but pulls a parameter whose tail is lighter or
heavier than the rest's toward theirs: on simulated pivots of two such parameters it covered
them 0.91, and in the 2D recovery g_w over-covered (1.000 on three draws of five, 0.985 over
200 agents) where its own tail covers 0.950 (docs/recovery2d.md).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential

from irc_torchrl.algorithms.fit import FitResult
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.checks import count
from irc_torchrl.envs.model import TaskModel, sensed_world
from irc_torchrl.modules.likelihood import CensoredGaussianActionModel
from irc_torchrl.objectives.fisher import Z95, narrow
from irc_torchrl.theta import ThetaSpace

__all__ = [
    "FEWEST_REFITS",
    "MIN_REFITS",
    "TAILS",
    "Calibration",
    "agent_intervals",
    "calibrate_intervals",
    "format_factors",
    "interval_pivots",
    "simulate_at_fits",
    "warn_too_few_refits",
]

#: unconstrained coordinates are clamped here when intervals are widened (as Wald ends are)
_EDGE = 40.0
#: refits per parameter below which its factor rests on too few (its own 95% quantile on its
#: last one or two)
MIN_REFITS = 40
#: refits per parameter without which no factor is given: the fewest whose largest is a
#: 95% quantile, exceeded by a new pivot 1/(m + 1) = 5% of the time
FEWEST_REFITS = 19
#: how a parameter's tail (the 95% quantile of |pivot| over its median) is read: its own shrunk
#: toward all parameters' by as much as it is noise, or its own alone (the default)
TAILS = ("shrunk", "own")
#: bootstrap resamples of the agents that measure how precisely each parameter's tail is read
_RESAMPLES = 200


def interval_pivots(space: ThetaSpace, theta_true: torch.Tensor, result: FitResult) -> torch.Tensor:
    """Where the truth lies relative to each free parameter's interval, ``[n, k]``.

    ``Z95 × (θ − θ̂) / h`` in the unconstrained coordinates, with ``h`` the interval's
    half-width on the truth's side: the Wald z-score for a Wald interval, and in every case
    ``|pivot| ≤ Z95`` exactly where the interval covers ``theta_true`` (``[n, d]``). NaN
    where the fit has no interval (an infinite sd: the whole range, whatever a factor).
    """
    theta_true = space.validate(theta_true, "theta_true")
    result.check_space(space)
    if theta_true.shape != result.theta_hat.shape:
        raise ValueError(
            f"theta_true: expected one θ per fitted agent, {list(result.theta_hat.shape)}, "
            f"got {list(theta_true.shape)}"
        )
    free = space.free_mask.to(result.theta_hat.device)

    def unconstrained(theta: torch.Tensor) -> torch.Tensor:
        return space.to_unconstrained(theta.to(result.theta_hat))[:, free]

    true, hat = unconstrained(theta_true), unconstrained(result.theta_hat)
    low, high = unconstrained(result.intervals.low), unconstrained(result.intervals.high)
    half = torch.where(true >= hat, high - hat, hat - low)
    # the ratio first: a truth on an end gives exactly Z95, as covered as score_recovery counts it
    pivot = torch.where(true == hat, torch.zeros_like(hat), Z95 * ((true - hat) / half))
    return torch.where(result.intervals.std[:, free].isinf(), torch.nan, pivot)


@dataclass
class Calibration:
    """Per free parameter (``names``), the factor ``[k]`` by which 95% intervals widen (or
    narrow) to cover in 95% of simulated datasets, and the pivots ``[n_datasets, n_agents, k]``
    it was read from (:func:`interval_pivots`). Refits without an interval for a parameter
    do not count (no factor changes theirs); where none has one, or the quantile is infinite
    (refits missing with zero-width intervals), the factor is infinite: nothing then vouches
    for the real intervals, which it leaves without any."""

    names: list[str]
    factor: torch.Tensor
    pivots: torch.Tensor
    #: how the factors' tails were read (one of :data:`TAILS`)
    tail: str = "own"

    @classmethod
    def from_pivots(cls, names: list[str], pivots: torch.Tensor, tail: str = "own") -> Calibration:
        """The factors from refits' pivots ``[n_datasets, n_agents, k]``: per parameter the 95%
        quantile of ``|pivot|`` over datasets and agents (at the rank a new pivot exceeds 5% of
        the time; none below :data:`FEWEST_REFITS` refits), over Z95. ``tail="own"`` reads it off
        the parameter's refits alone; ``"shrunk"`` as its median (of its nonzero ones: a refit
        exactly on θ̂, both on a bound, has no scale) times its tail, the quantile over the
        median, shrunk toward the tail of all parameters (:func:`_shrink_tails`). A parameter
        whose refits are more than 5% infinite (missing with zero-width intervals) gets an
        infinite factor either way."""
        _check_tail(tail)
        if pivots.ndim != 3 or pivots.shape[-1] != len(names):
            raise ValueError(
                f"pivots: expected [n_datasets, n_agents, {len(names)}], got {list(pivots.shape)}"
            )
        size = pivots.abs()
        flat = size.flatten(0, 1)
        top = torch.finfo(size.dtype).max
        quantile, scale = _quantile_and_scale(flat)
        if tail == "shrunk":
            quantile = scale * _shrink_tails(size, (quantile / scale).log()).exp()
        infinite = flat.isinf().sum(0) > 0.05 * (~flat.isnan()).sum(0)
        unknown = ~torch.isfinite(quantile) | (quantile >= top / 2) | infinite
        factor = torch.where(unknown, torch.inf, quantile / Z95)
        return cls(names=list(names), factor=factor, pivots=pivots, tail=tail)

    @property
    def refits(self) -> torch.Tensor:
        """Per parameter, the refits with an interval ``[k]``: what its factor rests on."""
        return (~self.pivots.isnan()).flatten(0, 1).sum(0)

    def to_dict(self) -> dict:
        """The JSON form: the datasets, the factor and the refits it rests on per parameter
        (null where infinite) and the pivots per dataset, agent and parameter (null where the
        refit had no interval)."""
        return {
            "n_datasets": self.pivots.shape[0],
            "tail": self.tail,
            "factor": {
                name: c if math.isfinite(c) else None
                for name, c in zip(self.names, self.factor.tolist(), strict=True)
            },
            "refits": dict(zip(self.names, self.refits.tolist(), strict=True)),
            "pivots": [
                [[None if math.isnan(v) else v for v in agent] for agent in dataset]
                for dataset in self.pivots.tolist()
            ],
        }

    def apply(self, space: ThetaSpace, result: FitResult) -> FitResult:
        """``result`` with every free parameter's interval scaled by its factor about θ̂ (in
        the unconstrained coordinates as :meth:`~irc_torchrl.theta.ThetaSpace.to_unconstrained`
        clamps them, so it stays inside θ's bounds; a fit without an interval stays without)
        and its standard deviation and covariance scaled alike."""
        if space.free_names != self.names:
            raise ValueError(
                f"space: expected the free parameters {self.names}, got {space.free_names}"
            )
        result.check_space(space)
        hat = result.theta_hat
        free = space.free_mask.to(hat.device)
        scale = torch.ones(space.dim, dtype=hat.dtype, device=hat.device)
        scale[free] = self.factor.to(scale)
        u_hat = space.to_unconstrained(hat)

        old = result.intervals
        # no interval (an infinite sd, the whole range) stays without one; an infinite factor
        # (nothing vouches for the intervals) leaves none
        kept = ~free | old.std.isinf()
        voided = free & scale.isinf()

        def scaled(end: torch.Tensor, bound: torch.Tensor) -> torch.Tensor:
            u = u_hat + scale * (space.to_unconstrained(end) - u_hat)
            moved = torch.where(voided, bound, space.from_unconstrained(u.clamp(-_EDGE, _EDGE)))
            # an end on θ's bound stays there as the interval widens (the unconstrained
            # coordinates clamp it, so the round trip would move it inside by ~1e-8 of the range)
            moved = torch.where((end == bound) & (scale >= 1), end, moved)
            return torch.where(kept, end, moved)

        low = scaled(old.low, space.low(hat.dtype, hat.device).expand_as(hat))
        high = scaled(old.high, space.high(hat.dtype, hat.device).expand_as(hat))
        std = torch.where(kept, old.std, torch.where(voided, torch.inf, old.std * scale))
        factor = self.factor.to(hat)
        covariance = old.covariance * factor.unsqueeze(-1) * factor
        none = factor.isinf()
        intervals = dataclasses.replace(
            old,
            std=std,
            low=low,
            high=high,
            identified=narrow(space, low, high) & torch.isfinite(std),
            covariance=torch.where(none.unsqueeze(-1) | none, torch.inf, covariance),
        )
        return dataclasses.replace(result, intervals=intervals)


def _check_tail(tail: str) -> None:
    """Refuse a tail rule that is not one of :data:`TAILS`."""
    if tail not in TAILS:
        raise ValueError(f"tail: expected one of {TAILS}, got {tail!r}")


def _quantile_and_scale(size: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per parameter of ``|pivot|`` ``[..., n, k]`` (NaN: no interval), its 95% quantile and
    its median over the nonzero ones, ``[..., k]`` each.

    The quantile is read at rank 0.95 (m + 1) of the parameter's m refits, between the two
    nearest (Weibull's; an infinite pivot counted as the largest float): the k-th smallest of
    m is exceeded by a new pivot exchangeable with them (m + 1 − k)/(m + 1) of the time, so
    this one 5% of the time at any m, where the quantile interpolated at rank 0.95 (m − 1) + 1
    is exceeded 6% at m = 80 (40 agents × 2 datasets), 11% at m = 12 and 34% at m = 2
    (|N(0, 1)| pivots). Below :data:`FEWEST_REFITS` refits that rank lies past the largest:
    infinite.
    """
    m = (~size.isnan()).sum(-2, keepdim=True)
    rank = 95 * (m + 1)  # in hundredths
    ordered = size.clamp_max(torch.finfo(size.dtype).max).sort(dim=-2).values  # NaN last
    below = (rank // 100 - 1).clamp(0, size.shape[-2] - 1)
    low = ordered.gather(-2, below)
    # at most the m-th (the largest with an interval; past it lie the NaN of the others)
    high = ordered.gather(-2, torch.minimum(below + 1, (m - 1).clamp_min(0)))
    quantile = low + (rank % 100) / 100 * (high - low)
    quantile = torch.where(rank <= 100 * m, quantile, torch.inf).squeeze(-2)
    return quantile, torch.nanquantile(size.where(size > 0, torch.nan), 0.5, dim=-2)


def _shrink_tails(size: torch.Tensor, log_tail: torch.Tensor) -> torch.Tensor:
    """The log tails ``[k]`` of ``|pivot|`` ``[n_datasets, n_agents, k]`` shrunk toward their
    precision-weighted mean by the share of their spread that is not noise.

    Each tail's variance ``v`` comes from a seeded bootstrap over agents (an agent's datasets
    stay together), the tails' true spread ``τ²`` is their variance less the mean ``v``, and a
    tail moves to ``mean + τ²/(τ² + v) (tail − mean)``: all the way to the mean where the tails
    differ no more than their noise, hardly at all where they differ by far more.
    """
    n_agents = size.shape[1]
    picks = torch.randint(
        n_agents,
        (_RESAMPLES, n_agents),
        generator=torch.Generator().manual_seed(0),
        device="cpu",
    ).to(size.device)
    quantile, scale = _quantile_and_scale(size[:, picks].movedim(1, 0).flatten(1, 2))
    resampled = (quantile / scale).log()
    ok = torch.isfinite(resampled)
    count = ok.sum(0)
    mean = torch.where(ok, resampled, 0.0).sum(0) / count.clamp_min(1)
    variance = torch.where(ok, resampled - mean, 0.0).pow(2).sum(0) / (count - 1).clamp_min(1)
    known = torch.isfinite(log_tail) & (count > 1)
    if known.sum() < 2:
        return log_tail
    tails, precision = log_tail[known], variance[known].clamp_min(1e-12).reciprocal()
    centre = (precision * tails).sum() / precision.sum()
    spread = (tails.var() - variance[known].mean()).clamp_min(0)
    total = spread + variance
    weight = torch.where(total > 0, spread / total.clamp_min(1e-300), 1.0)
    return torch.where(known, centre + weight * (log_tail - centre), log_tail)


def agent_intervals(result: FitResult) -> list[dict]:
    """Per agent, the intervals of :meth:`FitResult.agent` (``ci_low``, ``ci_high``, ``std``,
    ``identified``): what a calibrated fit changes, for ``summary.json``."""
    keys = ("ci_low", "ci_high", "std", "identified")
    return [
        {k: v for k, v in result.agent(i).items() if k in keys}
        for i in range(len(result.theta_hat))
    ]


def warn_too_few_refits(n_agents: int, calibrate: int) -> None:
    """Warn, before any refit, where ``n_agents × calibrate`` refits per parameter are too few
    for any factor: every calibrated interval would span θ's range."""
    refits = n_agents * calibrate
    if 0 < refits < FEWEST_REFITS:
        warnings.warn(
            f"calibrate={calibrate}: {n_agents} agent(s) × {calibrate} dataset(s) give {refits} "
            f"refits per parameter, fewer than the {FEWEST_REFITS} a 95% quantile needs, so "
            "every calibrated interval will span θ's range; expected calibrate ≥ "
            f"{math.ceil(FEWEST_REFITS / n_agents)} (about {MIN_REFITS} refits pin it)",
            stacklevel=3,
        )


def format_factors(calibration: dict) -> str:
    """``"g_v 1.32, g_w none, ..."`` from a :meth:`Calibration.to_dict`, for tables, with a
    caution where a factor rests on fewer than :data:`MIN_REFITS` refits."""
    text = ", ".join(
        f"{n} {'none' if c is None else format(c, '.2f')}" for n, c in calibration["factor"].items()
    )
    # a parameter no refit has an interval for gets none from more refits either
    fewest = min((n for n in calibration.get("refits", {}).values() if n), default=MIN_REFITS)
    if fewest < MIN_REFITS:
        enough = math.ceil(calibration["n_datasets"] * MIN_REFITS / fewest)
        needed = (
            f", and with fewer than {FEWEST_REFITS} a parameter gets none"
            if fewest < FEWEST_REFITS
            else ""
        )
        text += (
            f" (a factor rests on {fewest} refit(s) only; about {MIN_REFITS} pin a 95% quantile"
            f"{needed}: calibrate={enough})"
        )
    return text


def simulate_at_fits(
    model: TaskModel,
    actor: TensorDictSequential,
    action_model: CensoredGaussianActionModel,
    result: FitResult,
    world: torch.Tensor,
    n_trials: int,
    seed: int,
    senses: str = "agent",
) -> TensorDict:
    """Trials ``[n_agents, n_trials, T]`` of agents acting as fitted: each at its θ̂ with
    the motor noise and lapse rate of its nuisance (held or fitted, as ``action_model`` reads
    them), in its world ``[n_agents, d]`` (with ``senses="agent"`` observing as noisily as
    its θ̂ says, as the fits assume: :func:`~irc_torchrl.envs.model.sensed_world`). They run
    on the actor's device and come back on the CPU, as recordings are read."""
    device = next(actor.parameters()).device
    noise = action_model.motor_noise(result.nuisance).unsqueeze(1).float()  # [agents, 1, da]
    lapse = action_model.lapse_rate(result.nuisance).view(-1, 1, 1).float()
    policy = motor_noise_policy(actor, model.action_spec.to(device), noise, lapse)
    theta, world = (x.float().to(device) for x in (result.theta_hat, world))
    world = sensed_world(model, world, theta, senses)
    return simulate_agents(model, policy, theta, n_trials, task_theta=world, seed=seed).cpu()


def calibrate_intervals(
    space: ThetaSpace,
    theta_generating: torch.Tensor,
    refit: Callable[[int], dict[str, FitResult]],
    n_datasets: int,
    tail: str = "own",
) -> dict[str, Calibration]:
    """One :class:`Calibration` per estimator from ``n_datasets`` simulated datasets.

    Args:
        space: the fits' θ space (its free parameters are calibrated).
        theta_generating: the θ ``[n_agents, d]`` every dataset is simulated at (each agent's
            θ̂ from the real data).
        refit: ``refit(i)`` simulates dataset ``i`` at ``theta_generating`` and fits it the way
            the real data were, returning each estimator's :class:`FitResult`.
        n_datasets: how many datasets (each holds one per agent).
        tail: how the factors' tail is read (:meth:`Calibration.from_pivots`).
    """
    count("n_datasets", n_datasets)
    _check_tail(tail)
    theta_generating = space.validate(theta_generating, "theta_generating")
    if theta_generating.ndim != 2:
        raise ValueError(
            f"theta_generating: expected [n_agents, {space.dim}], "
            f"got {list(theta_generating.shape)}"
        )
    pivots: dict[str, list[torch.Tensor]] = {}
    for i in range(n_datasets):
        for method, result in refit(i).items():
            pivots.setdefault(method, []).append(interval_pivots(space, theta_generating, result))
    return {
        method: Calibration.from_pivots(space.free_names, torch.stack(rows), tail)
        for method, rows in pivots.items()
    }
