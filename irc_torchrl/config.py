"""Experiment configuration: dataclasses with embedded defaults, YAML files and ``key=value``.

The defaults in these dataclasses are the embedded default experiment; ``configs/*.yaml``
write the same values out for editing. ``key=value`` overrides address nested fields with dots
(``agents.n_agents=30``); an unknown key is an error that lists the valid ones.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from irc_torchrl.algorithms.ensemble import (
    DDPGConfig,
    EvaluationConfig,
    Firefly2DConfig,
)
from irc_torchrl.algorithms.qiteration import QIterationConfig

__all__ = [
    "AgentsConfig",
    "DDPGConfig",
    "EvaluationConfig",
    "FitConfig",
    "Firefly1DConfig",
    "Firefly2DConfig",
    "load_config",
    "load_firefly2d_config",
    "config_to_dict",
]


@dataclass
class AgentsConfig:
    """Simulated agents: θ* from the prior, acting by softmax over their Q in a fixed world."""

    n_agents: int = 20
    n_trials: int = 100
    temperature: float = 0.5
    #: "known": the world's θ is the task default and only actions inform θ̂;
    #: "shared": every agent lives in a world with its own θ and transitions count too
    world: str = "known"


@dataclass
class FitConfig:
    """Algorithm 2 settings (see :func:`irc_torchrl.algorithms.fit.fit_theta`)."""

    n_screen: int = 64
    n_starts: int = 4
    max_iter: int = 40


@dataclass
class Firefly1DConfig:
    """The 1D demo: train the factorised Q, simulate agents, fit them, report recovery."""

    task: str = "firefly1d"
    seed: int = 0
    #: torch threads; small networks run fastest on one thread per process
    threads: int = 1
    #: flush denormal floats to zero (they slow CPUs down several-fold)
    flush_denormal: bool = True
    q_iteration: QIterationConfig = field(default_factory=QIterationConfig)
    agents: AgentsConfig = field(default_factory=AgentsConfig)
    fit: FitConfig = field(default_factory=FitConfig)


def config_to_dict(config: Any) -> dict:
    """A plain dict (for YAML, JSON and ``summary.json``)."""
    return dataclasses.asdict(config)


def _valid_keys(config: Any, prefix: str = "") -> list[str]:
    keys = []
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            keys += _valid_keys(value, f"{prefix}{f.name}.")
        else:
            keys.append(prefix + f.name)
    return keys


def _set(config: Any, dotted: str, value: Any, root: Any, prefix: str = "") -> None:
    """Set the field at ``dotted`` below ``config`` (which sits at ``prefix`` in ``root``)."""
    head, _, rest = dotted.partition(".")
    names = {f.name for f in dataclasses.fields(config)}
    if head not in names or (rest and not dataclasses.is_dataclass(getattr(config, head))):
        valid = ", ".join(_valid_keys(root))
        raise KeyError(f"config: unknown key {prefix + dotted!r}; valid keys: {valid}")
    current = getattr(config, head)
    if rest:
        _set(current, rest, value, root, f"{prefix}{head}.")
        return
    if dataclasses.is_dataclass(current):
        if not isinstance(value, dict):
            raise ValueError(f"config: {prefix + head!r} expects a mapping, got {value!r}")
        for key, sub in value.items():
            _set(current, key, sub, root, f"{prefix}{head}.")
        return
    kind = type(current)
    try:
        if kind is bool and isinstance(value, str):
            cast = value.lower() in ("1", "true", "yes")
        else:
            cast = kind(value)
    except (TypeError, ValueError):
        name = prefix + dotted
        raise ValueError(f"config: {name}={value!r} is not a valid {kind.__name__}") from None
    setattr(config, head, cast)


def load_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> Firefly1DConfig:
    """The embedded default, updated by the YAML file at ``path`` and then by ``key=value``."""
    config = _update(Firefly1DConfig(), path, overrides)
    if config.agents.world not in ("known", "shared"):
        raise ValueError(
            f"config: agents.world must be 'known' or 'shared', got {config.agents.world!r}"
        )
    return config


def load_firefly2d_config(
    path: str | Path | None = None, overrides: Sequence[str] = ()
) -> Firefly2DConfig:
    """The 2D ensemble-training config: embedded default, then the YAML file, then ``key=value``."""
    return _update(Firefly2DConfig(), path, overrides).validate()


def _update(config: Any, path: str | Path | None, overrides: Sequence[str]) -> Any:
    """``config`` updated in place by the YAML file at ``path``, then by ``key=value`` items."""
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"config: no file at {path}")
        data = yaml.safe_load(path.read_text()) or {}
        if not isinstance(data, dict):
            raise ValueError(
                f"config: {path} must hold a mapping of keys, got {type(data).__name__}"
            )
        for key, value in data.items():
            _set(config, key, value, config)
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"config: override {item!r} must look like key=value")
        _set(config, key.strip(), yaml.safe_load(value), config)
    return config
