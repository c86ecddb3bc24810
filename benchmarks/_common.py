"""What the benchmark scripts share: argument types that refuse a bad size in one line before
any work, agents simulated into the fields an experimenter records, and ``irc recover``'s fit
settings."""

from __future__ import annotations

import argparse
from collections.abc import Callable

import torch
from tensordict import TensorDict

from irc_torchrl.algorithms.recover2d import Recovery2DConfig
from irc_torchrl.algorithms.simulate import simulate_agents
from irc_torchrl.data.trajectories import TRIAL_KEYS
from irc_torchrl.envs.model import TaskModel, sensed_world


def integer(least: int = 1) -> Callable[[str], int]:
    """An argparse type: an integer ≥ ``least`` (argparse names the option in its error)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < least:
            raise argparse.ArgumentTypeError(f"expected an integer ≥ {least}, got {text!r}")
        return value

    return parse


def recover_fit_settings() -> dict:
    """``fit_theta``'s settings in ``irc recover``'s default config (screened draws, starts,
    iterations, curvature, covariance), read from it so that a benchmark times what it runs."""
    fit = Recovery2DConfig().fit
    return {
        "n_screen": fit.n_screen,
        "n_starts": fit.n_starts,
        "max_iter": fit.max_iter,
        "curvature": fit.curvature,
        "covariance": fit.covariance,
    }


def recorded_agents(
    model: TaskModel, policy, theta: torch.Tensor, n_trials: int, seed: int
) -> TensorDict:
    """Agents of θ ``[n, d]`` acting by ``policy`` in the world of the θ space's defaults,
    each sensing as noisily as its θ says (as the fits assume), simulated with ``seed + 1``
    (``seed`` draws θ), as recorded: states, actions, targets."""
    world = sensed_world(model, model.theta_space.default(), theta)
    return simulate_agents(model, policy, theta, n_trials, world, seed=seed + 1).select(*TRIAL_KEYS)
