"""Recorded trials on the 2D task: simulate agents into files, fit θ from files, keep beliefs.

:func:`simulate_recordings` (``irc simulate``) lets agents with a chosen or prior-drawn θ act by
a trained ensemble policy plus motor noise and writes one recording per agent, in any format of
:mod:`irc_torchrl.data.io`, with the true θ in ``summary.json``. :func:`fit_recordings`
(``irc fit``) reads recordings (one agent each), fits every agent's θ with 95% intervals
(Algorithm 2, actions scored by :class:`CensoredGaussianActionModel` around the same policy),
and writes ``summary.json``, the recovered beliefs and figures. A recording written by
``irc simulate`` is scored against the truth found in its folder's ``summary.json``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
import warnings
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictSequential
from tqdm.auto import tqdm

import irc_torchrl
from irc_torchrl.algorithms.calibration import (
    MIN_REFITS,
    Calibration,
    agent_intervals,
    calibrate_intervals,
    format_factors,
    simulate_at_fits,
    warn_too_few_refits,
)
from irc_torchrl.algorithms.ensemble import TASK, load_ensemble_policy
from irc_torchrl.algorithms.fit import FitResult, check_sandwich, fit_theta, particle_check
from irc_torchrl.algorithms.recovery import score_recovery
from irc_torchrl.algorithms.runtime import (
    check_workers,
    finish,
    resolve_device,
    torch_settings,
)
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.algorithms.stages import Stages, fit_settings, format_resumed, stage_key
from irc_torchrl.checks import CALIBRATION, SIMULATION, derived_seed, real
from irc_torchrl.config import RecordingFitConfig, SimulateConfig, config_to_dict
from irc_torchrl.data.files import (
    earlier_summary,
    remove_stale,
    staged,
    write_json,
    write_npz,
)
from irc_torchrl.data.io import nwb_module, read_trials, recording_suffix, write_trials
from irc_torchrl.data.trajectories import TRIAL_KEYS
from irc_torchrl.data.units import UNITS
from irc_torchrl.envs.model import TaskModel, continuous_actions, sensed_world
from irc_torchrl.modules.actor_critic import censored_action_model
from irc_torchrl.modules.likelihood import LAPSE_MAX, CensoredGaussianActionModel
from irc_torchrl.objectives.inverse import METHODS, InverseRationalLoss
from irc_torchrl.plots import report_run
from irc_torchrl.theta import ThetaSpace

__all__ = [
    "FORMATS",
    "FIT_METHODS",
    "fit_recordings",
    "fit_space",
    "format_fit",
    "recording_stages",
    "simulate_recordings",
]

#: file suffix per ``--format`` (memmap: a TensorDict folder, no suffix)
FORMATS = {"csv": ".csv", "csv.gz": ".csv.gz", "npz": ".npz", "nwb": ".nwb", "memmap": ""}
#: the name ``irc simulate`` gives a recording, in any of its formats
RECORDING_NAME = re.compile(rf"agent\d+({'|'.join(re.escape(s) for s in FORMATS.values() if s)})?")
#: what ``--method`` accepts: one estimator, or both (marginal reported, map kept beside it)
FIT_METHODS = (*METHODS, "both")
#: the correlation of two estimates from which the table names them as traded off by the data
TRADED_OFF = 0.8


def _theta_values(values: dict, field: str, space: ThetaSpace | None = None) -> dict[str, float]:
    """``{name: float}`` from config values, refusing anything that is not a real number (a
    flag is not) and, given the agents' ``space``, another value for a parameter it holds
    fixed."""
    out = {}
    for name, value in values.items():
        out[str(name)] = real(f"config: {field}.{name}", value)
        fixed = None if space is None else space.fixed.get(str(name))
        if fixed is not None and out[str(name)] != fixed:
            raise ValueError(
                f"config: {field}.{name}={value!r}, but the checkpoint's θ space holds {name} "
                f"fixed at {fixed}"
            )
    return out


def simulate_recordings(
    config: SimulateConfig,
    out: str | Path,
    checkpoint: str | Path = TASK,
    file_format: str = "csv",
    seed: int = 0,
    device: str = "cpu",
    progress: bool = True,
    task: str = TASK,
    model: TaskModel | None = None,
) -> dict[str, Any]:
    """Simulate ``config.n_agents`` agents and write one recording per agent into ``out``.

    Each agent's θ is ``config.theta`` where given and a prior draw (seeded) elsewhere; the
    world's θ is ``config.task_theta`` over the θ space's default (with ``config.senses``
    "agent", the agent's own values of the task's ``sensory_names``). ``model``: a task of the
    user's own, whose policy ``checkpoint`` holds (``None``: the 2D firefly task). Returns the
    ``summary.json`` written beside the recordings (the true θ of every file).
    """
    if model is None and task != TASK:
        raise ValueError(f"task: recordings are simulated for {TASK!r} only, got {task!r}")
    if file_format not in FORMATS:
        raise ValueError(f"format: expected one of {sorted(FORMATS)}, got {file_format!r}")
    if file_format == "nwb":
        nwb_module()  # pynwb missing: say so before simulating anything
    config.validate()
    if config.lapse >= LAPSE_MAX:
        warnings.warn(
            f"lapse={config.lapse}: irc fit fits lapse rates within (0, {LAPSE_MAX}), so a fit "
            "of these recordings ends on that bound",
            stacklevel=2,
        )
    target = resolve_device(device)
    out = Path(out)
    with torch_settings(config.threads, True):
        start = time.perf_counter()
        actor, model, ckpt = load_ensemble_policy(checkpoint, model=model)
        actor = actor.to(target)
        space = model.theta_space
        prior = space.sample((config.n_agents,), generator=torch.Generator().manual_seed(seed))
        theta = space.from_dict(_theta_values(config.theta, "theta", space), prior, "theta")
        world = space.from_dict(_theta_values(config.task_theta, "task_theta"), None, "task_theta")
        _check_senses(config, model)
        # each agent observes as noisily as its own θ says, unless the world says (senses)
        worlds = sensed_world(model, world, theta, config.senses)
        policy = motor_noise_policy(
            actor, model.action_spec.to(target), config.motor_noise, config.lapse
        )
        bar = tqdm(total=model.max_steps, desc="simulate", unit="step", disable=not progress)
        trials = simulate_agents(
            model,
            policy,
            theta.to(target),
            config.n_trials,
            worlds.to(target),
            seed=derived_seed(seed, SIMULATION),
            progress=lambda i, n: bar.update(i - bar.n),
        ).cpu()
        bar.close()
        # the files hold the world's θ as an experimenter knows it, not the agents' senses
        trials["task_theta"] = world.expand_as(trials["task_theta"]).clone()
        simulate_s = time.perf_counter() - start
        agents = []
        earlier = [agent.get("file") for agent in _earlier_agents(out, "simulate") or []]
        # interrupted while writing, the folder keeps the earlier run's recordings and summary;
        # the summary moves in with the recordings, last
        with staged(out) as staging:
            for i in tqdm(range(config.n_agents), desc="write recordings", disable=not progress):
                name = f"agent{i}{FORMATS[file_format]}"
                write_trials(trials[i].select(*TRIAL_KEYS), staging / name, model)
                agents.append(
                    {
                        "file": name,
                        "theta_true": space.to_dict(theta[i]),
                        "n_trials": config.n_trials,
                        "mean_steps": float(trials[i]["mask"].sum(-1).double().mean()),
                    }
                )
            write_s = time.perf_counter() - start - simulate_s
            summary = {
                "task": model.name,
                "command": "simulate",
                "seed": seed,
                "checkpoint": str(ckpt["path"]),
                "format": file_format,
                "config": config_to_dict(config),
                "task_theta": space.to_dict(world),
                "units": _units(space),
                "agents": agents,
                "timings": {"simulate_s": simulate_s, "write_s": write_s},
            }
            write_json(staging / "summary.json", summary)
            # an earlier run's summary would claim the true θ of recordings it did not write
            (out / "summary.json").unlink(missing_ok=True)
    # an earlier run's recordings this one did not rewrite would pass for this run's
    stale = [n for n in earlier if isinstance(n, str) and RECORDING_NAME.fullmatch(n)]
    remove_stale(out, stale, {agent["file"] for agent in agents})
    return summary


def _check_senses(config: SimulateConfig, model: TaskModel) -> None:
    """Refuse a world's value of the agent's senses (``task_theta.obs_sigma_v``) where the
    agents' senses are their own (``senses=agent``): it would be overridden unseen."""
    given = [name for name in model.sensory_names if name in config.task_theta]
    if given and config.senses == "agent":
        raise ValueError(
            f"task_theta.{given[0]}: with senses=agent each agent observes as noisily as its own "
            f"θ says; expected theta.{given[0]} for the agents' value, or senses=world"
        )


def _earlier_agents(out: Path, command: str) -> list[dict] | None:
    """The ``agents`` of the ``summary.json`` an earlier ``irc <command>`` left in ``out``
    (``None`` where no such run did: then nothing there is that run's to remove)."""
    summary = earlier_summary(out, command)
    if summary is None:
        return None
    agents = summary.get("agents")
    return [a for a in agents if isinstance(a, dict)] if isinstance(agents, list) else []


def fit_space(space: ThetaSpace, free: Sequence[str] | None, fixed: dict) -> ThetaSpace:
    """``space`` with only ``free`` fitted (when ``None``: its free parameters not in ``fixed``).

    The others are held at ``fixed[name]`` where given, else at their default.
    """
    if isinstance(free, str):  # its letters would be taken for names
        raise TypeError(f"free: expected a list of parameter names, got the string {free!r}")
    values = _theta_values(fixed, "theta", space)
    for name, value in values.items():
        try:  # unknown names (a KeyError listing the valid ones), values outside the range
            space.fix(**{name: value})
        except (KeyError, ValueError) as error:
            raise type(error)(f"theta.{name}: {error.args[0]}") from None
    names = [n for n in space.free_names if n not in values] if free is None else list(free)
    for name in names:
        try:
            space[name]
        except KeyError as error:
            raise KeyError(f"free: {error.args[0]}") from None
        if name in space.fixed:
            raise ValueError(
                f"free: {name!r} is fixed at {space.fixed[name]} in the checkpoint's θ space; "
                f"free parameters: {', '.join(space.free_names)}"
            )
        if name in values:
            raise ValueError(f"free: {name!r} is both fitted (--free) and fixed (theta.{name})")
    if not names:
        raise ValueError("free: no parameter to fit")
    default = space.default(torch.float64)
    held = {
        n: values.get(n, float(default[space.index(n)])) for n in space.free_names if n not in names
    }
    return space.fix(**held)


def _units(space: ThetaSpace, declared: Mapping[str, str] | None = None) -> dict[str, str]:
    """Each parameter's unit; with recorded units declared (``units.x=cm``), the task's
    distance unit reads as the metre they were converted to."""
    return {p.name: _in_metres(p.unit, declared) for p in space.parameters}


def _in_metres(unit: str, declared: Mapping[str, str] | None) -> str:
    """``unit`` with the task's "distance" named "m" where a recorded distance or speed unit
    was declared (and converted to the metre)."""
    lengths = {**UNITS["distance"], **UNITS["distance/s"]}
    metres = any(u in lengths for u in (declared or {}).values())
    return unit.replace("distance", "m") if metres else unit


def _simulated_truth(
    path: Path, space: ThetaSpace, task: str, recording: TensorDict
) -> torch.Tensor | None:
    """The true θ of a recording written by ``irc simulate`` (its folder's summary), if any.

    It is checked in ``space`` before any fitting: a summary of ``irc simulate`` that names
    the recording but mangles its ``theta_true`` is refused, not ignored (the fit would be
    reported without its truth) nor found out after the fit; so is a recording it names as
    simulated for another task than ``task``, the fit's. A ``recording`` whose trials are not
    as many, or not as long on average, as the summary says is another file under that name
    (a lab's own, one copied over it): it is fitted without a truth, with a warning.
    """
    summary = path.parent / "summary.json"
    try:
        data = json.loads(summary.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("command") != "simulate":
        return None
    agents = data.get("agents", [])
    if not isinstance(agents, list) or not all(isinstance(a, dict) for a in agents):
        raise ValueError(
            f"{summary}: field 'agents' is {agents!r:.80}; expected a list of "
            "{file, theta_true} entries as irc simulate writes them"
        )
    for agent in agents:
        if agent.get("file") == path.name and "theta_true" in agent:
            simulated_for = data.get("task")
            if isinstance(simulated_for, str) and simulated_for != task:
                raise ValueError(
                    f"{path}: simulated for task {simulated_for!r} ({summary}), fitted here as "
                    f"{task!r}; expected that task's --model (and its policy's --checkpoint)"
                )
            truth, where = agent["theta_true"], f"{summary}: {path.name}'s theta_true"
            numbers = isinstance(truth, dict) and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in truth.values()
            )
            if not numbers:
                raise ValueError(f"{where} is {truth!r:.80}; expected {{name: number}}")
            truth = space.from_dict(truth, field=where)
            return truth if _as_simulated(path, recording, agent, summary) else None
    return None


def _as_simulated(path: Path, recording: TensorDict, agent: dict, summary: Path) -> bool:
    """Whether ``recording`` has the trial count and mean length ``irc simulate`` wrote for it
    (``agent``, its entry in ``summary``; a summary without them is taken at its word)."""
    n_trials, mean_steps = agent.get("n_trials"), agent.get("mean_steps")
    if not isinstance(n_trials, int) or not isinstance(mean_steps, float):
        return True
    steps = float(recording["mask"].sum(-1).double().mean())
    if len(recording) == n_trials and math.isclose(steps, mean_steps, rel_tol=1e-9):
        return True
    warnings.warn(
        f"{path}: {len(recording)} trials of {steps:.4g} steps on average, not the {n_trials} "
        f"of {mean_steps:.4g} irc simulate wrote under this name ({summary}): fitted without "
        "its true θ",
        stacklevel=3,
    )
    return False


def _labels(paths: Sequence[Path]) -> list[str]:
    """A short unique name per recording (its name without its format's suffix, numbered
    where those repeat, and marked where a number makes another file's)."""
    stems = [p.name.removesuffix(recording_suffix(p)) for p in paths]
    labels: list[str] = []
    for i, stem in enumerate(stems):
        label = stem if stems.count(stem) == 1 else f"{stem}_{i}"
        while label in labels or (label != stem and label in stems):
            label += "_"
        labels.append(label)
    return labels


def _pad_steps(trials: TensorDictBase, steps: int) -> TensorDictBase:
    """Held trials ``[n, T]`` padded to ``steps`` by repeating the last step, unrecorded."""
    n, length = trials.shape
    if length == steps:
        return trials
    tail = trials[:, -1:].expand(n, steps - length).clone()
    tail["mask"] = torch.zeros(n, steps - length, dtype=torch.bool, device=trials["mask"].device)
    return torch.cat([trials, tail], 1)


def fit_recordings(
    paths: Sequence[str | Path],
    out: str | Path,
    config: RecordingFitConfig,
    checkpoint: str | Path = TASK,
    method: str = "marginal",
    free: Sequence[str] | None = None,
    seed: int = 0,
    device: str = "cpu",
    progress: bool = True,
    model: TaskModel | None = None,
    resume: bool = False,
) -> dict[str, Any]:
    """Fit θ for each recording (one agent per file) and write the results into ``out``.

    ``method="marginal"`` starts from the ``map`` fit (the paper's estimator) and integrates
    over the agent's unseen observations; ``"both"`` keeps both results. Recordings with the
    same number of trials are fitted in one batched call (at convergence an agent's θ̂ does
    not depend on the others; a fit stopped by ``max_iter`` may end elsewhere). Writes
    ``summary.json``, ``beliefs.npz`` (the agent's belief at every recorded step under θ̂,
    with the recording's trial numbers) and figures; returns the summary. ``model``: a task of
    the user's own, whose policy ``checkpoint`` holds (``None``: the 2D firefly task). Each
    fit is kept in ``out/stages`` as it finishes; with ``resume`` those an earlier, interrupted
    fit of the same recordings and settings finished are read instead of fitted again (the
    same numbers; ``summary["resumed"]`` names them).
    """
    if method not in FIT_METHODS:
        raise ValueError(f"method: expected one of {FIT_METHODS}, got {method!r}")
    if not paths:
        raise ValueError("fit: no recording given")
    config.validate()
    target = resolve_device(device)
    check_workers(config.workers, target)
    warn_too_few_refits(len(paths), config.calibrate)
    paths = [Path(p) for p in paths]
    seen: dict[Path, Path] = {}
    for path in paths:
        if seen.setdefault(path.resolve(), path) is not path:
            raise ValueError(f"fit: {path} is given twice; expected each recording once")
    out = Path(out)
    with torch_settings(config.threads, True):
        actor, model, ckpt = load_ensemble_policy(checkpoint, model=model)
        actor = actor.to(target)  # whole: calibration's simulations run it as a policy
        space = fit_space(model.theta_space, free, config.theta)
        start = time.perf_counter()
        units = {str(k): str(v) for k, v in config.units.items()}
        columns = {"time_column": config.time_column, "trial_column": config.trial_column}
        recordings = [read_trials(p, model, units=units, **columns) for p in paths]
        read_s = time.perf_counter() - start
        truths = [
            _simulated_truth(p, space, model.name, r)
            for p, r in zip(paths, recordings, strict=True)
        ]
        action_model = censored_action_model(
            actor, model, config.actor_dtype, config.motor_noise, config.lapse, config.fit_lapse
        )
        # refused before any fit, naming the recording
        n_nuisance = action_model.nuisance_init.numel()
        labels = [str(path) for path in paths]
        _check_enough_actions(recordings, model, len(space.free_names), n_nuisance, labels)
        if config.covariance == "sandwich":
            n_trials = torch.tensor([len(recording) for recording in recordings], device="cpu")
            check_sandwich(n_trials, len(space.free_names), n_nuisance, agents=labels)
        stages = recording_stages(
            out, config, ckpt["path"], model, recordings, space.free_names, seed, target, resume
        )
        fits, beliefs, timings, checks, per_trial = _fit_groups(
            model, action_model, space, recordings, config, method, seed, target, progress, stages
        )
        calibrations = {}
        if config.calibrate:
            start = time.perf_counter()
            calibrations = _calibrate_fits(
                model, actor, action_model, space, recordings, fits, config, method, seed,
                target, progress, stages,
            )  # fmt: skip
            timings["calibrate_s"] = time.perf_counter() - start
    timings = {"read_s": read_s, **timings}
    labels = _labels(paths)
    by_method = {
        name: _scored(space, action_model, result, truths, paths, labels, recordings, checks[name])
        for name, result in fits.items()
    }
    for name, part in by_method.items():
        for agent, recording, values in zip(
            part["agents"], recordings, per_trial[name], strict=True
        ):
            agent["worst_trials"] = _worst_trials(recording, values)
    for name, calibration in calibrations.items():
        _add_calibrated(by_method[name], space, calibration, fits[name], truths)
    primary = "marginal" if method in ("marginal", "both") else "map"
    summary = {
        "task": model.name,
        "command": "fit",
        "method": method,
        # the top-level agents, their beliefs and the belief figures are this method's
        "primary_method": primary,
        "seed": seed,
        "version": irc_torchrl.__version__,
        "checkpoint": str(ckpt["path"]),
        "free": space.free_names,
        "fixed": {n: space.fixed[n] for n in space.names if n in space.fixed},
        "config": config_to_dict(config),
        "units": _units(space, config.units),
        **by_method[primary],
        "timings": timings,
    }
    if method == "both":
        summary["methods"] = by_method
    summary["state_names"] = list(model.state_names)
    summary["state_units"] = [_in_metres(unit, config.units) for unit in model.state_units]
    stages.summarise(summary)
    earlier = _earlier_agents(out, "fit")
    # interrupted while writing, the folder keeps the earlier run's files, not a mixture
    with staged(out) as staging:
        _write_beliefs(staging / "beliefs.npz", labels, recordings, beliefs, per_trial[primary])
        write_json(staging / "summary.json", summary)
        written = {path.name for path in report_run(staging)}
    stages.prune()
    if earlier is not None:  # an earlier fit's figures this one did not draw again
        kinds, methods = ("recovery", "estimates"), ("", "_map", "_marginal")
        figures = [f"{kind}{method}.png" for kind in kinds for method in methods]
        figures += [
            f"{agent['label']}_beliefs_{view}.png"
            for agent in earlier
            if isinstance(agent.get("label"), str)
            for view in ("overhead", "time")
        ]
        remove_stale(out, figures, written)
    return summary


def _check_enough_actions(
    recordings: Sequence[TensorDict], model: TaskModel, k: int, n_nuisance: int, labels: list[str]
) -> None:
    """Refuse a recording with fewer recorded action values than fitted coordinates (``k`` of
    θ, ``n_nuisance``): no data that few pins them down, and its fit could only end somewhere
    on a flat likelihood, unconverged."""
    per_step = model.action_spec.shape[-1] if continuous_actions(model.action_spec) else 1
    for recording, label in zip(recordings, labels, strict=True):
        actions = int(recording["mask"].sum()) * per_step
        if actions < k + n_nuisance:
            raise ValueError(
                f"{label}: {actions} recorded action values for {k + n_nuisance} fitted "
                f"coordinates ({k} of θ, {n_nuisance} nuisance): too few to fit; expected more "
                "trials, or fewer free parameters (--free)"
            )


def recording_stages(
    out: str | Path,
    config: RecordingFitConfig,
    checkpoint: str | Path,
    model: TaskModel,
    recordings: Sequence[TensorDictBase],
    free: Sequence[str],
    seed: int,
    device: torch.device | str,
    resume: bool = False,
) -> Stages:
    """The :class:`Stages` of a fit of ``recordings`` into ``out`` (``out/stages``), keyed by
    ``config``'s fields its fits depend on (:func:`fit_settings`), the policy's
    ``checkpoint``, the task ``model``, the recordings, the ``free`` parameters, ``seed`` and
    ``device``. Not by the method: map's fit is the same whichever follows it, and the stages
    are named by theirs."""
    settings = {"config": fit_settings(config), "free": list(free), "seed": seed}
    settings["device"] = str(torch.device(device))
    key = stage_key(settings, checkpoint, model, recordings)
    return Stages(Path(out) / "stages", key, resume, command="fit")


def _by_trial_count(recordings: list[TensorDict]) -> dict[int, list[int]]:
    """The indices of the recordings per number of trials (each group is fitted as one batch)."""
    groups: dict[int, list[int]] = {}
    for i, recording in enumerate(recordings):
        groups.setdefault(recording.shape[0], []).append(i)
    return groups


def _fit_groups(
    model: TaskModel,
    action_model: CensoredGaussianActionModel,
    space: ThetaSpace,
    recordings: list[TensorDict],
    config: RecordingFitConfig,
    method: str,
    seed: int,
    device: torch.device,
    progress: bool,
    stages: Stages,
    stage: str = "fit",
) -> tuple[
    dict[str, FitResult], list[TensorDict], dict[str, float], dict[str, list], dict[str, list]
]:
    """Fit every recording, batching those with equal trial counts; per method and per file.
    Each batch's fit is the stage ``{stage}_{n_trials}trials_{method}``, its particle check
    ``particles{n}_{n_trials}trials_{method}``.

    Returns the fit per method (agents in the order of ``recordings``), each recording's
    beliefs under the primary method's θ̂ (``[n_trials, T]``), the time of each method,
    with ``config.particles`` each recording's :func:`particle_check` at θ̂ per method
    (``None`` without), and per method each recording's log-likelihood per trial at θ̂.
    """
    groups = _by_trial_count(recordings)
    methods = ["map"] if method == "map" else ["map", "marginal"]
    parts: dict[str, list[tuple[list[int], FitResult]]] = {m: [] for m in methods}
    beliefs: list[TensorDict | None] = [None] * len(recordings)
    checks: dict[str, list] = {m: [None] * len(recordings) for m in methods}
    per_trial: dict[str, list] = {m: [None] * len(recordings) for m in methods}
    timings = {f"fit_{m}_s": 0.0 for m in methods}
    for members in groups.values():
        steps = max(recordings[i].shape[1] for i in members)
        held = torch.stack(
            [_pad_steps(recordings[i].select(*TRIAL_KEYS), steps) for i in members]
        ).to(device)
        starts = None
        for name in methods:
            loss = InverseRationalLoss(
                model, action_model, theta_space=space, n_agents=len(members),
                senses=config.senses, method=name, components=config.components,
            ).to(device)  # fmt: skip
            work = partial(_fit_batch, loss, held, config, seed, starts, progress)
            result, fit_s = stages.fit(f"{stage}_{held.shape[1]}trials_{name}", work, device)
            start = time.perf_counter() - fit_s  # the method's time: its fit's, then what follows
            starts = result.theta_hat
            parts[name].append((members, result))
            with torch.no_grad():
                values = loss.log_likelihood(result.theta_hat, result.nuisance, held, True)
            for j, i in enumerate(members):
                per_trial[name][i] = values[j].cpu()
            if name == methods[-1]:
                recovered = loss.recovered_beliefs(result.theta_hat, result.nuisance, held).cpu()
                for j, i in enumerate(members):
                    beliefs[i] = recovered[j, :, : recordings[i].shape[1]]
            timings[f"fit_{name}_s"] += time.perf_counter() - start
            if config.particles and (method == "both" or name == methods[-1]):  # reported
                work = partial(
                    particle_check, loss, held, result.theta_hat, result.nuisance,
                    config.particles, seed,
                )  # fmt: skip
                particles = f"particles{config.particles}_{held.shape[1]}trials_{name}"
                check, check_s = stages.check(particles, work, device)
                for j, i in enumerate(members):
                    checks[name][i] = {k: float(v[j]) for k, v in check.items()}
                key = f"particle_check_{name}_s"
                timings[key] = timings.get(key, 0.0) + check_s
    fits = {}
    for name, pieces in parts.items():
        order = [i for members, _ in pieces for i in members]
        combined = FitResult.cat([r.cpu() for _, r in pieces])
        rank = torch.tensor(order, device="cpu").argsort()
        fits[name] = combined.select(rank)
    timings["fit_s"] = sum(v for k, v in timings.items() if k.startswith("fit_"))
    return fits, beliefs, timings, checks, per_trial


def _fit_batch(
    loss: InverseRationalLoss,
    held: TensorDict,
    config: RecordingFitConfig,
    seed: int,
    starts: torch.Tensor | None,
    progress: bool,
) -> FitResult:
    """:func:`fit_theta` on one batch of recordings as ``config`` says, with a progress bar."""
    desc = f"fit {loss.method}: {held.shape[0]} recording(s) of {held.shape[1]} trials"
    with tqdm(total=config.max_iter, desc=desc, disable=not progress) as bar:
        result = fit_theta(
            loss,
            held,
            n_starts=config.n_starts,
            n_screen=config.n_screen,
            max_iter=config.max_iter,
            seed=seed,
            curvature=config.curvature,
            covariance=config.covariance,
            intervals=config.intervals,
            starts=starts,
            progress=lambda i, n: bar.update(1),
            workers=config.workers,
        )
        finish(bar)
    return result


def _worst_trials(recording: TensorDict, log_likelihood: torch.Tensor, n: int = 3) -> list[dict]:
    """The ``n`` trials whose actions θ̂ explains worst, by log-likelihood per recorded step
    (a tracking glitch, a trial the agent gave up on), each with its own trial number."""
    steps = recording["mask"].sum(-1).double()
    per_step = log_likelihood.double() / steps
    worst = per_step.argsort()[:n]
    return [
        {
            "trial": float(recording["trial"][i, 0]),
            "log_likelihood": float(log_likelihood[i]),
            "steps": int(steps[i]),
            "per_step": float(per_step[i]),
            "median_per_step": float(per_step.median()),
        }
        for i in worst.tolist()
    ]


def _calibrate_fits(
    model: TaskModel,
    actor: TensorDictSequential,
    action_model: CensoredGaussianActionModel,
    space: ThetaSpace,
    recordings: list[TensorDict],
    fits: dict[str, FitResult],
    config: RecordingFitConfig,
    method: str,
    seed: int,
    device: torch.device,
    progress: bool,
    stages: Stages,
) -> dict[str, Calibration]:
    """Every method's :class:`Calibration` from ``config.calibrate`` datasets simulated at
    each recording's θ̂ of the last method (its motor noise, its world, its number of
    trials), fitted by :func:`_fit_groups` as the recordings were (without particle checks;
    dataset ``k``'s fits the stages ``calibration{k + 1}at{method}_…``, named by the method
    whose θ̂ generates the data: the stages' key leaves the method out)."""
    last = list(fits)[-1]
    result = fits[last]
    world = torch.stack([r["task_theta"][0, 0] for r in recordings])
    groups = _by_trial_count(recordings)
    quiet = dataclasses.replace(config, particles=0)

    def refit(k: int) -> dict[str, FitResult]:
        synthetic: list[TensorDict | None] = [None] * len(recordings)
        for g, (n_trials, members) in enumerate(groups.items()):
            rows = torch.tensor(members, device=result.theta_hat.device)
            simulated = simulate_at_fits(
                model, actor, action_model, result.select(rows), world[rows], n_trials,
                derived_seed(seed, CALIBRATION, k, g), config.senses,
            )  # fmt: skip
            for j, i in enumerate(members):
                synthetic[i] = simulated[j].select(*TRIAL_KEYS)
        refits, *_ = _fit_groups(
            model, action_model, space, synthetic, quiet, method, seed, device, progress,
            stages, f"calibration{k + 1}at{last}",
        )  # fmt: skip
        return refits

    theta = result.theta_hat.float().cpu()
    return calibrate_intervals(space, theta, refit, config.calibrate, config.calibration_tail)


def _truth_scores(
    space: ThetaSpace, truths: list[torch.Tensor | None], result: FitResult
) -> dict[str, Any] | None:
    """:func:`score_recovery` over the recordings whose true θ is known (``None`` if none is):
    per-parameter coverage, errors and widths among those, the others left out."""
    known = [i for i, truth in enumerate(truths) if truth is not None]
    if not known:
        return None
    theta_true = torch.stack([truths[i] for i in known])
    return score_recovery(space, theta_true, result.select(known))


def _add_calibrated(
    scored: dict[str, Any],
    space: ThetaSpace,
    calibration: Calibration,
    result: FitResult,
    truths: list[torch.Tensor | None],
) -> None:
    """Each agent's calibrated intervals, the calibration and, where some truth is known, the
    calibrated intervals' coverage, into one method's :func:`_scored` entry."""
    calibrated = calibration.apply(space, result)
    scored["calibration"] = calibration.to_dict()
    for agent, intervals in zip(scored["agents"], agent_intervals(calibrated), strict=True):
        agent["calibrated"] = intervals
    truth_scores = _truth_scores(space, truths, calibrated)
    if truth_scores is not None:
        scored["calibrated_parameters"] = truth_scores["parameters"]


def _scored(
    space: ThetaSpace,
    action_model: CensoredGaussianActionModel,
    result: FitResult,
    truths: list[torch.Tensor | None],
    paths: list[Path],
    labels: list[str],
    recordings: list[TensorDict],
    checks: list[dict | None],
) -> dict[str, Any]:
    """The summary's ``agents`` of one method's fit, each with its motor noise and lapse rate
    (a fitted rate with its 95% interval from the observed information) and its true θ where
    known; with any truth, ``parameters`` scores the recordings whose truth is known."""
    scored: dict[str, Any] = {"agents": [result.agent(i) for i in range(len(paths))]}
    truth_scores = _truth_scores(space, truths, result)
    if truth_scores is not None:
        scored["parameters"] = truth_scores["parameters"]
        scored["truth_known"] = len(truth_scores["agents"])
        for agent, truth in zip(scored["agents"], truths, strict=True):
            if truth is not None:
                agent["theta_true"] = space.to_dict(truth)
    noise = action_model.motor_noise(result.nuisance)
    lapse = action_model.lapse_rate(result.nuisance)
    correlation = result.intervals.correlation(space.free_mask)
    free = space.free_names
    # the fit's intervals of the nuisance coordinates, mapped to motor noise and lapse rate
    ends = result.nuisance_intervals(torch.tensor(action_model.nuisance_bounded, device="cpu"))
    noise_ci = [action_model.motor_noise(end) for end in ends]
    lapse_ci = [action_model.lapse_rate(end) for end in ends]
    for i, agent in enumerate(scored["agents"]):
        agent.update(
            file=str(paths[i]),
            label=labels[i],
            n_trials=int(recordings[i].shape[0]),
            n_steps=int(recordings[i]["mask"].sum()),
            motor_noise=[float(v) for v in noise[i]],
            motor_noise_ci=[[float(end[i, j]) for end in noise_ci] for j in range(noise.shape[1])],
            lapse=float(lapse[i]),
            correlation={
                a: {b: float(correlation[i, j, m]) for m, b in enumerate(free)}
                for j, a in enumerate(free)
            },
        )
        if action_model.fit_lapse:
            agent["lapse_ci"] = [float(end[i]) for end in lapse_ci]
        if checks[i] is not None:
            agent["particle_check"] = checks[i]
    return scored


def _belief_arrays(
    recording: TensorDict, belief: TensorDict, log_likelihood: torch.Tensor
) -> dict[str, np.ndarray]:
    """What the belief figures and ``beliefs.npz`` hold for one recording."""
    return {
        "trial_log_likelihood": log_likelihood.double().numpy(),
        "trial": recording["trial"][:, 0].numpy(),  # the recording's own trial numbers
        "time": recording["time"].numpy(),
        "mask": recording["mask"].numpy(),
        "state": recording["state"].numpy(),
        "target": recording["target"].numpy(),
        "mean": belief["belief", "mean"].numpy(),
        "cov": belief["belief", "cov"].numpy(),
        "mean_cov": belief["belief", "mean_cov"].numpy(),
    }


def _write_beliefs(
    path: Path,
    labels: list[str],
    recordings: list[TensorDict],
    beliefs: list[TensorDict],
    log_likelihoods: list[torch.Tensor],
) -> None:
    """``beliefs.npz``: ``<label>/<array>`` for every recording (see :func:`_belief_arrays`)."""
    arrays = {
        f"{label}/{key}": value
        for label, recording, belief, values in zip(
            labels, recordings, beliefs, log_likelihoods, strict=True
        )
        for key, value in _belief_arrays(recording, belief, values).items()
    }
    write_npz(path, arrays)


def _interval(entry: Mapping[str, Any], name: str) -> str:
    """Parameter ``name``'s interval in ``entry`` for a table, an end within 1e-12 of 0 (a
    bound at 0, reached to rounding) printed as 0."""
    low, high = (
        0.0 if abs(x) < 1e-12 else x for x in (entry["ci_low"][name], entry["ci_high"][name])
    )
    return f"[{low:.4g}, {high:.4g}]"


def _traded_off(correlation: Mapping[str, Mapping[str, float | None]]) -> str:
    """The pairs of parameters whose estimates correlate at least :data:`TRADED_OFF`, most
    correlated first (``""`` if none)."""
    names = list(correlation)
    pairs = [
        (r, a, b)
        for i, a in enumerate(names)
        for b in names[i + 1 :]
        if (r := correlation[a][b]) is not None and math.isfinite(r) and abs(r) >= TRADED_OFF
    ]
    pairs.sort(key=lambda pair: -abs(pair[0]))
    return ", ".join(f"{a} ~ {b} (r {r:+.2f})" for r, a, b in pairs)


def _identified(agent: Mapping[str, Any], name: str) -> str:
    """``yes`` or ``NO`` by the curvature at θ̂; ``unsure`` short of the top, where the
    curvature is not the information the data hold (``NO`` after 15 iterations read ``yes``
    after 60)."""
    if not agent["converged"]:
        return "unsure"
    return "yes" if agent["identified"][name] else "NO"


def format_fit(summary: dict[str, Any]) -> str:
    """A readable table per recording: θ̂, its 95% interval, the truth if known, identified."""
    units = summary.get("units", {})
    lines = format_resumed(summary)
    for method, part in (summary.get("methods") or {summary["method"]: summary}).items():
        for agent in part["agents"]:
            truth = agent.get("theta_true")
            status = "converged" if agent["converged"] else "NOT converged (raise max_iter)"
            profiled = [n for n in summary["free"] if agent.get("profiled", {}).get(n)]
            if profiled:
                status += f", profile-likelihood intervals for {', '.join(profiled)}"
            lines.append(
                f"{agent['file']} ({method}): {agent['n_trials']} trials, {agent['n_steps']} "
                f"steps, log-likelihood {agent['log_likelihood']:.1f}, {status}"
            )
            calibrated = agent.get("calibrated")
            # 'θ̂' is two code points shown as one character: pad it one wider
            header = f"  {'parameter':<13}{'θ̂':>10}  {'95% CI':<21}"
            header += f"{'calibrated 95% CI':<21}" if calibrated else ""
            header += f"{'true':>9}  " if truth else ""
            lines.append(header + f"{'identified':<11}unit")
            for name in summary["free"]:
                ci = _interval(agent, name)
                row = f"  {name:<13}{agent['theta_hat'][name]:>9.4g}  {ci:<21}"
                if calibrated:
                    row += f"{_interval(calibrated, name):<21}"
                row += f"{truth[name]:>9.4g}  " if truth else ""
                row += f"{_identified(agent, name):<11}{units.get(name, '')}"
                lines.append(row)
            noise = ", ".join(f"{v:.3g}" for v in agent["motor_noise"])
            held = agent.get("lapse", summary.get("config", {}).get("lapse", 0.0))
            lapse = f"lapse rate (held): {held:g}"
            if "lapse_ci" in agent:
                low, high = agent["lapse_ci"]
                lapse = f"lapse rate (fitted): {agent['lapse']:.3g} [{low:.3g}, {high:.3g}]"
            lines.append(f"  motor noise std (fitted): {noise}; {lapse}")
            traded = _traded_off(agent.get("correlation", {}))
            if traded:
                lines.append(f"  traded off by the data (|r| ≥ {TRADED_OFF}): {traded}")
            worst = agent.get("worst_trials")
            if worst:
                trials = ", ".join(f"{w['trial']:.15g} ({w['per_step']:.2f})" for w in worst)
                lines.append(
                    f"  trials explained worst, log-likelihood per step (median of all "
                    f"{worst[0]['median_per_step']:.2f}): {trials}"
                )
            check = agent.get("particle_check")
            if check:
                gap = check["approximation_gap"]
                lines.append(
                    f"  particle check: the likelihood's approximation is {abs(gap):.1f} nats "
                    f"{'below' if gap >= 0 else 'above'} a particle filter's at θ̂ (fewest "
                    f"effective particles in a trial: {check['min_effective_particles']:.0f})"
                )
        calibration = part.get("calibration")
        if calibration:
            lines.append(
                f"{method}: intervals calibrated on {calibration['n_datasets']} simulated "
                f"dataset(s) per recording, scaled by {format_factors(calibration)}"
            )
        else:
            enough = math.ceil(MIN_REFITS / len(part["agents"]))
            lines.append(
                f"{method}: 95% intervals from the fit's likelihood alone, not calibrated: "
                "on simulated agents such intervals hold the truth less often than 95% "
                f"(docs/recovery2d.md); calibrate={enough} calibrates them by simulation"
            )
        for key, what in (("parameters", ""), ("calibrated_parameters", "calibrated ")):
            if key in part:
                covered = ", ".join(f"{n} {s['coverage']:.2f}" for n, s in part[key].items())
                scored = [agent for agent in part["agents"] if "theta_true" in agent]
                files = f"the {len(scored)} file{'s' * (len(scored) != 1)} whose truth is known"
                where = f"the {what}95% interval (fraction of {files})"
                unconverged = sum(not agent["converged"] for agent in scored)
                warning = (
                    f"; {unconverged} of these fits did NOT converge, and an interval of a "
                    "fit that did not converge may span all the data allow"
                    if unconverged
                    else ""
                )
                lines.append(f"{method}: truth inside {where}: {covered}{warning}")
    return "\n".join(lines)
