"""Units of a recording: which column holds which kind of quantity, and conversion to the model's.

A task's distances are in its own "distance" unit, taken to be the metre when a recording
says otherwise; angles are radians and times seconds. ``units={"x": "cm", "heading": "deg"}``
tells :func:`convert_units` how the recording differs, column by column.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from irc_torchrl.envs.model import TaskModel

__all__ = ["UNITS", "column_kinds", "convert_units", "unwrap_angles"]

#: per kind of quantity (the model's unit), the known recording units and their factor to it
UNITS: dict[str, dict[str, float]] = {
    "distance": {"m": 1.0, "cm": 0.01, "mm": 0.001},
    "distance/s": {"m/s": 1.0, "cm/s": 0.01, "mm/s": 0.001},
    "rad": {"rad": 1.0, "deg": math.pi / 180},
    "rad/s": {"rad/s": 1.0, "deg/s": math.pi / 180},
    "s": {"s": 1.0, "ms": 0.001},
}


#: how far past ±π a wrapped angle may lie (round-off of the recording's export)
_WRAP_SLACK = 1e-5


def column_kinds(model: TaskModel, time_column: str = "time") -> dict[str, str]:
    """The model's unit of every column that has one (actions are dimensionless: absent),
    ``theta.*`` columns too where their parameter's unit is one :data:`UNITS` converts."""
    kinds = dict(zip(model.state_names, model.state_units, strict=True))
    kinds.update({name: "distance" for name in model.target_names})
    kinds.update(
        {f"theta.{p.name}": p.unit for p in model.theta_space.parameters if p.unit in UNITS}
    )
    kinds[time_column] = "s"
    return kinds


def convert_units(
    columns: Mapping[str, np.ndarray],
    units: Mapping[str, str],
    model: TaskModel,
    source: str,
    time_column: str = "time",
) -> dict[str, np.ndarray]:
    """A copy of ``columns`` with every column named in ``units`` converted to the model's unit.

    Raises a ``KeyError`` for a column without a unit and a ``ValueError`` for an unknown
    unit, listing the ones known for that column.
    """
    kinds = column_kinds(model, time_column)
    out = dict(columns)
    for name, unit in units.items():
        if name not in kinds:
            raise KeyError(
                f"{source}: units: column {name!r} has no unit to convert; "
                f"expected one of {sorted(kinds)} (actions are dimensionless)"
            )
        table = UNITS.get(kinds[name], {})
        if unit not in table:
            raise ValueError(
                f"{source}: units: unknown unit {unit!r} for column {name!r} "
                f"(model unit {kinds[name]}); expected one of {', '.join(table)}"
            )
        if name in out:
            out[name] = np.asarray(out[name], dtype=np.float64) * table[unit]
    return out


def unwrap_angles(trial: Mapping[str, np.ndarray], model: TaskModel) -> dict[str, np.ndarray]:
    """A copy of one trial whose angles, if wrapped into ``[-π, π]`` (e.g. by ``atan2``) or
    ``[0, 2π)`` (a compass's 0–360°), are made continuous, as the model's heading is.

    A jump counts as a wrap only where the angle crosses ±π (both samples within ``[-π, π]``
    on either side of it) or 0 (both within ``[0, 2π]``), and changes by less than π/2 once
    the 2π is taken off. Any other jump is left for
    :func:`~irc_torchrl.data.validate.check_trial` to refuse (degrees read as radians jump
    anywhere).
    """
    out = dict(trial)
    for name, unit in zip(model.state_names, model.state_units, strict=True):
        if unit != "rad" or name not in out:
            continue
        angle = np.asarray(out[name], dtype=np.float64)
        before, after = angle[:-1], angle[1:]
        jump = after - before
        turn = jump - 2 * math.pi * np.round(jump / (2 * math.pi))
        low, high = np.minimum(before, after), np.maximum(before, after)
        signed = (np.maximum(-low, high) <= math.pi + _WRAP_SLACK) & (before * after < 0)
        positive = (low >= -_WRAP_SLACK) & (high <= 2 * math.pi + _WRAP_SLACK)
        wrap = (signed | positive) & (np.abs(jump) > math.pi) & (np.abs(turn) < math.pi / 2)
        if wrap.any():
            out[name] = angle + np.concatenate([[0.0], np.cumsum(np.where(wrap, turn - jump, 0.0))])
    return out
