"""Process-wide torch settings for a run, restored when the run ends, and its progress bars."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from tqdm.auto import tqdm

from irc_torchrl.checks import resolve_device

__all__ = [
    "check_workers",
    "finish",
    "float32_default",
    "flushing_denormals",
    "resolve_device",
    "torch_settings",
]


@contextmanager
def torch_settings(threads: int, flush_denormal: bool) -> Iterator[None]:
    """Run with ``threads`` torch threads, denormal flushing and a float32 default dtype
    (:func:`float32_default`), then restore all three.

    Small networks run fastest on one thread per process, and denormal floats slow CPUs down
    several-fold; both are settings of the run, not hidden defaults, and must not leak into the
    caller (a notebook, a test session) afterwards.
    """
    previous, flushing = torch.get_num_threads(), flushing_denormals()
    torch.set_num_threads(threads)
    torch.set_flush_denormal(flush_denormal)
    try:
        with float32_default():
            yield
    finally:
        torch.set_num_threads(previous)
        torch.set_flush_denormal(flushing)


@contextmanager
def float32_default() -> Iterator[None]:
    """Run with torch's default dtype float32, then restore the caller's.

    TorchRL's exploration modules draw their noise in the default dtype: under a float64
    default a seed would give other draws (and float64 actions the float32 networks refuse).
    The default dtype is the process's, as ``torch.set_default_dtype`` sets it: threads
    running torch beside a run see float32 too.
    """
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    try:
        yield
    finally:
        torch.set_default_dtype(previous)


def flushing_denormals() -> bool:
    """Whether this process flushes denormal floats to zero (torch has no getter: a denormal
    doubled reads zero only then), so worker processes can run as their parent does. The
    setting is the CPU's: read on it whatever the default device."""
    return bool(torch.tensor(1e-310, dtype=torch.float64, device="cpu") * 2 == 0)


def check_workers(workers: int, device: torch.device | str) -> None:
    """Refuse more than one worker process off the CPU: workers share a fit between cores."""
    if workers > 1 and torch.device(device).type != "cpu":
        raise ValueError(
            f"workers: processes share a fit between CPU cores; expected 1 on {device}, "
            f"got {workers}"
        )


def finish(bar: tqdm) -> None:
    """Close ``bar`` at the step its work ended on: a fit converged before its ``max_iter``
    shows 100%, not a run that seems to have stopped part-way (in a notebook its widget's
    length too, which tqdm sets only when the bar is made)."""
    bar.total = bar.n
    if hasattr(bar, "container"):  # tqdm.notebook: (description, widget, counts)
        bar.container.children[1].max = bar.n
    bar.refresh()
    bar.close()
