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

__all__ = ["UNITS", "column_kinds", "convert_units"]

#: per kind of quantity (the model's unit), the known recording units and their factor to it
UNITS: dict[str, dict[str, float]] = {
    "distance": {"m": 1.0, "cm": 0.01, "mm": 0.001},
    "distance/s": {"m/s": 1.0, "cm/s": 0.01, "mm/s": 0.001},
    "rad": {"rad": 1.0, "deg": math.pi / 180},
    "rad/s": {"rad/s": 1.0, "deg/s": math.pi / 180},
    "s": {"s": 1.0, "ms": 0.001},
}


def column_kinds(model: TaskModel, time_column: str = "time") -> dict[str, str]:
    """The model's unit of every column that has one (actions are dimensionless: absent)."""
    kinds = dict(zip(model.state_names, model.state_units, strict=True))
    kinds.update({name: "distance" for name in model.target_names})
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
