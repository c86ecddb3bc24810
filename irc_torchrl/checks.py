"""One-line refusals of unusable numbers, naming the field, raised before any work."""

from __future__ import annotations

import dataclasses
import math
from numbers import Integral, Real
from typing import Any

__all__ = ["SEED_LIMIT", "check_fields", "count", "positive", "positive_number", "seed"]

#: seeds are integers in [0, SEED_LIMIT): torch's generators take 64 bits, and the seeds
#: derived from one (``seed + 1000 * k``) must fit too
SEED_LIMIT = 2**63


def positive(**values: float) -> None:
    """Refuse a config value that is not a finite number > 0 (``.inf`` would pass ``> 0``)."""
    for name, value in values.items():
        if not value > 0:
            raise ValueError(f"config: {name} must be positive, got {value}")
        if not math.isfinite(value):
            raise ValueError(f"config: {name} must be finite, got {value}")


def positive_number(field: str, value: float) -> float:
    """``value`` as a float if it is a finite number > 0, else a one-line error naming
    ``field``."""
    if isinstance(value, bool) or not isinstance(value, Real) or not 0 < value < math.inf:
        raise ValueError(f"{field}: expected a positive finite number, got {value!r}")
    return float(value)


def count(field: str, value: int) -> int:
    """``value`` as an int if it is an integer ≥ 1, else a one-line error naming ``field``."""
    if isinstance(value, bool) or not isinstance(value, Integral) or value < 1:
        raise ValueError(f"{field}: expected an integer ≥ 1, got {value!r}")
    return int(value)


def _is(value: Any, kind: type) -> bool:
    """Whether ``value`` may stand for a field whose default is a ``kind`` (an int for a float,
    never a bool for a number)."""
    if kind is bool:
        return isinstance(value, bool)
    if kind in (int, float):
        number = Integral if kind is int else Real
        return isinstance(value, number) and not isinstance(value, bool)
    return isinstance(value, kind)


def check_fields(config: Any, prefix: str = "") -> None:
    """Refuse a field of the dataclass ``config`` (nested ones too) whose value is not of its
    default's type (``1.5`` or ``True`` for an integer), and a ``seed`` outside
    ``[0, SEED_LIMIT)``: what the YAML loader's parsing ensures, for a config built in Python."""
    for f in dataclasses.fields(config):
        value, name = getattr(config, f.name), prefix + f.name
        if dataclasses.is_dataclass(value):
            check_fields(value, f"{name}.")
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            continue
        if default is not None and not _is(value, type(default)):
            raise ValueError(f"config: {name}={value!r} is not a valid {type(default).__name__}")
        if f.name == "seed" and not 0 <= value < SEED_LIMIT:
            raise ValueError(f"config: {name} must be an integer in [0, 2**63), got {value}")


def seed(field: str, value: int) -> int:
    """``value`` as an int if it is an integer in ``[0, SEED_LIMIT)``, else a one-line error."""
    if isinstance(value, bool) or not isinstance(value, Integral) or not 0 <= value < SEED_LIMIT:
        raise ValueError(f"{field}: expected an integer in [0, 2**63), got {value!r}")
    return int(value)
