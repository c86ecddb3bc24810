"""Trained ensembles on disk: save and load, weights only.

A checkpoint is one ``torch.save`` of plain data (tensors, dicts, lists, strings, numbers):
network and optimiser state dicts, training counters, RNG states as tensors, the resolved
config, the θ space, the task name and the library version. :func:`load_checkpoint` reads it
with ``torch.load(weights_only=True)``, so a file can never run code when loaded, and checks
that it belongs to the task and θ space the caller expects. torch does not check the archive's
CRCs, so a damaged file would load with garbage weights: they are checked first, and a
non-finite tensor is refused. A bare name (``"firefly2d"``) loads the checkpoint shipped inside
the package.
"""

from __future__ import annotations

import pickle
import zipfile
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

import irc_torchrl
from irc_torchrl.checks import first_line, shown
from irc_torchrl.data.files import write_torch
from irc_torchrl.theta import ThetaSpace

__all__ = [
    "FORMAT",
    "HEADER",
    "PACKAGED",
    "load_checkpoint",
    "read_weights",
    "resolve_checkpoint",
    "save_checkpoint",
]

#: the format tag written into every checkpoint
FORMAT = "irc_torchrl.checkpoint/1"
#: where checkpoints shipped with the package live (loadable by bare name)
PACKAGED = Path(__file__).resolve().parent / "checkpoints"
#: the entries :func:`save_checkpoint` writes beside the caller's state
HEADER = ("format", "task", "version", "theta_space", "config")
#: the entries a caller's state may not use: the header's, and the ``path`` loading adds
RESERVED = (*HEADER, "path")
#: what ``torch.load(weights_only=True)`` reads back: containers and scalars, beside tensors
_CONTAINERS = (dict, OrderedDict, list, tuple)
_SCALARS = (type(None), bool, int, float, str)


def _major(version: str) -> str:
    return str(version).split(".")[0]


def save_checkpoint(
    path: str | Path,
    *,
    task: str,
    theta_space: ThetaSpace,
    config: Mapping[str, Any],
    state: Mapping[str, Any],
) -> Path:
    """Write a checkpoint atomically: a reader never sees a half-written file.

    Args:
        path: the file to write.
        task: the task's name (``"firefly2d"``).
        theta_space: the θ space the networks were trained over.
        config: the resolved config, as a plain dict.
        state: state dicts, counters and RNG states (plain data only).

    Raises:
        ValueError: before writing anything, where the arguments would make a file that
            :func:`load_checkpoint` refuses: a ``state`` entry named like a header entry
            (:data:`RESERVED`), anything but plain data (tensors, dicts, lists, tuples,
            strings, numbers, bools, None) in ``config`` or ``state``, or a tensor holding NaN
            or ±inf (diverged weights; the file at ``path`` is left as it was).
    """
    _check_save_arguments(task, theta_space, config, state)
    payload = {
        "format": FORMAT,
        "task": task,
        "version": irc_torchrl.__version__,
        "theta_space": theta_space.to_config(),
        "config": dict(config),
        **state,
    }
    return write_torch(path, payload)


def _check_save_arguments(
    task: str, theta_space: ThetaSpace, config: Mapping[str, Any], state: Mapping[str, Any]
) -> None:
    """Refuse what :func:`load_checkpoint` would refuse to read back, or read back as
    something else (a state entry ``task`` would overwrite the header's)."""
    if not isinstance(task, str) or not task:
        raise ValueError(f"save_checkpoint: task must be a non-empty string, got {shown(task)}")
    if not isinstance(theta_space, ThetaSpace):
        raise ValueError(
            f"save_checkpoint: theta_space must be a ThetaSpace, got {type(theta_space).__name__}"
        )
    for name, value in (("config", config), ("state", state)):
        if not isinstance(value, Mapping):
            raise ValueError(
                f"save_checkpoint: {name} must be a mapping, got {type(value).__name__}"
            )
    clash = [key for key in RESERVED if key in state]
    if clash:
        raise ValueError(
            f"save_checkpoint: state entries {clash} are reserved for the checkpoint's header "
            f"{list(RESERVED)}; rename them"
        )
    for name, value in (("config", config), ("state", state)):
        found = _not_plain(dict(value), name)
        if found is not None:
            raise ValueError(
                f"save_checkpoint: {found}; expected plain data (tensors, dicts, lists, "
                "tuples, strings, numbers, bools, None), which a weights-only load reads back"
            )
    entry = _non_finite(dict(state))
    if entry is not None:
        raise ValueError(
            f"save_checkpoint: state entry {entry} holds NaN or infinite values; expected "
            "finite weights (training diverged), which load_checkpoint accepts"
        )


def _not_plain(value: Any, name: str) -> str | None:
    """The first entry below ``value`` that a weights-only load refuses, as ``a/b is a T``."""
    if isinstance(value, torch.Tensor) or type(value) in _SCALARS:
        return None
    if type(value) not in _CONTAINERS:
        return f"{name} is a {type(value).__module__}.{type(value).__qualname__}"
    items = value.items() if isinstance(value, dict) else enumerate(value)
    for key, item in items:
        if type(key) not in _SCALARS:
            return f"{name} has a key {key!r:.40} of type {type(key).__name__}"
        found = _not_plain(item, f"{name}/{key}")
        if found is not None:
            return found
    return None


def resolve_checkpoint(source: str | Path) -> Path:
    """The file behind ``source``: a path, or the name of a checkpoint shipped in the package."""
    path = Path(source)
    if path.is_file():
        return path
    if isinstance(source, str) and path.suffix == "" and len(path.parts) == 1:
        packaged = PACKAGED / f"{source}.pt"
        if packaged.is_file():
            return packaged
        names = sorted(p.stem for p in PACKAGED.glob("*.pt")) if PACKAGED.is_dir() else []
        raise FileNotFoundError(
            f"checkpoint: no file at {path} and no packaged checkpoint named {source!r} "
            f"(packaged: {', '.join(names) or 'none'})"
        )
    raise FileNotFoundError(f"checkpoint: no file at {path}")


def load_checkpoint(
    source: str | Path,
    *,
    task: str | None = None,
    theta_space: ThetaSpace | None = None,
    required: Sequence[str] = (),
) -> dict[str, Any]:
    """Read a checkpoint (weights only) and check it matches the expected task and θ space.

    Args:
        source: a file path, or the name of a packaged checkpoint (``"firefly2d"``).
        task: the task the caller expects; ``None`` accepts any.
        theta_space: the θ space the caller expects; ``None`` accepts any.
        required: the state entries the caller reads (besides :data:`HEADER`'s); a string
            is one entry's name.

    Raises:
        FileNotFoundError: no such file or packaged name.
        ValueError: the file is not a readable checkpoint (truncated, garbage, failing its
            CRCs, or holding pickled objects other than plain data), lacks a required entry,
            holds a malformed θ space or a non-finite tensor, or its task, θ space or library
            major version does not match.
    """
    if theta_space is not None and not isinstance(theta_space, ThetaSpace):
        raise ValueError(
            f"load_checkpoint: theta_space must be a ThetaSpace or None, got "
            f"{type(theta_space).__name__}"
        )
    required = (required,) if isinstance(required, str) else tuple(required)
    path = resolve_checkpoint(source)
    data = read_weights(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"checkpoint {path}: format is {found!r}, expected {FORMAT!r}")
    _require(path, data, HEADER)
    for name in ("config", "theta_space"):
        if not isinstance(data[name], dict):
            raise ValueError(
                f"checkpoint {path}: entry {name} is a {type(data[name]).__name__}; expected "
                "a mapping, as irc train writes it"
            )
    if _major(data["version"]) != _major(irc_torchrl.__version__):
        raise ValueError(
            f"checkpoint {path}: version {data['version']} was written by another major version "
            f"than this library's {irc_torchrl.__version__}"
        )
    _require(path, data, required)
    if task is not None and data["task"] != task:
        raise ValueError(f"checkpoint {path}: task is {data['task']!r}, expected {task!r}")
    # parsed even when any θ space is accepted: callers build their models from it
    stored = ThetaSpace.from_config(data["theta_space"], f"checkpoint {path}: entry theta_space")
    if theta_space is not None and stored != theta_space:
        raise ValueError(f"checkpoint {path}: theta_space is {stored!r}, expected {theta_space!r}")
    entry = _non_finite(data)
    if entry is not None:
        raise ValueError(
            f"checkpoint {path}: entry {entry} holds NaN or infinite values; expected finite "
            "weights (the file is damaged or its training diverged)"
        )
    data["path"] = str(path)
    return data


def read_weights(path: Path) -> Any:
    """A file's weights-only payload, every failure a one-line ValueError naming ``path``.

    The archive's CRCs are checked first: ``torch.load`` reads a damaged tensor silently.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()
        if damaged is not None:
            raise ValueError(f"entry {damaged} fails its CRC check")
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        raise ValueError(
            f"checkpoint {path}: refused to load; it is not plain weights-only data "
            f"({first_line(error)})"
        ) from None
    except Exception as error:  # torch and zipfile raise many types for a damaged file
        raise ValueError(
            f"checkpoint {path}: not a readable irc_torchrl checkpoint "
            f"(truncated or corrupt: {first_line(error)}); expected a file written by irc train"
        ) from None


def _require(path: Path, data: Mapping[str, Any], names: Sequence[str]) -> None:
    """Refuse a checkpoint lacking any of the entries ``names``, naming every one missing."""
    missing = [name for name in names if name not in data]
    if missing:
        raise ValueError(
            f"checkpoint {path}: missing entries {missing}; expected a file written by irc train"
        )


def _non_finite(value: Any, name: str = "") -> str | None:
    """The first floating-point tensor below ``value`` holding NaN or ±inf, as ``a/b/c``."""
    if isinstance(value, torch.Tensor):
        bad = value.is_floating_point() and not bool(torch.isfinite(value).all())
        return name if bad else None
    if isinstance(value, Mapping):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = _non_finite(item, f"{name}/{key}" if name else str(key))
        if found is not None:
            return found
    return None
