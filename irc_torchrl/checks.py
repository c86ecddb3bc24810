"""One-line refusals of unusable numbers, naming the field, raised before any work."""

from __future__ import annotations

import math
from numbers import Integral, Real

__all__ = ["count", "positive", "positive_number"]


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
