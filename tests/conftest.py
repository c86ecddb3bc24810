"""Shared fixtures: one thread for torch, and the 1D factorised Q trained once per test run."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import torch
from filelock import FileLock
from xdist import is_xdist_worker

torch.set_num_threads(1)


#: the test files that take longest (about 1-5 min of one core each), run first: xdist hands
#: files to its workers in collection order (``--no-loadscope-reorder``), so the short ones
#: fill in at the end and the workers finish together
SLOW_FIRST = (
    "test_fit2d.py", "test_own_task.py", "test_stages.py", "test_inverse1d.py",
    "test_examples.py", "test_cli_fit.py", "test_lapse.py",
)  # fmt: skip


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The slowest test files first, each file's tests in their own order."""
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FIRST)))


@contextmanager
def default_dtype(dtype: torch.dtype) -> Iterator[None]:
    """torch's default dtype set to ``dtype`` inside the block, the caller's restored after."""
    default = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(default)


@pytest.fixture(autouse=True, scope="session")
def _single_thread():
    """Thread oversubscription on a small shared machine makes torch many times slower."""
    torch.set_num_threads(1)
    yield


@pytest.fixture(scope="session")
def firefly1d_model():
    from irc_torchrl.envs.firefly1d import Firefly1DModel

    return Firefly1DModel()


@pytest.fixture(scope="session")
def trained_q(firefly1d_model, tmp_path_factory, request):
    """Algorithm 1 on the 1D task with the default settings, seed 0 (about 40 s on 1 thread),
    trained by the first xdist worker that asks and read by the others from a file named by
    the run's id (never an earlier run's)."""
    from irc_torchrl.algorithms.qiteration import QIterationConfig, train_factorised_q

    def train():
        return train_factorised_q(firefly1d_model, QIterationConfig(), seed=0)

    if not is_xdist_worker(request):
        return train()
    # the workers' temporary folders share a parent
    run = request.config.workerinput["testrunuid"]
    shared = tmp_path_factory.getbasetemp().parent / f"trained_q-{run}.pt"
    with FileLock(f"{shared}.lock"):
        if shared.is_file():  # written whole below, by this run's first worker
            return torch.load(shared, weights_only=False)
        q = train()
        part = shared.with_name(f"{shared.name}.part")
        torch.save(q, part)
        part.replace(shared)
    return q
