"""The paper's figures, drawn with matplotlib and written atomically as PNG."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from irc_torchrl.data.files import atomic_path  # noqa: E402

__all__ = ["plot_q_function", "plot_recovery", "plot_dp_comparison"]

ACTION_NAMES = ("left", "stop", "right")


def _save(fig: plt.Figure, path: str | Path) -> Path:
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=150, bbox_inches="tight", format="png")
    plt.close(fig)
    return Path(path)


def plot_q_function(
    relative: torch.Tensor,
    learned: torch.Tensor,
    optimal: torch.Tensor,
    theta: dict,
    path: str | Path,
) -> Path:
    """Fig. 1B: ``Q(b, a; θ)`` at the start of a trial against the believed offset to the target."""
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for a, name in enumerate(ACTION_NAMES):
        (line,) = ax.plot(relative, learned[:, a], label=f"{name} (learned)")
        ax.plot(
            relative,
            optimal[:, a],
            "--",
            color=line.get_color(),
            alpha=0.7,
            label=f"{name} (exact DP)",
        )
    ax.set_xlabel("believed position − target (distance units)")
    ax.set_ylabel("Q(b, a; θ) (reward units)")
    ax.set_title("θ: " + ", ".join(f"{k}={v:.3g}" for k, v in theta.items()), fontsize=8)
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, path)


def plot_recovery(summary: dict, path: str | Path) -> Path:
    """Fig. 1C/1D: θ̂ against θ* with 95% intervals, one panel per free parameter."""
    names = list(summary["parameters"])
    fig, axes = plt.subplots(1, len(names), figsize=(3.6 * len(names), 3.4), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        truth = [a["theta_true"][name] for a in summary["agents"]]
        hat = [a["theta_hat"][name] for a in summary["agents"]]
        low = [a["theta_hat"][name] - a["ci_low"][name] for a in summary["agents"]]
        high = [a["ci_high"][name] - a["theta_hat"][name] for a in summary["agents"]]
        ax.errorbar(truth, hat, yerr=[low, high], fmt="o", ms=3, capsize=2, lw=0.8)
        lo, hi = min(truth + hat), max(truth + hat)
        ax.plot([lo, hi], [lo, hi], "k:", lw=0.8)
        stats = summary["parameters"][name]
        ax.set_title(f"{name}: coverage {stats['coverage']:.2f}", fontsize=9)
        ax.set_xlabel(f"true {name}")
        ax.set_ylabel(f"estimated {name} (95% CI)")
    return _save(fig, path)


def plot_dp_comparison(
    dp: torch.Tensor, learned: torch.Tensor, labels: list[str], path: str | Path
) -> Path:
    """Mean return per θ of the learned greedy policy against the exact DP optimum."""
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.scatter(dp, learned, s=12)
    lo, hi = float(min(dp.min(), learned.min())), float(max(dp.max(), learned.max()))
    ax.plot([lo, hi], [lo, hi], "k:", lw=0.8, label="equal")
    ax.plot([lo, hi], [0.95 * lo, 0.95 * hi], "r:", lw=0.8, label="95% of optimal")
    ax.set_xlabel("DP-optimal mean return (reward units)")
    ax.set_ylabel("learned greedy mean return (reward units)")
    ax.set_title(
        f"{len(labels)} θ over the prior; ratio of means {float(learned.mean() / dp.mean()):.3f}",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    return _save(fig, path)
