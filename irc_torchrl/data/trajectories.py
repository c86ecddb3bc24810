"""Held trials: the layout the inverse reads, and the checks that protect a fit from bad data.

Held trials are a TensorDict ``[n_agents, n_trials, T]`` (or ``[n_trials, T]`` for one agent)
with ``state [.., T, ds]``, ``action`` (``[.., T]`` discrete or ``[.., T, da]`` continuous),
``target [.., T, dt]``, ``mask [.., T]`` (the recorded steps, a prefix of each trial) and
``task_theta [.., T, d]``. :func:`validate_trials` checks all of it before any work is done.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, TensorSpec

from irc_torchrl.envs.model import TaskModel, action_in_spec, check_action_spec

__all__ = ["TRIAL_KEYS", "recorded_stops", "validate_trials"]

#: the fields every held trial has
TRIAL_KEYS = ("state", "action", "target", "mask", "task_theta")


def _where(bad: torch.Tensor) -> str:
    """Human-readable position of the first ``True`` of ``bad [A, n, T]``."""
    a, i, t = (int(x) for x in bad.nonzero()[0])
    return f"agent {a}, trial {i}, step {t}"


def validate_trials(trials: TensorDictBase, model: TaskModel) -> TensorDictBase:
    """Return ``trials`` as ``[n_agents, n_trials, T]`` if they are well formed, else raise.

    Checks presence and shapes of every field, that ``mask`` marks a non-empty prefix of
    each trial (and, where the env's ``step`` is kept, that it runs from the trial's start),
    that recorded steps are finite, that actions are floats for a continuous task and lie in
    the task's action set, that no trial goes on after a chosen stop (the task ends it
    there), that ``target`` and ``task_theta`` hold one value per trial (the fits read its
    first step's), and that ``task_theta`` lies in the θ space.
    """
    check_action_spec(model)
    if not isinstance(trials, TensorDictBase):
        raise TypeError(
            f"trials: expected a TensorDict [n_agents, n_trials, T], got {type(trials).__name__}"
        )
    missing = [k for k in TRIAL_KEYS if k not in trials.keys()]
    if missing:
        raise KeyError(f"trials: missing field(s) {missing}; held trials need {list(TRIAL_KEYS)}")
    if trials.ndim == 2:
        trials = trials.unsqueeze(0)
    if trials.ndim != 3:
        raise ValueError(
            f"trials: expected batch dims [n_agents, n_trials, T], got {list(trials.batch_size)}"
        )
    continuous = not isinstance(model.action_spec, Categorical)
    expected = {
        "state": (model.state_dim,),
        "target": (model.target_dim,),
        "task_theta": (model.theta_space.dim,),
        "mask": (),
        "action": tuple(model.action_spec.shape) if continuous else (),
    }
    for key, tail in expected.items():
        shape = tuple(trials[key].shape[3:])
        if shape != tail:
            raise ValueError(
                f"trials: field {key!r} expected shape "
                f"[n_agents, n_trials, T{''.join(f', {d}' for d in tail)}], "
                f"got {list(trials[key].shape)}"
            )
    mask = trials["mask"]
    if mask.dtype != torch.bool:
        raise TypeError(f"trials: field 'mask' expected dtype bool, got {mask.dtype}")
    if not mask[..., 0].all():
        raise ValueError(
            f"trials: field 'mask' marks no step at {_where(~mask[..., :1])}; "
            "every trial needs ≥ 1 step"
        )
    late = mask & (torch.arange(mask.shape[-1], device=mask.device) >= model.max_steps)
    if late.any():
        raise ValueError(
            f"trials: field 'mask' marks {_where(late)}; the task ends every trial within "
            f"max_steps={model.max_steps} steps (0 to {model.max_steps - 1}), so cut or drop "
            "longer trials"
        )
    gaps = mask[..., 1:] & ~mask[..., :-1]
    if gaps.any():
        raise ValueError(
            f"trials: field 'mask' must mark a prefix of each trial; a gap ends at {_where(gaps)}"
        )
    _refuse_cut_trials(trials, mask)
    if continuous and not trials["action"].is_floating_point():
        raise TypeError(
            f"trials: field 'action': expected a floating-point tensor (the task's actions are "
            f"continuous), got {trials['action'].dtype}"
        )
    for key in ("state", "target", "action"):
        value = trials[key]
        if value.is_floating_point():
            bad = ~torch.isfinite(value).reshape(*mask.shape, -1).all(-1) & mask
            if bad.any():
                raise ValueError(f"trials: field {key!r} has NaN or inf at {_where(bad)}")
    bad = ~action_in_spec(model.action_spec, trials["action"]) & mask
    if bad.any():
        raise ValueError(
            f"trials: field 'action' at {_where(bad)} is {trials['action'][bad][0].tolist()}, "
            f"outside the task's action set ({_describe(model.action_spec)})"
        )
    _refuse_steps_after_a_stop(trials, model)
    space, task_theta = model.theta_space, trials["task_theta"]
    if not task_theta.is_floating_point():
        raise TypeError(
            f"trials: field 'task_theta': expected a floating-point tensor, got {task_theta.dtype}"
        )
    bad = space.outside(task_theta).any(-1) & mask
    if bad.any():  # the first such step's values, named
        space.validate(task_theta[bad][:1], f"trials: field 'task_theta' at {_where(bad)}")
    for key in ("target", "task_theta"):  # read at each trial's first step
        value = trials[key].double()
        first = value[..., :1, :].expand_as(value)
        # beyond float32's rounding of values a file's checks found equal (rtol 1e-6)
        bad = ~torch.isclose(value, first, rtol=1e-5, atol=1e-6).all(-1) & mask
        if bad.any():
            raise ValueError(
                f"trials: field {key!r} at {_where(bad)} differs from its trial's first step; "
                "expected one value per trial"
            )
    return trials


def _refuse_cut_trials(trials: TensorDictBase, mask: torch.Tensor) -> None:
    """Where the env's step counter is kept, each trial's recorded steps are 0, 1, 2, ...: a
    trial a collector's batch cut (``split_trajs``) starts later, and its belief, time and stop
    rule would be read from a start it never had."""
    if "step" not in trials.keys():
        return
    step = trials["step"].reshape(*mask.shape, -1)[..., 0]
    late = (step != torch.arange(mask.shape[-1], device=mask.device)) & mask
    if late.any():
        raise ValueError(
            f"trials: field 'step' at {_where(late)} is {int(step[late][0])}; expected each "
            "trial from its start (0, 1, 2, ...): keep whole trials, not a batch's cut ones"
        )


def recorded_stops(trials: TensorDictBase, model: TaskModel) -> torch.Tensor:
    """The recorded steps ``[..., T]`` at which the task's stop rule ends the trial."""
    mask = trials["mask"]
    step = torch.arange(mask.shape[-1], device=mask.device).expand(mask.shape).unsqueeze(-1)
    return model.stops(trials["action"], step).squeeze(-1) & mask


def _refuse_steps_after_a_stop(trials: TensorDictBase, model: TaskModel) -> None:
    """A chosen stop (a discrete action) ends the trial: steps after it cannot be the task's.

    Continuous actions are left alone here (a recording read with them past a stop is warned
    of): one resampled to the task's step interpolates its controls, and can cross the stop
    threshold on the last steps before the trial ends.
    """
    if not isinstance(model.action_spec, Categorical):
        return
    on = recorded_stops(trials, model)[..., :-1] & trials["mask"][..., 1:]
    if on.any():
        raise ValueError(
            f"trials: field 'action' stops at {_where(on)} yet 'mask' marks the next step; the "
            "task ends a trial at its stop, so cut the trial there"
        )


def _describe(spec: TensorSpec) -> str:
    if isinstance(spec, Categorical):
        return f"integers 0..{spec.n - 1}"
    return f"the box [{spec.space.low.tolist()}, {spec.space.high.tolist()}]"
