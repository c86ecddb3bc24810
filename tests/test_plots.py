"""What each figure draws, read back from its matplotlib artists: the belief ellipses from the
position covariance, the bands and error bars from the intervals, each curve where it belongs,
and ``irc report`` drawing a run folder's own numbers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.patches import Circle, Ellipse

from irc_torchrl import plots

#: χ²₂'s 95% quantile, by its own closed form (P(χ²₂ ≤ q) = 1 − e^(−q/2)); 1.96², per axis
CHI2_2_95 = 5.991464547107979
Z95 = 1.959963984540054
STATE = ("x", "y", "heading", "v", "w")


@pytest.fixture
def drawn(monkeypatch, tmp_path) -> list[plt.Figure]:
    """The figures the plots draw, kept open to be read (an empty file in ``tmp_path``, the
    working folder, stands for each PNG)."""
    monkeypatch.chdir(tmp_path)
    figures: list[plt.Figure] = []

    def keep(fig: plt.Figure, path: str | Path) -> Path:
        Path(path).write_bytes(b"")
        figures.append(fig)
        return Path(path)

    monkeypatch.setattr(plots, "_save", keep)
    yield figures
    for fig in figures:
        plt.close(fig)


def _beliefs(seed: int = 0, n: int = 3, steps: int = 20, recorded: int = 17) -> dict:
    """``beliefs.npz``'s arrays for one recording: random beliefs with correlated position
    covariances, the last steps unrecorded (and far off, so that drawing one shows)."""
    rng = np.random.default_rng(seed)
    root = rng.normal(size=(n, steps, 5, 5))
    cov = root @ root.swapaxes(-1, -2) + 0.05 * np.eye(5)
    mask = np.zeros((n, steps))
    mask[:, :recorded] = 1
    arrays = {
        "state": rng.normal(size=(n, steps, 5)),
        "mean": rng.normal(size=(n, steps, 5)),
        "true_mean": rng.normal(size=(n, steps, 5)),
        "cov": cov,
        "target": np.repeat(rng.normal(size=(n, 1, 2)), steps, 1),
        "time": np.repeat(0.1 * np.arange(steps)[None], n, 0),
        "mask": mask,
        "trial": np.arange(n) * 10 + 7,
        "trial_log_likelihood": rng.normal(size=n),
    }
    for key in ("state", "mean", "true_mean"):
        arrays[key][:, recorded:] = 1e3
    return arrays


def _recorded(arrays: dict, row: int, key: str) -> np.ndarray:
    return arrays[key][row][arrays["mask"][row].astype(bool)]


def _lines(ax: plt.Axes) -> dict[str, plt.Line2D]:
    return {line.get_label(): line for line in ax.lines}


def _ellipse_cov(ellipse: Ellipse) -> np.ndarray:
    """The 2×2 covariance whose 95% region ``ellipse`` is."""
    a, b = ellipse.width / 2, ellipse.height / 2
    c, s = math.cos(math.radians(ellipse.angle)), math.sin(math.radians(ellipse.angle))
    rotation = np.array([[c, -s], [s, c]])
    return rotation @ np.diag([a * a, b * b]) @ rotation.T / CHI2_2_95


def test_belief_ellipses_are_95_percent_regions_of_each_steps_position_covariance(drawn):
    arrays = _beliefs()
    plots.plot_belief_overhead(arrays, "o.png", goal_radius=0.7, n_trials=2, distance_unit="m")
    axes = drawn[0].axes
    assert len(axes) == 2  # n_trials of the 3
    for row, ax in enumerate(axes):
        mean, cov = _recorded(arrays, row, "mean"), _recorded(arrays, row, "cov")
        ellipses = [p for p in ax.patches if type(p) is Ellipse]
        assert len(ellipses) >= 8
        steps = []
        for ellipse in ellipses:
            (k,) = np.flatnonzero(np.all(np.isclose(mean[:, :2], ellipse.center), axis=1))
            steps.append(k)
            np.testing.assert_allclose(_ellipse_cov(ellipse), cov[k, :2, :2], rtol=1e-9, atol=1e-12)
        assert steps[0] == 0 and steps == sorted(set(steps))
        lines = _lines(ax)
        for label, key in (("true path", "state"), ("belief mean", "mean")):
            np.testing.assert_array_equal(
                lines[label].get_xydata(), _recorded(arrays, row, key)[:, :2]
            )
        own = lines["agent's own belief mean"].get_xydata()
        np.testing.assert_array_equal(own, _recorded(arrays, row, "true_mean")[:, :2])
        target = arrays["target"][row, 0]
        np.testing.assert_array_equal(lines["target"].get_xydata(), [target])
        (goal,) = [p for p in ax.patches if isinstance(p, Circle)]
        np.testing.assert_array_equal(goal.center, target)
        assert goal.radius == 0.7
        assert ax.get_title() == f"trial {arrays['trial'][row]}"
        assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (m)", "y (m)")


def test_a_belief_of_one_component_is_drawn_over_time_on_one_panel(drawn):
    arrays = _beliefs(seed=2)
    arrays.update(
        state=arrays["state"][..., :1],
        mean=arrays["mean"][..., :1],
        true_mean=arrays["true_mean"][..., :1],
        cov=arrays["cov"][..., :1, :1],
    )
    plots.plot_belief_time(arrays, ["x"], ["m"], "t.png", n_trials=2)
    (ax,) = drawn[0].axes
    assert ax.get_ylabel() == "x\n(m)" and len(ax.collections) == 2


def test_belief_bands_are_the_mean_plus_minus_1_96_sd_of_each_component(drawn):
    arrays = _beliefs(seed=1)
    plots.plot_belief_time(arrays, STATE, ["m", "m", "rad", "m/s", "rad/s"], "t.png", n_trials=2)
    axes = drawn[0].axes
    assert [ax.get_ylabel() for ax in axes] == [
        "x\n(m)", "y\n(m)", "heading\n(rad)", "v\n(m/s)", "w\n(rad/s)"
    ]  # fmt: skip
    for i, ax in enumerate(axes):
        assert len(ax.collections) == 2  # one band per trial shown
        for row, band in enumerate(ax.collections):
            trial, time = arrays["trial"][row], _recorded(arrays, row, "time")
            mean = _recorded(arrays, row, "mean")[:, i]
            sd = np.sqrt(_recorded(arrays, row, "cov")[:, i, i])
            lines = _lines(ax)
            belief = lines[f"belief, trial {trial}"]
            np.testing.assert_array_equal(belief.get_xdata(), time)
            np.testing.assert_array_equal(belief.get_ydata(), mean)
            true = lines[f"true, trial {trial}"].get_ydata()
            np.testing.assert_array_equal(true, _recorded(arrays, row, "state")[:, i])
            own = lines[f"agent's own belief, trial {trial}"].get_ydata()
            np.testing.assert_array_equal(own, _recorded(arrays, row, "true_mean")[:, i])
            vertices = band.get_paths()[0].vertices
            for t, low, high in zip(time, mean - Z95 * sd, mean + Z95 * sd, strict=True):
                ys = vertices[np.isclose(vertices[:, 0], t), 1]
                assert ys.min() == pytest.approx(low) and ys.max() == pytest.approx(high)


def _agent(truth: dict | None, hat: dict, low: dict, high: dict, **extra) -> dict:
    agent = {"theta_hat": hat, "ci_low": low, "ci_high": high, **extra}
    return agent if truth is None else {**agent, "theta_true": truth}


def _errorbars(container) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An errorbar's points ``[n, 2]`` and the lower and upper ends of its bars."""
    points, _, (bars,) = container.lines
    segments = np.array(bars.get_segments())
    np.testing.assert_array_equal(segments[:, 0, 0], segments[:, 1, 0])  # vertical bars
    return points.get_xydata(), segments[:, 0], segments[:, 1]


#: three agents' θ̂ and asymmetric intervals of two parameters, and their truth
AGENTS = [
    ({"a": 1.0, "b": -2.0}, {"a": 1.1, "b": -1.0}, {"a": 0.9, "b": -3.0}, {"a": 1.6, "b": -0.5}),
    ({"a": 2.0, "b": 0.5}, {"a": 1.7, "b": 0.4}, {"a": 1.5, "b": 0.1}, {"a": 1.8, "b": 2.0}),
    ({"a": 3.0, "b": 1.0}, {"a": 3.3, "b": 1.2}, {"a": 3.2, "b": 0.2}, {"a": 4.5, "b": 1.3}),
]


def test_recovery_plots_the_estimate_against_the_truth_with_its_own_interval(drawn):
    summary = {
        "agents": [_agent(*values) for values in AGENTS],
        "parameters": {"a": {"coverage": 2 / 3}, "b": {"coverage": 1.0}},
    }
    plots.plot_recovery(summary, "r.png", title="map", units={"a": "m/s"})
    fig = drawn[0]
    assert fig.get_suptitle() == "map"
    for ax, name in zip(fig.axes, "ab", strict=True):
        points, low, high = _errorbars(ax.containers[0])
        truth, hat, lo, hi = (
            np.array([v[name] for v in column]) for column in zip(*AGENTS, strict=True)
        )
        np.testing.assert_allclose(points, np.column_stack([truth, hat]))
        np.testing.assert_allclose(low, np.column_stack([truth, lo]))
        np.testing.assert_allclose(high, np.column_stack([truth, hi]))
        ends = np.array([min(*truth, *hat), max(*truth, *hat)])
        diagonal = [line for line in ax.lines if line.get_linestyle() == ":"][0]
        np.testing.assert_allclose(diagonal.get_xydata(), np.column_stack([ends, ends]))
    titles = [(ax.get_title(), ax.get_xlabel(), ax.get_ylabel()) for ax in fig.axes]
    assert titles == [
        ("a: coverage 0.67", "true a (m/s)", "estimated a, 95% CI (m/s)"),
        ("b: coverage 1.00", "true b", "estimated b, 95% CI"),
    ]


def test_estimates_plot_each_recordings_interval_marking_the_unidentified(drawn):
    agents = [
        _agent(None, hat, low, high, label=f"rec{i}", identified={"a": i != 1, "b": True})
        for i, (_, hat, low, high) in enumerate(AGENTS)
    ]
    plots.plot_estimates({"agents": agents, "free": ["a"]}, "e.png", units={"a": "s"})
    (ax,) = drawn[0].axes
    assert [t.get_text() for t in ax.get_xticklabels()] == ["rec0", "rec1", "rec2"]
    assert ax.get_ylabel() == "a, θ̂ with 95% CI (s)"
    for container, rows, marker in ((ax.containers[0], [0, 2], "o"), (ax.containers[1], [1], "x")):
        points, low, high = _errorbars(container)
        assert container.get_label() == ("identified" if marker == "o" else "not identified")
        assert container.lines[0].get_marker() == marker
        hat, lo, hi = ([AGENTS[r][k]["a"] for r in rows] for k in (1, 2, 3))
        np.testing.assert_allclose(points, np.column_stack([rows, hat]))
        np.testing.assert_allclose(low, np.column_stack([rows, lo]))
        np.testing.assert_allclose(high, np.column_stack([rows, hi]))


def test_q_function_draws_each_actions_learned_and_exact_values_in_one_colour(drawn):
    rng = np.random.default_rng(2)
    relative, learned, optimal = (
        np.linspace(-3, 3, 7),
        rng.normal(size=(7, 3)),
        rng.normal(size=(7, 3)),
    )
    plots.plot_q_function(relative, learned, optimal, {"g_a": 1.25, "goal_radius": 1.0}, "q.png")
    (ax,) = drawn[0].axes
    lines = _lines(ax)
    for a, name in enumerate(("left", "stop", "right")):
        mine, exact = lines[f"{name} (learned)"], lines[f"{name} (exact DP)"]
        np.testing.assert_array_equal(mine.get_xydata(), np.column_stack([relative, learned[:, a]]))
        np.testing.assert_array_equal(
            exact.get_xydata(), np.column_stack([relative, optimal[:, a]])
        )
        assert (mine.get_linestyle(), exact.get_linestyle()) == ("-", "--")
        assert mine.get_color() == exact.get_color()
    assert ax.get_title() == "θ: g_a=1.25, goal_radius=1"


def _cell_centres(mesh) -> np.ndarray:
    corners = mesh.get_coordinates()
    return (corners[:-1, :-1] + corners[1:, 1:] + corners[:-1, 1:] + corners[1:, :-1]) / 4


def test_q_function_2d_puts_each_value_at_its_target_and_action(drawn):
    rng = np.random.default_rng(3)
    ahead, aside, action = np.linspace(-1, 4, 5), np.linspace(-2, 2, 5), np.linspace(-1, 1, 5)
    slices = {
        "ahead": ahead, "aside": aside, "action": action, "value": rng.normal(size=(5, 5)),
        "q_far": rng.normal(size=(5, 5)), "q_near": rng.normal(size=(5, 5)),
        "pi_far": np.array([0.3, -0.4]), "pi_near": np.array([-0.8, 0.1]),
        "target_far": [2.4, 1.0], "target_near": [0.0, 0.0],
        "goal_radius": 0.65, "stop_threshold": -0.5,
    }  # fmt: skip
    plots.plot_q_function_2d(slices, "q2.png")
    value_ax, far_ax, near_ax = drawn[0].axes[:3]
    # the value: rows ahead, columns the target's side, drawn from above (its left on the left)
    (mesh,) = value_ax.collections
    np.testing.assert_array_equal(mesh.get_array(), slices["value"])
    centres = _cell_centres(mesh)
    np.testing.assert_allclose(centres[..., 0], np.broadcast_to(-aside, (5, 5)))
    np.testing.assert_allclose(centres[..., 1], np.broadcast_to(ahead[:, None], (5, 5)))
    markers = [line.get_xydata()[0] for line in value_ax.lines if line.get_mec() == "r"]
    np.testing.assert_allclose(markers, [[-1.0, 2.4], [0.0, 0.0]])
    (goal,) = [p for p in value_ax.patches if isinstance(p, Circle)]
    assert goal.radius == 0.65
    for ax, name in ((far_ax, "far"), (near_ax, "near")):
        (mesh,) = ax.collections
        # x: forward control a_v (the first action index), y: angular control a_w
        np.testing.assert_array_equal(mesh.get_array(), slices[f"q_{name}"].T)
        centres = _cell_centres(mesh)
        np.testing.assert_allclose(centres[..., 0], np.broadcast_to(action, (5, 5)))
        np.testing.assert_allclose(centres[..., 1], np.broadcast_to(action[:, None], (5, 5)))
        np.testing.assert_array_equal(_lines(ax)["π(b)"].get_xydata(), [slices[f"pi_{name}"]])
        (stop,) = ax.patches
        x0, x1 = stop.get_x(), stop.get_x() + stop.get_width()
        assert (x0, x1) == pytest.approx((-1.0, -0.5))


def test_training_curves_plot_each_evaluation_and_logged_loss(drawn):
    history = [
        {"frames": 100, "success_rate": 0.1, "mean_return": -2.0},
        {"frames": 300, "success_rate": 0.6, "mean_return": 3.0},
    ]
    losses = {"loss_value": np.array([[50.0, 9.0], [250.0, 4.0]]), "loss_other": np.ones((1, 2))}
    plots.plot_training(history, losses, "train.png")
    success, returns, loss = drawn[0].axes
    np.testing.assert_array_equal(success.lines[0].get_xydata(), [[100, 0.1], [300, 0.6]])
    np.testing.assert_array_equal(returns.lines[0].get_xydata(), [[100, -2.0], [300, 3.0]])
    assert success.get_ylim() == (0, 1)
    lines = _lines(loss)
    np.testing.assert_array_equal(
        lines["loss_value (TD error², reward²)"].get_xydata(), losses["loss_value"]
    )
    np.testing.assert_array_equal(lines["loss_other"].get_xydata(), [[1.0, 1.0]])


def test_training_curves_of_a_task_without_success_plot_its_return_alone(drawn):
    history = [
        {"frames": 100, "success_rate": None, "mean_return": -9.0},
        {"frames": 300, "success_rate": None, "mean_return": -0.5},
    ]
    plots.plot_training(history, {}, "train.png")
    (returns,) = drawn[0].axes
    np.testing.assert_array_equal(returns.lines[0].get_xydata(), [[100, -9.0], [300, -0.5]])
    assert returns.get_ylabel() == "mean return (reward units)"


def test_dp_comparison_scatters_learned_against_optimal_with_the_95_percent_line(drawn):
    dp, learned = np.array([2.0, 4.0, 5.0]), np.array([1.0, 3.9, 5.0])
    plots.plot_dp_comparison(dp, learned, ["θ0", "θ1", "θ2"], "dp.png")
    (ax,) = drawn[0].axes
    np.testing.assert_array_equal(ax.collections[0].get_offsets(), np.column_stack([dp, learned]))
    lines = _lines(ax)
    np.testing.assert_allclose(lines["equal"].get_xydata(), [[1.0, 1.0], [5.0, 5.0]])
    np.testing.assert_allclose(lines["95% of optimal"].get_xydata(), [[1.0, 0.95], [5.0, 4.75]])
    assert ax.get_title() == "3 θ over the prior; ratio of means 0.900"


def _fit_folder(folder: Path) -> dict:
    """An ``irc fit`` folder of two recordings, ``a`` whose truth is known and ``b``."""
    (truth, hat, low, high), (_, hat_b, low_b, high_b) = AGENTS[:2]
    identified = {"a": True, "b": True}
    summary = {
        "command": "fit",
        "method": "both",
        "primary_method": "marginal",  # the top-level agents', beliefs' and figures' method
        "free": ["a", "b"],
        "units": {"a": "m", "b": "s"},
        "parameters": {"a": {"coverage": 1.0}, "b": {"coverage": 0.0}},
        "agents": [
            _agent(truth, hat | {"goal_radius": 0.4}, low, high, label="a", identified=identified),
            _agent(
                None, hat_b | {"goal_radius": 0.9}, low_b, high_b, label="b", identified=identified
            ),
        ],
        "state_names": list(STATE),
        "state_units": ["cm", "cm", "rad", "cm/s", "rad/s"],
    }
    beliefs = {f"{label}/{k}": v for label in "ab" for k, v in _beliefs(seed=ord(label)).items()}
    np.savez(folder / "beliefs.npz", **beliefs)
    (folder / "summary.json").write_text(json.dumps(summary))
    return summary


def test_report_of_a_fit_draws_the_known_truths_and_each_recordings_own_beliefs(drawn, tmp_path):
    summary = _fit_folder(tmp_path)
    written = plots.report_run(tmp_path)
    names = ["recovery.png", "a_beliefs_overhead.png", "a_beliefs_time.png"]
    names += ["b_beliefs_overhead.png", "b_beliefs_time.png"]
    assert written == [tmp_path / name for name in names]
    recovery, *belief_figures = drawn
    points, _, _ = _errorbars(recovery.axes[0].containers[0])  # agent a only: b has no truth
    np.testing.assert_array_equal(points, [[AGENTS[0][0]["a"], AGENTS[0][1]["a"]]])
    assert recovery.axes[0].get_xlabel() == "true a (m)"
    pairs = [belief_figures[i : i + 2] for i in range(0, len(belief_figures), 2)]
    for (overhead, timeline), agent in zip(pairs, summary["agents"], strict=True):
        arrays = _beliefs(seed=ord(agent["label"]))
        ax = overhead.axes[0]
        first = next(p for p in ax.patches if type(p) is Ellipse)
        np.testing.assert_array_equal(first.center, arrays["mean"][0, 0, :2])
        (goal,) = [p for p in ax.patches if isinstance(p, Circle)]
        assert goal.radius == agent["theta_hat"]["goal_radius"]
        assert ax.get_xlabel() == "x (cm)"
        assert overhead.get_suptitle() == f"{agent['label']}: beliefs under θ̂ (marginal)"
        belief = _lines(timeline.axes[3])["belief, trial 7"].get_ydata()
        np.testing.assert_array_equal(belief, _recorded(arrays, 0, "mean")[:, 3])
        assert timeline.axes[3].get_ylabel() == "v\n(cm/s)"


def test_report_of_a_fit_without_truth_draws_the_estimates(drawn, tmp_path):
    summary = _fit_folder(tmp_path)
    del summary["agents"][0]["theta_true"], summary["parameters"]
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    assert plots.report_run(tmp_path)[0] == tmp_path / "estimates.png"
    panels = drawn[0].axes
    assert [ax.get_ylabel() for ax in panels] == ["a, θ̂ with 95% CI (m)", "b, θ̂ with 95% CI (s)"]
    points, low, high = _errorbars(panels[1].containers[0])
    np.testing.assert_array_equal(points[:, 1], [AGENTS[0][1]["b"], AGENTS[1][1]["b"]])
    np.testing.assert_array_equal(high[:, 1], [AGENTS[0][3]["b"], AGENTS[1][3]["b"]])


def test_report_of_both_methods_titles_each_methods_figure_as_the_run_does(drawn, tmp_path):
    summary = _fit_folder(tmp_path)
    del summary["state_names"]  # no belief figures: the method figures alone
    methods = {
        method: {k: summary[k] for k in ("agents", "parameters")} for method in ("map", "ml")
    }
    (tmp_path / "summary.json").write_text(json.dumps({**summary, "methods": methods}))
    written = plots.report_run(tmp_path)
    assert written == [tmp_path / "recovery_map.png", tmp_path / "recovery_ml.png"]
    assert [fig.get_suptitle() for fig in drawn] == ["map", "ml"]
    assert drawn[1].axes[1].get_xlabel() == "true b (s)"


def test_report_of_an_interval_that_excludes_its_estimate_names_the_file(drawn, tmp_path):
    """A summary edited by hand so that an interval no longer holds its θ̂ cannot be drawn as
    error bars: one line naming the file, and no figure left behind."""
    summary = _fit_folder(tmp_path)
    summary["agents"][0]["ci_low"]["a"] = summary["agents"][0]["theta_hat"]["a"] + 1.0
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ValueError, match=r"^report: .*summary.json holds values that cannot be"):
        plots.report_run(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["beliefs.npz", "summary.json"]
