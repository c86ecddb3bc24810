"""The 2D Python API refuses bad input with one line naming the field, before any work.

Each case below once ran on: a silent wrong answer (a one-row θ broadcast to every agent,
swapped action bounds, a float32 filter), a traceback deep in torch after work had started,
or a message naming nothing.
"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import default_dtype
from torchrl.data import Bounded, OneHot
from torchrl.envs import (
    Compose,
    DTypeCastTransform,
    ExcludeTransform,
    ObservationNorm,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.utils import check_env_specs

from irc_torchrl.algorithms.calibration import interval_pivots
from irc_torchrl.algorithms.ensemble import (
    critic_slices,
    evaluate_policy,
    load_ensemble_critic,
    load_ensemble_policy,
    theta_grid,
)
from irc_torchrl.algorithms.fit import fit_theta, particle_check, profile_intervals
from irc_torchrl.algorithms.qiteration import QIterationConfig, train_factorised_q
from irc_torchrl.algorithms.recordings import fit_space
from irc_torchrl.algorithms.recover2d import Recovery2DConfig, predicted_widths
from irc_torchrl.algorithms.simulate import first_trial_mask, motor_noise_policy, simulate_agents
from irc_torchrl.config import Firefly2DConfig
from irc_torchrl.data.io import read_trials
from irc_torchrl.data.trajectories import validate_trials
from irc_torchrl.envs import (
    EKFBelief,
    Firefly1DEnv,
    Firefly1DModel,
    Firefly2DEnv,
    Firefly2DModel,
)
from irc_torchrl.envs.belief import BeliefReward
from irc_torchrl.envs.gym_adapter import Firefly2DGymEnv
from irc_torchrl.envs.task_env import TaskEnv
from irc_torchrl.modules.actor_critic import (
    FeaturePolicy,
    censored_action_model,
    make_actor,
    make_critic,
)
from irc_torchrl.modules.factorised_q import FactorisedQ
from irc_torchrl.modules.likelihood import BoltzmannActionModel, CensoredGaussianActionModel
from irc_torchrl.objectives.inverse import InverseRationalLoss


@pytest.fixture(scope="module")
def shipped():
    actor, model, _ = load_ensemble_policy("firefly2d")
    return actor, model


@pytest.fixture(scope="module")
def two_agents(shipped):
    """Two agents with their own θ, 3 trials each, and their recorded fields."""
    actor, model = shipped
    space = model.theta_space
    theta = space.sample((2,), generator=torch.Generator().manual_seed(4))
    policy = motor_noise_policy(actor, model.action_spec, 0.1)
    trials = simulate_agents(model, policy, theta, 3, space.default(), seed=2)
    return trials.select("state", "action", "target", "mask", "task_theta"), theta.double()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"low": torch.ones(2), "high": -torch.ones(2)}, "low, high: expected finite action"),
        ({"low": -torch.ones(3)}, "low, high: expected finite action bounds"),
        ({"motor_noise": math.nan}, "motor_noise: expected a positive finite number"),
        ({"motor_noise": 0.0}, "motor_noise: expected a positive finite number, got 0.0"),
        ({"atol": -1.0}, r"atol: expected a tolerance in \[0, 1\), got -1.0"),
    ],
)
def test_the_censored_action_model_refuses_bounds_and_noise_it_cannot_score(
    shipped, kwargs, message
):
    """Swapped bounds scored every action near 0 nats; a NaN noise failed in eigh after the
    screening; a zero noise raised "math domain error"."""
    actor, model = shipped
    policy = FeaturePolicy(actor)
    arguments = {"low": -torch.ones(2), "high": torch.ones(2), **kwargs}
    with pytest.raises(ValueError, match=message):
        CensoredGaussianActionModel(policy, **arguments)


def test_networks_and_their_precisions_are_named_or_refused(shipped):
    actor, model = shipped
    with pytest.raises(ValueError, match=r"actor_dtype: expected one of \['float64', 'float32'\]"):
        censored_action_model(actor, model, "float16")
    with pytest.raises(ValueError, match="dtype: expected None or one of"):
        FeaturePolicy(actor, "float32")
    with pytest.raises(ValueError, match="hidden: expected an integer ≥ 1, got 0"):
        make_actor(model, [0])
    with pytest.raises(ValueError, match="hidden: expected a list of layer widths, got '64'"):
        make_actor(model, "64")


def test_a_particle_check_takes_one_theta_per_agent_and_runs_in_float64(shipped, two_agents):
    """A one-row θ was broadcast (agent 1 scored at agent 0's θ); a float32 nuisance ran the
    whole filter in float32 (gaps off by tens of nats)."""
    actor, model = shipped
    held, theta = two_agents
    loss = InverseRationalLoss(model, censored_action_model(actor, model), n_agents=2)
    nuisance = torch.full((2, 2), -2.0, dtype=torch.float64)  # exact in float32 too
    theta = theta.float().double()
    with pytest.raises(ValueError, match=r"theta: expected one θ per agent, \[2, 9\], got \[1"):
        particle_check(loss, held, theta[:1], nuisance, n_particles=10)
    exact = particle_check(loss, held, theta, nuisance, n_particles=10)
    single = particle_check(loss, held, theta.float(), nuisance.float(), n_particles=10)
    for key, value in exact.items():
        assert value.dtype == single[key].dtype and torch.equal(value, single[key]), key
    start = loss.action_model.nuisance_init.expand(2, -1)  # None: as its siblings read it
    default = particle_check(loss, held, theta, None, n_particles=10)
    given = particle_check(loss, held, theta, start, n_particles=10)
    assert all(torch.equal(default[key], given[key]) for key in given)


def test_inverse_loss_and_fit_refuse_what_they_cannot_fit(shipped, two_agents):
    actor, model = shipped
    held, theta = two_agents
    action_model = censored_action_model(actor, model)
    with pytest.raises(ValueError, match="theta_space: expected the task's parameters"):
        InverseRationalLoss(model, action_model, Firefly1DModel().theta_space)
    with pytest.raises(ValueError, match="n_agents: expected an integer ≥ 1, got 0"):
        InverseRationalLoss(model, action_model, n_agents=0)
    with pytest.raises(ValueError, match="components: expected an integer ≥ 1, got 6.5"):
        InverseRationalLoss(model, action_model, method="marginal", components=6.5)
    loss = InverseRationalLoss(model, action_model, n_agents=2)
    # TorchRL's LossModule repr lists the keys a loss reads
    assert "in_keys=['state', 'action', 'target', 'mask', 'task_theta']" in repr(loss)
    cases = [
        ({"seed": -1}, "seed: expected an integer in"),
        ({"progress": "yes"}, "progress: expected progress"),
        ({"starts": theta.unsqueeze(1)}, r"starts: expected one θ per agent, \[2, 9\]"),
    ]
    for kwargs, message in cases:
        with pytest.raises((TypeError, ValueError), match=message):
            fit_theta(loss, held, max_iter=1, n_screen=2, n_starts=1, **kwargs)


def test_the_loss_reads_one_agents_trials_as_fit_does_and_refuses_cut_trials(shipped, two_agents):
    """Its forward refused ``[n_trials, T]`` that validate and fit_theta read as one agent's,
    and a dict met an AttributeError. A collector's batch split into trajectories holds trials
    that began in an earlier batch: scored as if from step 0, 7 such trials of a batch cost
    more nats than its whole."""
    actor, model = shipped
    held, _ = two_agents
    loss = InverseRationalLoss(model, censored_action_model(actor, model))
    one = held[0]
    assert torch.equal(loss(one)["log_likelihood"], loss(one.unsqueeze(0))["log_likelihood"])
    with pytest.raises(TypeError, match=r"trials: expected a TensorDict \[n_agents"):
        loss(dict(one.items()))
    with pytest.raises(ValueError, match=r"expected batch dims \[1 agents, n_trials, T\] \(th"):
        loss(held)
    steps = torch.arange(one.shape[-1]).expand(*one.shape).unsqueeze(-1)
    whole = loss(one.clone().set("step", steps))["log_likelihood"]
    assert torch.equal(whole, loss(one)["log_likelihood"])
    cut = one.clone().set("step", steps + 20)
    with pytest.raises(ValueError, match=r"field 'step' at agent 0, trial 0, step 0 is 20; exp"):
        loss(cut)
    with pytest.raises(ValueError, match=r"field 'step' at agent 0, trial 0, step 0 is 20"):
        fit_theta(loss, cut, max_iter=1, n_screen=1, n_starts=1)


class _Wordless(FactorisedQ):
    def forward(self, features: torch.Tensor) -> torch.Tensor:
        raise AttributeError


@pytest.mark.parametrize(
    "network, got",
    [
        ("2d actor", r"scores this task's .*, got an error \(KeyError"),
        ("q of 2 actions", r"scores this task's .*, got an error \(RuntimeError: index 2 is out"),
        ("q of 4 actions", r"reads this task's .* into probabilities of its 3 actions summing to "
         r"1, got probabilities summing to 0\.\d+; a network trained on another task\?"),
        ("q of another width", r"scores this task's .*, got an error \(RuntimeError"),
        ("q failing without a word",
         r"scores this task's .*, got an error \(AttributeError: AttributeError\); a network"),
    ],
)  # fmt: skip
def test_a_network_of_another_task_is_refused_by_the_1d_loss(shipped, network, got):
    """A 2D actor, or a Q of other actions or inputs, in a 1D loss failed deep in a fit (a
    KeyError of tensordict's, a shape error in a matrix product) or not at all (4 actions)."""
    model = Firefly1DModel()
    width, d = model.belief_feature_dim, model.theta_space.dim
    q = {
        "2d actor": lambda: shipped[0],
        "q of 2 actions": lambda: FactorisedQ(width, d, 2),
        "q of 4 actions": lambda: FactorisedQ(width, d, 4),
        "q of another width": lambda: FactorisedQ(width + 2, d, 3),
        "q failing without a word": lambda: _Wordless(width, d, 3),  # an IndexError before
    }[network]()
    InverseRationalLoss(model, BoltzmannActionModel(FactorisedQ(width, d, 3)))  # its own: taken
    features = rf"\(firefly1d\) belief features \[1, {width + d}\] in float64"
    with pytest.raises(
        ValueError, match=rf"action_model: expected a network that (?=.*{features}){got}"
    ):
        InverseRationalLoss(model, BoltzmannActionModel(q))


def test_a_policy_of_other_actions_is_refused_by_the_2d_loss(shipped):
    """A policy of one output read the 2D task's two actions by broadcasting, silently; an
    action model that needs the scored components, as the loss always passes them, is taken."""
    _, model = shipped
    width = model.belief_feature_dim + model.theta_space.dim
    one = CensoredGaussianActionModel(
        torch.nn.Linear(width, 1).double(), -torch.ones(2), torch.ones(2)
    )
    with pytest.raises(
        ValueError,
        match=r"\(firefly2d\) belief features \[1, 23\] in float64 into "
        r"actions \[1, 2\], got actions \[1, 1\]; a network trained on another task\?",
    ):
        InverseRationalLoss(model, one)

    class Scoring(CensoredGaussianActionModel):
        def log_prob(self, features, action, nuisance, scored):  # scored required
            return super().log_prob(features, action, nuisance, scored)

    two = Scoring(torch.nn.Linear(width, 2).double(), -torch.ones(2), torch.ones(2))
    InverseRationalLoss(model, two)


def test_the_loss_names_a_policy_given_for_its_action_model_and_a_fit_with_nothing_free(
    shipped, two_agents
):
    """A space with every parameter fixed scores trials (a specialist's θ) but fits nothing:
    the fit once failed inside torch's Sobol engine."""
    actor, model = shipped
    held, _ = two_agents
    with pytest.raises(TypeError, match="action_model: expected an action model with nuisance"):
        InverseRationalLoss(model, actor)
    space = model.theta_space
    held_at = space.default()[space.free_mask].tolist()
    frozen = space.fix(**dict(zip(space.free_names, held_at, strict=True)))
    loss = InverseRationalLoss(model, censored_action_model(actor, model), frozen, n_agents=2)
    assert torch.isfinite(loss(held)["log_likelihood"]).all()
    with pytest.raises(ValueError, match="theta_space: every parameter is fixed"):
        fit_theta(loss, held, max_iter=1)


def test_arguments_of_the_wrong_kind_are_named(shipped, two_agents):
    """The trained actor as load_ensemble_policy returns it, given to the action model, was
    refused as "a network of another task? (KeyError: 'cov')"; a string for the task or the
    loss failed on an attribute; a rollout's done as integers was cast without a word."""
    actor, model = shipped
    held, _ = two_agents
    low, high = model.action_spec.space.low, model.action_spec.space.high
    with pytest.raises(TypeError, match=r"^actor: expected a network of belief features .*"
                       r"TensorDictSequential.* FeaturePolicy\(actor\), or .* "
                       r"censored_action_model\(actor, model\)$"):  # fmt: skip
        CensoredGaussianActionModel(actor, low, high)
    with pytest.raises(ValueError, match="^lapse: expected a real number, got 'x'$"):
        CensoredGaussianActionModel(torch.nn.Identity(), low, high, lapse="x")
    with pytest.raises(TypeError, match="^model: expected a TaskModel, got str$"):
        TaskEnv("firefly2d")
    with pytest.raises(TypeError, match="^model: expected a TaskModel, got str$"):
        InverseRationalLoss("firefly2d", censored_action_model(actor, model))
    with pytest.raises(TypeError, match="^loss: expected an InverseRationalLoss, got str$"):
        fit_theta("marginal", held)
    with pytest.raises(TypeError, match=r"^done: expected a bool tensor \[\.\.\., T\], got "):
        first_trial_mask(torch.tensor([[0, 1, 0]]))
    from irc_torchrl.modules import censored_action_model as exported

    assert exported is censored_action_model


def test_recovered_beliefs_check_theta_nuisance_and_trials(shipped, two_agents):
    """Once a [2, 8] θ lost its last parameter, a [1, 9] θ served both agents and a NaN
    action gave NaN beliefs, silently."""
    actor, model = shipped
    held, theta = two_agents
    loss = InverseRationalLoss(model, censored_action_model(actor, model), n_agents=2)
    nuisance = loss.nuisance.detach()
    nan_action = held.clone()
    nan_action["action"][0, 0, 0, 0] = torch.nan
    cases = [
        ((theta[:, :-1], nuisance, held), r"theta: expected shape \[..., 9\]"),
        ((theta[:1], nuisance, held), r"one θ per agent \(or per trial\), \[2, 9\], got \[1"),
        ((theta * 10, nuisance, held), "is outside its space"),
        ((theta, nuisance[:, :1], held), r"nuisance: expected shape \[2, 2\], got \[2, 1\]"),
        ((theta, nuisance, nan_action), "field 'action' has NaN or inf at agent 0, trial 0"),
    ]
    for args, message in cases:
        with pytest.raises(ValueError, match=message):
            loss.recovered_beliefs(*args)
    per_trial = [x.unsqueeze(1).expand(-1, held.shape[1], -1) for x in (theta, nuisance)]
    assert (loss.recovered_beliefs(*per_trial, held) == loss.recovered_beliefs(
        theta, nuisance, held
    )).all()  # fmt: skip


def test_trials_hold_one_target_and_world_per_trial_and_float_actions(shipped, two_agents):
    """The fits read the target and the world's θ at each trial's first step; a continuous
    task's actions truncated to integers once moved θ̂ without a word."""
    actor, model = shipped
    held, theta = two_agents
    loss = InverseRationalLoss(model, censored_action_model(actor, model), n_agents=2)
    for key in ("target", "task_theta"):
        moved = held.clone()
        moved[key][1, 2, 4:] += 0.01
        with pytest.raises(ValueError, match=f"field '{key}' at agent 1, trial 2, step 4 differs"):
            loss(moved)
        rounded = held.clone()  # float32's rounding of values a file's checks found equal
        rounded[key][1, 2, 4:] *= 1 + 2e-6
        loss(rounded)
    rounded = held.clone().set("action", held["action"].long())
    with pytest.raises(TypeError, match="field 'action': expected a floating-point tensor"):
        fit_theta(loss, rounded, max_iter=1)


def test_a_loss_with_renamed_keys_fits_trials_under_those_names(shipped, two_agents):
    """``set_keys`` held for the loss's forward but not for ``fit_theta``, which asked for
    the default names; a field missing is named as the loss reads it."""
    actor, model = shipped
    held, _ = two_agents
    loss = InverseRationalLoss(model, censored_action_model(actor, model), n_agents=2)
    loss.set_keys(state="pos", action="act")
    renamed = held.clone().rename_key_("state", "pos").rename_key_("action", "act")
    result = fit_theta(loss, renamed, max_iter=1, n_screen=2, n_starts=1)
    assert result.theta_hat.shape == (2, 9) and torch.isfinite(result.log_likelihood).all()
    with pytest.raises(KeyError, match=r"missing field\(s\) \['pos', 'act'\]; this loss reads"):
        loss(held)


def _seeded_numbers() -> list[torch.Tensor]:
    """What a seed gives: Algorithm 1's 1D Q, simulated trials with motor noise and lapses,
    and a fit of them."""
    model1d = Firefly1DModel()
    small = QIterationConfig(n_envs=32, rounds=2, steps_per_round=20, sweeps=3)
    q = train_factorised_q(model1d, small, seed=0)
    actor, model, _ = load_ensemble_policy("firefly2d")
    theta = model.theta_space.default(torch.float32).expand(2, -1)
    agent = motor_noise_policy(actor, model.action_spec, 0.1, lapse=0.1)
    trials = simulate_agents(model, agent, theta, 2, seed=0)
    loss = InverseRationalLoss(model, censored_action_model(actor, model))
    held = trials.select("state", "action", "target", "mask", "task_theta")
    fit = fit_theta(loss, held, max_iter=2, n_screen=2, n_starts=1)
    numbers = [q.weight, trials["state"], trials["action"], fit.theta_hat, fit.log_likelihood]
    return numbers + [p for p in actor.parameters()]


def test_a_float64_default_dtype_gives_the_same_numbers_in_float32():
    """Under it the shipped policy came back in float64 and a rollout failed deep in torch, and
    TorchRL's noise modules drew other numbers from the same seed."""
    expected = _seeded_numbers()
    with default_dtype(torch.float64):
        numbers = _seeded_numbers()
        assert torch.get_default_dtype() == torch.float64  # the caller's, restored
    assert [x.dtype for x in numbers] == [x.dtype for x in expected]
    assert all(torch.equal(x, y) for x, y in zip(numbers, expected, strict=True))
    assert {x.dtype for x in numbers[5:]} == {torch.float32}


@pytest.mark.parametrize("env_class", [Firefly1DEnv, Firefly2DEnv])
def test_specs_hold_the_float32_the_envs_emit_under_a_float64_default(env_class):
    """Their real-valued specs took torch's default dtype: check_env_specs failed, and a
    collector's batch held float32 states beside float64 rewards."""
    with default_dtype(torch.float64):
        env = TransformedEnv(env_class(batch_size=[3], seed=0), EKFBelief(env_class.model_class()))
        check_env_specs(env, seed=None)
        rollout = env.rollout(4)
    for key in ("state", ("next", "reward"), ("belief", "mean"), ("belief", "cov")):
        assert rollout[key].dtype == torch.float32, key


def test_a_belief_filter_refuses_an_env_whose_observation_it_cannot_read():
    """With the observation excluded (or renamed) upstream, the 2D filter only predicted: its
    velocity variances grew to the process noise's while the agent saw every step."""
    model = Firefly2DModel()
    env = TransformedEnv(
        Firefly2DEnv(model=model, batch_size=[2], seed=0),
        Compose(ExcludeTransform("observation"), EKFBelief(model)),
    )
    message = r"EKFBelief: the env has no 'observation' to filter with"
    with pytest.raises(KeyError, match=message):
        _ = env.observation_spec
    with pytest.raises(KeyError, match=message):
        env.rollout(2)


@pytest.mark.parametrize("rewritten", ["observation", "state", "target"])
def test_a_belief_filter_refuses_a_transform_before_it_that_rewrites_what_it_reads(rewritten):
    """An ObservationNorm before the filter fed it normalised observations, which it weighed
    as the task's own (the filter cannot tell); now refused at a reset and at the spec. A cast
    or a transform writing other keys passes."""
    model = Firefly2DModel()
    norm = ObservationNorm(loc=0.0, scale=2.0, in_keys=[rewritten])
    env = TransformedEnv(Firefly2DEnv(model=model, batch_size=[2], seed=0), norm)
    env.append_transform(EKFBelief(model))
    message = rf"^EKFBelief: ObservationNorm before it rewrites '{rewritten}', which the filter"
    with pytest.raises(ValueError, match=message):
        env.reset()
    with pytest.raises(ValueError, match=message):
        _ = env.observation_spec
    for harmless in (DTypeCastTransform(torch.float32, torch.float64), StepCounter()):
        env = TransformedEnv(
            Firefly2DEnv(model=model, batch_size=[2], seed=0), Compose(harmless, EKFBelief(model))
        )
        assert env.observation_spec["belief", "mean"].shape == (2, 5)
    # first of a Compose that comes first: TorchRL's parent lookup fails there (IndexError)
    nested = Compose(Compose(EKFBelief(model), BeliefReward(model)))
    env = TransformedEnv(Firefly2DEnv(model=model, batch_size=[2], seed=0), nested)
    assert env.rollout(3)["next", "belief", "mean"].shape == (2, 3, 5)


@pytest.mark.parametrize("cast", [["observation"], ["theta"], ["state", "observation", "target"]])
def test_a_belief_filter_refuses_a_cast_of_some_of_what_it_reads(cast):
    """A cast of the observation alone passed the upstream check and failed in the filter's
    update ('expected scalar type Float but found Double'); a cast of all of them runs."""
    model = Firefly2DModel()
    env = TransformedEnv(
        Firefly2DEnv(model=model, batch_size=[2], seed=0),
        Compose(DTypeCastTransform(torch.float32, torch.float64, cast), EKFBelief(model)),
    )
    message = r"^EKFBelief: the env's '\w+' is torch.float\d+, its 'state' torch.float\d+; expected"
    with pytest.raises(ValueError, match=message):
        env.rollout(2)
    whole = DTypeCastTransform(torch.float32, torch.float64)
    env = TransformedEnv(Firefly2DEnv(model=model, batch_size=[2], seed=0), whole)
    env.append_transform(EKFBelief(model))
    assert env.rollout(2)["next", "belief", "cov"].dtype == torch.float64


def test_a_belief_filter_of_another_task_is_named_on_a_reset_before_any_spec_is_read():
    """A reset before the specs were read failed with torch's 'expanded size' error."""
    env = TransformedEnv(Firefly1DEnv(batch_size=[2], seed=0), EKFBelief(Firefly2DModel()))
    with pytest.raises(ValueError, match=r"the env's 'state' is \[2, 1\], its model's"):
        env.reset()


def test_a_belief_filter_of_another_task_and_a_string_of_names_are_refused():
    env = TransformedEnv(Firefly2DEnv(batch_size=[2]), EKFBelief(Firefly1DModel()))
    with pytest.raises(ValueError, match=r"EKFBelief: the env's 'state' is \[2, 5\], its model"):
        env.rollout(2)
    with pytest.raises(TypeError, match="free: expected a list of parameter names, got the str"):
        fit_space(Firefly2DModel().theta_space, "g_v", {})


def test_belief_features_that_do_not_broadcast_are_refused_up_front(shipped):
    """A task of one's own whose features concatenate their arguments as given worked in the
    env and in marginal, and failed in map's first pass with a bare size error: refused when
    the env or either estimator is built."""
    actor, model = shipped

    class Concatenating(Firefly2DModel):
        def belief_features(self, mean, cov, target, step, theta):
            features = super().belief_features(mean, cov, target, step, theta)
            belief = features[..., : self.belief_feature_dim]
            return torch.cat([belief, theta], -1)  # θ not expanded to the steps

    own = Concatenating()
    action_model = censored_action_model(actor, model)
    message = r"^model\.belief_features: expected features \[1, 1, 2, 23\] from beliefs "
    for method in ("map", "marginal"):
        with pytest.raises(ValueError, match=message):
            InverseRationalLoss(own, action_model, method=method)
    with pytest.raises(ValueError, match=message):
        Firefly2DEnv(model=own)
    InverseRationalLoss(model, action_model, method="map")


def test_pivots_take_one_truth_per_fitted_agent(shipped, two_agents):
    """A one-row truth was broadcast over every agent's interval."""
    actor, model = shipped
    held, theta = two_agents
    loss = InverseRationalLoss(model, censored_action_model(actor, model), n_agents=2)
    result = fit_theta(loss, held, max_iter=1, n_screen=2, n_starts=1)
    space = model.theta_space
    with pytest.raises(ValueError, match=r"theta_true: expected one θ per fitted agent"):
        interval_pivots(space, theta[:1], result)
    assert interval_pivots(space, theta, result).shape == (2, len(space.free_names))
    # one name is a name, not its characters
    assert profile_intervals(loss, held, result, names="g_v").profiled.shape == (2, space.dim)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"max_steps": 0}, "max_steps: expected an integer ≥ 1, got 0"),
        ({"min_steps": 61}, "min_steps: expected at most max_steps=60, got 61"),
        ({"target_distance": (0, 0)}, "target_distance: expected a positive finite number"),
        ({"target_distance": (3, 1)}, r"target_distance: expected \(nearest, farthest\)"),
        ({"reward_value": math.nan}, "reward_value: expected a positive finite number"),
        ({"stop_threshold": 1.5}, r"stop_threshold: expected a forward control in \(-1, 1\)"),
        ({"target_angle": -1.0}, r"target_angle: expected an angle in \[0, π\]"),
    ],
)
def test_a_2d_task_that_cannot_run_is_refused(kwargs, message):
    """``max_steps=0`` and a target distance of 0 put NaN into the belief features."""
    with pytest.raises(ValueError, match=message):
        Firefly2DModel(**kwargs)


def test_the_gym_adapter_critic_slices_and_evaluation_check_their_inputs(shipped):
    actor, model = shipped
    with pytest.raises(TypeError, match="model: expected a Firefly2DModel, got Firefly1DModel"):
        Firefly2DGymEnv(model=Firefly1DModel())
    env = Firefly2DGymEnv()
    with pytest.raises(ValueError, match=r"options: unknown key\(s\) \['thetaa'\]"):
        env.reset(options={"thetaa": {"g_v": 1.0}})
    critic, critic_actor, critic_model = load_ensemble_critic("firefly2d")
    space = model.theta_space
    with pytest.raises(ValueError, match=r"theta: expected one θ \[9\], got \[1, 9\]"):
        critic_slices(critic_model, critic, critic_actor, space.default().unsqueeze(0))
    with pytest.raises(ValueError, match="n: expected an integer ≥ 1, got 0"):
        critic_slices(critic_model, critic, critic_actor, space.default(), n=0)
    with pytest.raises(ValueError, match=r"thetas: expected shape \[n ≥ 1, 9\], got \[0, 9\]"):
        evaluate_policy(model, actor, space.default().expand(0, -1))
    with pytest.raises(ValueError, match="seed: expected an integer in"):
        theta_grid(space, 4, seed=-1)
    if not torch.cuda.is_available():  # an AssertionError 12 frames deep in the env before
        with pytest.raises(ValueError, match="device: 'cuda:3' requested but"):
            load_ensemble_policy(device="cuda:3")
        with pytest.raises(ValueError, match="device: 'cuda:3' requested but"):
            Firefly2DEnv(device="cuda:3")


@pytest.mark.parametrize(
    "config, message",
    [
        (lambda c: setattr(c, "seed", -1), r"seed must be an integer in \[0, 2\*\*63\)"),
        (lambda c: setattr(c, "threads", 1.5), "threads=1.5 is not a valid int"),
        (lambda c: setattr(c.ddpg, "hidden", "64"), "ddpg.hidden='64' is not a valid list"),
        (lambda c: setattr(c.ddpg, "hidden", [4.7]), r"ddpg.hidden=\[4.7\] is not a valid list"),
        (lambda c: setattr(c.ddpg, "hidden", [0]), "ddpg.hidden must list positive widths"),
        (lambda c: setattr(c.ddpg, "max_grad_norm", math.nan), "ddpg.max_grad_norm must be"),
        (lambda c: setattr(c.evaluation, "seed", -2), r"evaluation.seed must be an integer"),
    ],
)
def test_a_training_config_built_in_python_is_checked_as_a_loaded_one(config, message):
    """Built in Python, ``seed=-1`` failed after warm-up and pretraining, leaving a folder."""
    built = Firefly2DConfig()
    config(built)
    with pytest.raises(ValueError, match=message):
        built.validate()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"calibrate": 1.5}, "calibrate=1.5 is not a valid int"),
        ({"components": 6.5}, "components=6.5 is not a valid int"),
        ({"methods": "map,map"}, "methods must be a comma-separated subset .* each once"),
    ],
)
def test_a_recovery_config_built_in_python_is_checked_as_a_loaded_one(kwargs, message):
    """``calibrate=1.5`` failed only after the simulation and every fit; "map,map" fitted twice."""
    with pytest.raises(ValueError, match=message):
        Recovery2DConfig(**kwargs).validate()


def test_predicted_widths_refuses_no_agents(shipped):
    actor, model = shipped
    with pytest.raises(ValueError, match="n_prior_agents \\+ n_mistaken_agents must be ≥ 1"):
        predicted_widths(model, actor, n_agents=0)


def test_a_fit_is_read_only_in_the_theta_space_it_was_made_in(shipped, two_agents):
    """A fit read with another task's space, or with a space that fixes one of its free
    parameters, raised a size mismatch deep in torch (or read the wrong columns)."""
    from irc_torchrl.algorithms.calibration import Calibration

    actor, model = shipped
    held, _ = two_agents
    loss = InverseRationalLoss(model, censored_action_model(actor, model), n_agents=2)
    result = fit_theta(loss, held, max_iter=1, n_screen=2, n_starts=1)
    other = Firefly1DModel().theta_space
    with pytest.raises(ValueError, match=r"result: a fit of θ \['g_v'"):
        result.check_space(other)
    space = model.theta_space
    factor = torch.ones(len(space.free_names), dtype=torch.float64)
    calibration = Calibration(space.free_names, factor, torch.zeros(1, 2, len(factor)))
    assert calibration.apply(space, result).theta_hat.shape == (2, space.dim)
    narrow = space.fix(g_v=1.2)
    with pytest.raises(ValueError, match="result: a fit of θ .* with 8 free, not of the space"):
        result.check_space(narrow)
    with pytest.raises(ValueError, match="result: a fit of θ"):
        interval_pivots(narrow, space.default().expand(2, -1), result)
    theirs = Calibration(other.free_names, torch.ones(2, dtype=torch.float64), torch.zeros(1, 2, 2))
    with pytest.raises(ValueError, match="result: a fit of θ"):
        theirs.apply(other, result)


def test_configs_built_in_python_take_the_natural_python_forms_and_store_plain_ones():
    """A Path, a torch device, a tuple, numpy integers and 0-d tensors stand for what a YAML
    file would hold, and are stored as it would (so ``config.yaml`` can be written); a tensor
    that cannot is refused on one line."""
    from pathlib import Path

    import numpy as np

    config = Firefly2DConfig()
    config.ddpg.hidden = (np.int64(32), 32)
    config.ddpg.lr_actor = torch.tensor(1e-4, dtype=torch.float64)
    config.device = torch.device("cpu")
    config.validate()
    assert config.ddpg.hidden == [32, 32] and type(config.ddpg.hidden[0]) is int
    assert type(config.ddpg.lr_actor) is float and config.device == "cpu"
    recovery = Recovery2DConfig(checkpoint=Path("/tmp/policy.pt"), n_trials=np.int32(40))
    recovery.validate()
    assert recovery.checkpoint == "/tmp/policy.pt" and type(recovery.n_trials) is int
    config.ddpg.lr_actor = torch.ones(3, 3)
    with pytest.raises(ValueError, match="ddpg.lr_actor=tensor") as error:
        config.validate()
    assert "\n" not in str(error.value)


def test_what_the_checks_must_not_refuse(shipped, two_agents):
    """Seeds offset from a config's (``seed + 7919 k``) pass 2**63; ``min_steps=0`` lets a
    trial stop at once; numpy and tensor numbers are numbers; a shared world's loss reads
    ``task_theta`` too (its trials must hold it)."""
    import numpy as np

    actor, model = shipped
    held, _ = two_agents
    loss = InverseRationalLoss(model, censored_action_model(actor, model), n_agents=2)
    fit_theta(loss, held, max_iter=1, n_screen=2, n_starts=1, seed=2**63 + 1000)
    assert Firefly2DModel(min_steps=0).min_steps == 0
    stopped = Firefly2DModel(stop_threshold=np.float32(0.2), target_angle=torch.tensor(0.5))
    assert stopped.stop_threshold == pytest.approx(0.2) and stopped.target_angle == 0.5
    shared = InverseRationalLoss(model, censored_action_model(actor, model), world="shared")
    assert shared.in_keys == ["state", "action", "target", "mask", "task_theta"]
    assert make_actor(model, np.array([8, 8])) is not None


@pytest.mark.parametrize(
    "noise, lapse, message",
    [
        (torch.full((3, 2), 0.1), 0.0, r"motor_noise: expected one value per agent, .*\[3, 2\]"),
        (0.1, torch.full((3, 1), 0.05), r"lapse: expected one value per agent, .*\[3, 1\]"),
    ],
)
def test_noise_or_lapse_per_trial_instead_of_per_agent_is_refused(shipped, noise, lapse, message):
    """With as many trials as agents, ``[n_agents, da]`` would broadcast over trials silently."""
    actor, model = shipped
    theta = model.theta_space.default().expand(3, -1)
    policy = motor_noise_policy(actor, model.action_spec, noise, lapse)
    with pytest.raises(ValueError, match=message):
        simulate_agents(model, policy, theta, 3, seed=0)
    each = motor_noise_policy(actor, model.action_spec, torch.full((3, 1, 2), 0.1), lapse=0.0)
    assert simulate_agents(model, each, theta, 3, seed=0)["mask"].any()


@pytest.mark.parametrize("maker", [make_actor, make_critic])
def test_the_ddpg_networks_refuse_a_task_of_discrete_actions(maker):
    """The 1D task's Categorical spec has no action dimension: an IndexError deep in MLP."""
    with pytest.raises(TypeError, match=rf"model: {maker.__name__} needs continuous actions"):
        maker(Firefly1DModel())


@pytest.mark.parametrize(
    "spec",
    [OneHot(3), Bounded(-1.0, 1.0, shape=()), Bounded(-1.0, 1.0, shape=(2, 2))],
    ids=["one-hot", "scalar", "matrix"],
)
def test_a_task_of_actions_neither_an_index_nor_a_vector_is_refused_at_every_entry(
    spec, tmp_path, two_agents
):
    """A one-hot spec failed inside the rollout ('CategoricalBox' has no 'low'), a matrix of
    actions with a reshape error; the loss's network probe and the data read the two kinds
    by different tests of the spec."""
    model = Firefly1DModel()
    model.action_spec = spec
    message = r"model\.action_spec: expected Categorical\(n\) .* or a floating-point spec of sh"
    path = tmp_path / "agent.csv"
    path.write_text("trial,time,x\n0,0.0,0.0\n")
    entries = [
        lambda: TaskEnv(model, batch_size=[2], seed=0),
        lambda: InverseRationalLoss(model, torch.nn.Identity()),  # refused before its network
        lambda: validate_trials(two_agents[0], model),
        lambda: read_trials(path, model),
    ]
    for entry in entries:
        with pytest.raises(ValueError, match=message):
            entry()


@pytest.mark.parametrize(
    "transform, message",
    [
        (lambda m: BeliefReward(m), r"BeliefReward: the env has no belief to score; expected EKF"),
        (lambda m: EKFBelief(m, theta_key="nope"), r"EKFBelief: the env has no 'nope' to filter"),
    ],
)
def test_a_belief_transform_missing_what_it_reads_names_it(transform, message):
    """Both failed inside the rollout with a bare KeyError of TensorDict's."""
    model = Firefly2DModel()
    env = TransformedEnv(Firefly2DEnv(model=model, batch_size=[2]), transform(model))
    with pytest.raises(KeyError, match=message):
        env.rollout(2)
    with pytest.raises(KeyError, match=message):
        _ = env.observation_spec  # and checking the specs, before any step


def test_unseeded_envs_draw_their_own_worlds_and_torch_manual_seed_repeats_them():
    """``seed=None`` was seed 0: every unseeded env (each worker of a SerialEnv) drew the same
    θ and targets, whatever torch.manual_seed said."""
    with torch.random.fork_rng():
        torch.manual_seed(0)
        first, second = (Firefly2DEnv(batch_size=[4]).reset() for _ in range(2))
        torch.manual_seed(0)
        again = Firefly2DEnv(batch_size=[4]).reset()
    assert not torch.equal(first["theta"], second["theta"])
    assert not torch.equal(first["target"], second["target"])
    assert torch.equal(first["theta"], again["theta"])
    assert torch.equal(first["target"], again["target"])


def test_an_env_moved_to_its_own_device_keeps_its_stream():
    """``env.to`` makes a new generator only when the device changes: a move to where the env
    already draws (here the CPU, from no device named) leaves its seeded draws as they were."""

    def rollout(move: bool):
        torch.manual_seed(0)  # the random actions
        env = Firefly2DEnv(batch_size=[3], seed=4, theta=Firefly2DModel().theta_space.default())
        return (env.to("cpu") if move else env).rollout(6, break_when_any_done=False)

    with torch.random.fork_rng():
        moved, kept = rollout(True), rollout(False)
    assert torch.equal(moved["next", "state"], kept["next", "state"])
    assert torch.equal(moved["target"], kept["target"])
