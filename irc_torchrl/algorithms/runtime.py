"""Process-wide torch settings for a run, restored when the run ends."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["resolve_device", "torch_settings"]


@contextmanager
def torch_settings(threads: int, flush_denormal: bool) -> Iterator[None]:
    """Run with ``threads`` torch threads and denormal flushing, then restore both.

    Small networks run fastest on one thread per process, and denormal floats slow CPUs down
    several-fold; both are settings of the run, not hidden defaults, and must not leak into the
    caller (a notebook, a test session) afterwards.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    torch.set_flush_denormal(flush_denormal)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
        torch.set_flush_denormal(False)  # torch's default; it has no getter to restore from


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
    except (RuntimeError, AssertionError):  # a backend this torch build or machine lacks
        raise ValueError(
            f"device: {name!r} is not usable here (no working {device.type!r} backend in this "
            "torch); expected 'cpu' or an available accelerator"
        ) from None
    return device
