"""The recovery experiment: simulate agents with known θ*, fit them, and score the fits.

This is how the method is validated: θ̂ against θ* with intervals (the paper's Fig. 1C) and
the coverage of the 95% intervals per parameter over many agents.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Mapping
from numbers import Real

import scipy.stats
import torch
from tensordict import TensorDict

from irc_torchrl.algorithms.fit import FitResult, fit_theta
from irc_torchrl.algorithms.simulate import boltzmann_policy, simulate_agents
from irc_torchrl.checks import SIMULATION, STARTS, derived_seed, module_device
from irc_torchrl.config import AgentsConfig, FitConfig
from irc_torchrl.envs.model import TaskModel
from irc_torchrl.modules.likelihood import BoltzmannActionModel
from irc_torchrl.objectives.inverse import InverseRationalLoss
from irc_torchrl.theta import ThetaSpace

__all__ = [
    "coverage_interval",
    "format_parameters",
    "format_pooled",
    "pool_coverage",
    "recover_agents",
    "score_recovery",
]


def recover_agents(
    model: TaskModel,
    q_network: torch.nn.Module,
    agents: AgentsConfig,
    fit: FitConfig,
    seed: int,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[TensorDict, dict, FitResult]:
    """Draw θ* from the prior, simulate each agent, fit all of them in one batched call, on
    the Q's device.

    Returns the simulated trials, the summary's ``agents``, ``parameters`` and ``timings``
    entries, and the fit result.
    """
    agents.validate()
    fit.validate()
    start = time.perf_counter()
    space = model.theta_space
    device = module_device(q_network)
    theta_true = space.sample((agents.n_agents,), generator=torch.Generator().manual_seed(seed))
    theta_true = theta_true.to(device)
    task_theta = space.default(device=device) if agents.world == "known" else None
    policy = boltzmann_policy(model, q_network, agents.temperature)
    trials = simulate_agents(
        model, policy, theta_true, agents.n_trials, task_theta, seed=derived_seed(seed, SIMULATION)
    )
    simulated = time.perf_counter()
    action_model = BoltzmannActionModel(q_network, agents.temperature)
    loss = InverseRationalLoss(model, action_model, n_agents=agents.n_agents, world=agents.world)
    result = fit_theta(
        loss,
        trials,
        n_starts=fit.n_starts,
        n_screen=fit.n_screen,
        max_iter=fit.max_iter,
        curvature=fit.curvature,
        covariance=fit.covariance,
        intervals=fit.intervals,
        seed=derived_seed(seed, STARTS),
        progress=progress,
        workers=fit.workers,
    )
    summary = score_recovery(space, theta_true, result)
    # the fitted temperature and its 95% interval (Wald, in log τ), as irc fit's motor noise
    ends = [
        action_model.temperature(end)
        for end in result.nuisance_intervals(
            torch.tensor(action_model.nuisance_bounded, device=device)
        )
    ]
    for i, entry in enumerate(summary["agents"]):
        entry["temperature"] = float(action_model.temperature(result.nuisance[i]))
        entry["temperature_ci"] = [float(end[i]) for end in ends]
    summary["timings"] = {"simulate_s": simulated - start, "fit_s": time.perf_counter() - simulated}
    return trials, summary, result


def coverage_interval(covered: int, n: int, level: float = 0.95) -> list[float]:
    """Clopper-Pearson interval of a coverage measured as ``covered`` of ``n`` agents.

    Over 40 agents a calibrated 95% interval covers 36 to 40 times in 95% of experiments, so a
    coverage is judged by whether this interval holds the nominal level, not by its point value.
    """
    if not 0 <= covered <= n or n < 1:
        raise ValueError(f"covered: expected a count in [0, n] with n ≥ 1, got {covered} of {n}")
    tail = (1 - level) / 2
    low = float(scipy.stats.beta.ppf(tail, covered, n - covered + 1)) if covered else 0.0
    high = float(scipy.stats.beta.ppf(1 - tail, covered + 1, n - covered)) if covered < n else 1.0
    return [low, high]


def _z_calibration(z: torch.Tensor) -> dict[str, float | None]:
    """Median and robust sd (1.4826 × MAD) of z-scores: bias and width calibration that one
    unconverged fit with a tiny std cannot swamp, as it does a mean and sd."""
    if not len(z):
        return {"z_median": None, "z_robust_sd": None}
    median = torch.quantile(z, 0.5)
    return {
        "z_median": float(median),
        "z_robust_sd": float(1.4826 * torch.quantile((z - median).abs(), 0.5)),
    }


def score_recovery(space: ThetaSpace, theta_true: torch.Tensor, result: FitResult) -> dict:
    """Per-agent entries and per-parameter coverage (with its Clopper-Pearson interval),
    errors, interval widths and the median and robust sd of the z-scores ``(θ̂ − θ*) / std``
    (0 and 1 for honest intervals; a robust sd of 1.4 says the intervals are 1.4× too narrow).

    Errors are given relative to θ* and to the width of the parameter's prior range: the first
    grows without bound for a θ* near 0 (a small effort cost) and is ``None`` for a parameter
    that may be negative (a logarithm: no ratio scale), the second compares parameters.
    """
    names = space.names
    agents = []
    for i in range(theta_true.shape[0]):
        entry = result.agent(i)
        entry["theta_true"] = {n: float(v) for n, v in zip(names, theta_true[i], strict=True)}
        entry["nuisance"] = [float(v) for v in result.nuisance[i]]
        agents.append(entry)
    parameters = {}
    for name in space.free_names:
        j = names.index(name)
        truth, hat = theta_true[:, j].double(), result.theta_hat[:, j]
        low, high = result.intervals.low[:, j], result.intervals.high[:, j]
        error = (hat - truth).abs()
        span = space[name].high - space[name].low
        relative = None if space[name].low < 0 else error / truth.abs().clamp_min(1e-12)
        covered = int(((low <= truth) & (truth <= high)).sum())
        std = result.intervals.std[:, j].double()
        # fixed (std 0) and unidentified (std inf) parameters have no z-score
        z = ((hat - truth) / std)[(std > 0) & std.isfinite()]
        parameters[name] = {
            "coverage": covered / len(truth),
            "coverage_ci": coverage_interval(covered, len(truth)),
            **_z_calibration(z),
            "median_abs_error": statistics.median(error.tolist()),
            "median_rel_error": None if relative is None else statistics.median(relative.tolist()),
            "median_range_error": statistics.median(error.tolist()) / span,
            "median_ci_width": statistics.median((high - low).tolist()),
            "identified_fraction": float(result.intervals.identified[:, j].double().mean()),
            "profiled_fraction": float(result.intervals.profiled[:, j].double().mean()),
        }
    return {"agents": agents, "parameters": parameters}


#: what draws of one recovery experiment share (their seeds differ), ``streams`` the version
#: of the random streams a seed derives (:data:`~irc_torchrl.checks.STREAMS_VERSION`)
EXPERIMENT = ("command", "task", "checkpoint", "n_agents", "n_trials", "mistaken", "streams")


def pool_coverage(summaries: Mapping[str, Mapping]) -> dict:
    """Each method's coverage per parameter, raw and calibrated, pooled over the agents of
    several draws of one recovery experiment (``summaries`` by label, e.g. folder), with its
    Clopper-Pearson interval and each draw's.

    One draw of 40 agents lands inside [0.90, 0.98] with probability 0.82 even for exact
    intervals, all of 8 independent parameters with 0.21; pooled over five draws (200 agents)
    a coverage is known to about ±0.03. Within a draw the calibrated intervals share one
    factor per parameter, so their pooled interval is somewhat too narrow: the spread over
    draws is the honest measure there. The draws must share :data:`EXPERIMENT` and fit the same
    methods and parameters, with different seeds (a draw counted twice counts its agents twice).
    """
    if len(summaries) < 2:
        raise ValueError(f"summaries: expected two recovery draws or more, got {len(summaries)}")
    draws = {label: _covered(label, summary) for label, summary in summaries.items()}
    (first_label, first), seeds = next(iter(summaries.items())), {}
    for label, summary in summaries.items():
        for key in (*EXPERIMENT, "shape"):
            mine, theirs = _experiment(summary, key), _experiment(first, key)
            if mine != theirs:
                raise ValueError(
                    f"{label}: {key} {mine}, {first_label}'s {theirs}; expected draws of one "
                    "recovery experiment"
                )
        seed = summary.get("seed")
        if seed is None or seed in seeds:
            said = "no seed recorded" if seed is None else f"the same draw as {seeds[seed]}"
            raise ValueError(
                f"{label}: {said} (seed {seed}): expected draws of different seeds, each "
                "agent counted once"
            )
        seeds[seed] = label
    agents = [int(s["n_agents"]) for s in summaries.values()]
    pooled: dict = {}
    for method, kinds in next(iter(draws.values())).items():
        for kind, names in kinds.items():
            if any(kind not in draw[method] for draw in draws.values()):
                continue  # calibrated in some draws only
            pooled.setdefault(method, {})[kind] = {
                name: _pooled([draw[method][kind][name] for draw in draws.values()], agents)
                for name in names
            }
    return {"draws": list(summaries), "n_agents": sum(agents), "methods": pooled}


def _experiment(summary: Mapping, key: str) -> object:
    """A summary's ``key`` of :data:`EXPERIMENT` (``shape``: its methods' free parameters;
    ``streams`` unrecorded in summaries written before it was)."""
    if key == "streams":
        return summary.get(key, "unrecorded")
    if key == "shape":
        return "; ".join(
            f"{m}: {', '.join(e['parameters'])}" for m, e in summary["methods"].items()
        )
    return summary.get(key)


def _covered(label: str, summary: Mapping) -> dict:
    """``{method: {"raw"|"calibrated": {name: agents covered}}}`` of a recovery summary, each
    count read off its coverage; refused in one line where the summary is not one."""
    n = summary.get("n_agents") if isinstance(summary, Mapping) else None
    methods = summary.get("methods") if isinstance(summary, Mapping) else None
    if isinstance(n, bool) or not isinstance(n, int) or n < 1 or not isinstance(methods, Mapping):
        raise ValueError(
            f"{label}: not a recovery experiment's summary (irc recover, irc demo --task "
            "firefly2d): expected n_agents ≥ 1 and methods with per-parameter coverage"
        )
    covered: dict = {}
    for method, entry in methods.items():
        entry = entry if isinstance(entry, Mapping) else {}
        raw = _counts(f"{label}: methods.{method}", entry, n)
        covered[method] = {"raw": raw}
        if entry.get("calibrated") is not None:
            field = f"{label}: methods.{method}.calibrated"
            covered[method]["calibrated"] = _counts(field, entry["calibrated"], n, tuple(raw))
    return covered


def _counts(field: str, scores: object, n: int, names: tuple[str, ...] = ()) -> dict:
    """``{name: agents covered}`` of one method's ``scores`` (with ``names``: those only)."""
    parameters = scores.get("parameters") if isinstance(scores, Mapping) else None
    scored = isinstance(parameters, Mapping) and bool(parameters)
    if not scored or (names and tuple(parameters) != names):
        expected = f"scores of {', '.join(names)}" if names else "per-parameter scores"
        raise ValueError(f"{field}.parameters: expected {expected}")
    return {
        name: _count(f"{field}.parameters.{name}.coverage", score, n)
        for name, score in parameters.items()
    }


def _count(field: str, score: object, n: int) -> int:
    """How many of ``n`` agents a coverage ``score["coverage"]`` counts, refused where it is
    not a count over ``n``."""
    coverage = score.get("coverage") if isinstance(score, Mapping) else None
    count = coverage * n if isinstance(coverage, Real) and not isinstance(coverage, bool) else -1
    if not 0 <= count <= n or abs(count - round(count)) > 1e-6:
        raise ValueError(f"{field}: expected a share of the {n} agents, got {coverage!r}")
    return round(count)


def _pooled(covered: list[int], agents: list[int]) -> dict:
    """The coverage over all agents of draws that covered ``covered`` of their ``agents``,
    with its interval and each draw's coverage."""
    return {
        "coverage": sum(covered) / sum(agents),
        "coverage_ci": coverage_interval(sum(covered), sum(agents)),
        "by_draw": [c / n for c, n in zip(covered, agents, strict=True)],
    }


def format_pooled(pooled: dict) -> str:
    """:func:`pool_coverage` as a table: per method and kind of interval, each parameter's
    pooled coverage, its 95% interval and the draws' coverages."""
    lines = [f"coverage over {len(pooled['draws'])} draws, {pooled['n_agents']} agents"]
    for method, kinds in pooled["methods"].items():
        for kind, parameters in kinds.items():
            lines.append(f"{method}, {kind} intervals:")
            for name, p in parameters.items():
                low, high = p["coverage_ci"]
                draws = " ".join(f"{c:.3f}" for c in p["by_draw"])
                lines.append(
                    f"  {name:<14}{p['coverage']:>7.3f}{f'[{low:.3f}, {high:.3f}]':>18}   {draws}"
                )
    return "\n".join(lines)


def format_parameters(parameters: dict) -> list[str]:
    """Table rows of :func:`score_recovery`'s per-parameter scores, a header first."""

    def number(value: float | None, spec: str) -> str:
        return "n/a" if value is None else format(value, spec)

    lines = [
        f"{'parameter':<14}{'coverage':>9}{'its 95% CI':>14}{'z median':>9}{'z rsd':>7}"
        f"{'median |err|':>14}{'median rel err':>16}{'err/range':>11}{'median CI width':>17}"
    ]
    for name, s in parameters.items():
        low, high = s["coverage_ci"]
        lines.append(
            f"{name:<14}{s['coverage']:>9.2f}{f'{low:.2f}–{high:.2f}':>14}"
            f"{number(s['z_median'], '+.2f'):>9}{number(s['z_robust_sd'], '.2f'):>7}"
            f"{s['median_abs_error']:>14.4f}{number(s['median_rel_error'], '.4f'):>16}"
            f"{s['median_range_error']:>11.4f}"
            f"{s['median_ci_width']:>17.4f}"
        )
    return lines
