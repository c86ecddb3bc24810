"""The recovery experiment on the 2D task: simulated agents, both estimators, honest scores.

Agents act with the shipped (or given) θ-conditioned policy plus Gaussian motor noise (or, on
a task of the user's own, with the policy Algorithm 1 learned for it). Two
groups: agents whose model is right (the world's θ is their own θ*, drawn from the prior) and
"mistaken" agents, whose θ* (from the prior) differs from the fixed task θ they live in. Every
θ component and the motor-noise scales are fitted from states and actions alone, by the hard
E-step (``map``) and with the agent's observations integrated out (``marginal``, started from the
``map`` fit); coverage of the 95% intervals, errors and widths are scored per parameter, and the
beliefs recovered under θ̂ are compared with the beliefs the agents really held.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import yaml
from scipy.stats import chi2
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from tqdm.auto import tqdm

from irc_torchrl.algorithms.calibration import (
    TAILS,
    Calibration,
    agent_intervals,
    calibrate_intervals,
    format_factors,
    simulate_at_fits,
    warn_too_few_refits,
)
from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.fit import (
    FitResult,
    check_sandwich,
    expected_intervals,
    fit_theta,
    particle_check,
    score_check,
)
from irc_torchrl.algorithms.recovery import format_parameters, score_recovery
from irc_torchrl.algorithms.runtime import check_workers, finish, resolve_device, torch_settings
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.algorithms.stages import Stages, fit_settings, format_resumed, stage_key
from irc_torchrl.checkpoint import resolve_checkpoint
from irc_torchrl.checks import (
    CALIBRATION,
    INFORMATION,
    PARTICLES,
    SIMULATION,
    STARTS,
    STREAMS_VERSION,
    check_fields,
    derived_seed,
    non_negative,
    one_of,
    probability,
)
from irc_torchrl.config import (
    FitConfig,
    RecordingFitConfig,
    config_to_dict,
)
from irc_torchrl.data.files import (
    earlier_summary,
    remove_stale,
    staged,
    write_json,
    write_text,
)
from irc_torchrl.data.trajectories import TRIAL_KEYS
from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.envs.model import SENSES, TaskModel, sensed_world
from irc_torchrl.modules.actor_critic import ACTOR_DTYPES, censored_action_model
from irc_torchrl.modules.likelihood import LAPSE_MAX, CensoredGaussianActionModel
from irc_torchrl.objectives.inverse import METHODS, InverseRationalLoss
from irc_torchrl.objectives.marginal import FINAL_STEPS, check_mixture
from irc_torchrl.plots import (
    overhead_view,
    plot_belief_overhead,
    plot_belief_time,
    plot_recovery,
)

__all__ = [
    "Recovery2DConfig",
    "DEMO_OVERRIDES",
    "belief_agreement",
    "belief_figures",
    "format_recovery",
    "predicted_widths",
    "recover_firefly2d",
    "recovery_stages",
    "run_recovery",
    "state_layout",
    "write_recovery",
]


@dataclass
class Recovery2DConfig:
    """``irc recover``: ``n_prior_agents`` right and ``n_mistaken_agents`` mistaken agents.

    ``task`` is the 2D firefly's, or the name of a task of the user's own given as a model
    (with ``checkpoint`` a policy ``irc train --model`` learned for it).
    """

    task: str = "firefly2d"
    seed: int = 0
    #: torch threads
    threads: int = 2
    #: where simulation and fits run, e.g. "cpu" or "cuda:0" (trials and figures come back
    #: to the CPU)
    device: str = "cpu"
    #: a checkpoint path or the name of a packaged one
    checkpoint: str = "firefly2d"
    n_prior_agents: int = 30
    n_mistaken_agents: int = 10
    n_trials: int = 100
    #: the agents' motor-noise standard deviation (fitted as a nuisance, per action dimension)
    motor_noise: float = 0.1
    #: how often each action dimension lapses (is unrelated to the belief), for the simulated
    #: agents and, unless ``fit_lapse``, in the fitted action model alike (0: never)
    lapse: float = 0.0
    #: fit each agent's lapse rate beside its motor noise (from ``irc fit``'s default start,
    #: whatever the agents' rate) instead of holding ``lapse``
    fit_lapse: bool = False
    #: "agent": every agent's observations are as noisy as its own θ* says (the task's
    #: ``sensory_names``; a mistaken agent's world is the default in all else), and the fits
    #: take them from the candidate θ, as no experimenter measures them; "world": from the
    #: recorded world's θ, which for the agents whose model is right is their θ* (a sensory
    #: noise measured apart)
    senses: str = "agent"
    #: comma-separated estimators; when both run, ``marginal`` starts from the ``fit.n_starts``
    #: most likely (under its own likelihood) of ``map``'s θ̂ and the ``fit.n_screen`` prior draws
    methods: str = "map,marginal"
    #: particles for checking each fit against a particle filter's likelihood at θ̂ and at
    #: θ* (0: no check; 1000 take about 25 s per agent of 100 trials on 2 cores, both points)
    particles: int = 0
    #: with ``marginal``, Gaussians the outer filter's latent splits into for each trial's last
    #: 4 steps (1: one throughout; 16 come closer to the particle filter, for ~6× the time)
    components: int = 1
    #: datasets per agent simulated at the last method's θ̂ (with its fitted motor noise, in
    #: its own world) and refitted the same way, to calibrate every method's intervals
    #: (:mod:`~irc_torchrl.algorithms.calibration`; 0: none). Each costs about one recovery's
    #: fitting time; without it the 2D intervals are too narrow for some agents (raw coverage
    #: 0.70–1.00 per parameter and draw, 0.820–0.900 per parameter over five draws)
    calibrate: int = 2
    #: how each parameter's calibration factor reads its tail: its "own" 95% quantile (a new
    #: pivot beyond it 5% of the time, whatever the other parameters' tails), or "shrunk"
    #: toward all parameters' by as much as it is noise (which pulls a lighter or heavier
    #: tail than the rest toward theirs: docs/recovery2d.md)
    calibration_tail: str = "own"
    #: the precision the frozen actor runs in inside the float64 likelihood: "float32" makes
    #: the recovery about 1.3× faster, with the same intervals at a given θ (different fits:
    #: each estimator's path through the rugged likelihood changes) and calibrated coverage
    #: alike over three draws of agents
    actor_dtype: str = "float32"
    #: intervals from the sandwich: both estimators approximate the likelihood, and the
    #: trials' scores vary more than the approximation's curvature says
    fit: FitConfig = field(
        default_factory=lambda: FitConfig(
            n_screen=16, n_starts=2, max_iter=80, curvature="bfgs", covariance="sandwich"
        )
    )

    def validate(self, model: TaskModel | None = None) -> Recovery2DConfig:
        """Return ``self`` if every field is usable, else raise a one-line error naming it.

        ``model`` is the task of the user's own the agents act in (``None``: the 2D firefly).
        """
        check_fields(self)
        if model is None and self.task != "firefly2d":
            raise ValueError(
                "config: task must be 'firefly2d' (a task of your own is given as a model, "
                f"--model), got {self.task!r}"
            )
        if model is not None and self.task != model.name:
            raise ValueError(f"config: task must be the model's, {model.name!r}, got {self.task!r}")
        for name in ("threads", "n_trials"):
            if getattr(self, name) < 1:
                raise ValueError(f"config: {name} must be ≥ 1, got {getattr(self, name)}")
        non_negative(
            particles=self.particles, calibrate=self.calibrate,
            n_prior_agents=self.n_prior_agents, n_mistaken_agents=self.n_mistaken_agents,
        )  # fmt: skip
        check_mixture(model or Firefly2DModel(), self.components, FINAL_STEPS)
        if self.n_prior_agents + self.n_mistaken_agents < 1:
            raise ValueError("config: n_prior_agents + n_mistaken_agents must be ≥ 1")
        if not 0 < self.motor_noise < math.inf:
            raise ValueError(f"config: motor_noise must be > 0 and finite, got {self.motor_noise}")
        probability(lapse=self.lapse)
        self.fit.validate()
        one_of("actor_dtype", self.actor_dtype, ACTOR_DTYPES)
        check_workers(self.fit.workers, resolve_device(self.device))
        one_of("calibration_tail", self.calibration_tail, TAILS)
        one_of("senses", self.senses, SENSES)
        unknown = [m for m in self.method_list if m not in METHODS]
        repeated = len(set(self.method_list)) != len(self.method_list)
        if unknown or repeated or not self.method_list:
            raise ValueError(
                f"config: methods must be a comma-separated subset of {METHODS}, each once, "
                f"got {self.methods!r}"
            )
        return self

    @property
    def method_list(self) -> list[str]:
        """The estimators to run, in order."""
        return [m.strip() for m in self.methods.split(",") if m.strip()]


def simulate_recovery_agents(
    model: TaskModel,
    actor: TensorDictSequential,
    config: Recovery2DConfig,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[TensorDict, torch.Tensor, torch.Tensor]:
    """Draw θ* and simulate both groups: ``(trials, theta_true, mistaken)``, on the
    actor's device.

    ``mistaken`` ``[A]`` is True for agents living in the task's default world.
    """
    space, device = model.theta_space, next(actor.parameters()).device
    n = config.n_prior_agents + config.n_mistaken_agents
    theta_true = space.sample((n,), generator=torch.Generator().manual_seed(config.seed))
    theta_true = theta_true.to(device)
    mistaken = torch.arange(n, device=device) >= config.n_prior_agents
    world = torch.where(mistaken.unsqueeze(-1), space.default(device=device), theta_true)
    world = sensed_world(model, world, theta_true, config.senses)
    policy = motor_noise_policy(
        actor, model.action_spec.to(device), config.motor_noise, config.lapse
    )
    trials = simulate_agents(
        model,
        policy,
        theta_true,
        config.n_trials,
        task_theta=world,
        seed=derived_seed(config.seed, SIMULATION),
        progress=progress,
    )
    return trials, theta_true, mistaken


def predicted_widths(
    model: TaskModel,
    actor: TensorDictSequential,
    n_trials: tuple[int, ...] = (100,),
    n_agents: int = 20,
    seed: int = 0,
) -> dict[int, dict[str, float]]:
    """How much of θ Algorithm 2 can recover from agents acting with ``actor``, before any fit.

    For each count in ``n_trials``, the median over ``n_agents`` of ``irc recover``'s agents
    whose model is right (θ* from the prior, each in its own world, its motor noise; the first
    trials of one simulation) of the width of each free parameter's 95% interval that the
    Fisher information at θ* predicts (:func:`~irc_torchrl.algorithms.fit.expected_intervals`).
    """
    if not n_trials or min(n_trials) < 1:
        raise ValueError(f"n_trials: expected positive trial counts, got {n_trials}")
    config = Recovery2DConfig(
        task=model.name,
        seed=seed,
        n_prior_agents=n_agents,
        n_mistaken_agents=0,
        n_trials=max(n_trials),
    ).validate(model)
    trials, theta, _ = simulate_recovery_agents(model, actor, config)
    action_model = _recovery_action_model(config, actor, model)
    loss = InverseRationalLoss(
        model, action_model, n_agents=n_agents, senses=config.senses, method="marginal"
    )
    space = model.theta_space
    widths = {}
    for n in n_trials:
        held = trials[:, :n].select(*TRIAL_KEYS)
        intervals = expected_intervals(loss, held, theta, seed=derived_seed(seed, INFORMATION))
        median = (intervals.high - intervals.low)[:, space.free_mask].median(0).values
        widths[n] = dict(zip(space.free_names, median.tolist(), strict=True))
    return widths


def _recovery_action_model(
    config: Recovery2DConfig, actor: TensorDictSequential, model: TaskModel
) -> CensoredGaussianActionModel:
    """The action model the recovery fits with: the agents' lapse rate held, or with
    ``fit_lapse`` fitted from where ``irc fit`` starts it (not the agents' own rate)."""
    lapse = RecordingFitConfig.lapse if config.fit_lapse else config.lapse
    return censored_action_model(
        actor, model, config.actor_dtype, config.motor_noise, lapse, config.fit_lapse
    )


def _true_nuisance(
    config: Recovery2DConfig, action_model: CensoredGaussianActionModel, result: FitResult
) -> torch.Tensor:
    """The agents' own nuisance rows ``[A, dn]``: the motor noise they acted with and, where
    the fit estimates a lapse rate, theirs (a rate of 0 lies on that fit's bound, outside its
    coordinates: there ν̂'s)."""
    nuisance = result.nuisance.clone()
    da = action_model.low.numel()
    nuisance[:, :da] = math.log(config.motor_noise)
    if action_model.fit_lapse and config.lapse > 0:
        nuisance[:, da] = math.log(config.lapse / (LAPSE_MAX - config.lapse))
    return nuisance


def belief_agreement(
    recovered: torch.Tensor,
    true: torch.Tensor,
    state: torch.Tensor,
    mask: torch.Tensor,
    state_names: tuple[str, ...] = Firefly2DModel.state_names,
    state_units: tuple[str, ...] = Firefly2DModel.state_units,
) -> dict:
    """How well recovered belief means match the agents' own, over recorded steps.

    Returns the correlation of believed positions (the components in ``state_units``'
    "distance", pooled: x and y of the firefly), and the correlation of the belief *errors*
    (belief − true state) over the components that are not rates (position and heading): the
    part of the belief the states alone do not reveal, the demanding test of a recovered
    belief. A state with no distance uses its non-rates for both, one of rates alone all.
    ``belief_error_by_component``: that correlation for each component, rates included.
    """
    rates = [any(per in unit for per in ("/s", "/step")) for unit in state_units]
    pose = [i for i, rate in enumerate(rates) if not rate] or list(range(len(rates)))
    position = [i for i, unit in enumerate(state_units) if unit == "distance"] or pose
    rec, tru, st = recovered[mask], true[mask].to(recovered.dtype), state[mask].to(recovered.dtype)

    def corr(a: torch.Tensor, b: torch.Tensor) -> float:
        a, b = a - a.mean(), b - b.mean()
        return float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-300))

    errors = rec - st, tru - st
    return {
        "position_correlation": corr(rec[:, position].reshape(-1), tru[:, position].reshape(-1)),
        "belief_error_correlation": corr(*(e[:, pose].reshape(-1) for e in errors)),
        "belief_error_by_component": {
            name: corr(*(e[:, i] for e in errors)) for i, name in enumerate(state_names)
        },
    }


def recover_firefly2d(
    config: Recovery2DConfig,
    progress: Callable[[str, int, int], None] | None = None,
    model: TaskModel | None = None,
    stages: Stages | None = None,
) -> tuple[TensorDict, dict, dict[str, FitResult]]:
    """Simulate, fit with every configured estimator and score: ``(trials, summary, fits)``.

    ``trials`` holds the simulated data with the truth (``theta``, ``belief``) and, per method,
    the recovered belief under ``(method, "belief")``. ``model``: a task of the user's own,
    whose checkpoint ``config.checkpoint`` names (``None``: the 2D firefly). ``stages`` keeps
    each fit as it finishes and, resuming, reads those an earlier run finished
    (:func:`recovery_stages`).
    """
    config.validate(model)
    warn_too_few_refits(config.n_prior_agents + config.n_mistaken_agents, config.calibrate)
    stages = stages or Stages()
    actor, model, _ = load_ensemble_policy(config.checkpoint, resolve_device(config.device), model)
    space = model.theta_space
    action_model = _recovery_action_model(config, actor, model)
    if config.fit.covariance == "sandwich":
        n_nuisance = action_model.nuisance_init.numel()
        check_sandwich(
            torch.tensor([config.n_trials]), len(space.free_names), n_nuisance, "fit.covariance"
        )
    start = time.perf_counter()
    trials, theta_true, mistaken = simulate_recovery_agents(
        model, actor, config, None if progress is None else partial(progress, "simulate")
    )
    timings = {"simulate_s": time.perf_counter() - start}
    held = trials.select(*TRIAL_KEYS)
    stages.include([held])
    n_agents = theta_true.shape[0]
    summary: dict = {
        "task": config.task,
        "seed": config.seed,
        "streams": STREAMS_VERSION,
        "checkpoint": config.checkpoint,
        "n_agents": n_agents,
        "n_trials": config.n_trials,
        "mean_trial_length": float(held["mask"].sum(-1).double().mean()),
        "mistaken": mistaken.tolist(),
        "units": space.units,
        "state_names": list(model.state_names),
        "state_units": list(model.state_units),
        "dt": model.dt,
        "methods": {},
    }
    fitted = _fit_methods(config, model, action_model, held, stages, progress)
    for method, (loss, result, fit_s) in fitted.items():
        scored = score_recovery(space, theta_true, result)
        truth = _true_nuisance(config, action_model, result)
        groups = {
            group: score_recovery(space, theta_true[rows], result.select(rows))["parameters"]
            for group, rows in (("prior", ~mistaken), ("mistaken", mistaken))
            if rows.any()
        }
        with torch.no_grad():
            beliefs = loss.recovered_beliefs(result.theta_hat, result.nuisance, held)
        trials[method] = beliefs
        entry = summary["methods"][method] = {
            "parameters": scored["parameters"],
            "by_group": groups,
            "agents": scored["agents"],
            "beliefs": belief_agreement(
                beliefs["belief", "mean"],
                trials["belief", "mean"],
                held["state"],
                held["mask"],
                model.state_names,
                model.state_units,
            ),
            "converged_fraction": float(result.converged.double().mean()),
            "motor_noise_hat": statistics.median(
                action_model.motor_noise(result.nuisance).flatten().tolist()
            ),
            "lapse_hat": statistics.median(action_model.lapse_rate(result.nuisance).tolist()),
            "lapse_fitted": action_model.fit_lapse,
            "fit_s": fit_s,
            "truth_check": _truth_check(loss, held, result, theta_true, truth, scored["agents"]),
        }
        timings[f"fit_{method}_s"] = fit_s
        if config.particles:
            entry["particle_check"], timings[f"particle_check_{method}_s"] = _particle_check(
                loss, held, result, theta_true, truth, config, scored["agents"], stages
            )
    if config.calibrate:
        begin = time.perf_counter()
        last = fitted[config.method_list[-1]].result
        calibrations = _calibrate(config, model, actor, action_model, held, last, stages, progress)
        for method, calibration in calibrations.items():
            calibrated = calibration.apply(space, fitted[method].result)
            scored = score_recovery(space, theta_true, calibrated)
            summary["methods"][method]["calibrated"] = {
                **calibration.to_dict(),
                "parameters": scored["parameters"],
                "agents": agent_intervals(calibrated),
            }
        timings["calibrate_s"] = time.perf_counter() - begin
    summary["timings"] = timings
    stages.summarise(summary)
    return trials, summary, {method: fit.result for method, fit in fitted.items()}


class _Fitted(NamedTuple):
    """One estimator's fit of the recorded trials, with its objective and wall time."""

    loss: InverseRationalLoss
    result: FitResult
    seconds: float


def _fit_methods(
    config: Recovery2DConfig,
    model: TaskModel,
    action_model: CensoredGaussianActionModel,
    held: TensorDict,
    stages: Stages,
    progress: Callable[[str, int, int], None] | None = None,
    label: str = "",
    stage: str = "fit",
) -> dict[str, _Fitted]:
    """Every configured estimator on ``held``, in order, each the stage ``{stage}_{method}``;
    after map, map's θ̂ joins the marginal's screened draws. ``label`` tells the progress
    bars of refits apart."""
    fitted: dict[str, _Fitted] = {}
    for method in config.method_list:
        loss = InverseRationalLoss(
            model, action_model, n_agents=held.shape[0], senses=config.senses, method=method,
            components=config.components,
        )  # fmt: skip
        work = partial(
            fit_theta,
            loss,
            held,
            n_starts=config.fit.n_starts,
            n_screen=config.fit.n_screen,
            max_iter=config.fit.max_iter,
            curvature=config.fit.curvature,
            covariance=config.fit.covariance,
            intervals=config.fit.intervals,
            starts=fitted["map"].result.theta_hat if "map" in fitted else None,
            seed=derived_seed(config.seed, STARTS),
            progress=None if progress is None else partial(progress, method + label),
            workers=config.fit.workers,
        )
        fitted[method] = _Fitted(loss, *stages.fit(f"{stage}_{method}", work, held.device))
    return fitted


def _calibrate(
    config: Recovery2DConfig,
    model: TaskModel,
    actor: TensorDictSequential,
    action_model: CensoredGaussianActionModel,
    held: TensorDict,
    result: FitResult,
    stages: Stages,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, Calibration]:
    """Every method's :class:`Calibration` from ``config.calibrate`` datasets simulated at
    ``result``'s θ̂, motor noise and lapse rate, each agent in its recorded world, refitted
    as ``held`` (the stages ``calibration{i}_{method}``)."""
    world = held["task_theta"][:, 0, 0]

    def refit(i: int) -> dict[str, FitResult]:
        synthetic = simulate_at_fits(
            model, actor, action_model, result, world, config.n_trials,
            derived_seed(config.seed, CALIBRATION, i), config.senses,
        )  # fmt: skip
        synthetic = synthetic.select(*TRIAL_KEYS).to(held.device)
        label = f" (calibration {i + 1}/{config.calibrate})"
        fitted = _fit_methods(
            config, model, action_model, synthetic, stages, progress, label, f"calibration{i + 1}"
        )
        return {method: fit.result for method, fit in fitted.items()}

    space, theta = model.theta_space, result.theta_hat.float()
    return calibrate_intervals(space, theta, refit, config.calibrate, config.calibration_tail)


def _truth_check(
    loss: InverseRationalLoss,
    held: TensorDict,
    result: FitResult,
    theta_true: torch.Tensor,
    nuisance_true: torch.Tensor,
    agents: list[dict],
) -> dict:
    """``log L(θ̂, ν̂) − log L(θ*, ν*)`` under the fitted likelihood itself (ν: the nuisance,
    ``nuisance_true`` the agents' own) into each agent's entry, and its median against an
    exact likelihood's (half the χ² median, one degree of freedom per fitted coordinate; at
    θ̂'s nuisance the statistic would have fewer); ``below_truth`` counts the fits that ended
    below the truth, which no maximum can. Also :func:`score_check` at the truth: the rms of
    one scoring step in standard deviations and its share beyond ±1.96 (an exact
    likelihood's: 1 and 5%; at ν̂ the nuisance's steps would be about 0)."""
    theta_true = theta_true.to(result.nuisance)
    with torch.no_grad():
        at_truth = loss.log_likelihood(theta_true, nuisance_true, held)
    ratio = result.log_likelihood - at_truth
    for agent, value in zip(agents, ratio.tolist(), strict=True):
        agent["log_likelihood_ratio"] = value
    steps = score_check(loss, held, theta_true, nuisance_true)
    return {
        "median_log_likelihood_ratio": statistics.median(ratio.tolist()),
        "expected_median": float(chi2.median(len(loss.parameter_names))) / 2,
        "below_truth": int((ratio < -1e-6).sum()),
        "score_rms": float(steps.pow(2).mean().sqrt()),
        "score_beyond": float((steps.abs() > 1.96).double().mean()),
    }


def _particle_check(
    loss: InverseRationalLoss,
    held: TensorDict,
    result: FitResult,
    theta_true: torch.Tensor,
    nuisance_true: torch.Tensor,
    config: Recovery2DConfig,
    agents: list[dict],
    stages: Stages,
) -> tuple[dict, float]:
    """:func:`particle_check` at (θ̂, ν̂) and at the agents' own (θ*, ν*) into each agent's
    entry, and its medians with the seconds both took; ``more_likely_at_theta_true`` counts
    the agents whose (θ̂, ν̂) the particle filter finds less likely than their own (which no
    exact maximum of the likelihood can be). Each is the stage
    ``particles{n}_{where}_{method}``."""
    checks, seconds = {}, 0.0
    points = {
        "at_theta_hat": (result.theta_hat, result.nuisance),
        "at_theta_true": (theta_true, nuisance_true),
    }
    seed = derived_seed(config.seed, PARTICLES)  # both points alike: their noise cancels
    for where, (theta, nuisance) in points.items():
        work = partial(particle_check, loss, held, theta, nuisance, config.particles, seed=seed)
        name = f"particles{config.particles}_{where}_{loss.method}"
        checks[where], took = stages.check(name, work, held.device)
        seconds += took
    ratio = (
        checks["at_theta_hat"]["particle_log_likelihood"]
        - checks["at_theta_true"]["particle_log_likelihood"]
    )
    for i, agent in enumerate(agents):
        agent["particle_check"] = {
            where: {k: float(v[i]) for k, v in check.items()} for where, check in checks.items()
        }
        agent["particle_check"]["log_likelihood_ratio"] = float(ratio[i])
    entry = {
        "particles": config.particles,
        **{
            f"median_gap_{where}": statistics.median(check["approximation_gap"].tolist())
            for where, check in checks.items()
        },
        "median_log_likelihood_ratio": statistics.median(ratio.tolist()),
        "more_likely_at_theta_true": int((ratio < 0).sum()),
    }
    return entry, seconds


#: ``irc demo --task firefly2d``: the recovery experiment made small enough for minutes (3
#: agents' 6 refits could not pin a calibration's 95% quantile, so it shows raw intervals)
DEMO_OVERRIDES = ("n_prior_agents=2", "n_mistaken_agents=1", "n_trials=40", "calibrate=0")


def recovery_stages(
    config: Recovery2DConfig, out: str | Path, model: TaskModel | None = None, resume: bool = False
) -> Stages:
    """The :class:`Stages` of a recovery into ``out`` (``out/stages``), keyed by every setting
    its fits depend on (:func:`fit_settings`), the policy's checkpoint, a task of the user's
    own and, once :func:`recover_firefly2d` has simulated them, the agents' trials."""
    settings = fit_settings(config)
    del settings["checkpoint"]  # its contents, not its path
    key = stage_key(settings, resolve_checkpoint(config.checkpoint), model)
    return Stages(Path(out) / "stages", key, resume, command="recover")


def run_recovery(
    config: Recovery2DConfig,
    out: str | Path,
    show_progress: bool = True,
    model: TaskModel | None = None,
    resume: bool = False,
    keep: bool = True,
) -> dict:
    """Run :func:`recover_firefly2d` (on ``model``'s task where given) into ``out``:
    ``config.yaml``, ``summary.json``, ``trials/`` (the simulated data with truth and
    recovered beliefs) and figures. With ``keep``, each fit and particle check is kept in
    ``out/stages`` as it finishes; with ``resume`` those an earlier, interrupted run of the
    same settings finished are read instead of run again (the same numbers;
    ``summary["resumed"]`` names them)."""
    config.validate(model)
    out = Path(out)
    stages = recovery_stages(config, out, model, resume) if keep else Stages()
    with torch_settings(config.threads, True):
        bars: dict[str, tqdm] = {}

        def progress(method: str, i: int, n: int) -> None:
            if method not in bars:
                # the stages run one after another: the last one's bar ends where it stopped,
                # not with its time and rate running on through the stages after it
                for bar in bars.values():
                    finish(bar)
                bars.clear()
                desc = method if method == "simulate" else f"fit ({method})"
                bars[method] = tqdm(total=n, desc=desc, disable=not show_progress)
            bars[method].update(1)

        trials, summary, _ = recover_firefly2d(config, progress, model, stages)
        for bar in bars.values():
            finish(bar)
    # written once the run has worked: a refused checkpoint or config leaves no folder behind
    write_recovery(trials.cpu(), summary, out, config_to_dict(config))
    stages.prune()
    return summary


def write_recovery(
    trials: TensorDict, summary: dict, out: str | Path, config: dict | None = None
) -> None:
    """A recovery's ``summary.json``, ``trials/``, figures and (given) ``config.yaml``, into
    ``out`` together: interrupted, the folder keeps the earlier run's, not a mixture."""
    out = Path(out)
    earlier = earlier_summary(out, "recover")
    with staged(out) as staging:
        if config is not None:
            write_text(staging / "config.yaml", yaml.safe_dump(config, sort_keys=False))
        write_json(staging / "summary.json", {"command": "recover", **summary})
        trials.memmap(staging / "trials")
        units = summary.get("units") or Firefly2DModel().theta_space.units
        written = [
            plot_recovery(entry, staging / f"recovery_{method}.png", title=method, units=units)
            for method, entry in summary["methods"].items()
        ]
        written += belief_figures(trials, summary["methods"], staging, **state_layout(summary))
    if earlier is not None:  # an earlier recovery's figures this one did not draw again
        kinds = ("recovery", "beliefs_overhead", "beliefs_time")
        figures = [f"{kind}_{method}.png" for kind in kinds for method in METHODS]
        remove_stale(out, figures, {path.name for path in written})


def state_layout(summary: Mapping) -> dict:
    """The names and units of a recovery summary's state and its time step, as
    :func:`belief_figures` takes them; a summary naming none (written before they did) is the
    2D firefly's."""
    return {
        "state_names": tuple(summary.get("state_names", Firefly2DModel.state_names)),
        "state_units": tuple(summary.get("state_units", Firefly2DModel.state_units)),
        "dt": summary.get("dt", Firefly2DModel.dt),
    }


def belief_figures(
    trials: TensorDict,
    methods: Iterable[str],
    out: Path,
    state_names: tuple[str, ...] = Firefly2DModel.state_names,
    state_units: tuple[str, ...] = Firefly2DModel.state_units,
    dt: float = Firefly2DModel.dt,
) -> list[Path]:
    """Agent 0's beliefs recovered by each method against its own, over time and, for a
    position in the plane, overhead (the paper's Fig. 1F and 1E), into ``out``; ``irc
    report`` redraws them from ``trials/``. The state's names and units default to the 2D
    firefly's."""
    planar = overhead_view(state_names, trials["target"].shape[-1])
    written = []
    for method in methods:
        arrays = _belief_arrays(trials, method, agent=0, dt=dt)
        title = f"agent 0: beliefs recovered by {method} vs the agent's own"
        if planar:
            overhead = out / f"beliefs_overhead_{method}.png"
            written.append(plot_belief_overhead(arrays, overhead, title=title))
        timeline = out / f"beliefs_time_{method}.png"
        written.append(plot_belief_time(arrays, state_names, state_units, timeline, title=title))
    return written


def _belief_arrays(trials: TensorDict, method: str, agent: int, dt: float) -> dict[str, np.ndarray]:
    """One agent's trials as the arrays the belief figures read."""
    one = trials[agent]
    steps = one["mask"].shape[-1]
    return {
        "state": one["state"].numpy(),
        "target": one["target"].numpy(),
        "mask": one["mask"].numpy(),
        "time": np.broadcast_to(np.arange(steps) * dt, one["mask"].shape),
        "mean": one[method, "belief", "mean"].numpy(),
        "cov": one[method, "belief", "cov"].numpy(),
        "true_mean": one["belief", "mean"].numpy(),
    }


def format_recovery(summary: dict) -> str:
    """A readable table of the recovery, one block per estimator."""
    lines = format_resumed(summary)
    for method, entry in summary["methods"].items():
        beliefs = entry["beliefs"]
        lines.append(
            f"{method}: {summary['n_agents']} agents × {summary['n_trials']} trials, "
            f"fit {entry['fit_s']:.0f} s, converged {entry['converged_fraction']:.0%}, "
            f"belief position r {beliefs['position_correlation']:.3f}, "
            f"belief error r {beliefs['belief_error_correlation']:.3f}"
        )
        by_component = beliefs.get("belief_error_by_component")
        if by_component:
            rows = ", ".join(f"{name} {r:.3f}" for name, r in by_component.items())
            lines.append(f"  belief error r by component: {rows}")
        if entry.get("lapse_fitted"):
            lines.append(
                f"  fitted medians: motor noise {entry['motor_noise_hat']:.3f}, "
                f"lapse rate {entry['lapse_hat']:.4f}"
            )
        truth = entry.get("truth_check")
        if truth:
            lines.append(
                f"  log L(θ̂) − log L(θ*): median {truth['median_log_likelihood_ratio']:.1f} "
                f"nats (an exact likelihood's: {truth['expected_median']:.1f}); "
                f"{truth['below_truth']} fit(s) ended below θ*"
            )
            lines.append(
                f"  one scoring step from θ*: rms {truth['score_rms']:.2f} sd, "
                f"{truth['score_beyond']:.0%} beyond ±1.96 (an exact likelihood's: 1, 5%)"
            )
        check = entry.get("particle_check")
        if check:
            lines.append(
                f"  particle check ({check['particles']} particles): the approximation loses "
                f"{check['median_gap_at_theta_hat']:.1f} nats at θ̂ and "
                f"{check['median_gap_at_theta_true']:.1f} at θ* (medians); "
                f"{check['more_likely_at_theta_true']} agents' θ* more likely than θ̂"
            )
        lines += [f"  {row}" for row in format_parameters(entry["parameters"])]
        calibrated = entry.get("calibrated")
        if calibrated:
            lines.append(
                f"  calibrated by {calibrated['n_datasets']} simulated dataset(s) per agent "
                f"(interval factors: {format_factors(calibrated)}):"
            )
            lines += [f"  {row}" for row in format_parameters(calibrated["parameters"])]
    return "\n".join(lines)
