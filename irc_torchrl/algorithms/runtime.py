"""Process-wide torch settings for a run, restored when the run ends."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["torch_settings"]


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
