"""The agent's senses: whose θ sets the noise of its observations, the agent's or the world's.

The paper's observation model O_θo is the agent's: no experimenter measures how noisy a
subject's optic flow is. With ``senses="agent"`` (the default) the world draws the agent's
observations under the agent's own sensory parameters and the fits read them off the
candidate θ; with ``"world"`` both come from the recorded world's θ.
"""

import pytest
import torch

from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.recordings import simulate_recordings
from irc_torchrl.algorithms.recover2d import Recovery2DConfig
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.config import RecordingFitConfig, SimulateConfig
from irc_torchrl.data.trajectories import TRIAL_KEYS
from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.envs.model import sensed_world
from irc_torchrl.envs.probe import check_model
from irc_torchrl.modules.actor_critic import censored_action_model
from irc_torchrl.objectives.inverse import InverseRationalLoss

SENSORY = ("obs_sigma_v", "obs_sigma_w")


@pytest.fixture(scope="module")
def shipped():
    actor, model, _ = load_ensemble_policy("firefly2d")
    return actor, model


def test_a_sensed_world_takes_the_sensory_parameters_alone_from_the_agent():
    model = Firefly2DModel()
    space = model.theta_space
    world = space.default().expand(3, -1)
    theta = space.sample((3,), generator=torch.Generator().manual_seed(0))
    sensed = sensed_world(model, world, theta)
    for name in space.names:
        expected = theta if name in SENSORY else world
        assert torch.equal(sensed[:, space.index(name)], expected[:, space.index(name)]), name


def test_a_task_naming_a_sense_that_is_not_a_parameter_is_refused():
    class Misnamed(Firefly2DModel):
        sensory_names = ("obs_sigma_x",)

    with pytest.raises(ValueError, match=r"model.sensory_names: expected a tuple of θ parameter"):
        check_model(Misnamed())


def test_with_the_agents_senses_the_likelihood_reads_no_recorded_sensory_noise(shipped):
    """Two agents × 4 trials, marginal, at the agents' θ: the recorded world's sensory values
    (here halved) move the log-likelihood with ``senses="world"`` (a world noise that
    integrates the belief's spread) and leave it bit for bit alone with ``"agent"``."""
    actor, model = shipped
    space = model.theta_space
    theta = space.sample((2,), generator=torch.Generator().manual_seed(1))
    policy = motor_noise_policy(actor, model.action_spec, 0.1)
    trials = simulate_agents(model, policy, theta, 4, task_theta=theta, seed=2)
    held = trials.select(*TRIAL_KEYS)
    halved = held.clone()
    for name in SENSORY:
        halved["task_theta"][..., space.index(name)] *= 0.5
    action_model = censored_action_model(actor, model)
    motor = torch.full((2, 2), 0.1, dtype=torch.float64).log()
    values = {}
    for senses in ("agent", "world"):
        loss = InverseRationalLoss(
            model, action_model, n_agents=2, senses=senses, method="marginal"
        )
        with torch.no_grad():
            values[senses] = [loss.log_likelihood(theta.double(), motor, h) for h in (held, halved)]
    assert torch.equal(values["agent"][0], values["agent"][1])
    assert (values["world"][0] - values["world"][1]).abs().min() > 1e-3
    # the recorded world is the agents' own: both readings agree there
    torch.testing.assert_close(values["agent"][0], values["world"][0], rtol=1e-9, atol=0)
    with pytest.raises(ValueError, match=r"senses: expected one of \('agent', 'world'\)"):
        InverseRationalLoss(model, action_model, senses="own")


def test_simulated_agents_sense_by_their_own_theta_which_the_files_do_not_hold(
    tmp_path, monkeypatch
):
    """Each agent observes with its own obs_sigma_v (0.9); the recordings' theta.* columns
    and the summary hold the world's θ as an experimenter knows it, the default. A world's
    value of the senses is refused under ``senses=agent`` before anything is written."""
    worlds = []

    def simulate(model, policy, theta, n_trials, task_theta, **kwargs):
        worlds.append(task_theta)
        return simulate_agents(model, policy, theta, n_trials, task_theta, **kwargs)

    monkeypatch.setattr("irc_torchrl.algorithms.recordings.simulate_agents", simulate)
    config = SimulateConfig(n_agents=2, n_trials=1, theta={"obs_sigma_v": 0.9})
    summary = simulate_recordings(config, tmp_path / "agent", progress=False)
    space = Firefly2DModel().theta_space
    i = space.index("obs_sigma_v")
    assert worlds[0][:, i].tolist() == pytest.approx([0.9, 0.9])
    assert worlds[0][:, space.index("g_v")].tolist() == pytest.approx([1.2, 1.2])
    default = space["obs_sigma_v"].default
    assert summary["task_theta"]["obs_sigma_v"] == pytest.approx(default)  # float32
    columns = (tmp_path / "agent" / "agent0.csv").read_text().splitlines()
    row = dict(zip(columns[0].split(","), columns[1].split(","), strict=True))
    assert float(row["theta.obs_sigma_v"]) == pytest.approx(default)
    given = SimulateConfig(task_theta={"obs_sigma_w": 0.2})
    with pytest.raises(ValueError, match=r"task_theta.obs_sigma_w: with senses=agent each agent"):
        simulate_recordings(given, tmp_path / "refused", progress=False)
    assert not (tmp_path / "refused").exists() and len(worlds) == 1
    simulate_recordings(
        SimulateConfig(n_trials=1, task_theta={"obs_sigma_w": 0.2}, senses="world"),
        tmp_path / "world",
        progress=False,
    )
    assert worlds[1][space.index("obs_sigma_w")].item() == pytest.approx(0.2)
    for config in (RecordingFitConfig, Recovery2DConfig):
        with pytest.raises(ValueError, match="senses must be one of"):
            config(senses="rig").validate()
