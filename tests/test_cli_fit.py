"""``irc simulate``, ``irc fit`` and ``irc report`` on the 2D task with the shipped checkpoint.

Measured with the seeds below (1 agent, 20 trials, ``--method map``, free g_v, g_w,
obs_sigma_v): θ̂ g_v = 1.395 (truth 1.4, −0.4%), g_w = 0.803 (truth 0.8, +0.4%). The map
estimator is biased (most probable observations in place of the agent's) and its intervals
are narrow, so the test asks for the gains within 5% and does not ask the intervals to cover;
obs_sigma_v (0.64 against 0.6) is fitted but not asserted.
"""

from __future__ import annotations

import gzip
import json
import logging
import re
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from test_checkpoint import TINY as TINY_TRAIN

from irc_torchrl.algorithms import recordings
from irc_torchrl.algorithms.calibration import Calibration, agent_intervals, interval_pivots
from irc_torchrl.algorithms.fit import FitResult, fit_theta
from irc_torchrl.algorithms.recordings import format_fit
from irc_torchrl.algorithms.stages import Stages
from irc_torchrl.cli import _check_arguments, build_parser, main
from irc_torchrl.config import RecordingFitConfig
from irc_torchrl.data.files import held
from irc_torchrl.data.io import read_trials
from irc_torchrl.data.trajectories import TRIAL_KEYS
from irc_torchrl.envs.firefly2d import Firefly2DModel, firefly2d_theta_space
from irc_torchrl.modules.actor_critic import censored_action_model
from irc_torchrl.objectives.fisher import Intervals
from irc_torchrl.objectives.inverse import InverseRationalLoss
from irc_torchrl.theta import Parameter, ThetaSpace

SPACE = firefly2d_theta_space()
#: a GPU that is asked for is refused only where there is none
WITHOUT_GPU = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
#: the simulated agent: the prior's defaults except the three parameters the test fits
TRUTH = {**SPACE.to_dict(SPACE.default()), "g_v": 1.4, "g_w": 0.8, "obs_sigma_v": 0.6}
FREE = ["g_v", "g_w", "obs_sigma_v"]
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("simulated")
    theta = [f"theta.{name}={value}" for name, value in TRUTH.items()]
    assert main(["simulate", "--out", str(out), "--quiet", "n_trials=20", *theta]) == 0
    return out


@pytest.fixture(scope="module")
def fitted(simulated, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("fitted")
    args = ["fit", str(simulated / "agent0.csv"), "--out", str(out), "--quiet"]
    assert main([*args, "--method", "map", "--free", ",".join(FREE), "particles=200"]) == 0
    return out, json.loads((out / "summary.json").read_text())


def test_simulate_writes_a_recording_and_the_true_theta(simulated):
    summary = json.loads((simulated / "summary.json").read_text())
    assert (summary["task"], summary["command"], summary["format"]) == (
        "firefly2d",
        "simulate",
        "csv",
    )
    (agent,) = summary["agents"]
    assert agent["file"] == "agent0.csv"
    assert agent["theta_true"] == pytest.approx(TRUTH, abs=1e-6)
    trials = read_trials(simulated / "agent0.csv", Firefly2DModel())
    assert trials.shape[0] == 20 and trials["mask"].sum(-1).min() >= 2
    # the world keeps the task's default θ: the agent's θ, its senses' included (it observed
    # with its obs_sigma_v, 0.6), is not in the recording
    assert torch.allclose(trials["task_theta"][0, 0], SPACE.default())


def test_simulate_draws_unset_theta_from_the_prior_by_seed(tmp_path):
    runs = []
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        out = tmp_path / name
        args = ["simulate", "--out", str(out), "--quiet", "--seed", str(seed), "--format", "npz"]
        assert main([*args, "n_agents=2", "n_trials=2", "theta.g_v=1.1"]) == 0
        runs.append(
            [a["theta_true"] for a in json.loads((out / "summary.json").read_text())["agents"]]
        )
        assert sorted(p.name for p in out.iterdir()) == ["agent0.npz", "agent1.npz", "summary.json"]
    first, again, other = runs
    assert first == again and first != other
    assert [a["g_v"] for a in first] == pytest.approx([1.1, 1.1])
    assert first[0]["g_w"] != first[1]["g_w"]  # each agent its own draw
    for agent in first + other:
        for p in SPACE.parameters:
            assert p.low <= agent[p.name] <= p.high


def test_fit_of_the_csv_recovers_the_gains(fitted):
    out, summary = fitted
    assert (summary["method"], summary["free"]) == ("map", FREE)
    assert set(summary["fixed"]) == set(SPACE.names) - set(FREE)
    (agent,) = summary["agents"]
    assert agent["theta_true"] == pytest.approx(TRUTH, abs=1e-6)
    for name in ("g_v", "g_w"):
        assert agent["theta_hat"][name] == pytest.approx(TRUTH[name], rel=0.05)
        assert agent["identified"][name]
    for name in FREE:
        assert agent["ci_low"][name] < agent["theta_hat"][name] < agent["ci_high"][name]
    for name in summary["fixed"]:  # not fitted: held at the default
        assert agent["theta_hat"][name] == pytest.approx(TRUTH[name], abs=1e-6)
    assert set(summary["parameters"]) == set(FREE)
    assert len(agent["motor_noise"]) == 2 and all(0 < s < 1 for s in agent["motor_noise"])
    for std, (low, high) in zip(agent["motor_noise"], agent["motor_noise_ci"], strict=True):
        assert 0 < low < std < high
    table = format_fit(summary)
    assert "g_v" in table and "95% CI" in table and "true" in table and "sigma_w" not in table
    at_bound = json.loads(json.dumps(summary))
    at_bound["agents"][0]["ci_low"]["g_v"] = 3.4e-18  # a bound at 0, reached to rounding
    row = next(x for x in format_fit(at_bound).splitlines() if x.strip().startswith("g_v"))
    assert "[0, " in row and "e-18" not in row
    # the estimates' correlations over the free parameters: symmetric, ones on the diagonal
    correlation = agent["correlation"]
    assert list(correlation) == FREE and all(list(row) == FREE for row in correlation.values())
    for a in FREE:
        assert correlation[a][a] == pytest.approx(1.0)
        for b in FREE:
            assert correlation[a][b] == pytest.approx(correlation[b][a])
            assert -1 <= correlation[a][b] <= 1
    # uncalibrated intervals say so, and how many datasets per recording calibrate them
    # (about 40 refits per parameter: this one recording's 40)
    assert "95% intervals from the fit's likelihood alone, not calibrated" in table
    assert "(docs/recovery2d.md); calibrate=40 calibrates them by simulation" in table
    # irc fit's default, for recordings of real agents: the lapse rate fitted, from 0.01; this
    # agent never lapses, and its rate stays small (measured: 0.024, interval up to 0.042: the
    # hard E-step fitted here puts down to lapses some actions of a belief its own senses,
    # obs σ_v 0.6, made noisy; 0.0030 where the world sensed it with the default's 0.4)
    assert summary["config"]["lapse"] == 0.01 and summary["config"]["fit_lapse"]
    low, high = agent["lapse_ci"]
    assert 0 < low < agent["lapse"] < high < 0.1 and agent["lapse"] < 0.05
    assert f"lapse rate (fitted): {agent['lapse']:.3g} [" in table
    # the hard E-step ignores the spread of the agent's beliefs: a particle filter finds the
    # recorded actions far more likely than it does
    assert agent["particle_check"]["approximation_gap"] > 5
    gap = agent["particle_check"]["approximation_gap"]
    assert f"particle check: the likelihood's approximation is {gap:.1f} nats below" in table


def test_fit_names_the_trials_its_theta_explains_worst(simulated, tmp_path):
    """A trial whose turning commands were flipped (an export glitch) heads the list of the
    trials θ̂ explains worst, by its own trial number, well below the median trial (0.64 nats
    per step on these data; the next worst 0.43); beliefs.npz holds every trial's
    log-likelihood, which add up to the fit's."""
    lines = (simulated / "agent0.csv").read_text().splitlines()
    header = lines[0].split(",")
    trial, a_w = header.index("trial"), header.index("a_w")
    rows = []
    for line in lines[1:]:
        cells = line.split(",")
        if cells[trial] == "7":
            cells[a_w] = repr(-float(cells[a_w]))
        rows.append(",".join(cells))
    (tmp_path / "glitch.csv").write_text("\n".join([lines[0], *rows]) + "\n")
    out = tmp_path / "fit"
    settings = ["--quiet", "--method", "map", "--free", "g_v", "max_iter=5", "n_screen=2"]
    assert main(["fit", str(tmp_path / "glitch.csv"), "--out", str(out), *settings]) == 0
    summary = json.loads((out / "summary.json").read_text())
    (agent,) = summary["agents"]
    worst = agent["worst_trials"]
    assert [w["trial"] for w in worst][0] == 7.0 and len(worst) == 3
    assert [w["per_step"] for w in worst] == sorted(w["per_step"] for w in worst)
    assert worst[0]["per_step"] < worst[0]["median_per_step"] - 0.5
    assert worst[0]["per_step"] == pytest.approx(worst[0]["log_likelihood"] / worst[0]["steps"])
    with np.load(out / "beliefs.npz") as beliefs:
        per_trial = beliefs["glitch/trial_log_likelihood"]
    assert per_trial.shape == (20,)
    assert per_trial.sum() == pytest.approx(agent["log_likelihood"], rel=1e-6)
    assert "trials explained worst, log-likelihood per step" in format_fit(summary)


def test_fit_calibrates_its_intervals_on_refits_of_simulated_recordings(simulated, tmp_path):
    # calibrate=1: a recording simulated at θ̂ and refitted; each interval is the fit's own
    # scaled about θ̂ (in the fit's coordinates) by its parameter's factor, and one refit is
    # too few to read a 95% quantile from (19 are the fewest): no factor, no interval
    args = ["fit", str(simulated / "agent0.csv"), "--out", str(tmp_path), "--quiet"]
    options = ["calibrate=1", "calibration_tail=own", "n_screen=2", "n_starts=1", "max_iter=5"]
    assert main([*args, "--method", "map", "--free", ",".join(FREE), *options]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    calibration = summary["calibration"]
    assert calibration["n_datasets"] == 1 and list(calibration["factor"]) == FREE
    assert calibration["tail"] == "own"
    assert np.array(calibration["pivots"], dtype=float).shape == (1, 1, len(FREE))
    assert set(summary["calibrated_parameters"]) == set(FREE)
    (agent,) = summary["agents"]
    for name in FREE:
        factor = calibration["factor"][name]
        low, high = agent["calibrated"]["ci_low"][name], agent["calibrated"]["ci_high"][name]
        hat = agent["theta_hat"][name]
        assert low <= hat <= high
        bounds = (SPACE[name].low, SPACE[name].high)
        if factor is None:  # no refit had an interval
            assert (low, high) == pytest.approx(bounds, abs=1e-9 * (bounds[1] - bounds[0]))
            continue

        def logit(x, p=SPACE[name]):
            eps = np.finfo(np.float64).eps ** 0.5
            q = min(max((x - p.low) / (p.high - p.low), eps), 1 - eps)  # as to_unconstrained
            return float(np.log(q / (1 - q)))

        for raw, calibrated in ((agent["ci_low"][name], low), (agent["ci_high"][name], high)):
            expected = factor * (logit(raw) - logit(hat))
            assert logit(calibrated) - logit(hat) == pytest.approx(expected, rel=1e-6)
        assert agent["calibrated"]["std"][name] == pytest.approx(factor * agent["std"][name])
    table = format_fit(summary)
    assert "calibrated 95% CI" in table and "intervals calibrated on 1 simulated" in table
    assert "not calibrated" not in table
    assert all(factor is None for factor in calibration["factor"].values())
    assert "scaled by g_v none, g_w none, obs_sigma_v none" in table
    assert "truth inside the calibrated 95% interval" in table


def test_fit_writes_beliefs_and_figures(fitted, simulated):
    out, summary = fitted
    recording = read_trials(simulated / "agent0.csv", Firefly2DModel())
    with np.load(out / "beliefs.npz") as beliefs:
        mean, cov = beliefs["agent0/mean"], beliefs["agent0/cov"]
        assert mean.shape == (*recording.shape, 5) and cov.shape == (*recording.shape, 5, 5)
        assert np.array_equal(beliefs["agent0/mask"], recording["mask"].numpy())
    recorded = recording["mask"].numpy()
    assert np.isfinite(mean[recorded]).all()
    assert np.allclose(mean[:, 0, :2], 0)  # the agent knows where it starts
    # the belief tracks the true position within a few of its own standard deviations
    error = np.abs(mean[..., :2] - recording["state"].numpy()[..., :2])[recorded]
    std = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)[..., :2])[recorded]
    assert np.median(error / std) < 3
    for name in ("recovery.png", "agent0_beliefs_overhead.png", "agent0_beliefs_time.png"):
        assert (out / name).read_bytes()[:8] == PNG


def test_report_redraws_a_fit_folder(fitted, tmp_path, capsys):
    source, _ = fitted
    folder = tmp_path / "copy"
    folder.mkdir()
    for name in ("summary.json", "beliefs.npz"):
        shutil.copy(source / name, folder / name)
    assert main(["report", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "recovery.png" in out
    # the table the fit printed as it ended, from the summary alone
    summary = json.loads((folder / "summary.json").read_text())
    assert format_fit(summary) in out
    mangled = {**summary, "agents": [{**summary["agents"][0], "converged": None}]}
    del mangled["agents"][0]["log_likelihood"]
    (folder / "summary.json").write_text(json.dumps(mangled))
    with pytest.warns(UserWarning, match="report: summary.json lacks or mangles field "
                      "'log_likelihood': its table is not printed"):  # fmt: skip
        assert main(["report", str(folder)]) == 0
    for name in (
        "recovery.png",
        "agent0_beliefs_overhead.png",
        "agent0_beliefs_time.png",
        "q_function.png",  # Fig. 1B from the checkpoint the fit used
    ):
        assert (folder / name).read_bytes()[:8] == PNG


def test_report_without_truth_plots_the_estimates(fitted, tmp_path):
    source, _ = fitted
    summary = json.loads((source / "summary.json").read_text())  # a copy to edit
    for agent in summary["agents"]:
        del agent["theta_true"]
    del summary["parameters"]
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    # the summary alone, without beliefs.npz: the belief figures are missing, and it says so
    with pytest.warns(UserWarning, match="no beliefs.npz in .*: the belief figures are not"):
        assert main(["report", str(tmp_path)]) == 0
    assert (tmp_path / "estimates.png").read_bytes()[:8] == PNG
    assert not (tmp_path / "recovery.png").exists()


def test_report_draws_one_figure_per_method(fitted, tmp_path):
    _, summary = fitted  # the layout of `irc recover`: results under "methods" only
    part = {key: summary[key] for key in ("agents", "parameters")}
    recover = {"task": "firefly2d", "methods": {"map": part, "marginal": part}}
    (tmp_path / "summary.json").write_text(json.dumps(recover))
    assert main(["report", str(tmp_path)]) == 0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == ["q_function.png", "recovery_map.png", "recovery_marginal.png"]


def test_report_skips_the_q_figure_when_its_checkpoint_is_gone(fitted, tmp_path):
    _, summary = fitted
    moved = {**summary, "checkpoint": str(tmp_path / "elsewhere.pt")}
    (tmp_path / "summary.json").write_text(json.dumps(moved))
    with pytest.warns(UserWarning, match="report: no Q-function figure: .*elsewhere.pt"):
        assert main(["report", str(tmp_path)]) == 0
    assert (tmp_path / "recovery.png").is_file()
    assert not (tmp_path / "q_function.png").exists()


def test_report_draws_training_curves(tmp_path, capsys, monkeypatch):
    settings = [o for o in TINY_TRAIN if not o.startswith("logger=")]  # the CSV logger: logs/
    logged = []  # TorchRL's INFO lines (the buffer's size) went to irc's stdout
    handler = logging.Handler()
    handler.emit = logged.append
    monkeypatch.delenv("RL_LOGGING_LEVEL", raising=False)
    logging.getLogger("torchrl").addHandler(handler)
    try:
        assert main(["train", "--out", str(tmp_path), "--quiet", *settings]) == 0
    finally:
        logging.getLogger("torchrl").removeHandler(handler)
    assert [record.getMessage() for record in logged if record.levelno < logging.WARNING] == []
    trained = capsys.readouterr().out.splitlines()[0]
    assert main(["report", str(tmp_path)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == trained  # "best policy: …"
    for name in ("training.png", "q_function.png"):  # Q from the run's own checkpoint
        assert (tmp_path / name).read_bytes()[:8] == PNG


def test_report_of_a_folder_without_summary_exits_2(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 2
    assert "irc report: error: no summary.json in" in capsys.readouterr().err
    (tmp_path / "summary.json").write_text('{"command": "simulate", "agents": []}')
    assert main(["report", str(tmp_path)]) == 2  # nothing to draw, said once
    err = capsys.readouterr().err
    assert err.count("expected the summary.json of irc fit") == 1 and "holds neither" in err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "n_agent=2"], "key 'n_agent' (did you mean 'n_agents'?); valid keys: n_"),
        (["simulate", "theta.g_x=1"], "unknown θ parameter 'g_x'; valid names: g_v"),
        (["simulate", "theta.g_v=9"], "g_v=9 is outside its space"),
        (["simulate", "motor_noise=0"], "motor_noise must be positive"),
        (["simulate", "lapse=1"], "lapse must be a probability in [0, 1), got 1"),
        (["fit", "FILE", "lapse=-0.1"], "lapse must be a probability in [0, 1), got -0.1"),
        (["recover", "lapse=1.5"], "lapse must be a probability in [0, 1), got 1.5"),
        (["fit", "FILE", "lapse=0"], "lapse (the fitted rate's start) must be in (0, 0.5)"),
        (["fit", "FILE", "fit_lapse=maybe"], "fit_lapse='maybe' is not a valid bool"),
        (["simulate", "--device", "nonsense"], "device:"),
        (["fit", "FILE", "--device", "meta"], "device: 'meta' tensors hold no values"),
        pytest.param(
            ["simulate", "--device", "cuda"], "device: 'cuda' requested but", marks=WITHOUT_GPU
        ),
        pytest.param(
            ["recover", "--device", "cuda:0"], "device: 'cuda:0' requested but", marks=WITHOUT_GPU
        ),
        (["demo", "--task", "firefly2d", "device=meta"], "device: 'meta' tensors hold no values"),
        (["fit", "FILE", "max_iters=3"], "key 'max_iters' (did you mean 'max_iter'?); valid"),
        (["fit", "FILE", "--free", "g_v,g_x"], "unknown θ parameter 'g_x'"),
        (["fit", "FILE", "--free", "sigma_pos"], "'sigma_pos' is fixed"),
        (["fit", "FILE", "--free", ""], "free: no parameter to fit"),
        (["fit", "FILE", "FILE"], "agent0.csv is given twice; expected each recording once"),
        (["fit", "FILE", "--free", "g_v", "theta.g_v=1.0"], "both fitted"),
        (["fit", "FILE", "covariance=robust"], "covariance must be one of"),
        (["recover", "fit.covariance=robust"], "fit.covariance must be one of"),
        (["recover", "particles=-1"], "particles must be ≥ 0"),
        (["fit", "FILE", "particles=-5"], "particles must be ≥ 0"),
        (["recover", "calibrate=-1"], "calibrate must be ≥ 0"),
        (["fit", "FILE", "calibrate=-2"], "calibrate must be ≥ 0"),
        (["recover", "components=0"], "components: expected 1 or more than the belief's 5"),
        (["fit", "FILE", "components=0"], "components must be positive"),
        (["fit", "FILE", "workers=0"], "workers must be positive, got 0"),
        (["recover", "fit.workers=-2"], "fit.workers must be positive, got -2"),
        (["recover", "n_trials=10"], "fit.covariance: 'sandwich' needs more trials per agent"),
        (["recover", "n_trials=9"], "has 9; expected fit.covariance=hessian for so few trials"),
        (["fit", "FILE", "components=4"], "components: expected 1 or more than the belief's 5"),
        (["fit", "FILE", "theta.sigma_pos=0.05"], "holds sigma_pos fixed at 0"),
        (["simulate", "theta.sigma_pos=0.05"], "holds sigma_pos fixed at 0"),
        (["simulate", "n_agents=1.5"], "n_agents=1.5 is not a valid int"),
        (["fit", "FILE", "--seed", "-1"], "--seed: expected an integer in [0, 2**63), got -1"),
        (["train", "ddpg.warmup_frames=0"], "ddpg.warmup_frames must be positive"),
        (["train", "ddpg.sigma_init=-1"], "ddpg.sigma_init must be ≥ 0"),
        (["train", "ddpg.buffer_size=100"], "ddpg.buffer_size=100 must hold a batch"),
        (["train", "ddpg.hidden=64,64"], "ddpg.hidden='64,64' is not a list"),
        (["train", "evaluation.seed=-1"], "evaluation.seed must be an integer in [0, 2**63)"),
        (["train", "flush_denormal=ture"], "flush_denormal='ture' is not a valid bool"),
        (["train", "n_envs=[1"], "override 'n_envs=[1' is not valid YAML"),
        pytest.param(
            ["train", "--device", "cuda:0"], "device: 'cuda:0' requested but", marks=WITHOUT_GPU
        ),
        (["train", "--device", "meta"], "config: device must be 'cpu' or a 'cuda' device"),
        (["train", "device=mps"], "config: device must be 'cpu' or a 'cuda' device"),
        (["train", "device=nowhere"], "config: device must name a torch device"),
        (["train", "--device", "cuda", "ddpg.collector_workers=2"], "collector_workers must be 1"),
    ],
)
def test_bad_settings_exit_2_with_a_clear_message(argv, message, simulated, tmp_path, capsys):
    argv = [str(simulated / "agent0.csv") if a == "FILE" else a for a in argv]
    assert main([*argv, "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"irc {argv[0]}: error: ") and message in err
    assert not (tmp_path / "out" / "summary.json").exists()


def test_a_recording_too_short_for_the_sandwich_is_named_before_any_fit(tmp_path, capsys):
    short = tmp_path / "short"
    assert main(["simulate", "--out", str(short), "--quiet", "n_trials=4"]) == 0
    argv = ["fit", str(short / "agent0.csv"), "--out", str(tmp_path / "out"), "--quiet"]
    assert main([*argv, "covariance=sandwich"]) == 2
    err = capsys.readouterr().err
    assert f"); {short / 'agent0.csv'} has 4; expected covariance=hessian for so few" in err
    assert not (tmp_path / "out").exists()


def test_a_recording_too_short_to_fit_is_named_before_any_fit(simulated, tmp_path, capsys):
    """A one-row recording was fitted, 8 of θ from its 2 action values, ending only with 'NOT
    converged'; now refused, naming the file and how many values it holds."""
    header, first, second, *_ = (simulated / "agent0.csv").read_text().splitlines()
    short = tmp_path / "one_row.csv"
    short.write_text(f"{header}\n{first}\n")
    fit = ["fit", str(short), "--out", str(tmp_path / "out"), "--quiet"]
    assert main(fit) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"irc fit: error: {short}: 2 recorded action values for 11 fitted coordinates (8 of θ, "
        "3 nuisance): too few to fit; expected more trials, or fewer free parameters (--free)"
    ]
    assert not (tmp_path / "out").exists()
    short.write_text(f"{header}\n{first}\n{second}\n")  # 4 values: enough for 4 coordinates
    assert main([*fit, "--free", "g_v", "--method", "map", "n_screen=2", "n_starts=1"]) == 0


def test_out_that_cannot_take_the_output_exits_2_before_any_work(simulated, tmp_path, capsys):
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine")
    fit = ["fit", str(simulated / "agent0.csv"), "--quiet", "--out"]
    assert main([*fit, str(a_file)]) == 2
    assert "--out: expected a folder, " in capsys.readouterr().err
    truth = (simulated / "summary.json").read_text()
    assert main([*fit, str(simulated)]) == 2  # would overwrite the true θ of the recordings
    assert "holds the summary.json of irc simulate" in capsys.readouterr().err
    assert (simulated / "summary.json").read_text() == truth
    for command in ("demo", "recover", "train"):  # each run's summary says what wrote it
        run = tmp_path / command
        run.mkdir()
        (run / "summary.json").write_text(f'{{"command": "{command}"}}')
        assert main(["simulate", "--quiet", "--out", str(run)]) == 2
        assert f"holds the summary.json of irc {command}" in capsys.readouterr().err
    # the 1D demo's summary is not a recovery's (the 2D demo's is: it may redo that folder)
    recovery = str(tmp_path / "recover")
    assert main(["demo", "--quiet", "--out", recovery]) == 2
    assert "holds the summary.json of irc recover, which irc demo" in capsys.readouterr().err
    assert main(["demo", "--task", "firefly2d", "--quiet", "--out", str(tmp_path / "demo")]) == 2
    assert "holds the summary.json of irc demo, which irc demo" in capsys.readouterr().err
    # a lab's own summary.json was overwritten without a word
    lab = tmp_path / "lab"
    lab.mkdir()
    texts = ('{"experimenter": "me"}', "not json", '{"command": "analyse"}', '{"command": ["r"]}')
    for text in texts:
        (lab / "summary.json").write_text(text)
        assert main([*fit, str(lab)]) == 2
        assert capsys.readouterr().err.splitlines() == [
            f"irc fit: error: --out: {lab / 'summary.json'} was not written by irc (it names no "
            "irc command), and irc fit would overwrite it; choose another folder"
        ]
        assert [p.name for p in lab.iterdir()] == ["summary.json"]
    # demo, recover and train named no command before 2026-12-05: their folders are irc's
    (lab / "summary.json").write_text('{"task": "firefly2d", "seed": 0, "methods": {}}')
    _check_arguments(build_parser().parse_args(["recover", "--out", str(lab)]))


def test_a_fit_interrupted_while_drawing_leaves_the_earlier_fits_files(
    fitted, simulated, tmp_path, monkeypatch, capsys
):
    """Stopped in its figures, a rerun left its summary and beliefs beside the earlier fit's
    figures (and, into a new folder, a summary that passed for a finished run)."""
    out = tmp_path / "fit"
    shutil.copytree(fitted[0], out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    draw = recordings.report_run

    def stopped_after_drawing(folder):
        draw(folder)
        raise KeyboardInterrupt

    monkeypatch.setattr("irc_torchrl.algorithms.recordings.report_run", stopped_after_drawing)
    fit = ["fit", str(simulated / "agent0.csv"), "--quiet", "--method", "map", "--free", "g_v"]
    fit += ["n_screen=2", "n_starts=1", "max_iter=2"]
    for folder in (out, tmp_path / "new"):
        assert main([*fit, "--out", str(folder)]) == 130
        assert capsys.readouterr().err.splitlines() == [
            "irc fit: interrupted; --out keeps its earlier files, and the fits that finished "
            "(--out/stages): rerun with --resume to go on"
        ]
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    new = tmp_path / "new"
    assert [p.name for p in new.iterdir()] == ["stages"]
    # its finished fits are the fit's to resume: another command would prune them
    assert main(["recover", "--quiet", "--out", str(new)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"irc recover: error: --out: {new}/stages holds the finished fits of an interrupted irc "
        "fit, which irc recover would remove; choose another folder (or go on with irc fit "
        "--resume)"
    ]


def test_a_rerun_of_simulate_interrupted_while_writing_leaves_the_earlier_set(
    tmp_path, monkeypatch, capsys
):
    """Stopped after its first recording, a rerun left that one beside the earlier run's
    others with no summary: a mixture of two runs' agents. Now nothing of it is left."""
    out = tmp_path / "sim"
    simulate = ["simulate", "--out", str(out), "--quiet", "n_agents=2", "n_trials=2"]
    assert main(simulate) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    write = recordings.write_trials

    def stopped_at_the_second(trials, path, model):
        if path.name == "agent1.csv":
            raise KeyboardInterrupt
        write(trials, path, model)

    monkeypatch.setattr("irc_torchrl.algorithms.recordings.write_trials", stopped_at_the_second)
    assert main([*simulate, "--seed", "1"]) == 130
    assert capsys.readouterr().err.splitlines() == [
        "irc simulate: interrupted; --out keeps its earlier recordings and summary"
    ]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    monkeypatch.setattr("irc_torchrl.algorithms.recordings.write_trials", write)
    assert main([*simulate, "--seed", "1"]) == 0
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(after) == sorted(before) and after["agent0.csv"] != before["agent0.csv"]


def test_simulating_a_lapse_rate_fit_cannot_reach_says_so(tmp_path, recwarn):
    """irc simulate takes lapse rates up to 1 while irc fit fits them within (0, 0.5): a
    user's experiment, but one whose fits end on a bound, which the user is now told."""
    simulate = ["simulate", "--quiet", "n_agents=1", "n_trials=1"]
    assert main([*simulate, "--out", str(tmp_path / "a"), "lapse=0.49"]) == 0
    assert not [w for w in recwarn if "lapse" in str(w.message)]
    with pytest.warns(UserWarning, match=r"^lapse=0.5: irc fit fits lapse rates within \(0, "):
        assert main([*simulate, "--out", str(tmp_path / "b"), "lapse=0.5"]) == 0


@pytest.fixture
def default_signals():
    """Python's own SIGINT and SIGTERM handlers for the test, as in a fresh ``irc`` process:
    an earlier test in this worker may have left TorchRL's (its memmap storage installs one
    at its first use, a host program's handler that irc then leaves as it stands)."""
    kept = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    yield
    for number, handler in kept.items():
        signal.signal(number, handler)


@pytest.mark.usefixtures("default_signals")
def test_a_terminated_simulate_cleans_up_as_an_interrupted_one(tmp_path, monkeypatch, capsys):
    """kill (SIGTERM, a scheduler's time limit) ended the process where it stood, leaving a
    staging folder of half the recordings in --out; it now cleans up as Ctrl-C does."""
    out = tmp_path / "sim"
    write = recordings.write_trials

    def killed_at_the_second(trials, path, model):
        if path.name == "agent1.csv":
            signal.raise_signal(signal.SIGTERM)
        write(trials, path, model)

    handler = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr("irc_torchrl.algorithms.recordings.write_trials", killed_at_the_second)
    assert main(["simulate", "--out", str(out), "--quiet", "n_agents=2", "n_trials=2"]) == 143
    assert capsys.readouterr().err.splitlines() == [
        "irc simulate: terminated; --out keeps its earlier recordings and summary"
    ]
    assert not out.exists()  # nothing left, not even the folder it made
    assert signal.getsignal(signal.SIGTERM) is handler


@pytest.mark.usefixtures("default_signals")
def test_an_interrupt_a_library_turns_into_another_error_still_reads_as_an_interrupt(
    tmp_path, monkeypatch, capsys
):
    """Ctrl-C inside TorchRL's context managers during irc train came out as an 80-line
    traceback of 'RuntimeError: Converting a tensordict to boolean value', exit 1."""
    out = tmp_path / "sim"
    write = recordings.write_trials

    def converted(trials, path, model):
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt as error:
            raise RuntimeError("Converting a tensordict to boolean value") from error
        write(trials, path, model)

    handler = signal.getsignal(signal.SIGINT)
    monkeypatch.setattr("irc_torchrl.algorithms.recordings.write_trials", converted)
    assert main(["simulate", "--out", str(out), "--quiet", "n_agents=1", "n_trials=2"]) == 130
    assert capsys.readouterr().err.splitlines() == [
        "irc simulate: interrupted; --out keeps its earlier recordings and summary"
    ]
    assert not out.exists()
    assert signal.getsignal(signal.SIGINT) is handler


def test_an_out_that_cannot_be_made_is_refused_before_any_work(tmp_path, capsys):
    """A dangling link or a file on the path was found only when writing, after the run
    (1 min 35 s of the 2D demo lost to 'File exists: dangling')."""
    (tmp_path / "gone").symlink_to(tmp_path / "nowhere")
    (tmp_path / "afile").write_text("")
    simulate = ["simulate", "--quiet", "n_agents=1", "n_trials=1"]
    for out, message in [
        ("gone", r"gone links to .*nowhere, which does not exist; expected a folder"),
        ("gone/sub", r"gone links to .*nowhere, which does not exist"),
        ("afile/sub", r"afile/sub cannot be made, .*afile is a file; expected a folder"),
    ]:
        assert main([*simulate, "--out", str(tmp_path / out)]) == 2
        err = capsys.readouterr().err
        assert re.match(rf"^irc simulate: error: --out: .*{message}", err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "gone"]


def test_a_second_run_into_a_folder_in_use_is_refused_before_any_work(tmp_path, capsys):
    """Two runs into one --out wrote their files side by side, the last summary winning over a
    mixture of both runs' recordings; the second is refused now, the first's files untouched,
    and the folder is free again once the first ends."""
    out = tmp_path / "sim"
    simulate = ["simulate", "--out", str(out), "--quiet", "n_agents=1", "n_trials=1"]
    assert main(simulate) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with held(out):  # another run's hold (a lock of another open file, as another process's)
        assert main([*simulate, "--seed", "7"]) == 2
        err = capsys.readouterr().err
        assert re.fullmatch(
            r"irc simulate: error: --out: .*sim is in use by another irc run \(its files would "
            r"mix with this run's\); wait for it to end, or choose another folder\n",
            err,
        ), err
        assert main(["report", str(out)]) == 2
        assert "DIR: " in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert main([*simulate, "--seed", "7"]) == 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} != before


def test_a_killed_runs_temporaries_are_removed_by_the_next_run_into_its_folder(tmp_path):
    """A run killed before its cleanup (kill -9) left its staging folder, a half-written file
    and irc report's scratch in --out for good; the next run holding the folder removes them
    (from it and its stages/), and nothing else: not a user's dotfiles in an --out that is
    their home, nor another run's temporaries in a folder below."""
    out = tmp_path / "sim"
    (out / "stages").mkdir(parents=True)
    (out / "nested").mkdir()
    temporaries = [
        ".staged.q0a1b2c3.irc-tmp",
        ".report.ab12cd_4.irc-tmp",
        ".agent0.x1y2z3w4.irc-tmp",
        "stages/.draw0.pt.k2j4_a9x.irc-tmp",
    ]
    for name in temporaries:
        (out / name).mkdir()
        (out / name / "half").write_text("")
    for name in [".summary.json.abcdefgh.irc-tmp", ".agent0.csv.abcdefgh.irc-tmp.csv"]:
        (out / name).write_text("")
        temporaries.append(name)
    kept = [
        *(".notes.tmp", "notes.txt", ".x.abcdefgh.tmp", ".bashrc.20240101.old"),
        *(".report.20240101", ".summary.json.abcdefgh.irc-tmp.bak"),
        *("stages/.plan.abcdefgh", "nested/.staged.q0a1b2c3.irc-tmp"),
    ]
    for name in kept:
        (out / name).write_text("mine")
    (out / ".config.20231231.old").mkdir()
    simulate = ["simulate", "--out", str(out), "--quiet", "n_agents=1", "n_trials=1"]
    assert main(simulate) == 0
    assert not [name for name in temporaries if (out / name).exists()]
    assert all((out / name).read_text() == "mine" for name in kept)
    assert (out / ".config.20231231.old").is_dir()


def test_a_refused_run_leaves_no_out_folder_it_made(tmp_path, capsys):
    """The hold makes --out (and the folders above it) before the run; a run refused inside
    (a setting out of range) leaves no empty folder behind."""
    out = tmp_path / "a" / "b" / "sim"
    assert main(["simulate", "--out", str(out), "--quiet", "n_agents=0"]) == 2
    assert "n_agents" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_memmap_recording_larger_than_the_free_space_is_refused_before_writing(
    tmp_path, monkeypatch, capsys
):
    """A memmap written past a full disk ended irc simulate with SIGBUS (exit 135), a staging
    folder left behind; the space is checked before each recording is written."""
    out = tmp_path / "sim"
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda _: usage._replace(free=10_000))
    simulate = ["simulate", "--out", str(out), "--quiet", "--format", "memmap", "n_trials=20"]
    assert main(simulate) == 2
    assert re.fullmatch(
        r"irc simulate: error: \[Errno 28\] No space left on device: the memmap recording "
        r"agent0 needs 0\.\d+ MB, its file system has 0\.01 MB free\n",
        capsys.readouterr().err,
    )
    assert not out.exists()


def test_a_rerun_of_simulate_keeps_no_earlier_memmap_agent_nor_its_summary(tmp_path, monkeypatch):
    """Fewer memmap agents over an earlier run: the earlier agents' folders go; a rerun whose
    summary cannot be written leaves the earlier run's agent and summary as they were (it
    used to leave the new agent with no summary, and nothing to tell a later rerun whose
    recordings were stale)."""
    out = tmp_path / "sim"
    simulate = ["simulate", "--out", str(out), "--quiet", "--format", "memmap", "n_trials=2"]
    assert main([*simulate, "n_agents=2"]) == 0
    assert main([*simulate, "n_agents=1"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["agent0", "summary.json"]
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def disk_full(*args):
        raise OSError("disk full")

    monkeypatch.setattr(recordings, "write_json", disk_full)
    assert main([*simulate, "n_agents=1", "--seed", "1"]) == 2
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda folder: (folder / "summary.json").write_text("[]"), "holds a JSON list"),
        (
            lambda folder: (folder / "summary.json").write_text(
                '{"agents": [{"theta_hat": {"g_v": 1.0}}]}'
            ),
            "lacks or mangles field",
        ),
        (  # the θ̂ figure draws before the belief figures find their field missing
            lambda folder: (folder / "summary.json").write_text(
                json.dumps(
                    {
                        k: v
                        for k, v in json.loads((folder / "summary.json").read_text()).items()
                        if k != "state_units"
                    }
                )
            ),
            "lacks or mangles field 'state_units'",
        ),
        (
            lambda folder: (folder / "beliefs.npz").write_bytes(
                (folder / "beliefs.npz").read_bytes()[:200]
            ),
            "beliefs.npz is damaged",
        ),
    ],
)
def test_report_of_a_damaged_folder_exits_2_drawing_nothing(
    fitted, tmp_path, capsys, damage, message
):
    source, _ = fitted
    for name in ("summary.json", "beliefs.npz"):
        shutil.copy(source / name, tmp_path / name)
    damage(tmp_path)
    assert main(["report", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err
    assert not list(tmp_path.glob("*.png"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["beliefs.npz", "summary.json"]


def _agent(truth) -> list[dict]:
    """The ``agents`` of a summary of ``irc simulate`` giving agent0.csv the true θ ``truth``."""
    return [{"file": "agent0.csv", "theta_true": truth}]


@pytest.mark.parametrize(
    "agents, message",
    [
        (_agent("1.4"), "agent0.csv's theta_true is '1.4'; expected {name: number}"),
        (_agent({"g_v": "fast"}), "theta_true is {'g_v': 'fast'}; expected {name: number}"),
        (_agent({"g_v": 99.0}), "agent0.csv's theta_true: g_v=99 is outside its space"),
        (_agent({"g_x": 1.0}), "agent0.csv's theta_true: unknown θ parameter 'g_x'"),
        (["agent0.csv"], "field 'agents' is ['agent0.csv']; expected a list of {file, theta_true}"),
    ],
)
def test_a_mangled_true_theta_exits_2_before_fitting(
    agents, message, simulated, tmp_path, capsys, monkeypatch
):
    def no_work(*args, **kwargs):
        raise AssertionError("fitted before refusing the true θ")

    monkeypatch.setattr("irc_torchrl.algorithms.recordings._fit_groups", no_work)
    folder = tmp_path / "sim"
    folder.mkdir()
    shutil.copy(simulated / "agent0.csv", folder / "agent0.csv")
    summary = json.loads((simulated / "summary.json").read_text())
    (folder / "summary.json").write_text(json.dumps({**summary, "agents": agents}))
    assert main(["fit", str(folder / "agent0.csv"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"irc fit: error: {folder / 'summary.json'}: ") and message in err, err


def _edit(text: str, line: int, column: str, value: str) -> str:
    """``text`` (a CSV) with the cell at ``line`` (0: the header) and ``column`` replaced."""
    rows = [row.split(",") for row in text.splitlines()]
    rows[line][rows[0].index(column)] = value
    return "\n".join(",".join(row) for row in rows) + "\n"


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (
            lambda t: t.replace(",heading,", ",headng,", 1),
            "'headng' looks like a misnamed 'heading'",
        ),
        (lambda t: _edit(t, 3, "x", "nan"), "trial 0, field 'x': nan at time 0.2 s"),
        (lambda t: _edit(t, 3, "a_v", "3"), "trial 0, field 'a_v': 3 at time 0.2 s"),
        (lambda t: _edit(t, 5, "target_x", "9"), "trial 0, field 'target_x': 9 at sample 4"),
        (lambda t: _edit(t, 2, "time", "zero"), "line 3, column 'time': 'zero' is not a number"),
        (lambda t: t + "1,0.1\n", "has 2 values; expected 20"),
    ],
)
def test_malformed_csv_exits_2_naming_the_field(corrupt, message, simulated, tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text(corrupt((simulated / "agent0.csv").read_text()))
    assert main(["fit", str(bad), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"irc fit: error: {bad}: ") and message in err, err
    assert not (tmp_path / "out").exists()


def test_help_lists_every_subcommand_with_a_purpose(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    for line in (
        "simulate simulate agents of the 2D task (or --model) into recording files, with their "
        "true θ",
        "fit fit θ with 95% intervals to recorded trials",
        "report print the table of a run folder (fit, recover, demo or train), draw its figures",
        "demo ",
        "train ",
    ):
        assert line in text
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--method {marginal,map,both}" in text and "--free NAME,NAME" in text
    assert "--model MODEL" in text


def test_nwb_without_pynwb_is_refused_before_simulating(tmp_path, capsys, monkeypatch):
    import irc_torchrl.algorithms.recordings as recordings

    def missing():
        raise ImportError("NWB files need pynwb (no module); install it with: pip install x")

    def no_work(*args, **kwargs):
        raise AssertionError("simulated before refusing the format")

    monkeypatch.setattr(recordings, "nwb_module", missing)
    monkeypatch.setattr(recordings, "simulate_agents", no_work)
    code = main(["simulate", "--out", str(tmp_path / "sim"), "--format", "nwb", "--quiet"])
    assert code == 2
    assert "pynwb" in capsys.readouterr().err
    assert not (tmp_path / "sim" / "summary.json").exists()


def test_simulation_reports_each_time_step_without_changing_the_trials():
    from irc_torchrl.algorithms.simulate import simulate_agents
    from irc_torchrl.envs.firefly2d import Firefly2DModel

    model = Firefly2DModel()
    theta = model.theta_space.default().unsqueeze(0)
    calls = []
    seen = simulate_agents(model, None, theta, 2, seed=3, progress=lambda *c: calls.append(c))
    quiet = simulate_agents(model, None, theta, 2, seed=3)
    assert calls == [(i, model.max_steps) for i in range(1, model.max_steps + 1)]
    assert torch.equal(seen["action"], quiet["action"])


def test_a_fit_of_recordings_sharing_a_name_keeps_each_apart(simulated, tmp_path):
    """Two files named alike (one simulated, one not) and a third whose name is the numbered
    form of theirs (gzip-compressed): unique labels, θ̂ scored against the truth of the one
    recording whose truth is known, every recording's own trial numbers in beliefs.npz, a
    particle check of the reported fit alone."""
    (tmp_path / "lab").mkdir()
    lines = (simulated / "agent0.csv").read_text().splitlines()
    rows = [row.split(",", 1) for row in lines[1:]]  # trial numbers 100, 107, ...
    renumbered = [f"{100 + 7 * int(trial)},{rest}" for trial, rest in rows]
    (tmp_path / "lab" / "agent0.csv").write_text("\n".join([lines[0], *renumbered]) + "\n")
    packed = gzip.compress((simulated / "agent0.csv").read_bytes())  # labelled without .csv.gz
    (tmp_path / "lab" / "agent0_1.csv.gz").write_bytes(packed)
    files = [str(simulated / "agent0.csv"), str(tmp_path / "lab" / "agent0.csv")]
    files.append(str(tmp_path / "lab" / "agent0_1.csv.gz"))
    out = tmp_path / "fit"
    settings = ["--free", "g_v", "--method", "marginal", "max_iter=2", "particles=20",
                "n_screen=2", "n_starts=1"]  # fmt: skip
    assert main(["fit", *files, "--out", str(out), "--quiet", *settings]) == 0
    summary = json.loads((out / "summary.json").read_text())
    labels = [agent["label"] for agent in summary["agents"]]
    assert len(set(labels)) == 3 and labels[2] == "agent0_1", labels
    truths = [agent.get("theta_true") for agent in summary["agents"]]
    assert truths[0] == pytest.approx(TRUTH, abs=1e-6)
    assert truths[1:] == [None, None]
    assert summary["truth_known"] == 1
    first = summary["agents"][0]
    covered = first["ci_low"]["g_v"] <= truths[0]["g_v"] <= first["ci_high"]["g_v"]
    assert summary["parameters"]["g_v"]["coverage"] == float(covered)
    error = abs(first["theta_hat"]["g_v"] - truths[0]["g_v"])
    assert summary["parameters"]["g_v"]["median_abs_error"] == pytest.approx(error)
    assert (out / "recovery.png").is_file() and not (out / "estimates.png").exists()
    line = next(x for x in format_fit(summary).splitlines() if "truth inside" in x)
    assert "(fraction of the 1 file whose truth is known)" in line
    assert ("1 of these fits did NOT converge" in line) == (not first["converged"])
    assert "particle_check_marginal_s" in summary["timings"]
    assert "particle_check_map_s" not in summary["timings"]  # map's fit is not reported
    recorded = read_trials(simulated / "agent0.csv", Firefly2DModel())["trial"][:, 0]
    with np.load(out / "beliefs.npz") as beliefs:
        numbers = [beliefs[f"{label}/trial"].tolist() for label in labels]
    assert numbers == [recorded.tolist(), (100 + 7 * recorded).tolist(), recorded.tolist()]


def test_a_rerun_into_its_own_folder_leaves_nothing_of_the_earlier_run(tmp_path):
    """Simulating fewer agents over an earlier simulation left its other recordings, which a
    later ``irc fit sim/*.csv`` mixed in; refitting fewer recordings left their figures."""
    sim, fit = tmp_path / "sim", tmp_path / "fit"
    assert main(["simulate", "--out", str(sim), "--quiet", "n_agents=2", "n_trials=3"]) == 0
    (sim / "notes.txt").write_text("the lab's own file")
    assert main(["simulate", "--out", str(sim), "--quiet", "n_agents=1", "n_trials=3"]) == 0
    assert sorted(p.name for p in sim.iterdir()) == ["agent0.csv", "notes.txt", "summary.json"]
    settings = ["--quiet", "--free", "g_v", "--method", "map", "max_iter=2", "n_screen=2",
                "n_starts=1"]  # fmt: skip
    files = [str(sim / "agent0.csv"), str(tmp_path / "other.csv")]
    shutil.copy(sim / "agent0.csv", files[1])
    fit.mkdir()
    (fit / "estimates_map.png").write_bytes(b"the lab's own figure, no fit's")
    assert main(["fit", *files, "--out", str(fit), *settings]) == 0
    assert (fit / "estimates_map.png").read_bytes() == b"the lab's own figure, no fit's"
    (fit / "estimates_map.png").unlink()
    assert (fit / "other_beliefs_time.png").is_file() and (fit / "recovery.png").is_file()
    assert main(["fit", files[1], "--out", str(fit), *settings]) == 0
    figures = sorted(p.name for p in fit.glob("*.png"))
    drawn = ["estimates.png", "other_beliefs_overhead.png", "other_beliefs_time.png"]
    assert figures == [*drawn, "q_function.png"]


@pytest.mark.parametrize(
    "command, name, folder",
    [
        (["simulate", "--format", "memmap"], "agent0", True),
        (["simulate"], "agent3.csv", False),
        (["fit", "rec.csv", "--method", "both"], "recovery_marginal.png", False),
        (["fit", "rec.csv"], "beliefs.npz", True),
        (["demo"], "summary.json", True),
        (["demo", "--task", "firefly2d"], "trials", True),
        (["recover"], "config.yaml", False),
    ],
)
def test_a_run_refuses_to_replace_what_no_earlier_run_of_it_wrote(
    tmp_path, capsys, command, name, folder
):
    """An ``--out`` holding a file or folder named as the command's output, but no summary of
    an earlier run of it: the run replaced it, a lab's ``agent0/`` of raw sessions lost under
    ``irc simulate --format memmap``. Refused before any work, the entry left as it was."""
    out = tmp_path / "lab"
    entry = out / name / "session1.mat" if folder else out / name
    entry.parent.mkdir(parents=True)
    entry.write_text("the lab's own")
    assert main([*command, "--out", str(out), "--quiet"]) == 2
    assert f"holds {name!r}, a name irc {command[0]} writes, but no" in capsys.readouterr().err
    assert entry.read_text() == "the lab's own"


def test_each_name_a_run_writes_is_one_it_refuses_to_replace_unowned(simulated, fitted, tmp_path):
    """The check knows every name ``irc simulate`` and ``irc fit`` write (``stages/`` has its
    own): each, alone in a folder of no earlier run, is refused."""
    runs = [(["simulate"], simulated), (["fit", "rec.csv", "--method", "map"], fitted[0])]
    for command, folder in runs:
        names = sorted(e.name for e in folder.iterdir() if e.name != "stages")
        assert len(names) >= 2, names
        for name in names:
            out = tmp_path / command[0] / name
            (out / name).mkdir(parents=True)
            assert main([*command, "--out", str(out), "--quiet"]) == 2, name


def test_a_recording_copied_over_a_simulated_one_is_fitted_without_the_others_truth(tmp_path):
    """The true θ of ``irc simulate``'s summary was attached by file name alone: another
    agent's recording copied over ``agent0.csv`` was scored against agent 0's θ*. Trial count
    and mean length tell them apart."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--quiet", "n_agents=2", "n_trials=3"]) == 0
    steps = [a["mean_steps"] for a in json.loads((sim / "summary.json").read_text())["agents"]]
    assert steps[0] != steps[1]  # the case
    shutil.copy(sim / "agent1.csv", sim / "agent0.csv")
    config = RecordingFitConfig(n_screen=2, n_starts=1, max_iter=1)
    files = [sim / "agent0.csv", sim / "agent1.csv"]
    with pytest.warns(UserWarning, match=r"agent0.csv: 3 trials of .* irc simulate wrote"):
        summary = recordings.fit_recordings(
            files, tmp_path / "fit", config, method="map", free=["g_v"], progress=False
        )
    assert [("theta_true" in a) for a in summary["agents"]] == [False, True]


def test_a_fit_of_a_recording_in_cm_reports_its_distances_in_metres(simulated, tmp_path):
    """With units declared the recording is converted to metres: θ̂ and the figures' axes said
    "distance", which a lab reading a goal radius of 0.5 could take for its own cm."""
    lines = (simulated / "agent0.csv").read_text().splitlines()
    header = lines[0].split(",")
    scaled = [header.index(n) for n in ("x", "y", "target_x", "target_y", "v")]
    rows = []
    for line in lines[1:]:
        cells = line.split(",")
        cells = [repr(float(c) * 100) if i in scaled else c for i, c in enumerate(cells)]
        rows.append(",".join(cells))
    (tmp_path / "cm.csv").write_text("\n".join([lines[0], *rows]) + "\n")
    units = [f"units.{n}=cm" for n in ("x", "y", "target_x", "target_y")] + ["units.v=cm/s"]
    settings = ["--quiet", "--free", "g_v,goal_radius", "--method", "map", "max_iter=2",
                "n_screen=2", "n_starts=1"]  # fmt: skip
    cm_file, m_file = str(tmp_path / "cm.csv"), str(simulated / "agent0.csv")
    assert main(["fit", cm_file, "--out", str(tmp_path / "cm"), *settings, *units]) == 0
    assert main(["fit", m_file, "--out", str(tmp_path / "m"), *settings]) == 0
    seconds = ["units.time=s", "units.heading=rad"]  # declared, but no distance among them
    assert main(["fit", m_file, "--out", str(tmp_path / "s"), *settings, *seconds]) == 0
    cm, m, s = (json.loads((tmp_path / f / "summary.json").read_text()) for f in ("cm", "m", "s"))
    assert cm["units"]["goal_radius"] == "m" and m["units"]["goal_radius"] == "distance"
    assert s["units"]["goal_radius"] == "distance" and s["state_units"][0] == "distance"
    assert cm["state_units"][:2] == ["m", "m"] and cm["state_units"][3] == "m/s"
    assert cm["agents"][0]["theta_hat"] == pytest.approx(m["agents"][0]["theta_hat"], rel=1e-5)


def test_a_recovery_refused_for_its_checkpoint_leaves_no_folder(tmp_path, capsys):
    """``config.yaml`` was written before the checkpoint was read: a refused run left it."""
    out = tmp_path / "recover"
    argv = ["recover", "--out", str(out), "--quiet", f"checkpoint={tmp_path / 'none.pt'}"]
    assert main(argv) == 2
    assert "none.pt" in capsys.readouterr().err and not out.exists()


def test_the_worst_trials_are_ranked_by_log_likelihood_per_recorded_step():
    """Trials 10-13 recorded over 1, 4, 2 and 4 steps with log-likelihoods −2, −6, −1, −20:
    per step −2, −1.5, −0.5, −5, so the worst three are 13, 10, 11 (not the worst totals
    13, 11, 10), beside the lower median of all (−2), each with its own trial number."""
    mask = torch.tensor([[1, 0, 0, 0], [1, 1, 1, 1], [1, 1, 0, 0], [1, 1, 1, 1]], dtype=torch.bool)
    trial = torch.tensor([10.0, 11.0, 12.0, 13.0]).unsqueeze(-1).expand(4, 4)
    recording = TensorDict({"mask": mask, "trial": trial}, batch_size=[4, 4])
    worst = recordings._worst_trials(recording, torch.tensor([-2.0, -6.0, -1.0, -20.0]))
    assert [(w["trial"], w["steps"], w["log_likelihood"]) for w in worst] == [
        (13.0, 4, -20.0),
        (10.0, 1, -2.0),
        (11.0, 4, -6.0),
    ]
    assert [w["per_step"] for w in worst] == [-5.0, -2.0, -1.5]
    assert {w["median_per_step"] for w in worst} == {-2.0}


def test_traded_off_pairs_are_those_of_large_absolute_correlation_most_correlated_first():
    """|r| ≥ 0.8 flags a pair either way, the strongest first; each pair once, the diagonal
    and undefined correlations never."""
    correlation = {
        "a": {"a": 1.0, "b": -0.9, "c": 0.85, "d": None},
        "b": {"a": -0.9, "b": 1.0, "c": 0.5, "d": float("nan")},
        "c": {"a": 0.85, "b": 0.5, "c": 1.0, "d": -0.79},
        "d": {"a": None, "b": float("nan"), "c": -0.79, "d": 1.0},
    }
    assert recordings._traded_off(correlation) == "a ~ b (r -0.90), a ~ c (r +0.85)"
    assert recordings._traded_off({"a": {"a": 1.0}}) == ""


def _fit_of(hat: list[float]) -> FitResult:
    """A fit of one free parameter ``a`` per agent at ``hat``, intervals ±0.15."""
    theta = torch.tensor(hat, dtype=torch.float64).unsqueeze(-1)
    n = len(hat)
    intervals = Intervals(
        std=torch.full((n, 1), 0.15 / 1.96, dtype=torch.float64),
        low=theta - 0.15,
        high=theta + 0.15,
        identified=torch.ones(n, 1, dtype=torch.bool),
        covariance=torch.zeros(n, 1, 1),
        profiled=torch.zeros(n, 1, dtype=torch.bool),
    )
    return FitResult(
        theta_hat=theta,
        nuisance=torch.zeros(n, 1),
        log_likelihood=torch.zeros(n),
        intervals=intervals,
        converged=torch.ones(n, dtype=torch.bool),
        iterations=1,
        names=["a"],
        information=torch.eye(2).expand(n, 2, 2),
    )


def test_truth_scores_pair_each_known_truth_with_its_own_recordings_fit():
    """Three recordings, the truth known for the last two (1.0 and 2.0, fitted 1.1 and 2.2):
    errors 0.1 and 0.2 (median 0.15), only the first inside ±0.15; the first recording's fit
    (5.0, truth unknown) is left out; no truth at all scores nothing."""
    space = ThetaSpace([Parameter("a", 0.0, 10.0, 1.0)])
    truths = [None, torch.tensor([1.0]), torch.tensor([2.0])]
    scores = recordings._truth_scores(space, truths, _fit_of([5.0, 1.1, 2.2]))
    assert [agent["theta_hat"]["a"] for agent in scores["agents"]] == pytest.approx([1.1, 2.2])
    assert scores["parameters"]["a"]["median_abs_error"] == pytest.approx(0.15)
    assert scores["parameters"]["a"]["coverage"] == 0.5
    assert recordings._truth_scores(space, [None, None], _fit_of([1.0, 2.0])) is None


def test_calibrated_coverage_scores_the_calibrated_intervals_against_the_known_truths():
    """Fits 5.0, 1.1, 2.2 (±0.15), truths unknown, 1.0 and 2.0: twice as wide about θ̂ (in
    the fit's logit coordinates of [0, 10]) the intervals reach 0.819 and 1.908, covering
    both truths (the fit's own intervals cover one); every recording gets its own."""
    space = ThetaSpace([Parameter("a", 0.0, 10.0, 1.0)])
    fit = _fit_of([5.0, 1.1, 2.2])
    calibration = Calibration(["a"], torch.tensor([2.0]), torch.zeros(1, 3, 1))
    scored = {"agents": [{}, {}, {}]}
    truths = [None, torch.tensor([1.0]), torch.tensor([2.0])]
    recordings._add_calibrated(scored, space, calibration, fit, truths)
    calibrated = agent_intervals(calibration.apply(space, fit))
    assert [agent["calibrated"] for agent in scored["agents"]] == calibrated
    lows = [agent["calibrated"]["ci_low"]["a"] for agent in scored["agents"][1:]]
    assert lows == pytest.approx([0.819, 1.908], abs=1e-3)
    assert scored["calibrated_parameters"]["a"]["coverage"] == 1.0
    assert scored["calibration"]["factor"] == {"a": 2.0}


def test_calibration_simulates_each_recording_at_its_last_methods_fit_in_its_own_world(
    monkeypatch,
):
    """Recordings of 2, 1 and 2 trials in worlds 0.5, 0.25, 0.75, fitted 1.5, 2.5, 3.5 by
    marginal (1, 2, 3 by map): each dataset is simulated per batch at marginal's θ̂ of its
    members, in their worlds, with their trial count and a seed of its own; every recording's
    refits (map 0.03 above, marginal 0.06 below the θ̂ its data were simulated at) are scored
    against its own θ̂, without particle checks."""
    space = ThetaSpace([Parameter("a", 0.0, 10.0, 1.0)])
    records = [
        TensorDict({"task_theta": torch.full((n, 4, 1), w)}, batch_size=[n, 4])
        for n, w in ((2, 0.5), (1, 0.25), (2, 0.75))
    ]
    fits = {"map": _fit_of([1.0, 2.0, 3.0]), "marginal": _fit_of([1.5, 2.5, 3.5])}
    simulated, refitted = [], []

    def simulate(model, actor, action_model, result, world, n_trials, seed, senses):
        assert senses == "agent"  # the fit's
        simulated.append((result.theta_hat[:, 0].tolist(), world[:, 0].tolist(), n_trials, seed))
        at = result.theta_hat.view(-1, 1, 1, 1).expand(-1, n_trials, 1, 1)
        fields = {key: at for key in TRIAL_KEYS}  # each trial holds the θ it was simulated at
        return TensorDict(fields, batch_size=at.shape[:3])

    def refit(model, action_model, space, synthetic, config, method, *args):
        refitted.append((method, config.particles, [s.shape[0] for s in synthetic], args[-1]))
        at = [float(s["state"][0, 0, 0]) for s in synthetic]
        shifted = {"map": [a + 0.03 for a in at], "marginal": [a - 0.06 for a in at]}
        return {m: _fit_of(theta) for m, theta in shifted.items()}, None, None, None, None

    monkeypatch.setattr(recordings, "simulate_at_fits", simulate)
    monkeypatch.setattr(recordings, "_fit_groups", refit)
    config = RecordingFitConfig(calibrate=2, particles=5, calibration_tail="own")
    calibrations = recordings._calibrate_fits(
        None, None, None, space, records, fits, config, "both", 0, "cpu", False, Stages()
    )
    batches = [([1.5, 3.5], [0.5, 0.75], 2), ([2.5], [0.25], 1)]
    assert [call[:3] for call in simulated] == batches * 2
    assert len({call[3] for call in simulated}) == 4  # every dataset and batch its own draw
    # each dataset's stages named by the method whose θ̂ generates it
    assert refitted == [("both", 0, [2, 1, 2], f"calibration{k}atmarginal") for k in (1, 2)]
    generating = fits["marginal"].theta_hat.float()
    for method, shift in (("map", 0.03), ("marginal", -0.06)):
        refits = _fit_of([a + shift for a in generating[:, 0].tolist()])
        expected = interval_pivots(space, generating, refits)
        assert torch.equal(calibrations[method].pivots, torch.stack([expected, expected]))


def test_recordings_are_grouped_by_their_number_of_trials():
    """Recordings of 3, 5, 3 and 3 trials: two batches, in the order first seen."""
    shapes = [(3, 7), (5, 7), (3, 9), (3, 7)]
    groups = recordings._by_trial_count([TensorDict({}, batch_size=s) for s in shapes])
    assert groups == {3: [0, 2, 3], 5: [1]}
    assert list(groups) == [3, 5]


def test_fit_space_holds_the_given_values_and_defaults_and_frees_the_rest():
    """Without --free every free parameter not given a value is fitted; the held ones keep
    their given values, the others their defaults."""
    space = firefly2d_theta_space()
    fitted = recordings.fit_space(space, None, {"g_v": 1.1, "goal_radius": 0.3})
    assert fitted.free_names == [n for n in space.free_names if n not in ("g_v", "goal_radius")]
    assert fitted.fixed["g_v"] == pytest.approx(1.1) and fitted.fixed["goal_radius"] == 0.3
    chosen = recordings.fit_space(space, ["g_w"], {"g_v": 1.1})
    assert chosen.free_names == ["g_w"]
    assert chosen.fixed["g_v"] == pytest.approx(1.1)
    for name in set(space.free_names) - {"g_v", "g_w"}:
        assert chosen.fixed[name] == pytest.approx(space[name].default), name


def test_the_simulated_truth_is_the_one_irc_simulate_wrote_for_that_file(tmp_path):
    """A summary of irc simulate names each file's θ*: a file reads its own, a file it does
    not name none; a summary of another command gives no truth. One simulated for another
    task (fitted without its --model) was refused for its θ names, not for its task."""
    space = firefly2d_theta_space()
    first = {**space.to_dict(space.default()), "g_v": 1.1}
    second = {**first, "g_v": 1.5}
    agents = [{"file": "a.csv", "theta_true": first}, {"file": "b.csv", "theta_true": second}]
    summary = {"command": "simulate", "task": "firefly2d", "agents": agents}
    (tmp_path / "summary.json").write_text(json.dumps(summary))

    def truth_of(name: str):  # the summary names no trial counts: the recording is not read
        return recordings._simulated_truth(tmp_path / name, space, "firefly2d", TensorDict())

    truth = truth_of("b.csv")
    assert float(truth[space.index("g_v")]) == pytest.approx(1.5)
    assert truth_of("c.csv") is None
    (tmp_path / "summary.json").write_text(json.dumps({**summary, "task": "reach_and_hold"}))
    with pytest.raises(
        ValueError, match=r"b.csv: simulated for task 'reach_and_hold' \(.*\), fitted here as "
        r"'firefly2d'; expected that task's --model \(and its policy's --checkpoint\)$"
    ):
        truth_of("b.csv")
    # a file of one's own beside them is not the summary's: no truth, no refusal
    assert truth_of("c.csv") is None
    (tmp_path / "summary.json").write_text(json.dumps({**summary, "command": "fit"}))
    assert truth_of("b.csv") is None


def _agent(file: str, converged: bool, truth: dict | None = None) -> dict:
    """One recording's entry of an irc fit summary, g_v and g_w fitted, g_w unidentified."""
    entry = {
        "file": file, "converged": converged, "n_trials": 20, "n_steps": 400,
        "log_likelihood": -12.5, "theta_hat": {"g_v": 1.375, "g_w": 0.75},
        "ci_low": {"g_v": 1.25, "g_w": 0.5}, "ci_high": {"g_v": 1.5, "g_w": 1.0},
        "identified": {"g_v": True, "g_w": False}, "motor_noise": [0.1, 0.2], "lapse": 0.0,
    }  # fmt: skip
    return entry if truth is None else {**entry, "theta_true": truth}


def test_format_fit_shows_each_truth_and_identification_and_counts_known_unconverged_fits():
    """The truth column holds θ*, not θ̂; an unidentified parameter reads NO, and any of a fit
    short of its top unsure (NO after 15 iterations read yes after 60); the coverage line
    counts the files whose truth is known, and of those the fits that did not converge."""
    agents = [
        _agent("a.csv", True, {"g_v": 1.4, "g_w": 0.8}),
        _agent("b.csv", False),
        _agent("c.csv", False, {"g_v": 1.2, "g_w": 0.9}),
    ]
    summary = {
        "method": "map", "free": ["g_v", "g_w"], "units": {"g_v": "m/s"}, "agents": agents,
        "parameters": {"g_v": {"coverage": 0.5}, "g_w": {"coverage": 1.0}},
    }  # fmt: skip
    lines = format_fit(summary).splitlines()
    rows = [line.split() for line in lines if line.split()[0] in ("g_v", "g_w")]
    assert rows[:2] == [
        ["g_v", "1.375", "[1.25,", "1.5]", "1.4", "yes", "m/s"],
        ["g_w", "0.75", "[0.5,", "1]", "0.8", "NO"],
    ]
    assert rows[2:4] == [
        ["g_v", "1.375", "[1.25,", "1.5]", "unsure", "m/s"],
        ["g_w", "0.75", "[0.5,", "1]", "unsure"],
    ]
    assert lines[-1] == (
        "map: truth inside the 95% interval (fraction of the 2 files whose truth is known): "
        "g_v 0.50, g_w 1.00; 1 of these fits did NOT converge, and an interval of a fit that "
        "did not converge may span all the data allow"
    )


def _trials_of(simulated: Path, path: Path, trials: list[int]) -> Path:
    """``path``: the CSV of the simulated agent0.csv's ``trials`` alone (their own numbers)."""
    header, *rows = (simulated / "agent0.csv").read_text().splitlines()
    kept = [row for row in rows if int(row.split(",", 1)[0]) in trials]
    path.write_text("\n".join([header, *kept]) + "\n")
    return path


def test_recordings_of_interleaved_trial_counts_each_get_their_own_fit(
    simulated, tmp_path, monkeypatch
):
    """Recordings of 3, 2, 2 and 3 trials, fitted in two batches ([a, d], d padded to a's 27
    steps, then [b, c], c padded to b's 27): each method's log-likelihood, recomputed on the
    recording alone at its θ̂ (float64 actor: to round-off), its trials' log-likelihoods,
    beliefs, particle check and calibrated intervals are its own recording's; g_w is held at
    the given 0.9; marginal starts from each agent's map θ̂."""
    picks = {"a": [4, 5, 7], "b": [10, 12], "c": [1, 3], "d": [2, 14, 17]}
    files = [_trials_of(simulated, tmp_path / f"{n}.csv", t) for n, t in picks.items()]
    actor, model, _ = recordings.load_ensemble_policy("firefly2d")
    records = [read_trials(path, model) for path in files]
    assert [r.shape[1] for r in records] == [27, 27, 16, 24]
    calls = []

    def spy(loss, held, **kwargs):
        calls.append((loss.method, held["mask"].clone(), kwargs["starts"]))
        return fit_theta(loss, held, **kwargs)

    factors = {"map": 2.0, "marginal": 3.0}

    def calibrate(model, actor, action_model, space, records, fits, *args):
        assert list(fits) == list(factors) and len(records) == 4
        pivots = torch.zeros(1, 4, 1)
        return {m: Calibration(["g_v"], torch.tensor([f]), pivots) for m, f in factors.items()}

    monkeypatch.setattr(recordings, "fit_theta", spy)
    monkeypatch.setattr(recordings, "_calibrate_fits", calibrate)
    config = RecordingFitConfig(
        n_screen=2, n_starts=1, max_iter=2, fit_lapse=False, calibrate=1, particles=4,
        actor_dtype="float64", theta={"g_w": 0.9},
    )  # fmt: skip
    out = tmp_path / "fit"
    summary = recordings.fit_recordings(files, out, config, method="both", free=["g_v"])
    assert summary["free"] == ["g_v"] and summary["fixed"]["g_w"] == pytest.approx(0.9)
    assert [(method, mask.shape) for method, mask, _ in calls] == [
        ("map", (2, 3, 27)), ("marginal", (2, 3, 27)), ("map", (2, 2, 27)), ("marginal", (2, 2, 27))
    ]  # fmt: skip
    batches = {0: (0, 0), 3: (0, 1), 1: (2, 0), 2: (2, 1)}  # recording: (map's call, row)
    for i, (call, row) in batches.items():  # padded steps are not recorded
        assert torch.equal(calls[call][1][row].sum(-1), records[i]["mask"].sum(-1))
    assert calls[0][2] is None and calls[2][2] is None  # map screens its own starts
    space = recordings.fit_space(model.theta_space, ["g_v"], {"g_w": 0.9})
    action_model = censored_action_model(actor, model, "float64", lapse=0.01, fit_lapse=False)
    with np.load(out / "beliefs.npz") as arrays:
        beliefs = dict(arrays)
    for method, part in summary["methods"].items():
        loss = InverseRationalLoss(model, action_model, theta_space=space, method=method)
        for i, (agent, record) in enumerate(zip(part["agents"], records, strict=True)):
            recorded = (str(files[i]), record.shape[0], int(record["mask"].sum()))
            assert (agent["file"], agent["n_trials"], agent["n_steps"]) == recorded
            assert agent["theta_hat"]["g_w"] == pytest.approx(0.9)
            assert agent["lapse"] == 0.01 and "lapse_ci" not in agent  # held, not fitted
            hat, noise = [[agent["theta_hat"][n] for n in space.names]], [agent["motor_noise"]]
            theta, nuisance = (torch.tensor(x, dtype=torch.float64) for x in (hat, noise))
            nuisance = nuisance.log()
            alone = record.select(*TRIAL_KEYS).unsqueeze(0)
            with torch.no_grad():
                per_trial = loss.log_likelihood(theta, nuisance, alone, True)[0]
            assert agent["log_likelihood"] == pytest.approx(float(per_trial.sum()), rel=1e-9)
            check = agent["particle_check"]  # beside its own approximation's log-likelihood
            approximation = check["particle_log_likelihood"] - check["approximation_gap"]
            assert approximation == pytest.approx(agent["log_likelihood"], rel=1e-9)
            numbers = record["trial"][:, 0].tolist()
            for worst in agent["worst_trials"]:
                own = per_trial[numbers.index(worst["trial"])]
                assert worst["log_likelihood"] == pytest.approx(float(own), rel=1e-9)
            calibrated = agent["calibrated"]["std"]["g_v"]
            assert calibrated == pytest.approx(factors[method] * agent["std"]["g_v"])
            if method == "map":
                continue
            call, row = batches[i]
            assert float(calls[call + 1][2][row, space.index("g_v")]) == pytest.approx(
                summary["methods"]["map"]["agents"][i]["theta_hat"]["g_v"], rel=1e-12
            )
            label = agent["label"]  # the reported method's beliefs
            assert np.array_equal(beliefs[f"{label}/trial"], np.array(numbers))
            ours = beliefs[f"{label}/trial_log_likelihood"]
            np.testing.assert_allclose(ours, per_trial.numpy(), rtol=1e-9)
            with torch.no_grad():
                mean = loss.recovered_beliefs(theta, nuisance, alone)["belief", "mean"][0]
            np.testing.assert_allclose(beliefs[f"{label}/mean"], mean.numpy(), atol=1e-9)


def test_a_recordings_own_column_names_are_set_on_the_command_line(simulated, tmp_path):
    """``time_column`` and ``trial_column`` were read_trials' alone: irc fit refused them."""
    lines = (simulated / "agent0.csv").read_text().splitlines()
    header = ["t" if n == "time" else "id" if n == "trial" else n for n in lines[0].split(",")]
    (tmp_path / "lab.csv").write_text("\n".join([",".join(header), *lines[1:]]) + "\n")
    out = tmp_path / "fit"
    settings = ["--quiet", "--method", "map", "--free", "g_v", "max_iter=2", "n_screen=2"]
    names = ["time_column=t", "trial_column=id"]
    assert main(["fit", str(tmp_path / "lab.csv"), "--out", str(out), *settings, *names]) == 0
    (agent,) = json.loads((out / "summary.json").read_text())["agents"]
    trials = read_trials(simulated / "agent0.csv", Firefly2DModel())
    assert (agent["n_trials"], agent["n_steps"]) == (20, int(trials["mask"].sum()))
    assert main(["fit", str(tmp_path / "lab.csv"), "--out", str(out), *settings]) == 2
