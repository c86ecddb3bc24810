"""The main job: Inverse Rational Control end to end on the 1D task, in a few minutes.

Algorithm 1 learns one factorised Q over the θ prior, which is checked against exact dynamic
programming; simulated agents with θ* from the prior act by softmax over their Q; Algorithm 2
recovers every agent's θ with 95% intervals in one batched fit; the coverage is reported.
"""

from __future__ import annotations

import copy
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import yaml
from tqdm.auto import tqdm

from irc_torchrl.algorithms.dp import greedy_returns, optimal_values
from irc_torchrl.algorithms.fit import check_sandwich
from irc_torchrl.algorithms.qiteration import train_factorised_q
from irc_torchrl.algorithms.recovery import format_parameters, recover_agents
from irc_torchrl.algorithms.runtime import finish, torch_settings
from irc_torchrl.config import Firefly1DConfig, config_to_dict
from irc_torchrl.data.files import staged, write_json, write_npz, write_text
from irc_torchrl.envs.firefly1d import Firefly1DModel
from irc_torchrl.modules.likelihood import BoltzmannActionModel
from irc_torchrl.plots import demo_figures, plot_recovery

__all__ = ["run_demo", "dp_comparison", "format_summary"]

#: the share of the exact optimum below which a θ of the DP grid is warned about: the agents
#: simulated there act by a Q that is not near-optimal (training seeds 0 and 1: 0.92, 0.86)
NEAR_OPTIMAL = 0.9


def dp_comparison(
    model: Firefly1DModel,
    q_network: torch.nn.Module,
    n_grid: int = 5,
    n_starts: int = 49,
    gamma: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Learned greedy return against the DP optimum on a θ grid over the free parameters,
    both under the discount ``gamma`` the Q was trained with."""
    space = model.theta_space
    axes = [
        torch.linspace(space[n].low, space[n].high, n_grid, dtype=torch.float64)
        for n in space.free_names
    ]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))
    theta = space.default(torch.float64).expand(grid.shape[0], -1).clone()
    theta[:, space.free_mask] = grid
    starts = torch.linspace(-model.target_range, model.target_range, n_starts, dtype=torch.float64)
    optimal = optimal_values(model, theta, starts, gamma).max(-1).values
    learned = greedy_returns(model, q_network, theta, starts, gamma)
    return theta, starts, optimal, learned


def run_demo(config: Firefly1DConfig, out: str | Path, show_progress: bool = True) -> dict:
    """Run the 1D demo into ``out``: ``config.yaml``, ``summary.json``, three figures and
    ``figures.npz`` (what two of them show); returns the summary. ``config`` holds every
    setting (its seed, device and threads included); ``show_progress``: progress bars."""
    config.validate()
    with torch_settings(config.threads, config.flush_denormal):
        return _run_demo(config, Path(out), show_progress)


def _run_demo(config: Firefly1DConfig, out: Path, show_progress: bool) -> dict:
    model = Firefly1DModel()
    if config.fit.covariance == "sandwich":  # refused before Q-iteration, not after it
        n_nuisance = len(BoltzmannActionModel.nuisance_bounded)
        check_sandwich(
            torch.tensor([config.agents.n_trials]),
            len(model.theta_space.free_names),
            n_nuisance,
            "fit.covariance",
        )
    start = time.perf_counter()
    with tqdm(
        total=config.q_iteration.rounds,
        desc="Algorithm 1: fitted Q-iteration",
        disable=not show_progress,
    ) as bar:
        q = train_factorised_q(
            model, config.q_iteration, config.seed, lambda i, n: bar.update(1), config.device
        )
    train_s = time.perf_counter() - start

    on_cpu = copy.deepcopy(q).cpu()  # exact dynamic programming and the figures run here
    theta_grid, starts, optimal, learned = dp_comparison(
        model, on_cpu, gamma=config.q_iteration.gamma
    )
    dp_ratio = float(learned.mean() / optimal.mean())
    per_theta = learned.mean(1) / optimal.mean(1)
    warn_far_from_optimal(model, theta_grid, per_theta)

    with tqdm(
        total=config.fit.max_iter, desc="Algorithm 2: batched Newton fit", disable=not show_progress
    ) as bar:
        _, recovery, _ = recover_agents(
            model, q, config.agents, config.fit, config.seed, progress=lambda i, n: bar.update(1)
        )
        finish(bar)
    summary = {
        "command": "demo",
        "task": config.task,
        "method": "exact",
        "seed": config.seed,
        "agents": recovery["agents"],
        "parameters": recovery["parameters"],
        "dp_ratio": dp_ratio,
        "dp_ratio_min_per_theta": float(per_theta.min()),
        "timings": {"train_s": train_s, **recovery["timings"]},
    }
    arrays = _figure_arrays(model, on_cpu, theta_grid, optimal, learned, config.q_iteration.gamma)
    # interrupted while writing, the folder keeps the earlier run's files, not a mixture
    with staged(out) as staging:
        write_text(staging / "config.yaml", yaml.safe_dump(config_to_dict(config), sort_keys=False))
        write_json(staging / "summary.json", summary)
        write_npz(staging / "figures.npz", arrays)
        plot_recovery(summary, staging / "recovery.png", units=model.theta_space.units)
        demo_figures(arrays, staging)
    return summary


def warn_far_from_optimal(
    model: Firefly1DModel, theta_grid: torch.Tensor, per_theta: torch.Tensor
) -> None:
    """Warn when the learned Q earns under ``NEAR_OPTIMAL`` of the exact optimum at a θ of the
    grid (``per_theta [n]``): the mean ratio alone hides a Q that fails where θ is extreme."""
    worst = int(per_theta.argmin())
    if per_theta[worst] < NEAR_OPTIMAL:
        warnings.warn(
            f"demo: the learned Q earns {float(per_theta[worst]):.3f} of the exact optimum at "
            f"{model.theta_space.format(theta_grid[worst])} (expected at least {NEAR_OPTIMAL}); "
            "its agents there are not near-optimal, so the fit reads them by a wrong policy; "
            "another seed trains another Q",
            stacklevel=4,  # run_demo's caller
        )


def _figure_arrays(
    model: Firefly1DModel,
    q_network: torch.nn.Module,
    theta_grid: torch.Tensor,
    optimal: torch.Tensor,
    learned: torch.Tensor,
    gamma: float,
) -> dict[str, np.ndarray]:
    """What ``q_function.png`` and ``dp_comparison.png`` show (``figures.npz``, from which
    ``irc report`` redraws them): Q at the start of a trial at the default θ, learned and
    exact, and the mean greedy return per θ of the grid, learned and exact."""
    theta = model.theta_space.default(torch.float64).unsqueeze(0)
    relative = torch.linspace(-model.target_range, model.target_range, 241, dtype=torch.float64)
    target = -relative.view(-1, 1)
    mean, cov = model.initial_belief(
        torch.zeros_like(target), target, theta.expand(len(relative), -1)
    )
    step = torch.zeros(len(relative), 1, dtype=torch.long)
    with torch.no_grad():
        q_learned = q_network(model.belief_features(mean, cov, target, step, theta).float())
    return {
        "q_relative": relative.numpy(),
        "q_learned": q_learned.numpy(),
        "q_optimal": optimal_values(model, theta, relative, gamma)[0].numpy(),
        "theta": theta[0].numpy(),
        "theta_names": np.array(model.theta_space.names),
        "dp_theta": theta_grid.numpy(),
        "dp_optimal": optimal.mean(1).numpy(),
        "dp_learned": learned.mean(1).numpy(),
    }


def format_summary(summary: dict) -> str:
    """A readable table of the recovery (printed at the end of ``irc demo``)."""
    lines = format_parameters(summary["parameters"])
    t = summary["timings"]
    lines.append(
        f"DP ratio {summary['dp_ratio']:.4f} (min per θ {summary['dp_ratio_min_per_theta']:.3f}); "
        + ", ".join(f"{k} {v:.1f}" for k, v in t.items())
    )
    return "\n".join(lines)
