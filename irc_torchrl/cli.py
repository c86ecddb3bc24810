"""The ``irc`` command: thin wrappers over the functions in :mod:`irc_torchrl.algorithms`."""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import signal
import sys
import threading
import warnings
from collections.abc import Sequence
from contextlib import AbstractContextManager, nullcontext
from functools import partial
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from irc_torchrl.envs.model import TaskModel

__all__ = ["main"]

#: a ``key=value`` setting (``max_iter=60``, ``theta.g_v=1.2``) among positional arguments
KEY_VALUE = re.compile(r"^[A-Za-z_][\w.]*=")
#: a setting's key alone (``max_iter``), which a stray argument may be
KEY = re.compile(r"^[A-Za-z_][\w.]*$")


def _demo(args: argparse.Namespace) -> int:
    from irc_torchrl.algorithms.demo import format_summary, run_demo
    from irc_torchrl.config import load_config

    options = _option_settings(args)
    if args.task == "firefly2d":
        from irc_torchrl.algorithms.recover2d import DEMO_OVERRIDES

        return _run_recovery(args.config, [*DEMO_OVERRIDES, *args.overrides], args, options)
    config = load_config(args.config, args.overrides, options)
    summary = run_demo(config, args.out, show_progress=not args.quiet)
    print(format_summary(summary))
    print(
        f"wrote {args.out}/: summary.json, config.yaml, figures.npz, "
        "q_function.png, recovery.png, dp_comparison.png"
    )
    return 0


def _recover(args: argparse.Namespace) -> int:
    return _run_recovery(args.config, args.overrides, args, _option_settings(args))


def _option_settings(args: argparse.Namespace, skip: tuple[str, ...] = ()) -> dict[str, Any]:
    """The config settings the command's options give (:data:`OPTION_SETTINGS`, but ``skip``;
    ``--seed 3``: ``seed``), their values as given: a path or a device name is not read as
    YAML (``#`` a comment)."""
    keys = [key for key in OPTION_SETTINGS.get(args.command, ()) if key not in skip]
    return {key: getattr(args, key) for key in keys if getattr(args, key) is not None}


def _run_recovery(
    config_path: str | None,
    overrides: Sequence[str],
    args: argparse.Namespace,
    options: dict[str, Any],
) -> int:
    from irc_torchrl.algorithms.recover2d import format_recovery, run_recovery
    from irc_torchrl.config import load_recovery2d_config

    spec = getattr(args, "model", None)  # `irc demo` recovers the firefly's agents only
    model = _task_model(spec)
    config = load_recovery2d_config(config_path, overrides, model, options)
    _check_policy(config.checkpoint, model)
    _check_sendable(spec, "fit.workers", config.fit.workers)
    resume = getattr(args, "resume", None)  # `irc demo` runs whole, in minutes: keeps none
    summary = run_recovery(
        config, args.out, not args.quiet, model, bool(resume), keep=resume is not None
    )
    print(format_recovery(summary))
    drawn = any(Path(args.out).glob("beliefs_overhead_*.png"))  # for a position in the plane
    overhead = "beliefs_overhead_*.png, " if drawn else ""
    stages = "stages/ (the fits) and " if resume is not None else ""
    print(
        f"wrote {args.out}/: summary.json, config.yaml, trials/, {stages}figures "
        f"(recovery_*.png, {overhead}beliefs_time_*.png)"
    )
    return 0


def _check_policy(checkpoint: str, model: TaskModel | None) -> None:
    """Refuse a policy learned for another task than ``--model``'s (the 2D firefly's without
    it) before any work, naming the option that mends it."""
    from irc_torchrl.checkpoint import load_checkpoint

    task = "firefly2d" if model is None else model.name
    found = load_checkpoint(checkpoint)["task"]
    if found == task:
        return
    if model is None:
        raise ValueError(
            f"--checkpoint: {checkpoint} holds a policy for {found!r}; expected --model naming "
            "that task (FILE.py:Class or module:Class), or a policy for 'firefly2d'"
        )
    given = f"{checkpoint}, a policy for {found!r}" if Path(checkpoint).is_file() else None
    raise ValueError(
        f"--checkpoint: expected the policy `irc train --model` learned for {task!r} (a file), "
        f"got {given or f'the packaged {checkpoint}'}"
    )


def _train(args: argparse.Namespace) -> int:
    from irc_torchrl.algorithms.ensemble import train_ensemble
    from irc_torchrl.config import load_firefly2d_config

    model = _task_model(args.model)
    base = None
    if args.resume is not None and args.config is None:  # resumed, its settings go on
        from irc_torchrl.checkpoint import load_checkpoint

        # but its device (another machine's, maybe) and task (the library checks it)
        saved = load_checkpoint(args.resume)["config"]
        base = {key: value for key, value in saved.items() if key not in ("device", "task")}
    options = _option_settings(args, skip=("seed",))  # the seed goes to train_ensemble
    config = load_firefly2d_config(
        args.config, args.overrides, model, base, options, fresh=args.resume is None
    )
    _check_sendable(args.model, "ddpg.collector_workers", config.ddpg.collector_workers)
    result = train_ensemble(
        config,
        out=args.out,
        resume=args.resume,
        progress=not args.quiet,
        seed=args.seed,
        model=model,
    )
    print(_best_policy(result.best))
    logs = ", logs/" if config.logger != "none" else ""
    print(f"wrote {args.out}/: checkpoint.pt, config.yaml, summary.json{logs}")
    return 0


def _best_policy(best: dict[str, Any]) -> str:
    """The line ``irc train`` ends with: the kept policy's evaluation."""
    success = f"success {best['success_rate']:.1%}, " if best["success_rate"] is not None else ""
    return (
        f"best policy: {success}return {best['mean_return']:.2f}, "
        f"trial length {best['mean_length']:.1f} steps (after {best['updates']} updates)"
    )


def _task_file(spec: str) -> bool:
    """Whether ``--model`` names its task by a file (``FILE.py:Class``), not a module."""
    return spec.rpartition(":")[0].endswith(".py")


def _task_model(spec: str | None) -> TaskModel | None:
    """The task ``--model`` names, ``FILE.py:Class`` or ``module:Class`` (importable: installed
    or on the path), built without arguments (None: none named)."""
    import importlib
    import inspect

    from irc_torchrl.checks import first_line
    from irc_torchrl.envs.model import TaskModel, continuous_actions

    if spec is None:
        return None
    source, _, name = spec.rpartition(":")
    if not source or not name.isidentifier():
        raise ValueError(f"--model: expected FILE.py:Class or module:Class, got {spec!r}")
    try:
        if _task_file(spec):
            module = _task_file_module(Path(source))
        else:
            module = importlib.import_module(source)
    except (ImportError, SyntaxError) as error:
        raise ValueError(
            f"--model: cannot import {source} ({first_line(error)}); expected a file or an "
            "installed module"
        ) from None
    task = getattr(module, name, None)
    if not (isinstance(task, type) and issubclass(task, TaskModel)):
        if task is None:
            found = "nothing by that name"
        elif isinstance(task, type):
            bases = ", ".join(base.__name__ for base in task.__bases__)
            found = f"class {task.__name__} (bases: {bases})"
        else:
            found = f"a value of type {type(task).__name__}"
        raise ValueError(
            f"--model: expected {name} in {source} to be a TaskModel subclass, got {found}"
        )
    if inspect.isabstract(task):
        missing = ", ".join(sorted(task.__abstractmethods__))
        raise ValueError(f"--model: {name} is abstract; expected it to define {missing}")
    try:
        inspect.signature(task).bind()
    except TypeError as error:
        raise ValueError(f"--model: {name}() must build without arguments ({error})") from None
    model = task()
    spec = model.action_spec
    if not continuous_actions(spec):
        raise ValueError(
            f"--model: {name}'s actions are {type(spec).__name__} {list(spec.shape)}; expected "
            "continuous actions [da], which these commands' DDPG policy acts by (a discrete "
            "task learns a factorised Q in Python, train_factorised_q and recover_agents: see "
            "`irc demo --task firefly1d`)"
        )
    return model


def _task_file_module(path: Path) -> ModuleType:
    """The module of a task file, registered under its own name (dataclasses, typing and
    pickling look a class's module up there); its folder goes on ``sys.path`` (last: a file
    there does not shadow an installed module), so that it imports the modules beside it."""
    import importlib.util

    if not path.is_file():
        raise FileNotFoundError(f"--model: no file at {path}")
    folder = str(path.resolve().parent)
    if folder not in sys.path:
        sys.path.append(folder)
    found = importlib.util.spec_from_file_location(f"irc_task_{path.stem}", path)
    module = importlib.util.module_from_spec(found)
    sys.modules[found.name] = module
    try:
        found.loader.exec_module(module)
    except BaseException:
        del sys.modules[found.name]
        raise
    return module


def _check_sendable(spec: str | None, field: str, processes: int) -> None:
    """Refuse to send a task read from a file to other processes, which cannot import it."""
    if spec is not None and _task_file(spec) and processes > 1:
        raise ValueError(
            f"--model: a task from a file ({spec}) cannot be sent to other processes; "
            f"expected {field}=1 (or the task as module:Class), got {processes}"
        )


def _simulate(args: argparse.Namespace) -> int:
    from irc_torchrl.algorithms.recordings import simulate_recordings
    from irc_torchrl.config import load_simulate_config

    config = load_simulate_config(args.overrides)
    model = _task_model(args.model)
    _check_policy(args.checkpoint, model)
    summary = simulate_recordings(
        config,
        args.out,
        args.checkpoint,
        args.format,
        args.seed,
        args.device,
        progress=not args.quiet,
        task=args.task,
        model=model,
    )
    for agent in summary["agents"]:
        theta = ", ".join(f"{k}={v:.3g}" for k, v in agent["theta_true"].items())
        print(f"{agent['file']}: {agent['n_trials']} trials, θ* {theta}")
    print(f"wrote {args.out}/: {len(summary['agents'])} recording(s), summary.json (the true θ)")
    return 0


def _fit(args: argparse.Namespace) -> int:
    from irc_torchrl.algorithms.recordings import fit_recordings, format_fit
    from irc_torchrl.config import load_recording_fit_config

    files, settings = _files_and_settings(args)
    config = load_recording_fit_config(settings)
    # an empty --free names nothing to fit (refused), not every parameter
    free = None if args.free is None else [n.strip() for n in args.free.split(",") if n.strip()]
    _check_sendable(args.model, "workers", config.workers)
    model = _task_model(args.model)
    _check_policy(args.checkpoint, model)
    summary = fit_recordings(
        files,
        args.out,
        config,
        checkpoint=args.checkpoint,
        method=args.method,
        free=free,
        seed=args.seed,
        device=args.device,
        progress=not args.quiet,
        model=model,
        resume=args.resume,
    )
    print(format_fit(summary))
    print(f"wrote {args.out}/: summary.json, beliefs.npz, stages/ (the fits) and figures (PNG)")
    return 0


def _is_setting(item: str) -> bool:
    """Whether a positional item is a ``key=value`` setting: shaped like one and naming no
    existing file or folder (a folder ``runs/lr=3e-3`` is a path)."""
    return bool(KEY_VALUE.match(item)) and not Path(item).exists()


def _files_and_settings(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    """``irc fit``'s recordings and its ``key=value`` settings: argparse gives every
    positional to FILE, and an item that names an existing file is a recording."""
    items = [*args.files, *args.overrides]
    setting = [_is_setting(i) for i in items]
    return (
        [i for i, s in zip(items, setting, strict=True) if not s],
        [i for i, s in zip(items, setting, strict=True) if s],
    )


def _report(args: argparse.Namespace) -> int:
    from irc_torchrl.plots import read_summary, report_run

    seen = set()
    for folder in args.folders:
        if _is_setting(folder):
            raise ValueError(f"DIR: {folder} is a setting; irc report takes run folders only")
        resolved = Path(folder).resolve()
        if resolved in seen:
            raise ValueError(f"DIR: {folder} given twice; expected each draw once")
        seen.add(resolved)
    if len(args.folders) > 1:
        from irc_torchrl.algorithms.recovery import format_pooled, pool_coverage

        summaries = {folder: read_summary(folder) for folder in args.folders}
        print(format_pooled(pool_coverage(summaries)))
        return 0
    (folder,) = args.folders
    summary = read_summary(folder)
    drawn = report_run(folder, summary)
    table = _table(summary)
    if table:
        print(table)
    for path in drawn:
        print(f"wrote {path}")
    return 0


def _table(summary: dict[str, Any]) -> str | None:
    """The table the run printed as it ended, from its summary (``None``: it printed none); a
    hand-edited summary the figures could be drawn from but the table not is warned about."""
    from irc_torchrl.algorithms.demo import format_summary
    from irc_torchrl.algorithms.recordings import format_fit
    from irc_torchrl.algorithms.recover2d import format_recovery
    from irc_torchrl.plots import is_recovery

    command = summary.get("command")
    try:
        if command == "train":
            return _best_policy(summary["best"])
        if is_recovery(summary):  # the 2D demo's too
            return format_recovery(summary)
        if command in ("fit", "demo"):
            return (format_fit if command == "fit" else format_summary)(summary)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as error:
        warnings.warn(
            f"report: summary.json lacks or mangles field {error}: its table is not printed",
            stacklevel=2,
        )
    return None


def _add_common(parser: argparse.ArgumentParser, overrides_help: str) -> None:
    """The options every 2D subcommand shares: checkpoint, model, seed, device, quiet,
    key=value."""
    parser.add_argument(
        "--checkpoint",
        default="firefly2d",
        help="a checkpoint file of `irc train`, or the name of a packaged one (default firefly2d)",
    )
    _add_model(parser, "the checkpoint's task")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random draw (default 0)")
    parser.add_argument(
        "--device", default="cpu", help="torch device to run on, e.g. cpu or cuda:0 (default cpu)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help=overrides_help)


def _add_resume(parser: argparse.ArgumentParser, same: str) -> None:
    """``--resume``: read the fits and checks an earlier run into ``--out`` finished
    (``--out/stages``)."""
    parser.add_argument(
        "--resume",
        action="store_true",
        help=f"read the fits and particle checks an earlier run into --out with the same {same} "
        "finished (kept in --out/stages as each ends) instead of running them again: an "
        "interrupted run goes on where it stopped, with the same numbers, and a larger "
        "calibrate reuses the datasets already refitted",
    )


def _add_model(parser: argparse.ArgumentParser, note: str) -> None:
    """``--model``: a task of the user's own instead of the 2D firefly."""
    parser.add_argument(
        "--model",
        default=None,
        help=f"a continuous-action TaskModel of your own, as FILE.py:Class or module:Class, "
        f"built without arguments ({note}; default: the firefly2d task)",
    )


def _add_recording_commands(commands: argparse._SubParsersAction) -> None:
    """``irc simulate``, ``irc fit`` and ``irc report``."""
    simulate = commands.add_parser(
        "simulate",
        help="simulate agents of the 2D task (or --model) into recording files, with their true θ",
        description=(
            "Agents act by a trained θ-conditioned policy plus Gaussian motor noise in a world "
            "with a known θ, one recording file per agent (agent0.csv, ...) in the trajectory "
            "schema (docs/trajectory_schema.md); summary.json holds each agent's true θ. The "
            "agents' θ: theta.<name>=value where given, drawn from the prior (with --seed) "
            "elsewhere."
        ),
    )
    simulate.add_argument(
        "--task", choices=["firefly2d"], default="firefly2d", help="the task (default firefly2d)"
    )
    simulate.add_argument("--out", required=True, help="output folder")
    simulate.add_argument(
        "--format",
        choices=["csv", "csv.gz", "npz", "nwb", "memmap"],
        default="csv",
        help="recording format (default csv; csv.gz: gzip-compressed; nwb needs pynwb; memmap: "
        "a TensorDict folder)",
    )
    _add_common(
        simulate,
        "settings: n_agents (default 1), n_trials (default 100), motor_noise (default 0.1), "
        "lapse (how often an action dimension is unrelated to the belief; default 0.0), "
        "threads (default 1), theta.<name> (the agents' θ, what they believe; drawn from the "
        "prior where not given), task_theta.<name> (the world's θ, at its default where not "
        "given; the recordings' theta.* columns), senses (agent: each agent observes as "
        "noisily as its own θ says, the default; world: as task_theta says), e.g. "
        "n_trials=50 theta.g_v=1.3",
    )
    simulate.set_defaults(run=_simulate)
    fit = commands.add_parser(
        "fit",
        help="fit θ with 95%% intervals to recorded trials (one agent per file, 2D task or "
        "--model)",
        description=(
            "Read recordings (CSV, NPZ, NWB or TensorDict folders; docs/trajectory_schema.md), "
            "fit each agent's θ (Algorithm 2) with 95% intervals from the observed Fisher "
            "information, print a table per file and write summary.json, beliefs.npz (the "
            "agent's belief at every step under θ̂) and figures into --out. A file written by "
            "`irc simulate` is compared with the true θ from its folder's summary.json."
        ),
    )
    fit.add_argument("files", nargs="+", metavar="FILE", help="recordings, one agent each")
    fit.add_argument("--out", required=True, help="output folder")
    _add_resume(fit, "recordings and settings")
    fit.add_argument(
        "--method",
        choices=["marginal", "map", "both"],
        default="marginal",
        help="map: the paper's estimator (most probable observations); marginal (default): "
        "the agent's observations integrated out, started from the map fit; both: report both",
    )
    fit.add_argument(
        "--free",
        default=None,
        metavar="NAME,NAME",
        help="the θ parameters to fit (default: every free parameter of the checkpoint's θ "
        "space not set by theta.<name>=value); the others stay at theta.<name>=value if "
        "given, else at their default",
    )
    _add_common(
        fit,
        "settings: n_screen (default 16), n_starts (default 2), max_iter (default 80), "
        "motor_noise (where its fit starts, default 0.1), lapse (the action model's lapse "
        "rate: where its fit starts, default 0.01), fit_lapse (default true; false holds lapse "
        "fixed, 0: none), threads (default 1), workers (processes the recordings' fits are "
        "shared among, CPU; default 1), "
        "curvature (bfgs, fisher or hessian: how the iterations measure curvature), "
        "covariance (hessian, or sandwich: H⁻¹ Σ sᵢsᵢᵀ H⁻¹ over the trials' scores), "
        "intervals (wald, or profile: where the profile likelihood falls 1.92 below its top), "
        "particles (e.g. 1000: check each fit against a particle filter's likelihood), "
        "components (e.g. 16: marginal's belief as a Gaussian sum over trials' last 4 steps), "
        "actor_dtype (float32, or float64: the frozen actor's precision, ~1.3× slower), "
        "calibrate (e.g. 2: datasets simulated at each θ̂ and refitted to calibrate the "
        "intervals; each costs about the fit again), calibration_tail (own: each "
        "parameter's 95%% quantile, or shrunk toward all parameters' tails), "
        "senses (agent: the noise of the agent's observations is its candidate θ's, the "
        "default; world: the recordings' theta.obs_sigma_* columns'), "
        "theta.<name> (value of a parameter not fitted), units.<column> (a recorded unit, "
        "e.g. units.x=cm units.heading=deg), time_column and trial_column (the columns' "
        "names; default time and trial), e.g. max_iter=60",
    )
    fit.set_defaults(run=_fit)
    report = commands.add_parser(
        "report",
        help="print the table of a run folder (fit, recover, demo or train), draw its figures; "
        "pool the coverage of several recovery draws",
        description=(
            "Read DIR/summary.json, print the table the run ended with (the best policy for "
            "`irc train`) and write PNG figures into DIR: θ̂ against the true θ with "
            "95% intervals for the recordings whose truth is known (the others' θ̂ is in the "
            "table and summary.json; with no truth, θ̂ with intervals per recording), "
            "the recovered beliefs (from beliefs.npz), training curves for `irc train`, and for "
            "the 2D task q_function.png (Q of the run's checkpoint, paper Fig. 1B). With several "
            "folders of `irc recover` draws (different seeds), print instead each method's "
            "coverage per parameter pooled over all their agents, raw and calibrated, with its "
            "95% Clopper-Pearson interval and each draw's: one draw of 40 agents cannot tell "
            "0.95 from 0.90 (draws nothing)."
        ),
    )
    report.add_argument(
        "folders",
        metavar="DIR",
        nargs="+",
        help="a run folder with a summary.json (two or more: recovery draws to pool)",
    )
    report.set_defaults(run=_report)


def build_parser() -> argparse.ArgumentParser:
    """The ``irc`` command's parser: one subcommand per job, each with its options."""
    parser = argparse.ArgumentParser(
        prog="irc",
        description="Inverse Rational Control: what internal model makes behaviour rational?",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = commands.add_parser(
        "demo",
        help="train, simulate agents and recover their θ end to end (the main job)",
        description=(
            "Learn one Q over the θ prior (Algorithm 1), check it against exact DP, simulate "
            "agents with θ* from the prior, fit each agent's θ with 95% intervals (Algorithm 2) "
            "and report coverage. Writes config.yaml, summary.json and figures into --out "
            "(firefly1d also figures.npz, firefly2d trials/)."
        ),
    )
    demo.add_argument(
        "--task",
        choices=["firefly1d", "firefly2d"],
        default="firefly1d",
        help=(
            "firefly1d (default): the above, about a minute; firefly2d: the recovery experiment "
            "of `irc recover` on 3 agents × 40 trials with the shipped 2D policy, "
            "1-2 minutes on 2 cores"
        ),
    )
    demo.add_argument(
        "--out", default=None, help="output folder (default runs/demo; runs/demo2d with firefly2d)"
    )
    demo.add_argument(
        "--seed", type=int, default=None, help="seed of every random draw (overrides the config's)"
    )
    demo.add_argument(
        "--config",
        default=None,
        help=(
            "a YAML config (default: the embedded one); with --task firefly2d the demo's size "
            "(n_prior_agents=2 n_mistaken_agents=1 n_trials=40 calibrate=0) replaces the "
            "file's, and key=value overrides replace both"
        ),
    )
    demo.add_argument("--quiet", action="store_true", help="no progress bars")
    demo.add_argument(
        "overrides",
        nargs="*",
        metavar="key=value",
        help="config overrides, e.g. agents.n_agents=30 (firefly2d: n_trials=60)",
    )
    demo.set_defaults(run=_demo)
    train = commands.add_parser(
        "train",
        help="train one θ-conditioned policy over the θ prior (Algorithm 1, 2D task or --model)",
        description=(
            "DDPG over the whole θ prior of the 2D firefly task, or of a task of your own "
            "(--model); writes checkpoint.pt (every checkpoint_every updates and at the end), "
            "config.yaml, summary.json and logs."
        ),
    )
    _add_model(train, "warmed up with random actions by default")
    train.add_argument("--config", default=None, help="a YAML config (default: the embedded one)")
    train.add_argument("--out", default="runs/train", help="output folder (default runs/train)")
    train.add_argument(
        "--resume",
        default=None,
        help="a checkpoint to continue from, with its settings (without --config) and the "
        "key=value overrides given, e.g. ddpg.total_frames=768000",
    )
    train.add_argument("--seed", type=int, default=None, help="overrides the config's seed")
    train.add_argument(
        "--device",
        default=None,
        help="torch device to train on, e.g. cuda:0 (default: the config's, cpu)",
    )
    train.add_argument("--quiet", action="store_true", help="no progress bar")
    train.add_argument(
        "overrides", nargs="*", metavar="key=value", help="config overrides, e.g. ddpg.n_envs=128"
    )
    train.set_defaults(run=_train)
    recover = commands.add_parser(
        "recover",
        help="simulate 2D agents (or --model's) with known θ*, fit them by both estimators, "
        "score the intervals",
        description=(
            "The recovery experiment on the 2D task: n_prior_agents agents whose model is right "
            "and n_mistaken_agents living in the default world with another θ, acting with the "
            "shipped policy plus motor noise; every θ component and the motor noise fitted from "
            "states and actions by the hard E-step (map) and with the agent's observations "
            "integrated out (marginal). Writes summary.json (coverage, errors, widths, belief "
            "agreement per method), config.yaml, trials/ and figures into --out. particles=1000 "
            "also checks every fit against a particle filter's likelihood at θ̂ and θ*; "
            "components=16 carries marginal's belief as 16 Gaussians through each trial's "
            "last 4 steps; calibrate=2 (the default; 0: raw intervals only, in a third of the "
            "time) simulates 2 datasets per agent at its θ̂, refits them the same way and "
            "scales each parameter's intervals until 95% of the refits' cover (by its own "
            "refits; calibration_tail=shrunk: its tail shrunk toward all parameters' by as "
            "much as it is noise). lapse=0.05 makes the agents lapse (an "
            "action dimension unrelated to the belief) and the fit hold that rate; with "
            "fit_lapse=true the fit estimates each agent's rate instead, from 0.01. "
            "Every agent observes as noisily as its own θ* says and the fits read that noise "
            "off the candidate θ (senses=world: off the world's θ, the agents' θ* for those "
            "whose model is right, and the default for the mistaken ones). "
            "fit.workers=2 shares the agents' fits among 2 processes (CPU; 1.2–1.3× faster "
            "on 2 cores; the numbers depend on the count, not on the machine). --model with "
            "--checkpoint runs the experiment on a task of your own, its agents acting "
            "with the policy `irc train --model` learned for it (the mistaken ones in the "
            "world of its θ space's defaults)."
        ),
    )
    _add_model(recover, "with --checkpoint, its policy from `irc train --model`")
    recover.add_argument("--config", default=None, help="a YAML config (default: the embedded one)")
    recover.add_argument(
        "--out", default="runs/recover", help="output folder (default runs/recover)"
    )
    recover.add_argument("--seed", type=int, default=None, help="overrides the config's seed")
    recover.add_argument(
        "--checkpoint",
        default=None,
        help="the agents' policy: a checkpoint file of `irc train`, or the name of a packaged "
        "one (default: the config's, the packaged firefly2d)",
    )
    recover.add_argument(
        "--device",
        default=None,
        help="torch device to simulate and fit on, e.g. cuda:0 (default: the config's, cpu)",
    )
    recover.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_resume(recover, "settings")
    recover.add_argument(
        "overrides", nargs="*", metavar="key=value", help="config overrides, e.g. n_trials=50"
    )
    recover.set_defaults(run=_recover)
    _add_recording_commands(commands)
    return parser


def _check_arguments(args: argparse.Namespace) -> None:
    """Refuse a ``--seed`` outside [0, 2**63), a setting given twice, and an ``--out`` that
    cannot take this command's output (a file, or a folder holding another command's
    ``summary.json``, or one irc did not write) before any work."""
    _check_settings_once(args)
    if getattr(args, "seed", None) is not None:
        from irc_torchrl.config import SEED_LIMIT

        if not 0 <= args.seed < SEED_LIMIT:
            raise ValueError(f"--seed: expected an integer in [0, 2**63), got {args.seed}")
    out = getattr(args, "out", None)
    if out is None:
        return
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: expected a folder, {out} is a file")
    _check_writable(out)
    path = out / "summary.json"
    if not path.is_file():
        _check_stages(args, out)
        _check_not_replacing(args, out)
        return
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        summary = None
    written_by = summary.get("command") if isinstance(summary, dict) else None
    # before 2026-12-05 demo, recover and train named no command; every summary has these
    older = written_by is None and isinstance(summary, dict) and {"task", "seed"} <= set(summary)
    if older:
        return
    if not isinstance(written_by, str) or written_by not in _WRITERS:
        raise ValueError(
            f"--out: {path} was not written by irc (it names no irc command), and irc "
            f"{args.command} would overwrite it; choose another folder"
        )
    if written_by != _writes(args):
        if written_by == "recover" and summary.get("task") == "firefly2d":
            written_by += " (or irc demo --task firefly2d)"
        raise ValueError(
            f"--out: {out} holds the summary.json of irc {written_by}, which irc "
            f"{args.command} would overwrite; choose another folder"
        )


def _outputs(args: argparse.Namespace) -> re.Pattern:
    """The names of what this command writes into its ``--out`` (its summary included)."""
    from irc_torchrl.algorithms.recordings import RECORDING_NAME

    # irc fit names its estimates' figures by method where it fits both, irc recover always
    by_method = "_(map|marginal)"
    fitted = by_method if getattr(args, "method", None) == "both" else ""
    names = {
        "simulate": RECORDING_NAME.pattern,
        "fit": rf"beliefs\.npz|q_function\.png|(recovery|estimates){fitted}\.png"
        r"|.+_beliefs_(overhead|time)\.png",
        "recover": rf"config\.yaml|trials|(recovery|beliefs_overhead|beliefs_time){by_method}\.png",
        "demo": r"config\.yaml|figures\.npz|(recovery|q_function|dp_comparison)\.png",
    }
    # a file system that ignores case (macOS, Windows) replaces `Trials/` by `trials/`
    return re.compile(rf"summary\.json|{names[_writes(args)]}", re.IGNORECASE)


def _check_not_replacing(args: argparse.Namespace, out: Path) -> None:
    """Refuse an ``--out`` no earlier run of this command wrote (it holds no summary) that holds
    something named as the command's output: the run would replace a user's file or folder."""
    command = _writes(args)
    if command == "train" or not out.is_dir():  # train resumes into a folder of its own
        return
    outputs = _outputs(args)
    named = sorted(e.name for e in out.iterdir() if outputs.fullmatch(e.name))
    if named:
        raise ValueError(
            f"--out: {out} holds {named[0]!r}, a name irc {args.command} writes, but no "
            f"summary.json of an earlier irc {command}: it is not irc's to replace; choose "
            "another folder (or remove it, if a run stopped while moving its files in left it)"
        )


def _check_writable(out: Path) -> None:
    """Refuse an ``--out`` that cannot be made or written (a dangling link, a file on its
    path, a read-only file system) before any work: found when writing, it cost the run."""
    folder = out
    while not folder.exists():
        if folder.is_symlink():
            raise ValueError(
                f"--out: {folder} links to {os.readlink(folder)}, which does not exist; expected "
                "a folder, or a path where one can be made"
            )
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(
            f"--out: {out} cannot be made, {folder} is a file; expected a folder, or a path "
            "where one can be made"
        )
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(
            f"--out: {folder} cannot be written (a read-only file system, or no permission); "
            "expected a writable folder"
        )


def _held(args: argparse.Namespace) -> AbstractContextManager:
    """The command's folder (``--out``, or the run folder ``irc report`` draws into) held for
    the run: a concurrent irc run into it is refused."""
    from irc_torchrl.data.files import held

    if getattr(args, "out", None) is not None:
        return held(args.out)
    folders = getattr(args, "folders", None)
    if folders is not None and len(folders) == 1 and Path(folders[0]).is_dir():
        return held(folders[0], field="DIR")
    return nullcontext()


def _writes(args: argparse.Namespace) -> str:
    """The command whose summary (and stages) this one writes: `irc demo --task firefly2d` is
    a short `irc recover` and writes its summary."""
    is_recovery = args.command == "demo" and getattr(args, "task", None) == "firefly2d"
    return "recover" if is_recovery else args.command


def _check_stages(args: argparse.Namespace, out: Path) -> None:
    """Refuse an ``--out`` holding only another command's stages (a run interrupted before its
    summary): this command's run would prune them, hours of fits."""
    from irc_torchrl.algorithms.stages import staged_by

    owner = staged_by(out / "stages")
    if owner is not None and owner != _writes(args):
        raise ValueError(
            f"--out: {out}/stages holds the finished fits of an interrupted irc {owner}, which "
            f"irc {args.command} would remove; choose another folder (or go on with irc {owner} "
            "--resume)"
        )


#: the options that set a key of their command's config (``--seed 3`` sets ``seed=3``)
OPTION_SETTINGS = {
    "demo": ("seed",),
    "recover": ("seed", "device", "checkpoint"),
    "train": ("seed", "device"),
}


def _check_settings_once(args: argparse.Namespace) -> None:
    """Refuse a ``key=value`` setting whose key the command line gives twice (``units.x=cm
    units.x=m``, ``seed=5`` with ``--seed 3``, or ``theta.g_v=1.1`` with the whole mapping
    ``theta={g_w: 1.0}``): which one was meant is the user's to say, not the order's."""
    if hasattr(args, "files"):
        settings = _files_and_settings(args)[1]
    else:
        settings = getattr(args, "overrides", [])
    # a setting without "=" is the config's to refuse, saying what a setting looks like
    items = [(item.partition("=")[0].strip(), item) for item in settings if "=" in item]
    for key in OPTION_SETTINGS.get(args.command, ()):
        if getattr(args, key, None) is not None:
            items.append((key, f"--{key} {getattr(args, key)}"))
    for i, (key, item) in enumerate(items):
        for other, earlier in items[:i]:
            if _overlap(key, other):
                shorter = min(key, other, key=len)
                raise ValueError(f"{shorter}: given twice ({earlier!r} and {item!r}); give it once")


def _overlap(key: str, other: str) -> bool:
    """Whether two settings' keys set one value twice: the same key, or one a dotted prefix of
    the other (``agents={n_agents: 2}`` and ``agents.n_agents=3``)."""
    return key == other or key.startswith(f"{other}.") or other.startswith(f"{key}.")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``irc`` command; a clear error on bad input exits with status 2."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    # key=value settings may also follow options (`irc fit a.csv --out r max_iter=60`), and
    # recordings too (`irc fit max_iter=60 --out r a.csv`: argparse took the setting as FILE)
    takes_settings, takes_files = hasattr(args, "overrides"), hasattr(args, "files")
    recordings = [i for i in extra if takes_files and _recording(i)]
    stray = [
        item
        for item in extra
        if item not in recordings and not (takes_settings and KEY_VALUE.match(item))
    ]
    if stray:
        bare = takes_settings and any(KEY.match(item) for item in stray)  # a key without "="
        form = f" (irc {args.command} takes settings as key=value)" if bare else ""
        parser.error(f"unrecognized arguments: {' '.join(stray)}{form}")
    if extra:  # irc fit's FILE and settings are told apart by _files_and_settings
        args.overrides = [*args.overrides, *extra]
    if args.command == "demo" and args.out is None:  # the two demos' outputs apart
        args.out = "runs/demo2d" if args.task == "firefly2d" else "runs/demo"
    formatwarning = warnings.formatwarning  # catch_warnings does not restore it
    warnings.formatwarning = partial(_format_warning, args.command)
    # where a signal would end the process as it stands (a host program's handler, an ignored
    # signal or a thread's call stays as it is)
    main_thread = threading.current_thread() is threading.main_thread()
    handled = [
        (number, default)
        for number, default in _DEFAULT_HANDLERS.items()
        if main_thread and signal.getsignal(number) is default
    ]
    if handled:  # a command in another thread keeps its hands off the record
        _RECEIVED.clear()
    for number, _ in handled:
        signal.signal(number, _stop)
    torchrl_logger = logging.getLogger("torchrl")
    level = torchrl_logger.level
    if "RL_LOGGING_LEVEL" not in os.environ:  # TorchRL's INFO lines went to irc's stdout
        torchrl_logger.setLevel(logging.WARNING)
    try:
        _check_arguments(args)
        with _held(args):
            return args.run(args)
    except KeyboardInterrupt:  # Ctrl-C or kill: what was written before stays as it was
        return _stopped(args)
    except Exception as error:
        if handled and _RECEIVED:  # an interrupt a library turned into another error
            return _stopped(args)
        if not isinstance(error, (KeyError, ValueError, TypeError, OSError, ImportError)):
            raise
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"irc {args.command}: error: {_unprefixed(args.command, message)}", file=sys.stderr)
        return 2
    finally:
        warnings.formatwarning = formatwarning
        torchrl_logger.setLevel(level)
        for number, default in handled:
            signal.signal(number, default)


#: the signals irc turns into an interrupt, with the handlers it replaces only where they stand
_DEFAULT_HANDLERS = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
#: the signals received during the command
_RECEIVED: list[int] = []


def _stop(signum: int, _frame: object) -> None:
    """Ctrl-C, or SIGTERM (``kill``, a scheduler's time limit), raised as an interrupt so that
    the same cleanup runs on both: staging folders and temporaries removed, nothing half
    written. It is recorded too: TorchRL's context managers turn it into a RuntimeError."""
    _RECEIVED.append(signum)
    raise KeyboardInterrupt


def _stopped(args: argparse.Namespace) -> int:
    """The one line of a command interrupted (exit 130) or terminated (143)."""
    left = _RESUME[args.command].format(out=getattr(args, "out", None))
    terminated = signal.SIGTERM in _RECEIVED
    how, status = ("terminated", 143) if terminated else ("interrupted", 130)
    print(f"irc {args.command}: {how}; {left}", file=sys.stderr)
    return status


#: what an interrupted fit (irc fit, irc recover) leaves, and how to go on
_STAGED = (
    "--out keeps its earlier files, and the fits that finished (--out/stages): rerun with "
    "--resume to go on"
)
#: what an interrupted command leaves, and how to go on (its keys: irc's commands)
_RESUME = {
    "fit": _STAGED,
    "recover": _STAGED,
    "train": "--out keeps the last checkpoint.pt written there, with its config.yaml (every "
    "checkpoint_every updates; an earlier run's before the first, beside this run's logs): "
    "rerun with --resume {out}/checkpoint.pt --out {out} to go on from it",
    "simulate": "--out keeps its earlier recordings and summary",
    "demo": "--out keeps its earlier files",
    "report": "each figure is the earlier one or the redrawn one, whole",
}
#: the commands that write a summary.json into --out
_WRITERS = set(_RESUME) - {"report"}


def _recording(item: str) -> bool:
    """Whether a command-line item names a recording: a path that exists, or one with a
    recording's suffix (read_trials then says it is missing)."""
    from irc_torchrl.data.io import SUFFIXES, recording_suffix

    return Path(item).exists() or recording_suffix(item) in SUFFIXES


def _format_warning(command: str, message: Warning | str, *args: Any, **kwargs: Any) -> str:
    """A warning of ``irc command`` as one line, as its errors are (not the Python source
    line that raised it)."""
    return f"irc {command}: warning: {_unprefixed(command, message)}\n"


def _unprefixed(command: str, message: object) -> str:
    """A library message without the ``command: `` it leads with (``report: no summary.json``
    of ``report_run``), which the ``irc command:`` before it already says."""
    return str(message).removeprefix(f"{command}: ")


if __name__ == "__main__":
    sys.exit(main())
