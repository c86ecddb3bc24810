"""Experiment configuration: dataclasses with embedded defaults, YAML files and ``key=value``.

The defaults in these dataclasses are the embedded default experiment; ``configs/*.yaml``
write the same values out for editing. ``key=value`` overrides address nested fields with dots
(``agents.n_agents=30``); an unknown key is an error that lists the valid ones.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import yaml

from irc_torchrl.algorithms.calibration import TAILS
from irc_torchrl.algorithms.ensemble import (
    DDPGConfig,
    EvaluationConfig,
    Firefly2DConfig,
)
from irc_torchrl.algorithms.fit import COVARIANCES, CURVATURES, INTERVALS
from irc_torchrl.algorithms.qiteration import QIterationConfig
from irc_torchrl.algorithms.runtime import check_workers
from irc_torchrl.checks import (
    SEED_LIMIT,
    check_fields,
    first_line,
    non_negative,
    one_of,
    probability,
    resolve_device,
)
from irc_torchrl.checks import positive as _positive
from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.envs.model import SENSES, TaskModel
from irc_torchrl.modules.actor_critic import ACTOR_DTYPES
from irc_torchrl.modules.likelihood import LAPSE_MAX

if TYPE_CHECKING:  # recover2d imports this module
    from irc_torchrl.algorithms.recover2d import Recovery2DConfig

__all__ = [
    "SEED_LIMIT",
    "AgentsConfig",
    "DDPGConfig",
    "EvaluationConfig",
    "FitConfig",
    "Firefly1DConfig",
    "Firefly2DConfig",
    "RecordingFitConfig",
    "SimulateConfig",
    "load_config",
    "load_firefly2d_config",
    "load_recording_fit_config",
    "load_simulate_config",
    "config_to_dict",
]


@dataclass
class AgentsConfig:
    """Simulated agents: θ* from the prior, acting by softmax over their Q in the task's world
    (``world="known"``) or each in a world of its own (``"shared"``)."""

    n_agents: int = 20
    n_trials: int = 100
    temperature: float = 0.5
    #: "known": the world's θ is the task default and only actions inform θ̂;
    #: "shared": every agent lives in a world with its own θ and transitions count too
    world: str = "known"

    def validate(self) -> AgentsConfig:
        """Return ``self`` if every field is usable, else raise a one-line error naming it."""
        check_fields(self, "agents.")
        _positive(
            **{"agents.n_agents": self.n_agents, "agents.n_trials": self.n_trials},
            **{"agents.temperature": self.temperature},
        )
        one_of("agents.world", self.world, ("known", "shared"))
        return self


@dataclass
class FitConfig:
    """Algorithm 2 settings (see :func:`irc_torchrl.algorithms.fit.fit_theta`)."""

    n_screen: int = 64
    n_starts: int = 4
    max_iter: int = 40
    #: "hessian" (exact Newton), "fisher" (Fisher scoring far from θ̂, Newton near it) or
    #: "bfgs" (Fisher scoring far from θ̂, BFGS near it: no second derivatives until θ̂)
    curvature: str = "hessian"
    #: intervals from "hessian" (the observed information) or "sandwich" (H⁻¹ Σ sᵢsᵢᵀ H⁻¹;
    #: it needs more trials per agent than fitted coordinates)
    covariance: str = "hessian"
    #: 95% intervals from that covariance ("wald") or from the profile likelihood ("profile")
    intervals: str = "wald"
    #: processes the agents are shared among (CPU; the numbers depend on it, not on the machine)
    workers: int = 1

    def validate(self) -> FitConfig:
        """Return ``self`` if every field is usable, else raise a one-line error naming it."""
        check_fields(self, "fit.")
        _positive(
            **{"fit.workers": self.workers, "fit.n_screen": self.n_screen},
            **{"fit.n_starts": self.n_starts, "fit.max_iter": self.max_iter},
        )
        _starts_within_screen(self.n_starts, self.n_screen, "fit.")
        one_of("fit.curvature", self.curvature, CURVATURES)
        one_of("fit.covariance", self.covariance, COVARIANCES)
        one_of("fit.intervals", self.intervals, INTERVALS)
        return self


def _starts_within_screen(n_starts: int, n_screen: int, prefix: str = "") -> None:
    """Refuse more starts than screened draws, which the fit picks them from."""
    if n_starts > n_screen:
        raise ValueError(
            f"config: {prefix}n_starts={n_starts} exceeds {prefix}n_screen={n_screen}; "
            "the starts are the best of the screened draws"
        )


@dataclass
class Firefly1DConfig:
    """The 1D demo: train the factorised Q, simulate agents, fit them, report recovery."""

    task: str = "firefly1d"
    seed: int = 0
    #: torch threads; small networks run fastest on one thread per process
    threads: int = 1
    #: flush denormal floats to zero (they slow CPUs down several-fold)
    flush_denormal: bool = True
    #: where Algorithm 1's Q, the simulation and the fits run, e.g. "cpu" or "cuda:0" (the
    #: dynamic-programming check and the figures run on the CPU)
    device: str = "cpu"
    q_iteration: QIterationConfig = field(default_factory=QIterationConfig)
    agents: AgentsConfig = field(default_factory=AgentsConfig)
    fit: FitConfig = field(default_factory=FitConfig)

    def validate(self) -> Firefly1DConfig:
        """Return ``self`` if every field is usable, else raise a one-line error naming it."""
        check_fields(self)
        if self.task != "firefly1d":
            raise ValueError(f"config: task must be 'firefly1d', got {self.task!r}")
        _positive(threads=self.threads)
        self.q_iteration.validate()
        self.agents.validate()
        self.fit.validate()
        check_workers(self.fit.workers, resolve_device(self.device))
        return self


@dataclass
class SimulateConfig:
    """``irc simulate``: agents acting by a trained policy plus motor noise, in a known world."""

    #: what ``irc simulate`` takes as options, not as settings
    command_options: ClassVar[tuple[str, ...]] = (
        "checkpoint",
        "model",
        "seed",
        "device",
        "task",
        "format",
    )
    n_agents: int = 1
    n_trials: int = 100
    #: std of the Gaussian motor noise added to the policy's action (then clipped to the bounds)
    motor_noise: float = 0.1
    #: how often each action dimension lapses: replaced by a draw unrelated to the belief
    #: (uniform over the bounds widened by half their width on each side, clipped; 0: never)
    lapse: float = 0.0
    #: the agents' θ, e.g. ``theta.g_v=1.3``; a parameter left out is drawn from the prior
    theta: dict = field(default_factory=dict)
    #: the world's θ, e.g. ``task_theta.g_v=1.2``; a parameter left out takes its default
    task_theta: dict = field(default_factory=dict)
    #: "agent": each agent observes as noisily as its own θ says (the task's sensory
    #: parameters, e.g. obs_sigma_v), as ``irc fit`` assumes by default; "world": as the
    #: world's θ says
    senses: str = "agent"
    #: torch threads (small networks run fastest on one)
    threads: int = 1

    def validate(self) -> SimulateConfig:
        """Return ``self`` if every number is usable, else raise a one-line error naming it."""
        check_fields(self)
        _positive(
            n_agents=self.n_agents,
            n_trials=self.n_trials,
            motor_noise=self.motor_noise,
            threads=self.threads,
        )
        probability(lapse=self.lapse)
        one_of("senses", self.senses, SENSES)
        return self


@dataclass
class RecordingFitConfig:
    """``irc fit``: Algorithm 2 on recorded trials, actions scored by a censored Gaussian."""

    #: what ``irc fit`` takes as options, not as settings
    command_options: ClassVar[tuple[str, ...]] = (
        "checkpoint",
        "model",
        "seed",
        "device",
        "method",
        "free",
    )
    #: prior draws scored by likelihood alone; Newton starts from the best ``n_starts``
    n_screen: int = 16
    n_starts: int = 2
    #: BFGS iterations are cheap; slow climbs through a rugged likelihood need many of them
    max_iter: int = 80
    #: the motor-noise std the fit starts from (a nuisance parameter, fitted beside θ)
    motor_noise: float = 0.1
    #: the probability that an action dimension lapses (is unrelated to the belief) in the
    #: action model: where its fit starts, or with ``fit_lapse=false`` its value held fixed.
    #: Recordings of real agents hold actions no policy explains (inattention); a lapse caps
    #: what each costs, where without one the motor noise widens to absorb them and the
    #: marginal fit's gradient can explode (0, only when held: none)
    lapse: float = 0.01
    #: fit each recording's lapse rate beside its motor noise (within (0, 0.5); on simulated
    #: agents lapsing 5% or 15% it comes within 0.004 and 0.016 of the truth, and where
    #: there are none it ends on its floor, 0.0012: README)
    fit_lapse: bool = True
    #: how the iterations measure curvature (see ``fit.curvature`` of ``irc recover``)
    curvature: str = "bfgs"
    #: intervals from "hessian" (the observed information) or "sandwich" (H⁻¹ Σ sᵢsᵢᵀ H⁻¹;
    #: it needs more trials per recording than fitted coordinates)
    covariance: str = "hessian"
    #: 95% intervals from that covariance ("wald") or from the profile likelihood ("profile")
    intervals: str = "wald"
    #: particles for checking each fit against a particle filter's likelihood at θ̂
    #: (0: no check; 1000 take about 12 s per recording of 100 trials on 2 cores)
    particles: int = 0
    #: with ``marginal``, Gaussians the outer filter's latent splits into for each trial's last
    #: 4 steps (1: one throughout; 16 come closer to the particle filter, for ~6× the time)
    components: int = 1
    #: datasets per recording simulated at its θ̂ (its fitted motor noise, its world, its
    #: number of trials) and refitted the same way, to calibrate the intervals
    #: (:mod:`~irc_torchrl.algorithms.calibration`; 0: none). Each costs about the fit again
    calibrate: int = 0
    #: how each parameter's calibration factor reads its tail: its "own" 95% quantile, or
    #: "shrunk" toward all parameters' by as much as it is noise
    calibration_tail: str = "own"
    #: the precision the frozen actor runs in inside the float64 likelihood (see
    #: ``actor_dtype`` of ``irc recover``)
    actor_dtype: str = "float32"
    #: "agent": the noise of the agent's observations is its own θ's (the task's sensory
    #: parameters, fitted with the rest: no experimenter measures them); "world": the
    #: recordings' (their theta.obs_sigma_v ... columns, else the defaults)
    senses: str = "agent"
    #: values of the parameters left out of ``--free``, e.g. ``theta.sigma_v=0.3``;
    #: a parameter named nowhere takes its default
    theta: dict = field(default_factory=dict)
    #: units of recorded columns that differ from the task's, e.g. ``units.x=cm``
    #: (docs/trajectory_schema.md lists the known units)
    units: dict = field(default_factory=dict)
    #: the names of the recordings' time (s) and trial-number columns
    time_column: str = "time"
    trial_column: str = "trial"
    #: torch threads (small networks run fastest on one)
    threads: int = 1
    #: processes the recordings are shared among (see ``fit.workers`` of ``irc recover``)
    workers: int = 1

    def validate(self) -> RecordingFitConfig:
        """Return ``self`` if every number is usable, else raise a one-line error naming it."""
        check_fields(self)
        _positive(
            n_screen=self.n_screen,
            n_starts=self.n_starts,
            max_iter=self.max_iter,
            motor_noise=self.motor_noise,
            threads=self.threads,
            workers=self.workers,
            components=self.components,
        )
        non_negative(particles=self.particles, calibrate=self.calibrate)
        _starts_within_screen(self.n_starts, self.n_screen)
        one_of("curvature", self.curvature, CURVATURES)
        one_of("covariance", self.covariance, COVARIANCES)
        one_of("intervals", self.intervals, INTERVALS)
        one_of("actor_dtype", self.actor_dtype, ACTOR_DTYPES)
        one_of("calibration_tail", self.calibration_tail, TAILS)
        one_of("senses", self.senses, SENSES)
        probability(lapse=self.lapse)
        if self.fit_lapse:
            _fitted_lapse_start(self.lapse)
        if not (self.time_column and self.trial_column) or self.time_column == self.trial_column:
            raise ValueError(
                f"config: time_column and trial_column must name two columns, got "
                f"{self.time_column!r} and {self.trial_column!r}"
            )
        return self


def _fitted_lapse_start(value: float) -> None:
    if not 0 < value < LAPSE_MAX:
        raise ValueError(
            f"config: lapse (the fitted rate's start) must be in (0, {LAPSE_MAX}) with "
            f"fit_lapse=true, got {value}"
        )


def config_to_dict(config: Any) -> dict:
    """A plain dict (for YAML, JSON and ``summary.json``)."""
    return dataclasses.asdict(config)


def _valid_keys(config: Any, prefix: str = "") -> list[str]:
    keys = []
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            keys += _valid_keys(value, f"{prefix}{f.name}.")
        elif isinstance(value, dict):
            keys.append(f"{prefix}{f.name}.<name>")
        else:
            keys.append(prefix + f.name)
    return keys


def _set(config: Any, dotted: str, value: Any, root: Any, prefix: str = "") -> None:
    """Set the field at ``dotted`` below ``config`` (which sits at ``prefix`` in ``root``)."""
    head, _, rest = dotted.partition(".")
    names = {f.name for f in dataclasses.fields(config)}
    current = getattr(config, head) if head in names else None
    nested = dataclasses.is_dataclass(current) or isinstance(current, dict)
    if head not in names or (rest and not nested):
        valid = _valid_keys(root)
        close = difflib.get_close_matches(prefix + dotted, valid, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        if prefix + dotted in getattr(root, "command_options", ()):
            hint = f" (set by the option --{dotted})"
        raise KeyError(
            f"config: unknown key {prefix + dotted!r}{hint}; valid keys: {', '.join(valid)}"
        )
    if rest and isinstance(current, dict):  # a mapping field: ``theta.g_v=1.2``
        current[rest] = value
        return
    if rest:
        _set(current, rest, value, root, f"{prefix}{head}.")
        return
    if dataclasses.is_dataclass(current):
        if not isinstance(value, dict):
            raise ValueError(f"config: {prefix + head!r} expects a mapping, got {value!r}")
        for key, sub in value.items():
            _set(current, key, sub, root, f"{prefix}{head}.")
        return
    setattr(config, head, _cast(prefix + dotted, value, current))


def _cast(name: str, value: Any, current: Any) -> Any:
    """``value`` as the type of the field's ``current`` value, refusing lossy conversions
    (``1.5`` for an integer, ``ture`` for a flag) with a one-line error naming the field."""
    kind = type(current)
    if isinstance(current, list):
        if not isinstance(value, list):
            raise ValueError(f"config: {name}={value!r} is not a list (write it as [a, b])")
        if not current:  # no element to take the type from
            return value
        return [_cast(f"{name}[{i}]", v, current[0]) for i, v in enumerate(value)]
    if kind is bool:
        words = {"true": True, "yes": True, "1": True, "false": False, "no": False, "0": False}
        if isinstance(value, bool):
            return value
        if isinstance(value, (str, int)) and str(value).lower() in words:
            return words[str(value).lower()]
    elif kind is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif kind is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # a number quoted, or inf and nan (YAML's .inf, .nan)
            try:
                return float(value)
            except ValueError:
                pass
    elif isinstance(value, kind):
        return value
    raise ValueError(f"config: {name}={value!r} is not a valid {kind.__name__}")


def load_config(
    path: str | Path | None = None,
    overrides: Sequence[str] = (),
    options: Mapping[str, Any] | None = None,
) -> Firefly1DConfig:
    """The embedded default, updated by the YAML file at ``path``, then by ``key=value`` and
    then by ``options`` (``{key: value}``, set as given: a command's options)."""
    return _update(Firefly1DConfig(), path, overrides, options).validate()


def load_firefly2d_config(
    path: str | Path | None = None,
    overrides: Sequence[str] = (),
    model: TaskModel | None = None,
    base: Mapping[str, Any] | None = None,
    options: Mapping[str, Any] | None = None,
    fresh: bool = True,
) -> Firefly2DConfig:
    """The ensemble-training config: embedded default, then the YAML file, then ``key=value``,
    then ``options``; ``fresh`` as in :meth:`Firefly2DConfig.validate` (``False`` resuming).

    ``model``: a task of the user's own; the default then names it as its task and warms up
    with random actions (the pursuit controller knows the 2D firefly only) (``None``: the 2D
    firefly task). ``base``: settings in plain-dict form over the embedded default (a
    checkpoint's ``config``, so that a resumed run goes on with them). ``options``:
    ``{key: value}`` set as given, not read as YAML (a command's options, ``--device``).
    """
    config = Firefly2DConfig()
    if model is not None:
        config.task = model.name
        if not isinstance(model, Firefly2DModel):
            config.ddpg.warmup_policy = "random"
    for key, value in (base or {}).items():
        _set(config, key, value, config)
    return _update(config, path, overrides, options).validate(model, fresh)


def load_simulate_config(overrides: Sequence[str] = ()) -> SimulateConfig:
    """``irc simulate``'s settings: the embedded default updated by ``key=value`` items."""
    return _update(SimulateConfig(), None, overrides).validate()


def load_recording_fit_config(overrides: Sequence[str] = ()) -> RecordingFitConfig:
    """``irc fit``'s settings: the embedded default updated by ``key=value`` items."""
    return _update(RecordingFitConfig(), None, overrides).validate()


def _file_commands() -> dict[type, str]:
    """The command that reads each kind of config file (``configs/`` holds one of each)."""
    from irc_torchrl.algorithms.recover2d import Recovery2DConfig

    return {
        Firefly1DConfig: "irc demo --task firefly1d",
        Firefly2DConfig: "irc train",
        Recovery2DConfig: "irc recover or irc demo --task firefly2d",
    }


def _check_file_kind(config: Any, data: dict, path: Path) -> None:
    """Refuse a file written for another command, naming both commands, where the first key
    this command lacks would be reported alone: all its keys that command's, two or more not
    this one's, one of them no other command's (a misplaced key keeps the unknown-key error)."""
    names = {f.name for f in dataclasses.fields(config)}
    unknown = [key for key in data if key not in names]
    if len(unknown) < 2:
        return
    commands = _file_commands()
    fields = {kind: {f.name for f in dataclasses.fields(kind)} for kind in commands}
    for kind, command in commands.items():
        others = set().union(*(names for k, names in fields.items() if k is not kind))
        own = [key for key in unknown if key not in others]
        if kind is not type(config) and own and set(data) <= fields[kind]:
            this = commands.get(type(config), type(config).__name__)
            raise KeyError(
                f"config: {path} holds `{command}`'s settings (e.g. {own[0]!r}), not "
                f"`{this}`'s; configs/ holds a file of each"
            )


def _update(
    config: Any,
    path: str | Path | None,
    overrides: Sequence[str],
    options: Mapping[str, Any] | None = None,
) -> Any:
    """``config`` updated in place by the YAML file at ``path``, then by ``key=value`` items,
    then by ``options``' values as given (not read as YAML)."""
    if path is not None:
        path = Path(path)
        if path.is_dir():
            raise ValueError(f"config: {path} is a folder; expected a YAML file")
        if not path.is_file():
            raise FileNotFoundError(f"config: no file at {path}")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as error:
            raise ValueError(
                f"config: {path} is not UTF-8 text ({error.reason} at byte {error.start}); "
                "expected a YAML file"
            ) from None
        data = _yaml(text, str(path)) or {}
        if not isinstance(data, dict):
            raise ValueError(
                f"config: {path} must hold a mapping of keys, got {type(data).__name__}"
            )
        _check_names(data, str(path))
        _check_file_kind(config, data, path)
        for key, value in data.items():
            _set(config, key, value, config)
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"config: override {item!r} must look like key=value")
        value = _yaml(value, f"override {item!r}")
        _check_names({key.strip(): value}, f"override {item!r}")
        _set(config, key.strip(), value, config)
    for key, value in (options or {}).items():
        _set(config, key, value, config)
    return config


def _check_names(data: Any, source: str, field: str = "") -> None:
    """Refuse a mapping key that is not a name (YAML reads ``1:``, ``true:`` and ``~:`` as a
    number, a flag and null), naming it and where it stands: in ``source``, under ``field``."""
    if not isinstance(data, dict):
        return
    for key, value in data.items():
        if not isinstance(key, str):
            under = f" under {field}" if field else ""
            raise KeyError(f"config: key {key!r} in {source}{under}: expected a name")
        _check_names(value, source, f"{field}.{key}" if field else key)


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a mapping that gives a key twice (plain YAML keeps the
    last): which value was meant is the user's to say, as on the command line."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # ``<<: *base``: keys given here override the merged ones
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, Hashable):
                break  # the safe loader refuses an unhashable key itself
            if key in first:
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"the key {key!r} is given twice (also on line {first[key] + 1})",
                    key_node.start_mark,
                )
            first[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


# YAML 1.1 reads a number with an exponent but no dot or no exponent sign (``1e6``, ``1e-3``,
# ``1.0e6``) as text; it is read as the number YAML 1.2 (and whoever wrote it) takes it for
_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _yaml(text: str, source: str) -> Any:
    """``text`` parsed as YAML, or a one-line error naming ``source`` and the problem."""
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # a safe loader: no objects built
    except yaml.YAMLError as error:
        problem = getattr(error, "problem", None) or first_line(error)
        mark = getattr(error, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        raise ValueError(f"config: {source} is not valid YAML: {problem}{where}") from None


def load_recovery2d_config(
    path: str | Path | None = None,
    overrides: Sequence[str] = (),
    model: TaskModel | None = None,
    options: Mapping[str, Any] | None = None,
) -> Recovery2DConfig:
    """The 2D recovery experiment's config: embedded default, the YAML file, then ``key=value``,
    then ``options`` (``{key: value}``, set as given: a command's options, ``--checkpoint``).

    ``model``: a task of the user's own; the default then names it as its task (``None``: the
    2D firefly task).
    """
    from irc_torchrl.algorithms.recover2d import Recovery2DConfig

    config = Recovery2DConfig() if model is None else Recovery2DConfig(task=model.name)
    return _update(config, path, overrides, options).validate(model)
