"""One-line refusals of unusable input, naming the field, raised before any work."""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Mapping, Sequence
from numbers import Integral, Real
from typing import Any

import numpy as np
import torch

__all__ = [
    "CALIBRATION",
    "INFORMATION",
    "PARTICLES",
    "SEED_LIMIT",
    "SIMULATION",
    "STARTS",
    "STREAMS_VERSION",
    "check_fields",
    "count",
    "derived_seed",
    "first_line",
    "non_negative",
    "one_of",
    "positive",
    "positive_number",
    "probability",
    "real",
    "resolve_device",
    "seed",
    "shown",
]

#: a config's seeds are integers in [0, SEED_LIMIT): torch's generators take 64 bits, and the
#: seeds offset from one (training's ``seed + 7919 * k``) must fit too
SEED_LIMIT = 2**63


def shown(value: object, width: int = 80) -> str:
    """``repr(value)`` on one line, cut to ``width`` characters (a tensor's spans several)."""
    text = " ".join(repr(value).split())
    return text if len(text) <= width else text[: width - 1] + "…"


def first_line(error: Exception) -> str:
    """An exception's message in one line (its first), or its type where it has none."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def _scalar(value: object) -> object:
    """A 0-d tensor or numpy scalar as the Python number it holds; anything else unchanged."""
    if getattr(value, "shape", None) == () and hasattr(value, "item"):
        return value.item()
    return value


def real(field: str, value: object) -> float:
    """``value`` as a float if it is a real number (a 0-d tensor or numpy scalar counts; a
    bool or a numeric string does not), else a one-line error naming ``field``."""
    value = _scalar(value)
    if isinstance(value, bool) or not isinstance(value, Real):
        raise ValueError(f"{field}: expected a real number, got {shown(value)}")
    return float(value)


def positive(**values: float) -> None:
    """Refuse a config value that is not a finite number > 0 (``.inf`` would pass ``> 0``)."""
    _finite(values, "positive", lambda value: value > 0)


def non_negative(**values: float) -> None:
    """Refuse a config value that is not a finite number ≥ 0."""
    _finite(values, "≥ 0", lambda value: value >= 0)


def probability(**values: float) -> None:
    """Refuse a config value that is not a probability in [0, 1)."""
    _finite(values, "a probability in [0, 1)", lambda value: 0 <= value < 1)


def one_of(name: str, value: str, choices: Sequence[str]) -> None:
    """Refuse a config value that is not one of ``choices``."""
    if value not in choices:
        raise ValueError(f"config: {name} must be one of {tuple(choices)}, got {value!r}")


def _finite(values: Mapping[str, float], what: str, holds: Callable[[float], bool]) -> None:
    """Refuse a config value for which ``holds`` fails (NaN fails every comparison), saying it
    must be ``what``, or that is infinite."""
    for name, value in values.items():
        if not holds(value):
            raise ValueError(f"config: {name} must be {what}, got {value}")
        if not math.isfinite(value):
            raise ValueError(f"config: {name} must be finite, got {value}")


def positive_number(field: str, value: float) -> float:
    """``value`` as a float if it is a finite number > 0, else a one-line error naming
    ``field``."""
    number = _scalar(value)
    if isinstance(number, bool) or not isinstance(number, Real) or not 0 < number < math.inf:
        raise ValueError(f"{field}: expected a positive finite number, got {shown(value)}")
    return float(number)


def count(field: str, value: int, least: int = 1) -> int:
    """``value`` as an int if it is an integer ≥ ``least``, else a one-line error naming
    ``field``."""
    number = _scalar(value)
    if isinstance(number, bool) or not isinstance(number, Integral) or number < least:
        raise ValueError(f"{field}: expected an integer ≥ {least}, got {shown(value)}")
    return int(number)


def seed(field: str, value: int) -> int:
    """``value`` as an int if torch's generators take it as a seed, ``[0, 2**64)`` (a config's
    seed stays below :data:`SEED_LIMIT`, so the seeds derived from it fit here)."""
    number = _scalar(value)
    if isinstance(number, bool) or not isinstance(number, Integral) or not 0 <= number < 2**64:
        raise ValueError(f"{field}: expected an integer in [0, 2**64), got {shown(value)}")
    return int(number)


#: the random streams of a seeded run, each its own seed from :func:`derived_seed` (a draw of
#: θ from the prior takes the run's seed itself); a value changed changes every run's data
SIMULATION, STARTS, PARTICLES, CALIBRATION, INFORMATION = range(1, 6)
#: the version of those streams, which recovery summaries record so that draws of different
#: data are never pooled (1: each stream the seed plus a constant; 2: :func:`derived_seed`)
STREAMS_VERSION = 2


def derived_seed(seed: int, *stream: int) -> int:
    """A seed in ``[0, 2**63)`` for the random stream ``stream`` of a run seeded ``seed``,
    by numpy's ``SeedSequence``: unlike ``seed + k``, the streams of runs with neighbouring
    seeds share no draws (run 4's calibration is not run 5's shifted by one)."""
    words = np.random.SeedSequence(seed, spawn_key=stream).generate_state(2, np.uint32)
    return (int(words[0]) << 31) ^ int(words[1])


def _canonical(value: Any, default: Any) -> Any:
    """``value`` in the form of the field's ``default`` (its type, its list elements'), or
    ``None`` if it cannot stand for it: a Path or torch device for a text field, a tuple or
    array for a list, a numpy or 0-d tensor number for a number; never a bool for a number."""
    kind = type(default)
    if kind is str:
        return str(value) if isinstance(value, (str, os.PathLike, torch.device)) else None
    if kind in (list, tuple):
        if isinstance(value, (str, Mapping)) or not hasattr(value, "__iter__"):
            return None
        items = list(value)
        if default:  # no element to take the type from otherwise
            items = [_canonical(item, default[0]) for item in items]
            if any(item is None for item in items):
                return None
        return kind(items)
    if isinstance(default, Mapping):
        return dict(value) if isinstance(value, Mapping) else None
    value = _scalar(value)
    if kind is bool:
        return value if isinstance(value, bool) else None
    if kind in (int, float):
        number = Integral if kind is int else Real
        good = isinstance(value, number) and not isinstance(value, bool)
        return kind(value) if good else None
    return value if isinstance(value, kind) else None


def check_fields(config: Any, prefix: str = "") -> None:
    """Put every field of the dataclass ``config`` (nested ones too) in its default's form,
    refusing one that cannot take it (``1.5`` or ``True`` for an integer) and a ``seed``
    outside ``[0, SEED_LIMIT)``: what the YAML loader's parsing ensures, for a config built in
    Python (and what ``config.yaml`` can then hold)."""
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
        if default is not None:
            canonical = _canonical(value, default)
            if canonical is None:
                raise ValueError(
                    f"config: {name}={shown(value)} is not a valid {type(default).__name__}"
                )
            setattr(config, f.name, canonical)
        if f.name == "seed" and not 0 <= getattr(config, f.name) < SEED_LIMIT:
            raise ValueError(f"config: {name} must be an integer in [0, 2**63), got {value}")


def resolve_device(name: str) -> torch.device:
    """The torch device called ``name``, refused early when this machine has none of it."""
    try:
        device = torch.device(name)
    except RuntimeError as error:
        raise ValueError(f"device: {error}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device: {name!r} requested but torch.cuda.is_available() is False")
    if device.type == "meta":
        raise ValueError("device: 'meta' tensors hold no values; expected 'cpu' or 'cuda'")
    try:
        torch.zeros(1, device=device)
    except (RuntimeError, AssertionError, ImportError):  # a backend this build or machine lacks
        raise ValueError(
            f"device: {name!r} is not usable here (no working {device.type!r} backend in this "
            "torch); expected 'cpu' or an available accelerator"
        ) from None
    return device


def module_device(module: torch.nn.Module) -> torch.device:
    """Where a module's first parameter or buffer lives (the CPU for one that holds none)."""
    held = next(iter([*module.parameters(), *module.buffers()]), None)
    return held.device if held is not None else torch.device("cpu")
