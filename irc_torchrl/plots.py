"""The paper's figures and the run reports, drawn with matplotlib and written atomically as PNG.

:func:`report_run` turns a run folder (``irc fit``, ``recover``, ``demo`` or ``train``) into
figures from its ``summary.json`` (and ``beliefs.npz``, ``figures.npz``, ``trials/`` or ``logs/``
where present).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import warnings
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.patches import Circle, Ellipse  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from irc_torchrl.checks import first_line  # noqa: E402
from irc_torchrl.data.files import MARK, atomic_path  # noqa: E402
from irc_torchrl.data.io import load_memmap  # noqa: E402
from irc_torchrl.objectives.fisher import Z95  # noqa: E402

__all__ = [
    "demo_figures",
    "plot_belief_overhead",
    "plot_belief_time",
    "plot_dp_comparison",
    "plot_estimates",
    "plot_q_function",
    "plot_q_function_2d",
    "plot_recovery",
    "plot_training",
    "report_run",
]

#: radius, in standard deviations, of a 2D Gaussian's 95% ellipse (√χ²₂(0.95))
ELLIPSE_95 = math.sqrt(-2 * math.log(0.05))

ACTION_NAMES = ("left", "stop", "right")


def _save(fig: plt.Figure, path: str | Path) -> Path:
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=150, bbox_inches="tight", format="png")
    plt.close(fig)
    return Path(path)


def plot_q_function(
    relative: np.ndarray,
    learned: np.ndarray,
    optimal: np.ndarray,
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


def plot_q_function_2d(
    slices: Mapping[str, torch.Tensor | float], path: str | Path, distance_unit: str = "m"
) -> Path:
    """Fig. 1B on the 2D task, from :func:`~irc_torchrl.algorithms.ensemble.critic_slices`.

    Left: the value ``Q(b, π(b); θ)`` against where the agent believes the target is.
    Middle and right: ``Q(b, a; θ)`` over the action square for two beliefs, ``π(b)`` marked,
    the stop region (forward control below the threshold) hatched.
    """
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 4.2))
    ax = axes[0]
    # drawn as seen from above, behind the agent: its left on the left (x = −aside)
    right, ahead = -np.asarray(slices["aside"]), np.asarray(slices["ahead"])
    image = ax.pcolormesh(right, ahead, np.asarray(slices["value"]), shading="auto")
    fig.colorbar(image, ax=ax, label="Q(b, π(b); θ) (reward units)")
    ax.add_patch(Circle((0, 0), float(slices["goal_radius"]), fill=False, color="w", ls="--"))
    ax.plot(0, 0, "w^", ms=8)
    for name, marker in (("far", "o"), ("near", "s")):
        ahead_t, aside_t = slices[f"target_{name}"]
        ax.plot(-aside_t, ahead_t, marker, mfc="none", mec="r", ms=9)
    ax.set_xlabel(f"believed target, right of the agent ({distance_unit})")
    ax.set_ylabel(f"believed target, ahead of the agent ({distance_unit})")
    ax.set_title("value of the believed target position\n(agent ▲ at rest, goal dashed)")
    ax.set_aspect("equal")
    action = np.asarray(slices["action"])
    for ax, name, where in (
        (axes[1], "far", "target ○ ahead-left"),
        (axes[2], "near", "target □ at the agent"),
    ):
        image = ax.pcolormesh(action, action, np.asarray(slices[f"q_{name}"]).T, shading="auto")
        fig.colorbar(image, ax=ax, label="Q(b, a; θ) (reward units)")
        ax.axvspan(-1, float(slices["stop_threshold"]), fill=False, hatch="//", ec="w", lw=0)
        pi = np.asarray(slices[f"pi_{name}"])
        ax.plot(pi[0], pi[1], "r*", ms=14, label="π(b)")
        ax.set_xlabel("forward control a_v (stop if < threshold, hatched)")
        ax.set_ylabel("angular control a_w")
        ax.set_title(f"Q over actions, {where}")
        ax.legend(loc="lower right", fontsize=8)
    return _save(fig, path)


def _with_unit(label: str, unit: str | None) -> str:
    return f"{label} ({unit})" if unit else label


def plot_recovery(
    summary: dict,
    path: str | Path,
    title: str | None = None,
    units: Mapping[str, str] | None = None,
) -> Path:
    """Fig. 1C/1D: θ̂ against θ* with 95% intervals, one panel per free parameter."""
    units = units or {}
    names = list(summary["parameters"])
    cols = min(4, len(names))
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.flat[len(names) :]:
        ax.set_visible(False)
    if title is not None:
        fig.suptitle(title)
    for ax, name in zip(axes.flat, names, strict=False):
        truth = [a["theta_true"][name] for a in summary["agents"]]
        hat = [a["theta_hat"][name] for a in summary["agents"]]
        low = [a["theta_hat"][name] - a["ci_low"][name] for a in summary["agents"]]
        high = [a["ci_high"][name] - a["theta_hat"][name] for a in summary["agents"]]
        ax.errorbar(truth, hat, yerr=[low, high], fmt="o", ms=3, capsize=2, lw=0.8)
        lo, hi = min(truth + hat), max(truth + hat)
        ax.plot([lo, hi], [lo, hi], "k:", lw=0.8)
        stats = summary["parameters"][name]
        ax.set_title(f"{name}: coverage {stats['coverage']:.2f}", fontsize=9)
        ax.set_xlabel(_with_unit(f"true {name}", units.get(name)))
        ax.set_ylabel(_with_unit(f"estimated {name}, 95% CI", units.get(name)))
    return _save(fig, path)


def plot_dp_comparison(
    dp: np.ndarray, learned: np.ndarray, labels: list[str], path: str | Path
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


def demo_figures(arrays: Mapping[str, np.ndarray], out: Path) -> list[Path]:
    """The 1D demo's ``q_function.png`` (Fig. 1B) and ``dp_comparison.png``, into ``out``,
    from the arrays of its ``figures.npz``."""
    theta = dict(zip(arrays["theta_names"].tolist(), arrays["theta"].tolist(), strict=True))
    labels = [str(row) for row in arrays["dp_theta"].tolist()]
    return [
        plot_q_function(
            arrays["q_relative"], arrays["q_learned"], arrays["q_optimal"], theta,
            out / "q_function.png",
        ),
        plot_dp_comparison(
            arrays["dp_optimal"], arrays["dp_learned"], labels, out / "dp_comparison.png"
        ),
    ]  # fmt: skip


def plot_estimates(summary: dict, path: str | Path, units: Mapping[str, str] | None = None) -> Path:
    """θ̂ with 95% intervals per agent, one panel per fitted parameter (no truth to compare)."""
    units = units or {}
    agents = summary["agents"]
    names = summary.get("free") or list(summary.get("parameters") or agents[0]["theta_hat"])
    labels = [a.get("label", str(i)) for i, a in enumerate(agents)]
    width = max(3.2, 0.45 * len(agents) + 1.5)  # per panel: room for every recording's label
    fig, axes = plt.subplots(1, len(names), figsize=(width * len(names), 3.4), squeeze=False)
    x = np.arange(len(agents))
    for ax, name in zip(axes[0], names, strict=True):
        hat = np.array([a["theta_hat"][name] for a in agents])
        low = np.array([a["ci_low"][name] for a in agents])
        high = np.array([a["ci_high"][name] for a in agents])
        identified = np.array([a["identified"][name] for a in agents], dtype=bool)
        groups = ((identified, "o", "identified"), (~identified, "x", "not identified"))
        for keep, style, tag in groups:
            if keep.any():
                ax.errorbar(
                    x[keep], hat[keep], yerr=[hat[keep] - low[keep], high[keep] - hat[keep]],
                    fmt=style, ms=4, capsize=3, lw=0.9, label=tag,
                )  # fmt: skip
        ax.set_xticks(x, labels, rotation=45 if len(agents) > 3 else 0, fontsize=7)
        ax.set_xlabel("recording")
        ax.set_ylabel(_with_unit(f"{name}, θ̂ with 95% CI", units.get(name)))
        ax.set_title(name, fontsize=9)
    axes[0][0].legend(fontsize=7)
    return _save(fig, path)


def _recorded(arrays: Mapping[str, np.ndarray], trial: int) -> dict[str, np.ndarray]:
    """One trial's recorded steps of the belief arrays (see ``beliefs.npz``)."""
    keep = arrays["mask"][trial].astype(bool)
    per_trial = ("mask", "trial", "trial_log_likelihood")  # no step axis to select
    return {k: v[trial][keep] for k, v in arrays.items() if k not in per_trial}


def _trial_name(arrays: Mapping[str, np.ndarray], row: int) -> str:
    """A trial's number in its recording (``trial``), else its row."""
    return str(arrays["trial"][row]) if "trial" in arrays else str(row)


def overhead_view(state_names: Sequence[str], target_dim: int) -> bool:
    """Whether beliefs can be seen from above: the state starts with a position in the plane
    (x, y) and the target is a point of it (the firefly's; a task of one's own need not be)."""
    return tuple(state_names[:2]) == ("x", "y") and target_dim == 2


def plot_belief_overhead(
    arrays: Mapping[str, np.ndarray],
    path: str | Path,
    goal_radius: float | None = None,
    n_trials: int = 4,
    distance_unit: str = "distance",
    title: str = "",
) -> Path:
    """Overhead view of a few trials: true path, believed position with 95% ellipses, target.

    ``arrays`` holds ``state [n, T, ds]`` (x, y first), ``target [n, T, 2]``, ``mask [n, T]``
    and the belief ``mean [n, T, ds]``, ``cov [n, T, ds, ds]``, as in ``beliefs.npz``; with
    ``true_mean [n, T, ds]`` (simulated agents) the belief the agent really held is drawn too
    (the paper's Fig. 1E).
    """
    shown = min(n_trials, arrays["state"].shape[0])
    fig, axes = plt.subplots(1, shown, figsize=(3.4 * shown, 3.6), squeeze=False)
    for trial, ax in enumerate(axes[0]):
        t = _recorded(arrays, trial)
        stride = max(1, len(t["mean"]) // 8)
        for k in range(0, len(t["mean"]), stride):
            eigval, eigvec = np.linalg.eigh(t["cov"][k, :2, :2])
            width, height = 2 * ELLIPSE_95 * np.sqrt(np.clip(eigval[::-1], 0, None))
            angle = math.degrees(math.atan2(eigvec[1, 1], eigvec[0, 1]))
            ax.add_patch(
                Ellipse(
                    t["mean"][k, :2], width, height, angle=angle, fill=False, color="tab:blue",
                    alpha=0.6, lw=0.8, label="belief, 95% ellipse" if k == 0 else None,
                )
            )  # fmt: skip
        ax.plot(t["state"][:, 0], t["state"][:, 1], "k-", lw=1.2, label="true path")
        ax.plot(t["mean"][:, 0], t["mean"][:, 1], "--", color="tab:blue", lw=1, label="belief mean")
        if "true_mean" in t:  # simulated agents: the belief the agent really held
            ax.plot(
                t["true_mean"][:, 0], t["true_mean"][:, 1], "-", color="tab:orange", lw=1,
                label="agent's own belief mean",
            )  # fmt: skip
        target = t["target"][0]
        ax.plot(*target, "r*", ms=10, label="target")
        if goal_radius is not None:
            ax.add_patch(Circle(target, goal_radius, fill=False, color="r", ls=":", lw=0.8))
        ax.plot(*t["state"][0, :2], "ko", ms=3)  # where the trial starts
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"x ({distance_unit})")
        ax.set_ylabel(f"y ({distance_unit})")
        ax.set_title(f"trial {_trial_name(arrays, trial)}", fontsize=9)
    axes[0][0].legend(fontsize=6, loc="best")
    if title:
        fig.suptitle(title, fontsize=9)
    return _save(fig, path)


def plot_belief_time(
    arrays: Mapping[str, np.ndarray],
    names: Sequence[str],
    units: Sequence[str],
    path: str | Path,
    n_trials: int = 3,
    title: str = "",
) -> Path:
    """Each belief component over time for a few trials: the truth, the mean and its 95% band
    (and, with ``true_mean``, the belief the agent really held: the paper's Fig. 1F)."""
    shown = min(n_trials, arrays["state"].shape[0])
    fig, grid = plt.subplots(
        len(names), 1, figsize=(6, 1.6 * len(names) + 0.6), sharex=True, squeeze=False
    )
    axes = grid[:, 0]
    for row in range(shown):
        t, trial = _recorded(arrays, row), _trial_name(arrays, row)
        std = np.sqrt(np.clip(np.diagonal(t["cov"], axis1=-2, axis2=-1), 0, None))
        for i, ax in enumerate(axes):
            mean = t["mean"][:, i]
            (line,) = ax.plot(t["time"], mean, "--", lw=1, label=f"belief, trial {trial}")
            color = line.get_color()
            ax.fill_between(
                t["time"], mean - Z95 * std[:, i], mean + Z95 * std[:, i],
                color=color, alpha=0.15, lw=0,
            )  # fmt: skip
            true = t["state"][:, i]
            ax.plot(t["time"], true, "-", color=color, lw=0.8, label=f"true, trial {trial}")
            if "true_mean" in t:  # simulated agents: the belief the agent really held
                ax.plot(t["time"], t["true_mean"][:, i], ":", color=color, lw=1.2,
                        label=f"agent's own belief, trial {trial}")  # fmt: skip
    for ax, name, unit in zip(axes, names, units, strict=True):
        ax.set_ylabel(f"{name}\n({unit})", fontsize=8)
    axes[-1].set_xlabel("time in trial (s)")
    axes[0].legend(fontsize=6, ncol=2, loc="best")
    fig.suptitle(title or "belief (dashed, 95% band) against the true state (solid)", fontsize=9)
    return _save(fig, path)


def plot_training(
    history: Sequence[Mapping[str, float]],
    losses: Mapping[str, np.ndarray],
    path: str | Path,
) -> Path:
    """Training curves of ``irc train``: evaluation success and return, and the DDPG losses.

    ``history`` is ``summary.json``'s list of evaluations; ``losses`` maps a logged name to
    ``[n, 2]`` rows of (frames, value), as the CSV logger writes them under ``logs/``. A task
    without success (its rates None) gets the return alone.
    """
    frames = [row["frames"] for row in history]
    success = all(row.get("success_rate") is not None for row in history)
    panels = success + 1 + bool(losses)
    fig, axes = plt.subplots(1, panels, figsize=(4 * panels, 3.3), squeeze=False)
    axes = list(axes[0])
    if success:
        ax = axes.pop(0)
        ax.plot(frames, [row["success_rate"] for row in history], "o-", ms=3)
        ax.set_ylim(0, 1)
        ax.set_xlabel("environment frames")
        ax.set_ylabel("success rate (fraction of trials)")
    ax = axes.pop(0)
    ax.plot(frames, [row["mean_return"] for row in history], "o-", ms=3)
    ax.set_xlabel("environment frames")
    ax.set_ylabel("mean return (reward units)")
    fig.axes[0].set_title("greedy policy on the θ grid", fontsize=9)
    if losses:
        ax = axes.pop(0)
        meaning = {"loss_value": "TD error², reward²", "loss_actor": "−Q, reward units"}
        for name, rows in sorted(losses.items()):
            label = f"{name} ({meaning[name]})" if name in meaning else name
            ax.plot(rows[:, 0], rows[:, 1], lw=0.8, label=label)
        ax.set_xlabel("environment frames")
        ax.set_ylabel("DDPG loss")
        ax.legend(fontsize=7)
    return _save(fig, path)


def _logged_losses(logs: Path) -> dict[str, np.ndarray]:
    """The ``loss_*`` scalars TorchRL's CSV logger wrote under ``logs/`` (rows: step, value)."""
    losses = {}
    for csv in sorted(logs.glob("*/scalars/loss_*.csv")):
        rows = np.loadtxt(csv, delimiter=",", ndmin=2)
        if rows.size:
            losses[csv.stem] = rows
    return losses


def _task_units(task: str | None) -> dict[str, str]:
    """θ units of a task by name (summaries written before they carried their own)."""
    from irc_torchrl.envs.firefly1d import firefly1d_theta_space
    from irc_torchrl.envs.firefly2d import firefly2d_theta_space

    spaces = {"firefly1d": firefly1d_theta_space, "firefly2d": firefly2d_theta_space}
    if task not in spaces:
        return {}
    return spaces[task]().units


def _agent_figures(
    part: Mapping, path: Path, units: Mapping[str, str], title: str | None = None
) -> Path:
    """θ̂ against the truth for the agents that have one (where coverage was scored), else θ̂
    alone."""
    known = [a for a in part["agents"] if "theta_true" in a]
    if "parameters" in part and known:
        scored = {**part, "agents": known}
        path = path.with_name(f"recovery{path.name}")
        return plot_recovery(scored, path, title=title, units=units)
    return plot_estimates(dict(part), path.with_name(f"estimates{path.name}"), units)


def read_summary(folder: str | Path) -> dict:
    """A run folder's ``summary.json``, refused in one line where it is missing, not JSON or
    not a JSON object."""
    path = Path(folder) / "summary.json"
    if not path.is_file():
        raise FileNotFoundError(f"report: no summary.json in {folder}")
    try:
        summary = json.loads(path.read_text())
    except ValueError as error:
        raise ValueError(f"report: {path} is not valid JSON ({error})") from None
    if not isinstance(summary, dict):
        raise ValueError(f"report: {path} holds a JSON {type(summary).__name__}; {_EXPECTED}")
    return summary


def is_recovery(summary: Mapping) -> bool:
    """Whether ``summary`` is a recovery experiment's (``irc recover``, ``irc demo --task
    firefly2d``): agents with known θ* fitted per method, their trials kept in ``trials/``."""
    return summary.get("command") in ("recover", "demo") and bool(summary.get("methods"))


def report_run(folder: str | Path, summary: dict | None = None) -> list[Path]:
    """Draw the figures of a run folder from its ``summary.json``; returns the PNGs written.

    Agents (``irc fit``, ``recover``, ``demo``): θ̂ against θ* with 95% intervals for the agents
    whose truth is known (when any is), else θ̂ with intervals per recording; per method too
    where the summary
    has ``methods`` (``--method both``, ``irc recover``). ``beliefs.npz`` (``irc fit``): the
    recovered beliefs overhead and over time, per recording; ``trials/`` (``irc recover``, ``irc
    demo --task firefly2d``): agent 0's recovered beliefs against its own, per method;
    ``figures.npz`` (``irc demo``, 1D): Q against the exact DP's, and the DP comparison.
    ``history`` (``irc train``): training curves, with the losses logged under ``logs/``.
    ``summary``: the folder's, where the caller has read it already (:func:`read_summary`).
    """
    folder = Path(folder)
    path = folder / "summary.json"
    summary = read_summary(folder) if summary is None else summary
    beliefs, figures = _archive(folder / "beliefs.npz"), _archive(folder / "figures.npz")
    recovered = is_recovery(summary)
    demo_1d = summary.get("command") == "demo" and not recovered
    for lacking, name, figures_of in (
        (summary.get("command") == "fit" and beliefs is None, "beliefs.npz", "belief"),
        (recovered and not (folder / "trials").is_dir(), "trials/", "belief"),
        (demo_1d and figures is None, "figures.npz", "Q and DP"),
    ):
        if lacking:
            warnings.warn(
                f"report: no {name} in {folder}: the {figures_of} figures are not drawn",
                stacklevel=2,
            )
    trials = _recovered_trials(summary, folder / "trials")
    # every figure is drawn aside first, so a field found lacking half-way leaves none behind
    with tempfile.TemporaryDirectory(dir=folder, prefix=".report.", suffix=MARK) as scratch:
        try:
            drawn = _report(summary, beliefs, figures, trials, folder, Path(scratch))
        except (KeyError, TypeError, AttributeError, IndexError) as error:
            raise ValueError(
                f"report: {path} lacks or mangles field {error}; {_EXPECTED}"
            ) from None
        except ValueError as error:  # e.g. an interval edited to exclude its own θ̂
            raise ValueError(
                f"report: {path} holds values that cannot be drawn ({first_line(error)}); "
                f"{_EXPECTED}"
            ) from None
        if not drawn:
            raise ValueError(
                f"report: {path} holds neither fitted agents nor a training history; {_EXPECTED}"
            )
        for figure in drawn:
            os.replace(figure, folder / figure.name)
    return [folder / figure.name for figure in drawn]


#: what ``irc report`` reads, for its errors
_EXPECTED = "expected the summary.json of irc fit, recover, demo or train"


def _archive(path: Path) -> dict[str, np.ndarray] | None:
    """An ``.npz`` archive of the run read whole, before anything is drawn (a damaged one fails
    here); None where there is none."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as error:
        raise ValueError(f"report: {path} is damaged ({error})") from None


def _recovered_trials(summary: dict, path: Path) -> TensorDict | None:
    """Agent 0's ``[1, trial, step]`` of ``irc recover``'s ``trials/`` (simulated trials, the
    agents' own beliefs and each method's recovered ones), read before anything is drawn;
    None where there is none."""
    methods = summary.get("methods")
    if not (isinstance(methods, dict) and path.is_dir()):
        return None
    try:
        trials = load_memmap(path)
    except ValueError as error:
        raise ValueError(f"report: {error}") from None
    needed = ["state", "target", "mask", ("belief", "mean")]
    needed += [(method, "belief", part) for method in methods for part in ("mean", "cov")]
    missing = [key for key in needed if key not in trials.keys(True)]
    if missing or trials.batch_dims != 3:
        raise ValueError(
            f"report: {path} lacks {missing or 'the [agent, trial, step] layout'}; expected "
            "irc recover's trials/ for the methods of its summary.json"
        )
    return trials[:1].to_tensordict()  # the figures show agent 0


def _report(
    summary: dict,
    beliefs: Mapping[str, np.ndarray] | None,
    figures: Mapping[str, np.ndarray] | None,
    trials: TensorDict | None,
    folder: Path,
    out: Path,
) -> list[Path]:
    """The figures of a run folder's ``summary`` (and of its ``beliefs.npz``, ``figures.npz``
    and ``trials/``), one by one, into ``out``."""
    written = []
    if summary.get("history"):
        losses = _logged_losses(folder / "logs")
        written.append(plot_training(summary["history"], losses, out / "training.png"))
    units = summary.get("units") or _task_units(summary.get("task"))
    # with per-method results, the top-level agents repeat one of them
    if summary.get("agents") and "theta_hat" in summary["agents"][0] and not summary.get("methods"):
        written.append(_agent_figures(summary, out / ".png", units))
    for method, part in summary.get("methods", {}).items():
        if part.get("agents"):
            part = {"free": summary.get("free"), **part}
            written.append(_agent_figures(part, out / f"_{method}.png", units, title=method))
    if beliefs is not None and "state_names" in summary:
        written += _belief_figures(summary, beliefs, out)
    if figures is not None and summary.get("task") == "firefly1d":
        written += demo_figures(figures, out)
    if trials is not None:
        from irc_torchrl.algorithms.recover2d import belief_figures, state_layout

        written += belief_figures(trials, summary["methods"], out, **state_layout(summary))
    if written and summary.get("task") == "firefly2d":
        written += _q_figure(summary, folder, out)
    return written


def _q_figure(summary: Mapping, folder: Path, out: Path) -> list[Path]:
    """Fig. 1B of a 2D run at the default θ (into ``out``), from the run's own checkpoint in
    ``folder`` or the one it used.

    A checkpoint that is gone (a summary copied from elsewhere) skips the figure with a warning.
    """
    from irc_torchrl.algorithms.ensemble import critic_slices, load_ensemble_critic

    own = folder / "checkpoint.pt"
    source = own if own.is_file() else summary.get("checkpoint") or "firefly2d"
    try:
        critic, actor, model = load_ensemble_critic(source)
    except (FileNotFoundError, ValueError) as error:
        warnings.warn(f"report: no Q-function figure: {error}", stacklevel=3)
        return []
    slices = critic_slices(model, critic, actor, model.theta_space.default())
    return [plot_q_function_2d(slices, out / "q_function.png")]


def _belief_figures(summary: Mapping, beliefs: Mapping[str, np.ndarray], out: Path) -> list[Path]:
    """The two belief figures of each fitted recording, from ``beliefs.npz``'s arrays."""
    written = []
    distance = summary["state_units"][0]
    for agent in summary["agents"]:
        label = agent["label"]
        arrays = {
            key.split("/", 1)[1]: value
            for key, value in beliefs.items()
            if key.split("/", 1)[0] == label
        }
        method = summary.get("primary_method", summary.get("method", ""))
        title = f"{label}: beliefs under θ̂ ({method})"
        if overhead_view(summary["state_names"], arrays["target"].shape[-1]):
            written.append(
                plot_belief_overhead(
                    arrays, out / f"{label}_beliefs_overhead.png",
                    agent["theta_hat"].get("goal_radius"), distance_unit=distance, title=title,
                )
            )  # fmt: skip
        written.append(
            plot_belief_time(
                arrays, summary["state_names"], summary["state_units"],
                out / f"{label}_beliefs_time.png", title=title,
            )
        )  # fmt: skip
    return written
