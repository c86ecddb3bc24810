"""Shared fixtures: one thread for torch, and the 1D factorised Q trained once per session."""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)


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
def trained_q(firefly1d_model):
    """Algorithm 1 on the 1D task with the default settings, seed 0 (about 20 s on 1 thread)."""
    from irc_torchrl.algorithms.qiteration import QIterationConfig, train_factorised_q

    return train_factorised_q(firefly1d_model, QIterationConfig(), seed=0)
