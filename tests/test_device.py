"""Tensors follow their inputs' device, checked without a GPU.

Under ``torch.device("meta")`` as the default device, any tensor created without an explicit
device is a meta tensor (no data): mixing one with the CPU inputs fails, or the result
differs. On a GPU the same omission mixes CPU and CUDA tensors (e.g. the outer filter's step
index, fixed here, failed every marginal evaluation on CUDA).
"""

from __future__ import annotations

import pytest
import torch

from irc_torchrl.algorithms.ensemble import (
    critic_slices,
    load_ensemble_critic,
    load_ensemble_policy,
)
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.modules.actor_critic import censored_action_model
from irc_torchrl.objectives.inverse import InverseRationalLoss


@pytest.fixture(scope="module")
def setting():
    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    theta = space.sample((2,), generator=torch.Generator().manual_seed(0))
    policy = motor_noise_policy(actor, model.action_spec, 0.1)
    return model, censored_action_model(actor, model, "float32"), policy, theta, space.default()


def test_simulation_creates_nothing_on_the_default_device(setting):
    model, _, policy, theta, world = setting
    expected = simulate_agents(model, policy, theta, 3, world, seed=1)
    with torch.device("meta"):
        trials = simulate_agents(model, policy, theta, 3, world, seed=1)
    assert trials["state"].device.type == "cpu"
    assert torch.equal(trials["state"], expected["state"])
    assert torch.equal(trials["action"], expected["action"])


@pytest.mark.parametrize("method", ["marginal", "map"])
@pytest.mark.parametrize("world", ["known", "shared"])
def test_likelihood_and_its_draws_create_nothing_on_the_default_device(setting, method, world):
    model, action_model, policy, theta, task_theta = setting
    trials = simulate_agents(model, policy, theta, 3, task_theta, seed=1)
    held = trials.select("state", "action", "target", "mask", "task_theta")
    loss = InverseRationalLoss(model, action_model, n_agents=2, method=method, world=world)
    nuisance = action_model.nuisance_init.double().expand(2, -1)
    expected = loss.log_likelihood_and_draws(
        theta.double(), nuisance, held, torch.Generator().manual_seed(0)
    )
    with torch.device("meta"):
        got = loss.log_likelihood_and_draws(
            theta.double(), nuisance, held, torch.Generator(device="cpu").manual_seed(0)
        )
    for a, b in zip(got, expected, strict=True):
        assert a.device.type == "cpu"
        torch.testing.assert_close(a, b)


def test_recovery_runs_where_its_config_says():
    """``irc recover``'s whole pipeline (simulate, both fits, a calibration refit, beliefs)
    on the config's device: nothing lands on the default device, and the numbers agree."""
    from irc_torchrl.algorithms.recover2d import Recovery2DConfig, recover_firefly2d

    config = Recovery2DConfig(
        n_prior_agents=1, n_mistaken_agents=1, n_trials=4, calibrate=1, device="cpu"
    )
    config.fit.n_screen, config.fit.n_starts, config.fit.max_iter = 2, 1, 2
    config.fit.covariance = "hessian"  # 4 trials are too few for the sandwich's 10 coordinates
    expected_trials, expected, _ = recover_firefly2d(config)
    with torch.device("meta"):
        trials, summary, fits = recover_firefly2d(config)
    assert trials["marginal", "belief", "mean"].device.type == "cpu"
    assert fits["marginal"].theta_hat.device.type == "cpu"
    key = ("marginal", "belief", "mean")
    torch.testing.assert_close(trials[key], expected_trials[key])
    for method in ("map", "marginal"):
        got, want = summary["methods"][method], expected["methods"][method]
        assert got["agents"] == want["agents"]
        assert got["calibrated"]["factor"] == want["calibrated"]["factor"]


def test_training_runs_where_its_config_says(tmp_path, monkeypatch):
    """Algorithm 1 (collector, n-step replay, DDPG updates, evaluation, the kept policy's
    report) on the config's device: nothing lands on the default device, the numbers agree."""
    import json

    from test_checkpoint import tiny
    from torchrl.collectors.utils import _TrajectoryPool

    from irc_torchrl.algorithms.ensemble import train_ensemble

    # TorchRL's trajectory counter makes its ids on the default device and then moves them to
    # the collector's: harmless on a GPU, impossible from meta tensors
    count = _TrajectoryPool.get_traj_and_increment

    def on_cpu(self, *args, **kwargs):
        with torch.device("cpu"):
            return count(self, *args, **kwargs)

    monkeypatch.setattr(_TrajectoryPool, "get_traj_and_increment", on_cpu)
    config = tiny("device=cpu")
    expected = train_ensemble(config, out=tmp_path / "plain", progress=False)
    with torch.device("meta"):
        got = train_ensemble(config, out=tmp_path / "meta", progress=False)
    for name, value in expected.actor.state_dict().items():
        assert got.actor.state_dict()[name].device.type == "cpu"
        assert torch.equal(got.actor.state_dict()[name], value)
    for name, value in expected.critic.state_dict().items():
        assert torch.equal(got.critic.state_dict()[name], value)
    returns = [[row["mean_return"] for row in r.history] for r in (got, expected)]
    assert returns[0] == returns[1]
    reports = [json.loads((tmp_path / f / "summary.json").read_text()) for f in ("meta", "plain")]
    for key in ("theta_sensitivity", "stop_sharpness"):
        assert reports[0][key] == reports[1][key]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_an_env_moved_to_the_gpu_draws_there_with_its_fixed_theta():
    """``env.to`` moved the specs only: the CPU generator and fixed θ then met CUDA tensors."""
    from torchrl.envs import TransformedEnv

    from irc_torchrl.envs import EKFBelief, Firefly2DEnv, Firefly2DModel

    model = Firefly2DModel()
    base = Firefly2DEnv(model=model, batch_size=(3,), theta=model.theta_space.default(), seed=1)
    env = TransformedEnv(base, EKFBelief(model)).to("cuda")
    rollout = env.rollout(5, break_when_any_done=False)
    assert rollout["state"].device.type == "cuda" and base.rng.device.type == "cuda"
    assert torch.equal(rollout["theta"][:, 0].cpu(), model.theta_space.default().expand(3, -1))


def test_the_1d_q_and_its_recovery_run_where_they_are_put():
    """Algorithm 1 of the 1D task (fitted Q-iteration on its env) and the recovery of agents
    acting by that Q (simulation, the batched fit, intervals and temperature) on the Q's
    device: nothing lands on the default device, and the numbers agree."""
    from irc_torchrl.algorithms.qiteration import QIterationConfig, train_factorised_q
    from irc_torchrl.algorithms.recovery import recover_agents
    from irc_torchrl.config import AgentsConfig, FitConfig
    from irc_torchrl.envs import Firefly1DModel

    model = Firefly1DModel()
    q_config = QIterationConfig(rounds=2, n_envs=32, steps_per_round=30, sweeps=5)
    agents, fit = (
        AgentsConfig(n_agents=2, n_trials=10),
        FitConfig(n_screen=2, n_starts=1, max_iter=3),
    )
    runs = []
    for default in ("cpu", "meta"):
        with torch.device(default):
            q = train_factorised_q(model, q_config, seed=1, device="cpu")
            trials, summary, result = recover_agents(model, q, agents, fit, seed=2)
        runs.append((q, trials, summary, result))
    (q, trials, summary, result), (q_meta, trials_meta, summary_meta, result_meta) = runs
    assert q_meta.weight.device.type == "cpu" and torch.equal(q_meta.weight, q.weight)
    assert q.weight.abs().sum() > 0  # a Q was learned
    assert trials_meta["action"].device.type == result_meta.theta_hat.device.type == "cpu"
    assert torch.equal(trials_meta["action"], trials["action"])
    del summary["timings"], summary_meta["timings"]
    assert summary_meta == summary


def test_irc_simulate_and_fit_create_nothing_on_the_default_device(tmp_path, monkeypatch):
    """``irc simulate`` and ``irc fit`` (both methods, a calibration refit, particle checks,
    profile intervals): nothing lands on the default device, and the summaries agree (the
    recordings' order was restored by a meta index: garbage θ̂, no error)."""
    import json

    from irc_torchrl.algorithms import recordings
    from irc_torchrl.config import RecordingFitConfig, SimulateConfig

    monkeypatch.setattr(recordings, "report_run", lambda folder: [])  # figures: not the point
    simulated = {}
    for default in ("cpu", "meta"):
        with torch.device(default):
            simulated[default] = recordings.simulate_recordings(
                SimulateConfig(n_agents=2, n_trials=6, lapse=0.05), tmp_path / default,
                seed=1, progress=False,
            )  # fmt: skip
    assert simulated["meta"]["agents"] == simulated["cpu"]["agents"]
    files = [tmp_path / "cpu" / f"agent{i}.csv" for i in range(2)]
    config = RecordingFitConfig(
        n_screen=2, n_starts=1, max_iter=2, calibrate=1, particles=20, intervals="profile"
    )
    fits = {}
    for default in ("cpu", "meta"):
        with torch.device(default):
            fits[default] = recordings.fit_recordings(
                files, tmp_path / f"fit_{default}", config, method="both", progress=False
            )
    for method in ("map", "marginal"):
        got, want = (json.dumps(fits[d]["methods"][method]["agents"]) for d in ("meta", "cpu"))
        assert got == want  # (as text: NaN entries equal)


def test_a_fit_finds_the_device_of_trials_held_without_one():
    """A TensorDict built without ``device=`` (its ``.device`` None) holding a GPU's tensors:
    the fit's own tensors go where the trials' are, not to the default device."""
    from tensordict import TensorDict

    from irc_torchrl.algorithms.fit import fit_theta

    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    theta = space.sample((2,), generator=torch.Generator().manual_seed(0))
    policy = motor_noise_policy(actor, model.action_spec, 0.1)
    held = simulate_agents(model, policy, theta, 4, space.default(), seed=1).select(
        "state", "action", "target", "mask", "task_theta"
    )
    bare = TensorDict(held.to_dict(), batch_size=held.batch_size)
    assert bare.device is None
    loss = InverseRationalLoss(
        model, censored_action_model(actor, model, "float32"), n_agents=2, method="map"
    )
    settings = {"n_screen": 2, "n_starts": 1, "max_iter": 2, "curvature": "bfgs"}
    expected = fit_theta(loss, held, **settings)
    with torch.device("meta"):
        got = fit_theta(loss, bare, **settings)
    assert got.theta_hat.device.type == "cpu"
    assert torch.equal(got.theta_hat, expected.theta_hat)
    # a loss reading the mask under another key: the device is not looked up by "mask"
    loss.set_keys(mask="valid")
    renamed = bare.rename_key_("mask", "valid")
    with torch.device("meta"):
        got = fit_theta(loss, renamed, **settings)
    assert torch.equal(got.theta_hat, expected.theta_hat)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_a_policy_loaded_on_the_gpu_simulates_and_its_1d_draws_score_there():
    """``load_ensemble_policy(device="cuda")`` builds the model's action spec there: the task
    probe (on the CPU) read its bounds as they were; a Boltzmann model's drawn actions took the
    fit's CPU generator with CUDA probabilities."""
    from irc_torchrl.envs import Firefly1DModel
    from irc_torchrl.modules.factorised_q import FactorisedQ
    from irc_torchrl.modules.likelihood import BoltzmannActionModel

    actor, model, _ = load_ensemble_policy("firefly2d", device="cuda")
    theta = model.theta_space.default(device="cuda").expand(2, -1)
    policy = motor_noise_policy(actor, model.action_spec, 0.1, 0.05)
    trials = simulate_agents(model, policy, theta, 3, seed=1)
    assert trials["state"].device.type == "cuda"
    one = Firefly1DModel()
    q = FactorisedQ(one.belief_feature_dim, one.theta_space.dim, 3).cuda()
    features = torch.zeros(4, one.belief_feature_dim + one.theta_space.dim, device="cuda")
    nuisance = torch.zeros(4, 1, device="cuda")
    logp = BoltzmannActionModel(q).log_prob_of_draw(features, nuisance, torch.Generator())
    assert logp.device.type == "cuda"


def test_the_critic_loads_on_the_device_asked_and_its_slices_are_taken_there():
    """``load_ensemble_critic(device=...)`` as ``load_ensemble_policy``: built there whatever the
    default device, and Fig. 1B's slices computed where the critic is, returned on the CPU."""
    critic, actor, model = load_ensemble_critic("firefly2d")
    expected = critic_slices(model, critic, actor, model.theta_space.default(), n=5)
    with torch.device("meta"):
        critic, actor, model = load_ensemble_critic("firefly2d", device="cpu")
        assert {p.device.type for p in [*critic.parameters(), *actor.parameters()]} == {"cpu"}
        got = critic_slices(model, critic, actor, model.theta_space.default(device="cpu"), n=5)
    for key, value in expected.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(got[key], value), key
