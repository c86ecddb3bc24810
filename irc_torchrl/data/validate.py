"""Checks on a raw recording, before it becomes held trials: one clear message per problem.

A recording is a table of columns, one value per time step, with a trial column. Every check
of what a fit would misread raises one ``KeyError`` (columns) or ``ValueError`` (values) whose
message names the file, the trial, the field and what was expected, so that a fit never starts
on it; what may be the lab's choice (samples past the task's stop, actions that do not drive
the recorded velocities) is warned of instead.
Values are checked in the model's units (after :func:`~irc_torchrl.data.units.convert_units`);
a velocity far beyond anything the θ space allows usually means a unit mistake.
"""

from __future__ import annotations

import difflib
import math
import warnings
from collections.abc import Mapping

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical

from irc_torchrl.data.trajectories import recorded_stops
from irc_torchrl.envs.model import ABSURD, TaskModel, action_in_spec

__all__ = [
    "ABSURD",
    "THETA_PREFIX",
    "KINEMATIC_RATIO",
    "WORLD_RATIO",
    "check_columns",
    "check_kinematics",
    "check_stops",
    "check_targets",
    "check_trial",
    "required_columns",
    "split_trials",
]

#: columns ``theta.<name>`` give the task's θ per trial
THETA_PREFIX = "theta."

Trial = dict[str, np.ndarray]

#: recorded steps a trial may go on past the task's stop before a warning (a control
#: resampled on its way down crosses the threshold a step or two before the recording ends)
AFTER_STOP = 2
#: the unit a recording most likely used by mistake, per kind of checked field
_LIKELY_MISTAKE = {"distance": "cm", "distance/s": "cm/s", "rad/s": "deg/s"}
#: how far the distance the positions (or angles) cover may differ from what their velocity
#: column says, as a ratio either way: a unit mistake is 17× (deg) to 1000× (ms)
KINEMATIC_RATIO = 3.0
#: how far the velocities the actions drive may follow them otherwise than the world's θ says
#: before a warning: a rig's gain outside the task's, or a filtered joystick, misleads the fit
WORLD_RATIO = 1.25


def required_columns(model: TaskModel, time_column: str, trial_column: str) -> list[str]:
    """Every column a recording of ``model`` must have, in the schema's order."""
    names = [*model.state_names, *model.action_names, *model.target_names]
    return [trial_column, time_column, *names]


def check_columns(
    columns: Mapping[str, np.ndarray],
    model: TaskModel,
    source: str,
    time_column: str = "time",
    trial_column: str = "trial",
) -> None:
    """Refuse an empty table, missing or misnamed columns, unknown θ, ragged or text columns."""
    required = required_columns(model, time_column, trial_column)
    if not columns or all(np.size(v) == 0 for v in columns.values()):
        raise ValueError(
            f"{source}: the file holds no samples; expected one row per time step "
            f"with columns {required}"
        )
    known = set(required) | {THETA_PREFIX + n for n in model.theta_space.names}
    unknown = [name for name in columns if name not in known]
    for name in required:
        if name not in columns:
            close = [n for n in unknown if n.lower() == name.lower()]  # `X` for `x`
            close = close or difflib.get_close_matches(name, unknown, n=1, cutoff=0.6)
            hint = f"; column {close[0]!r} looks like a misnamed {name!r}" if close else ""
            setting = {time_column: "time_column", trial_column: "trial_column"}.get(name)
            if close and setting:  # the recording's own name for it may be declared
                hint += f" (rename it, or declare {setting}={close[0]})"
            raise KeyError(
                f"{source}: missing column {name!r}{hint}; expected columns {required} "
                f"(optional {THETA_PREFIX}<name> for θ: {', '.join(model.theta_space.names)})"
            )
    for name in unknown:
        if name.startswith(THETA_PREFIX):
            close = difflib.get_close_matches(
                name[len(THETA_PREFIX) :], model.theta_space.names, n=1
            )
            hint = f"; did you mean {THETA_PREFIX + close[0]!r}?" if close else ""
            raise KeyError(
                f"{source}: column {name!r} names no θ parameter{hint} "
                f"expected {THETA_PREFIX}<name> with name in {model.theta_space.names}"
            )
    n_rows = np.asarray(columns[trial_column]).reshape(-1).shape[0]
    for name in [*required, *(n for n in columns if n.startswith(THETA_PREFIX))]:
        value = np.asarray(columns[name])
        if value.ndim != 1:
            raise ValueError(
                f"{source}: column {name!r} has shape {list(value.shape)}; "
                "expected one value per time step (a 1-D array)"
            )
        if len(value) != n_rows:
            raise ValueError(
                f"{source}: column {name!r} has {len(value)} values but column "
                f"{trial_column!r} has {n_rows}; expected one value per time step in every column"
            )
        real = np.issubdtype(value.dtype, np.number) and not np.iscomplexobj(value)
        if not (real or value.dtype == np.bool_):
            raise ValueError(
                f"{source}: column {name!r} holds {value.dtype} values; expected numbers"
            )


#: how a recording's rows are numbered in messages (a CSV's data row 1 is its file's line 2)
_ROWS = "(the table's rows counted from 1, after a CSV's header)"


def split_trials(
    columns: Mapping[str, np.ndarray], source: str, trial_column: str = "trial"
) -> list[tuple[int | float, Trial]]:
    """The rows of each trial, in order of first appearance, as ``(label, {column: values})``;
    a trial's rows must lie together (two sessions pooled with the same numbers do not)."""
    ids = np.asarray(columns[trial_column], dtype=np.float64)
    if not np.isfinite(ids).all():
        row = int(np.flatnonzero(~np.isfinite(ids))[0])
        raise ValueError(
            f"{source}: field {trial_column!r} is {ids[row]} at row {row + 1} {_ROWS}; "
            "expected a trial number on every row"
        )
    labels, first = np.unique(ids, return_index=True)
    out = []
    for label in labels[np.argsort(first)]:
        rows = ids == label
        name = int(label) if float(label).is_integer() else float(label)
        at = np.flatnonzero(rows)
        if at[-1] - at[0] + 1 != len(at):
            end = int(at[np.flatnonzero(np.diff(at) > 1)[0]])
            block = f"row {end + 1}" if end == at[0] else f"rows {at[0] + 1}–{end + 1}"
            raise ValueError(
                f"{source}: field {trial_column!r}: trial {name} is on {block} and again from "
                f"row {at[at > end][0] + 1} {_ROWS}; expected each trial's rows together (two "
                "sessions pooled under the same trial numbers? number them apart, e.g. "
                "20240501.001; rows out of order? sort them by trial and time)"
            )
        out.append((name, {k: np.asarray(v)[rows] for k, v in columns.items()}))
    return out


def check_trial(
    label: int | float, trial: Trial, model: TaskModel, source: str, time_column: str = "time"
) -> None:
    """Refuse a trial whose values a fit would misread (see the module docstring)."""
    where = f"{source}: trial {label}"
    time = np.asarray(trial[time_column], dtype=np.float64)  # one sample: a trial of one step
    for name, value in trial.items():
        bad = ~np.isfinite(np.asarray(value, dtype=np.float64))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            at = f"sample {i}" if name == time_column else f"time {time[i]:.6g} s (sample {i})"
            raise ValueError(
                f"{where}, field {name!r}: {value[i]} at {at}; expected finite values "
                "(fill or cut NaN gaps before fitting)"
            )
    steps = np.diff(time)
    if (steps <= 0).any():
        i = int(np.flatnonzero(steps <= 0)[0])
        # back to the trial's first time or before: another trial under the same number
        again = " (it starts over: two trials under one number?)" if time[i + 1] <= time[0] else ""
        raise ValueError(
            f"{where}, field {time_column!r}: time goes from {time[i]:.6g} s to "
            f"{time[i + 1]:.6g} s at sample {i + 1}; expected strictly increasing times{again}"
        )
    _check_constant(where, trial, model)
    _check_actions(where, trial, model, time)
    _check_speeds(where, trial, model, time, time_column)


def _check_constant(where: str, trial: Trial, model: TaskModel) -> None:
    """The target and θ are fixed within a trial; θ lies in its space."""
    space = model.theta_space
    thetas = [n for n in trial if n.startswith(THETA_PREFIX)]
    for name in [*model.target_names, *thetas]:
        value = np.asarray(trial[name], dtype=np.float64)
        if not np.allclose(value, value[0], rtol=1e-6, atol=1e-9):
            i = int(np.flatnonzero(~np.isclose(value, value[0], rtol=1e-6, atol=1e-9))[0])
            raise ValueError(
                f"{where}, field {name!r}: {value[i]:.6g} at sample {i} differs from "
                f"{value[0]:.6g} at its start; expected one value per trial"
            )
    for name in thetas:
        p = space[name[len(THETA_PREFIX) :]]
        value = float(trial[name][0])
        slack = space.tolerance * (p.high - p.low)
        if not p.low - slack <= value <= p.high + slack:
            raise ValueError(
                f"{where}, field {name!r}: {value:.6g}; expected a value in its space "
                f"[{p.low}, {p.high}] ({p.unit})"
            )


def _check_actions(where: str, trial: Trial, model: TaskModel, time: np.ndarray) -> None:
    """Actions lie in the task's action set (integers) or its bounds (continuous)."""
    spec = model.action_spec
    discrete = isinstance(spec, Categorical)
    value = np.stack([np.asarray(trial[n], np.float64) for n in model.action_names], -1)
    action = torch.from_numpy(value[..., 0] if discrete else value)
    bad = ~action_in_spec(spec, action, slack=0.0 if discrete else 1e-6).numpy()
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        if discrete:
            name, v, bounds = model.action_names[0], value[i, 0], ""
            expected = f"an action index, an integer in 0..{spec.n - 1}"
        else:
            low, high = (
                x.to("cpu", torch.float64).numpy() for x in (spec.space.low, spec.space.high)
            )
            j = int(np.argmax(np.maximum(low - value[i], value[i] - high)))  # the worst component
            name, v, bounds = model.action_names[j], value[i, j], f" [{low[j]:g}, {high[j]:g}]"
            expected = "a dimensionless control within the action bounds"
        raise ValueError(
            f"{where}, field {name!r}: {v:.6g} at time {time[i]:.6g} s; expected {expected}{bounds}"
        )


def _check_speeds(
    where: str, trial: Trial, model: TaskModel, time: np.ndarray, time_column: str
) -> None:
    """Velocities, displacements and heading changes within reach of the θ space."""
    units = dict(zip(model.state_names, model.state_units, strict=True))
    dt = np.diff(time)
    step = float(np.median(dt)) if dt.size else model.dt
    rates: list[tuple[str, np.ndarray, np.ndarray, str, str]] = []  # field, |rate|, at, units
    for name, unit in units.items():
        if unit in ("distance/s", "rad/s"):
            rates.append((name, np.abs(trial[name].astype(np.float64)), time, unit, unit))
    positions = [n for n, u in units.items() if u == "distance"]
    if positions:
        xy = np.stack([trial[n].astype(np.float64) for n in positions], -1)
        speed = np.linalg.norm(np.diff(xy, axis=0), axis=-1) / dt
        rates.append(("/".join(positions), speed, time[1:], "distance/s", "distance"))
    for name, rate, at, unit, field_unit in rates:
        limit = model.rate_limit(unit)
        if limit is not None and (rate > limit).any():
            i = int(np.flatnonzero(rate > limit)[0])
            kind = "the speed between samples of " if field_unit == "distance" else ""
            hint = _LIKELY_MISTAKE[field_unit]
            # a median step a thousandth of the task's (within 3×): seconds read as ms
            timing = (
                f"Times in seconds given units.{time_column}=ms (a median step of {step:.3g} s "
                f"against the task's {model.dt:g} s)? Drop it. Or a unit mistake of the "
                "positions? "
                if field_unit == "distance" and 1 / 3 < step * 1000 / model.dt < 3
                else "A unit mistake? "
            )
            fields = name.split("/")  # the positions' speed: each may be the one undeclared
            settings = " ".join(f"units.{n}={hint}" for n in fields)
            raise ValueError(
                f"{where}, field {name!r}: {kind}{rate[i]:.6g} {unit} at time {at[i]:.6g} s; "
                f"expected below {limit:.6g} {unit} (the task's rate_limit: by default "
                f"{ABSURD:g}× the θ space's fastest). "
                f"{timing}Declare {'them' if len(fields) > 1 else 'it'}: {settings} (irc fit) "
                f"or units={dict.fromkeys(fields, hint)} (read_trials), or similar"
            )
    for name, unit in units.items():
        if unit == "rad":
            jump = np.abs(np.diff(trial[name].astype(np.float64)))
            if (jump > math.pi).any():
                i = int(np.flatnonzero(jump > math.pi)[0])
                raise ValueError(
                    f"{where}, field {name!r}: changes by {jump[i]:.6g} rad at time "
                    f"{time[i + 1]:.6g} s; expected < π per sample (degrees? declare "
                    f"units.{name}=deg, or units={{{name!r}: 'deg'}} in Python; a wrapped "
                    "angle? np.unwrap it)"
                )


def check_kinematics(held: TensorDictBase, model: TaskModel, source: str) -> None:
    """Refuse a recording whose positions, angles or velocities do not move as the task's
    transition says.

    Each column is checked alone against the θ space's reach, so a velocity declared in the
    wrong unit (``v`` in m/s declared as cm/s beside positions in cm) passes, and so does an
    action of the other sign convention. Here each recorded step's change of the distance
    (angle) fields of the held trials ``[n, T]`` is regressed on the change the transition
    predicts from the recorded state and action (under the world's θ): a slope beyond
    :data:`KINEMATIC_RATIO` either way, many standard errors from 1, is a unit mistake. A
    recording that hardly moves (its predicted changes all zero) or whose tracker jitters as
    much as it moves leaves the slope unsure, and is let through. Velocities are checked
    against the actions driving them (:func:`_check_action_driven`).
    """
    stepped = held["mask"][:, 1:]  # a recorded step and the recorded one after it
    state = held["state"].double()
    before, after = state[:, :-1][stepped], state[:, 1:][stepped]
    action = held["action"][:, :-1][stepped]
    action = action if isinstance(model.action_spec, Categorical) else action.double()
    world = held["task_theta"].double()[:, :-1][stepped]
    predicted = model.transition(before, action, world)
    names = model.state_names
    units = dict(zip(names, model.state_units, strict=True))
    for kind in ("rad", "distance"):  # a heading's mistake also bends the predicted path
        columns = [i for i, n in enumerate(names) if units[n] == kind]
        fit = _slope(predicted - before, after - before, columns)
        if fit is None or _about_one(*fit, KINEMATIC_RATIO):
            continue
        slope, error = fit
        fields = "/".join(repr(names[i]) for i in columns)
        drivers = [n for n in names if units[n] == f"{kind}/s"]
        cause = f"{'/'.join(map(repr, drivers))}" if drivers else "the actions and the world's θ"
        angles = [repr(n) for n in names if units[n] == "rad"]
        convention = (
            f"; is {'/'.join(angles)} measured as the task's, from the x axis counter-clockwise?"
            if kind == "distance" and angles
            else ""
        )
        raise ValueError(
            f"{source}: field(s) {fields}: each step moves {slope:.3g}× as far as the task's "
            f"transition predicts from {cause} (a slope of ±{error:.2g} over the recording); "
            f"expected about 1: are {fields} and {cause} in the units declared? "
            f"(units.<column>=... on the command line){convention}"
        )
    if not isinstance(model.action_spec, Categorical):
        later = held["action"][:, 1:][stepped].double()  # the action recorded a row later
        _check_action_driven(model, before, predicted, later, world, after, source)


def _check_action_driven(
    model: TaskModel,
    before: torch.Tensor,
    predicted: torch.Tensor,
    later: torch.Tensor,
    world: torch.Tensor,
    after: torch.Tensor,
    source: str,
) -> None:
    """Refuse velocities that follow the continuous actions with the other sign or at a gain
    beyond :data:`KINEMATIC_RATIO`, and warn beyond :data:`WORLD_RATIO`.

    What the recording adds to each next state beyond the transition's with a zero action is
    regressed on what the action adds by the transition: the slope is the rig's gain over the
    world θ's. A flipped joystick convention (-1) read as the task's, or a rig faster than the
    θ space's world, passed every other check and gave a converged, confident, wrong θ̂.
    ``predicted`` is the transition from each step's action (as :func:`check_kinematics`
    computed it), ``later`` the action recorded a row later: where the slope is about 1 with
    that one, each row holds the action that set its own velocity, one sample late for the
    task (whose action at a step sets the next step's velocity).
    """
    idle = model.transition(before, torch.zeros_like(later), world)
    names = model.state_names
    for kind in ("distance/s", "rad/s"):
        columns = [i for i, u in enumerate(model.state_units) if u == kind]
        fit = _slope(predicted - idle, after - idle, columns)
        if fit is None or _about_one(*fit, WORLD_RATIO):
            continue
        slope, error = fit
        fields = "/".join(repr(names[i]) for i in columns)
        shifted = _slope(model.transition(before, later, world) - idle, after - idle, columns)
        if shifted is not None and _about_one(*shifted, WORLD_RATIO):
            cause = (
                f"they follow the action of the row after by {shifted[0]:.3g}×: each row holds "
                "the action that set its own velocity, where the task's action at a step sets "
                "the next step's; shift the actions one sample earlier"
            )
        else:
            cause = (
                f"are {fields} in the units declared (units.<column>=...), the actions "
                f"{'/'.join(map(repr, model.action_names))} of the task's signs and times, and "
                "the world's θ the rig's (theta.<name> columns)?"
            )
        message = (
            f"{source}: field(s) {fields}: follow the actions {slope:.3g}× as strongly as the "
            f"task's transition predicts under the world's θ (a slope of ±{error:.2g} over the "
            f"recording); expected about 1: {cause}"
        )
        if _about_one(slope, error, KINEMATIC_RATIO):
            warnings.warn(message, stacklevel=4)
        else:
            raise ValueError(message)


def check_stops(held: TensorDictBase, model: TaskModel, source: str) -> None:
    """Refuse a trial that goes on after a chosen stop (a discrete action: the task ends the
    trial there), and warn where trials go on more than :data:`AFTER_STOP` steps past a
    continuous task's stop rule (a reward period, the agent standing still): each such step
    is scored as the agent's choice to go on, which its policy never made."""
    mask, stopped = held["mask"], recorded_stops(held, model)
    first = stopped.long().argmax(-1)  # the first stop (0 where none: masked out below)
    after = mask.sum(-1) - 1 - first
    chosen = isinstance(model.action_spec, Categorical)
    late = stopped.any(-1) & (after > (0 if chosen else AFTER_STOP))
    if late.any():
        i = int(late.nonzero()[0])
        label, at = held["trial"][i, 0].item(), held["time"][i, first[i]].item()
        if chosen:
            raise ValueError(
                f"{source}: trial {label}: field 'action' stops {at:.6g} s into it, yet "
                f"{int(after[i])} steps follow; the task ends a trial at its stop, so cut the "
                "trial there"
            )
        warnings.warn(
            f"{source}: {int(late.sum())} of {len(mask)} trials go on past the task's stop "
            f"(trial {label}: {int(after[i])} steps after its stop at {at:.6g} s into it), each "
            "scored as the agent's choice to go on: cut each trial at its stop",
            stacklevel=3,
        )


def check_targets(held: TensorDictBase, model: TaskModel, source: str) -> None:
    """Refuse targets lying more than :data:`ABSURD` times farther from their trial's start
    than the task ever puts one (its ``initial_state`` over the θ prior): a unit mistake.

    Checked where the target is a position (as many components as the state's distance
    fields); the targets' unit is declared apart from the positions', so targets in cm beside
    positions in m passed every other check and gave a converged, wrong θ̂.
    """
    positions = [i for i, unit in enumerate(model.state_units) if unit == "distance"]
    if len(positions) != model.target_dim:
        return
    theta = model.theta_space.sample((256,), generator=torch.Generator().manual_seed(0))
    state, target = model.initial_state(theta, torch.Generator().manual_seed(0))
    reach = float((target - state[..., positions]).norm(dim=-1).max())
    if reach == 0:  # the task puts its targets at the start: nothing to scale a mistake by
        return
    offset = (held["target"][:, 0].double() - held["state"][:, 0, positions].double()).norm(dim=-1)
    worst = int(offset.argmax())
    if offset[worst] > ABSURD * reach:
        names = "/".join(map(repr, model.target_names))
        label = held["trial"][worst, 0].item() if "trial" in held.keys() else worst
        raise ValueError(
            f"{source}: trial {label}, field(s) {names}: {offset[worst]:.6g} from the trial's "
            f"first position; expected within {ABSURD:g}× the task's farthest target "
            f"({reach:.3g}). A unit mistake? Declare it: units.{model.target_names[0]}=cm "
            "(irc fit), or similar, for each target column"
        )


def _slope(x: torch.Tensor, y: torch.Tensor, columns: list[int]) -> tuple[float, float] | None:
    """The least-squares slope through 0 of ``y`` on ``x`` over ``columns``, and its standard
    error; ``None`` where ``x`` does not vary (nothing to read a slope from)."""
    x, y = x[:, columns].reshape(-1), y[:, columns].reshape(-1)
    spread = float(x @ x)
    if spread == 0 or len(x) < 3:
        return None
    slope = float(x @ y) / spread
    return slope, math.sqrt(float(((y - slope * x) ** 2).sum()) / (len(x) - 1) / spread)


def _about_one(slope: float, error: float, ratio: float) -> bool:
    """Whether a slope lies within ``ratio`` of 1 either way, or within 5 standard errors."""
    return 1 / ratio <= slope <= ratio or abs(slope - 1) < 5 * error
