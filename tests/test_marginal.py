"""The marginal likelihood (agent's observations integrated out) against brute-force Monte Carlo."""

import math

import pytest
import torch
from torchrl.modules import MLP

from irc_torchrl.envs.belief import ekf_step
from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.modules.likelihood import CensoredGaussianActionModel
from irc_torchrl.objectives.marginal import marginal_filter, particle_log_likelihood

MODEL = Firefly2DModel()
SPACE = MODEL.theta_space
T = 10


class _Policy(torch.nn.Module):
    """A smooth stand-in actor: steers by the believed target (features 0-1) and damps the
    believed velocities (features 5-6), so its actions reveal the agent's belief; a larger
    ``sharpness`` makes it switch more abruptly with the belief."""

    def __init__(self, sharpness: float = 1.0):
        super().__init__()
        self.sharpness = sharpness
        torch.manual_seed(0)
        self.mlp = MLP(in_features=23, out_features=2, num_cells=[16]).double()
        with torch.no_grad():
            for p in self.mlp.parameters():
                p.mul_(0.3)

    def forward(self, features):
        ahead, aside, v, w = (features[..., i] for i in (0, 1, 5, 6))
        drive = torch.stack([2.5 * ahead + 0.6 - 0.8 * v, 3.0 * aside - 0.8 * w], -1)
        return torch.tanh(self.sharpness * drive + self.mlp(features))


def _simulate(
    theta, motor, n, seed, sharpness=1.0, lapse=0.0, world=None, model=MODEL, policy=None
):
    """Trials of an agent running its EKF under ``theta`` on noisy observations of a world
    run by ``world`` (default: ``theta``), acting by ``policy`` (default: the stand-in);
    returns states, actions."""
    g = torch.Generator().manual_seed(seed)
    actor = _Policy(sharpness) if policy is None else policy
    action_model = CensoredGaussianActionModel(actor, -torch.ones(2), torch.ones(2), lapse=lapse)
    theta = theta.expand(n, -1)
    world = theta if world is None else world.expand(n, -1)
    state, target = model.initial_state(world, g)
    mean, cov = model.initial_belief(state, target, theta)
    states, actions = [], []
    for t in range(T):
        step = torch.full((n, 1), t)
        features = model.belief_features(mean, cov, target, step, theta)
        noise = motor * torch.randn(n, 2, generator=g, dtype=torch.float64)
        action = (action_model.actor(features) + noise).clamp(-1, 1)
        states.append(state)
        actions.append(action)
        nxt = model.transition(state, action, world)
        std = model.process_cov(state, action, world).diagonal(dim1=-2, dim2=-1).sqrt()
        state = nxt + std * torch.randn(n, 5, generator=g, dtype=torch.float64)
        o_std = model.observation_cov(state, world).diagonal(dim1=-2, dim2=-1).sqrt()
        observation = model.observe(state, world) + o_std * torch.randn(
            n, 2, generator=g, dtype=torch.float64
        )
        mean, cov = ekf_step(model, mean, cov, action, observation, theta)
    return action_model, torch.stack(states, 1), torch.stack(actions, 1), target


def _monte_carlo(
    action_model, theta, nuisance, state, action, target, samples, seed, world=None, model=MODEL
):
    """``log E_v[Π_t p(a_t | z_t(v))]`` over the agent's observation noise ``v``, which the
    world run by ``world`` (default: ``theta``) draws."""
    g = torch.Generator().manual_seed(seed)
    n = state.shape[0]
    rep = lambda x: x.repeat_interleave(samples, 0)  # noqa: E731
    theta_r, world_r, state_r, action_r, target_r = (
        rep(theta.expand(n, -1)),
        rep((theta if world is None else world).expand(n, -1)),
        rep(state),
        rep(action),
        rep(target),
    )
    mean, cov = model.initial_belief(state_r[:, 0], target_r, theta_r)
    total = torch.zeros(n * samples, dtype=torch.float64)
    for t in range(T):
        features = model.belief_features(
            mean, cov, target_r, torch.full((len(mean), 1), t), theta_r
        )
        scored = model.scored_actions(action_r[:, t], torch.full((len(mean), 1), t))
        total += action_model.log_prob(features, action_r[:, t], rep(nuisance), scored)
        if t + 1 < T:
            nxt = state_r[:, t + 1]
            o_std = model.observation_cov(nxt, world_r).diagonal(dim1=-2, dim2=-1).sqrt()
            noise = o_std * torch.randn(len(mean), 2, generator=g, dtype=torch.float64)
            observation = model.observe(nxt, world_r) + noise
            mean, cov = ekf_step(model, mean, cov, action_r[:, t], observation, theta_r)
    total = total.view(n, samples)
    return total.logsumexp(-1) - math.log(samples)


def _stand_in_trials(obs_noise, n=6, seed=1, **simulate):
    """``n`` trials of the stand-in agent (motor noise 0.15) with its θ and motor nuisance."""
    theta = SPACE.from_dict(
        {"obs_sigma_v": obs_noise, "obs_sigma_w": obs_noise, "sigma_v": 0.1, "sigma_w": 0.1}
    ).double()
    action_model, state, action, target = _simulate(theta, 0.15, n=n, seed=seed, **simulate)
    nuisance = torch.full((n, 2), math.log(0.15), dtype=torch.float64)
    return action_model, theta, nuisance, state, action, target


@pytest.mark.parametrize(
    "obs_noise, lapse, moments",
    [
        (0.3, 0.0, "cubature"),
        (0.8, 0.0, "cubature"),
        (0.8, 1e-3, "cubature"),
        (0.3, 0.0, "linearised"),
    ],
)
def test_marginal_likelihood_matches_monte_carlo(obs_noise, lapse, moments):
    """The outer filter's likelihood is within 0.1 nats (per 10-step trial) of brute force
    (measured ≤ 0.01); the hard E-step is much further off (it ignores the spread of the
    agent's beliefs)."""
    action_model, theta, nuisance, state, action, target = _stand_in_trials(obs_noise, lapse=lapse)
    theta_b = theta.expand(6, -1)
    logp = marginal_filter(
        MODEL, action_model, theta_b, nuisance, state, action, target, theta_b, moments=moments
    )[0].sum(-1)
    mc = _monte_carlo(action_model, theta, nuisance, state, action, target, 20000, seed=2)
    # the hard E-step: the same filter with the outer covariance held at zero
    map_logp = torch.zeros(6, dtype=torch.float64)
    mean, cov = MODEL.initial_belief(state[:, 0], target, theta_b)
    for t in range(T):
        features = MODEL.belief_features(mean, cov, target, torch.full((6, 1), t), theta_b)
        map_logp += action_model.log_prob(features, action[:, t], nuisance)
        if t + 1 < T:
            obs = MODEL.observe(state[:, t + 1], theta_b)
            mean, cov = ekf_step(MODEL, mean, cov, action[:, t], obs, theta_b)
    assert (logp - mc).abs().max() < 0.1, logp - mc
    assert (map_logp - mc).abs().mean() > 3 * (logp - mc).abs().mean()


class _ScaledFlow(Firefly2DModel):
    """The 2D task with its optic flow scaled by 1 + goal radius: an observation that
    depends on θ (through a parameter the stand-in actor does not read)."""

    def _scale(self, theta):
        return 1 + self.parameter(theta, "goal_radius")

    def observe(self, state, theta):
        return self._scale(theta) * super().observe(state, theta)

    def observation_jacobian(self, state, theta):
        return self._scale(theta).unsqueeze(-1) * super().observation_jacobian(state, theta)


def test_the_world_makes_the_observation_the_agent_predicts_under_its_own_theta():
    """The agent (goal radius 0.25) expects flow scaled by 1.25 in a world (0.45) that scales
    it by 1.45. The outer filter, the particle filter and the hard E-step take the world's
    observation and the agent's prediction of it: within 0.2 nats per 10-step trial of brute
    force (measured 0.04 and 0.09, two brute-force seeds 0.04 apart; with the agent's θ for
    both, 0.8 nats off)."""
    model = _ScaledFlow()
    noise = {"obs_sigma_v": 0.3, "obs_sigma_w": 0.3}
    agent = SPACE.from_dict({"goal_radius": 0.25, **noise}).double()
    world = SPACE.from_dict({"goal_radius": 0.45, **noise}).double()
    action_model, state, action, target = _simulate(
        agent, 0.15, n=6, seed=4, world=world, model=model
    )
    nuisance = torch.full((6, 2), math.log(0.15), dtype=torch.float64)
    mc = _monte_carlo(
        action_model, agent, nuisance, state, action, target, 20000, 2, world=world, model=model
    )
    theta_b, world_b = agent.expand(6, -1), world.expand(6, -1)
    recorded = (model, action_model, theta_b, nuisance, state, action, target, world_b)
    outer = marginal_filter(*recorded)[0].sum(-1)
    particles = particle_log_likelihood(
        *recorded, n_particles=2000, generator=torch.Generator().manual_seed(0)
    )[0]
    assert (outer - mc).abs().max() < 0.2, outer - mc
    assert (particles - mc).abs().max() < 0.2, particles - mc
    # the hard E-step's agent sees the world's noiseless observation of each recorded state
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    loss = InverseRationalLoss(model, action_model, method="map")
    mean, _ = loss.beliefs(*(x.unsqueeze(0) for x in (theta_b, state, action, target, world_b)))
    expected, cov = model.initial_belief(state[:, 0], target, theta_b)
    for t in range(T - 1):
        seen = model.observe(state[:, t + 1], world_b)
        expected, cov = ekf_step(model, expected, cov, action[:, t], seen, theta_b)
    torch.testing.assert_close(mean[0, :, -1], expected)


def test_cubature_follows_a_sharply_switching_policy_better_than_the_tangent():
    """Where the policy bends within the spread of the agent's belief, the cubature rule's
    likelihood is nearer brute force than the linearisation's (measured mean error 0.017
    against 0.051 nats per trial)."""
    action_model, theta, nuisance, state, action, target = _stand_in_trials(0.3, sharpness=6.0)
    theta_b = theta.expand(6, -1)
    mc = _monte_carlo(action_model, theta, nuisance, state, action, target, 20000, seed=2)
    error = {
        rule: (
            marginal_filter(
                MODEL, action_model, theta_b, nuisance, state, action, target, theta_b,
                moments=rule,
            )[0].sum(-1) - mc
        ).abs().mean()
        for rule in ("cubature", "linearised")
    }  # fmt: skip
    assert error["cubature"] < 0.6 * error["linearised"], error


def _trials(n_agents, n_trials, theta, motor, seed):
    """Held trials ``[n_agents, n_trials, T]`` of the stand-in agent (every step recorded)."""
    rows = [_simulate(theta[i : i + 1], motor, n_trials, seed + i) for i in range(n_agents)]
    action_model = rows[0][0]
    stack = lambda k: torch.stack([r[k] for r in rows])  # noqa: E731
    from tensordict import TensorDict

    trials = TensorDict(
        {
            "state": stack(1),
            "action": stack(2),
            "target": stack(3).unsqueeze(2).expand(-1, -1, T, -1),
            "mask": torch.ones(n_agents, n_trials, T, dtype=torch.bool),
            "task_theta": theta.unsqueeze(1).unsqueeze(2).expand(-1, n_trials, T, -1),
        },
        batch_size=[n_agents, n_trials, T],
    )
    return action_model, trials


@pytest.mark.parametrize("components, fit_lapse", [(1, False), (16, False), (1, True)])
def test_marginal_loss_gradient_matches_finite_differences(components, fit_lapse):
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.6, "sigma_v": 0.3}).double().unsqueeze(0)
    action_model, trials = _trials(1, 4, theta, 0.15, seed=3)
    if fit_lapse:  # the lapse rate's coordinate too, where it weighs each action's update
        action_model = CensoredGaussianActionModel(
            action_model.actor, -torch.ones(2), torch.ones(2), 0.15, lapse=0.05, fit_lapse=True
        )
    loss = InverseRationalLoss(MODEL, action_model, method="marginal", components=components)
    with torch.no_grad():
        loss.theta_free.add_(0.1 * torch.randn(loss.theta_free.shape, dtype=torch.float64))
    params = torch.cat([loss.theta_free, loss.nuisance], -1).detach().requires_grad_(True)
    k = loss.theta_free.shape[1]

    def nll(p):
        return -loss.log_likelihood(loss.theta(p[:, :k]), p[:, k:], trials).sum()

    (grad,) = torch.autograd.grad(nll(params), params)
    eps = 1e-6
    for j in range(params.shape[1]):
        e = torch.zeros_like(params)
        e[0, j] = eps
        fd = (nll(params + e) - nll(params - e)) / (2 * eps)
        torch.testing.assert_close(grad[0, j], fd.detach(), rtol=1e-5, atol=1e-6)


def test_marginal_recovers_the_agents_belief_better_than_the_hard_e_step():
    """Under the true θ, the marginal posterior mean of the agent's believed velocity tracks
    the belief the agent really held more closely than the hard E-step's plug-in belief."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.8, "sigma_v": 0.5, "obs_sigma_w": 0.6}).double()
    g = torch.Generator().manual_seed(5)
    action_model = CensoredGaussianActionModel(_Policy(), -torch.ones(2), torch.ones(2))
    n = 200
    th = theta.expand(n, -1)
    state, target = MODEL.initial_state(th, g)
    mean, cov = MODEL.initial_belief(state, target, th)
    states, actions, beliefs = [], [], []
    for t in range(T):
        features = MODEL.belief_features(mean, cov, target, torch.full((n, 1), t), th)
        noise = 0.05 * torch.randn(n, 2, generator=g, dtype=torch.float64)
        action = (action_model.actor(features) + noise).clamp(-1, 1)
        states.append(state), actions.append(action), beliefs.append(mean)
        std = MODEL.process_cov(state, action, th).diagonal(dim1=-2, dim2=-1).sqrt()
        state = MODEL.transition(state, action, th) + std * torch.randn(
            n, 5, generator=g, dtype=torch.float64
        )
        o_std = MODEL.observation_cov(state, th).diagonal(dim1=-2, dim2=-1).sqrt()
        obs = MODEL.observe(state, th) + o_std * torch.randn(n, 2, generator=g, dtype=torch.float64)
        mean, cov = ekf_step(MODEL, mean, cov, action, obs, th)
    from tensordict import TensorDict

    trials = TensorDict(
        {
            "state": torch.stack(states, 1)[None],
            "action": torch.stack(actions, 1)[None],
            "target": target[None, :, None].expand(1, n, T, 2),
            "mask": torch.ones(1, n, T, dtype=torch.bool),
            "task_theta": th[None, :, None].expand(1, n, T, -1),
        },
        batch_size=[1, n, T],
    )
    truth = torch.stack(beliefs, 1)
    errors = {}
    for method, components in (("map", 1), ("marginal", 1), ("marginal", 16)):
        loss = InverseRationalLoss(MODEL, action_model, method=method, components=components)
        nuisance = torch.full((1, 2), math.log(0.05), dtype=torch.float64)
        rec = loss.recovered_beliefs(theta[None], nuisance, trials)["belief", "mean"][0]
        errors[method, components] = (rec - truth)[:, 1:].pow(2).mean().sqrt()
    # measured: 0.0753 (one Gaussian and sixteen alike) vs 0.1012
    assert errors["marginal", 1] < 0.85 * errors["map", 1], errors
    assert errors["marginal", 16] < 0.85 * errors["map", 1], errors


def test_unknown_method_or_moment_rule_and_a_discrete_action_model_are_refused():
    from irc_torchrl.modules.likelihood import BoltzmannActionModel
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    action_model = CensoredGaussianActionModel(_Policy(), -torch.ones(2), torch.ones(2))
    with pytest.raises(ValueError, match="method: expected one of"):
        InverseRationalLoss(MODEL, action_model, method="laplace")
    with pytest.raises(ValueError, match="moments: expected one of"):
        InverseRationalLoss(MODEL, action_model, method="marginal", moments="unscented")
    theta = SPACE.default().double().expand(1, -1)
    zeros = torch.zeros(1, T, 5, dtype=torch.float64)
    with pytest.raises(ValueError, match="moments: expected one of"):
        marginal_filter(
            MODEL, action_model, theta, torch.zeros(1, 2), zeros, zeros[..., :2],
            torch.ones(1, 2), theta, moments="unscented",
        )  # fmt: skip
    with pytest.raises(ValueError, match="'marginal' needs a continuous action model"):
        InverseRationalLoss(MODEL, BoltzmannActionModel(torch.nn.Linear(23, 3)), method="marginal")
    with pytest.raises(ValueError, match="components: expected 1 or more than the belief's 5"):
        InverseRationalLoss(MODEL, action_model, method="marginal", components=4)
    with pytest.raises(ValueError, match="final_steps: expected an integer ≥ 1"):
        InverseRationalLoss(MODEL, action_model, method="marginal", components=16, final_steps=0)


def test_the_mixture_rescores_only_each_trials_last_steps():
    """Split ``final_steps`` before each trial's end, the mixture leaves the earlier steps'
    scores as the single Gaussian gives them (to round-off), changes the later ones, and
    scores nothing past a trial's end, whatever the padding holds; trials too short to split
    late split after their first step."""
    action_model, theta, nuisance, state, action, target = _stand_in_trials(0.8, sharpness=6.0)
    theta_b = theta.expand(6, -1)
    length = torch.tensor([10, 7, 3, 1, 9, 5])
    mask = torch.arange(T) < length.unsqueeze(-1)
    padded = state.masked_fill(~mask.unsqueeze(-1), torch.nan)

    def per_step(components):
        return marginal_filter(
            MODEL, action_model, theta_b, nuisance, padded, action, target, theta_b, mask,
            components=components, final_steps=4,
        )  # fmt: skip

    single, mixture = per_step(1), per_step(32)
    split = torch.minimum(length, (length - 4).clamp(1)).unsqueeze(-1)
    early = torch.arange(T) < split
    for one, many in zip(single, mixture, strict=True):
        assert torch.isfinite(many).all()
        torch.testing.assert_close(many[early], one[early], rtol=0, atol=1e-12)
    late = mask & ~early
    assert ((mixture[0] - single[0]).abs()[late] > 1e-11).all()
    assert (mixture[0][~mask] == 0).all()
    # the drawn actions' scores (Fisher scoring's curvature) come from the mixture's moments
    drawn = marginal_filter(
        MODEL, action_model, theta_b, nuisance, padded, action, target, theta_b, mask,
        generator=torch.Generator().manual_seed(0), components=32,
    )[4]  # fmt: skip
    assert torch.isfinite(drawn).all() and (drawn[~mask] == 0).all() and (drawn[mask] != 0).all()


@pytest.mark.parametrize("components", [1, 32])
def test_the_likelihood_alone_equals_the_likelihood_beside_the_beliefs(components):
    """``beliefs=False`` (what a fit runs) skips gathering the beliefs, nothing else: the same
    per-step scores and drawn scores, bit for bit, with and without a mixture."""
    action_model, theta, nuisance, state, action, target = _stand_in_trials(0.8, sharpness=6.0)
    theta_b = theta.expand(6, -1)
    mask = torch.arange(T) < torch.tensor([10, 7, 3, 1, 9, 5]).unsqueeze(-1)

    def run(beliefs):
        return marginal_filter(
            MODEL, action_model, theta_b, nuisance, state, action, target, theta_b, mask,
            generator=torch.Generator().manual_seed(0), components=components, beliefs=beliefs,
        )  # fmt: skip

    full, alone = run(True), run(False)
    assert alone[1:4] == (None, None, None)
    assert all(x.shape == (6, T) + x.shape[2:] for x in full)
    assert torch.equal(alone[0], full[0]) and torch.equal(alone[4], full[4])


def test_a_stop_is_scored_by_its_forward_control_only():
    step = torch.tensor([[5], [1], [5]])
    action = torch.tensor([[0.05, 0.9], [0.05, 0.9], [0.5, 0.9]])
    # a stop (a_v under the threshold once stopping is allowed) leaves a_w unscored
    expected = torch.tensor([[True, False], [True, True], [True, True]])
    assert torch.equal(MODEL.scored_actions(action, step), expected)


@pytest.mark.parametrize("method", ["map", "marginal"])
def test_the_angular_control_of_a_stop_does_not_change_the_likelihood(method):
    """a_w on a stop step moves nothing and is not scored; on any other step it is."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.default().double().unsqueeze(0)
    action_model, trials = _trials(1, 3, theta, 0.15, seed=4)
    loss = InverseRationalLoss(MODEL, action_model, method=method)

    def log_likelihood(action):
        data = trials.clone()
        data["action"] = action
        return loss.log_likelihood(theta, loss.nuisance, data, per_trial=True)[0, 0]

    action = trials["action"].clone()
    action[0, 0, T - 1] = torch.tensor([-1.0, 0.8], dtype=action.dtype)  # the last step stops
    base = log_likelihood(action)
    turned = action.clone()
    turned[0, 0, T - 1, 1] = -0.8
    torch.testing.assert_close(log_likelihood(turned), base, rtol=0, atol=1e-12)
    going = action.clone()
    going[0, 0, T - 2] = torch.tensor([0.5, 0.8], dtype=action.dtype)  # the step before goes on
    other = going.clone()
    other[0, 0, T - 2, 1] = -0.8
    assert (log_likelihood(other) - log_likelihood(going)).abs() > 1e-3


def _moved(trials, angle: float, shift: tuple[float, float]):
    """The same trials recorded in an arena frame: turned by ``angle``, moved by ``shift``."""
    c, s = math.cos(angle), math.sin(angle)
    turn = torch.tensor([[c, s], [-s, c]], dtype=torch.float64)  # row vectors: p @ turn = R p
    moved = trials.clone()
    state = trials["state"].clone()
    state[..., :2] = state[..., :2] @ turn + torch.tensor(shift, dtype=torch.float64)
    state[..., 2] += angle
    moved["state"] = state
    moved["target"] = trials["target"] @ turn + torch.tensor(shift, dtype=torch.float64)
    return moved


@pytest.mark.parametrize("method, atol", [("map", 1e-9), ("marginal", 1e-4)])  # measured 3e-6
def test_the_likelihood_does_not_depend_on_the_arena_frame(method, atol):
    """Trials need not start at the origin facing +x: the agent's belief starts at the recorded
    pose and its policy reads the target egocentrically. The hard E-step is invariant to
    round-off; the cubature rule's sigma points turn with the frame only approximately."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.6, "obs_sigma_w": 0.5}).double().unsqueeze(0)
    action_model, trials = _trials(1, 8, theta, 0.1, seed=6)
    loss = InverseRationalLoss(MODEL, action_model, method=method)
    per_trial = [
        loss.log_likelihood(theta, loss.nuisance, data, per_trial=True)
        for data in (trials, _moved(trials, 2.9, (5.0, -3.0)))
    ]
    torch.testing.assert_close(per_trial[1], per_trial[0], rtol=0, atol=atol)
    # the frame matters to nothing else: a wrong target does change the likelihood
    wrong = trials.clone()
    wrong["target"] = trials["target"] + 0.3
    shifted = loss.log_likelihood(theta, loss.nuisance, wrong, per_trial=True)
    assert (shifted - per_trial[0]).abs().max() > 10 * atol


@pytest.mark.parametrize("obs_noise", [0.3, 0.8])
def test_particle_likelihood_matches_monte_carlo(obs_noise):
    """The particle filter estimates the same likelihood as brute force, within 0.1 nats per
    10-step trial with 2000 particles (measured ≤ 0.025), and the same seed gives the same
    numbers."""
    action_model, theta, nuisance, state, action, target = _stand_in_trials(obs_noise)
    theta_b = theta.expand(len(state), -1)
    mc = _monte_carlo(action_model, theta, nuisance, state, action, target, 20000, seed=2)

    def particles(seed):
        return particle_log_likelihood(
            MODEL, action_model, theta_b, nuisance, state, action, target, theta_b,
            n_particles=2000, generator=torch.Generator().manual_seed(seed),
        )  # fmt: skip

    (estimate, ess), (again, _) = particles(0), particles(0)
    assert (estimate - mc).abs().max() < 0.1, estimate - mc
    assert torch.equal(estimate, again)
    assert (ess > 100).all()


def test_particle_likelihood_ignores_steps_after_a_trial_ends():
    """A trial masked after step 6 scores as the same trial cut at step 6."""
    action_model, theta, nuisance, state, action, target = _stand_in_trials(0.5, n=3)
    theta_b = theta.expand(3, -1)
    mask = torch.ones(3, T, dtype=torch.bool)
    mask[0, 6:] = False
    padded = state.clone()
    padded[0, 6:] = torch.nan  # nothing after the end may be read into the estimate
    full = particle_log_likelihood(
        MODEL, action_model, theta_b, nuisance, padded, action, target, theta_b, mask, 500
    )[0]
    cut = particle_log_likelihood(
        MODEL, action_model, theta_b[:1], nuisance[:1], state[:1, :6], action[:1, :6],
        target[:1], theta_b[:1], n_particles=500,
    )[0]  # fmt: skip
    assert torch.isfinite(full).all()
    torch.testing.assert_close(full[0], cut[0], rtol=0, atol=0.2)


def test_particle_likelihood_refuses_no_particles():
    action_model, theta, nuisance, state, action, target = _stand_in_trials(0.5, n=2)
    theta_b = theta.expand(2, -1)
    with pytest.raises(ValueError, match="n_particles"):
        particle_log_likelihood(
            MODEL, action_model, theta_b, nuisance, state, action, target, theta_b,
            n_particles=0,
        )  # fmt: skip


def test_the_loss_scores_transitions_beside_the_particle_likelihood_where_the_world_is_shared():
    from irc_torchrl.envs import Firefly1DModel
    from irc_torchrl.modules.factorised_q import FactorisedQ
    from irc_torchrl.modules.likelihood import BoltzmannActionModel
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.6, "sigma_v": 0.3}).double().unsqueeze(0)
    action_model, trials = _trials(1, 3, theta, 0.15, seed=3)
    nuisance = torch.full((1, 2), math.log(0.15), dtype=torch.float64)
    known, shared = (
        InverseRationalLoss(MODEL, action_model, world=world) for world in ("known", "shared")
    )
    actions_only, ess = known.particle_log_likelihood(theta, nuisance, trials, 300, seed=4)
    with_moves, _ = shared.particle_log_likelihood(theta, nuisance, trials, 300, seed=4)
    moves = shared.log_likelihood(theta, nuisance, trials, per_trial=True) - known.log_likelihood(
        theta, nuisance, trials, per_trial=True
    )
    assert ess.shape == (1, 3) and (moves.abs() > 1).all()
    torch.testing.assert_close(with_moves, actions_only + moves)
    # a discrete task's: nothing to filter its belief by (refused before reading anything)
    task = Firefly1DModel()
    q = FactorisedQ(task.belief_feature_dim, task.theta_space.dim, 3)
    discrete = InverseRationalLoss(task, BoltzmannActionModel(q))
    with pytest.raises(ValueError, match="continuous action model"):
        discrete.particle_log_likelihood(theta, nuisance, trials)


@pytest.mark.parametrize("method", ["marginal", "map"])
def test_a_shared_world_is_run_by_the_candidate_theta_not_the_recorded_one(method):
    """With ``world="shared"`` the agent's model is the world's: a candidate θ runs the world
    whose observation noise moves the agent's belief, so the recorded ``task_theta`` is not
    read; with the recorded one set to the candidate, the known world's likelihood differs
    from it by the transitions alone."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.6, "sigma_v": 0.3}).double().unsqueeze(0)
    action_model, trials = _trials(1, 3, theta, 0.15, seed=3)
    nuisance = torch.full((1, 2), math.log(0.15), dtype=torch.float64)
    candidate = SPACE.from_dict({"obs_sigma_v": 0.9, "sigma_v": 0.2}).double().unsqueeze(0)
    known, shared = (
        InverseRationalLoss(MODEL, action_model, world=world, method=method)
        for world in ("known", "shared")
    )
    elsewhere, as_candidate = trials.clone(), trials.clone()
    elsewhere["task_theta"] = (
        SPACE.from_dict({"obs_sigma_v": 0.2}).double().expand_as(trials["task_theta"])
    )
    as_candidate["task_theta"] = candidate.expand_as(trials["task_theta"])
    at = shared.log_likelihood(candidate, nuisance, trials, per_trial=True)
    torch.testing.assert_close(
        shared.log_likelihood(candidate, nuisance, elsewhere, per_trial=True), at
    )
    moves = shared.log_likelihood(
        candidate, nuisance, as_candidate, per_trial=True
    ) - known.log_likelihood(candidate, nuisance, as_candidate, per_trial=True)
    torch.testing.assert_close(
        at - moves, known.log_likelihood(candidate, nuisance, as_candidate, per_trial=True)
    )


@pytest.mark.parametrize("world", ["known", "shared"])
@pytest.mark.parametrize("method", ["marginal", "map"])
def test_nan_after_a_trials_end_changes_neither_the_loss_nor_its_gradient(method, world):
    """Steps after a trial's end may hold anything (``validate_trials`` reads only recorded
    steps); the filters run over them, so a NaN there must be kept from the value and from the
    gradient (0 × NaN), the recovered beliefs of recorded steps too."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.6, "sigma_v": 0.3}).double().unsqueeze(0)
    action_model, trials = _trials(1, 3, theta, 0.15, seed=3)
    trials["mask"][0, :2, 6:] = False
    padded = trials.clone()
    padded["state"][~padded["mask"]] = float("nan")
    padded["action"][~padded["mask"]] = float("nan")
    results = []
    for held in (trials, padded):
        loss = InverseRationalLoss(MODEL, action_model, world=world, method=method)
        out = loss(held)
        out["loss_nll"].backward()
        grads = (loss.theta_free.grad, loss.nuisance.grad)
        belief = loss.recovered_beliefs(loss.theta(), loss.nuisance, held)[held["mask"]]
        results.append((out["loss_nll"].detach(), *grads, belief["belief", "mean"].detach()))
    assert all(torch.isfinite(x).all() for x in results[1])
    torch.testing.assert_close(results[1], results[0], rtol=1e-12, atol=1e-12)


def _drop_a_w(trials):
    return trials.set("action", trials["action"][..., :1])


def _nan_recorded(trials):
    trials["action"][0, 0, 2, 0] = float("nan")
    return trials


def _outside(trials):
    trials["action"][0, 0, 2, 0] = 7.0
    return trials


@pytest.mark.parametrize(
    "damage, error, message",
    [
        (_drop_a_w, ValueError, r"field 'action' expected shape \[n_agents, n_trials, T, 2\]"),
        (_nan_recorded, ValueError, "field 'action' has NaN or inf at agent 0, trial 0, step 2"),
        (_outside, ValueError, "field 'action' at agent 0, trial 0, step 2 is \\[7.0"),
        (lambda t: t.set("mask", t["mask"].float()), TypeError, "'mask' expected dtype bool"),
        (lambda t: t.exclude("target"), KeyError, r"missing field\(s\) \['target'\]"),
    ],
)
def test_the_loss_refuses_malformed_trials_before_any_work(damage, error, message, monkeypatch):
    """``loss(trials)`` in a user's own loop checks the trials as ``fit_theta`` does: a
    malformed field is a one-line error, not a silently broadcast or wrong loss."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.default().double().unsqueeze(0)
    action_model, trials = _trials(1, 2, theta, 0.15, seed=3)
    loss = InverseRationalLoss(MODEL, action_model)

    def no_work(*args, **kwargs):
        raise AssertionError("the likelihood ran on malformed trials")

    monkeypatch.setattr(loss, "log_likelihood", no_work)
    with pytest.raises(error, match=message):
        loss(damage(trials.clone()))


def test_the_loss_reads_trials_under_the_keys_it_is_set_to():
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.default().double().unsqueeze(0)
    action_model, trials = _trials(1, 2, theta, 0.15, seed=3)
    loss = InverseRationalLoss(MODEL, action_model)
    renamed = InverseRationalLoss(MODEL, action_model)
    renamed.set_keys(state=("world", "state"), action="control")
    moved = trials.clone().rename_key_("action", "control")
    moved["world", "state"] = moved.pop("state")
    torch.testing.assert_close(renamed(moved)["loss_nll"], loss(trials)["loss_nll"])


def test_the_particle_check_tells_the_marginal_approximation_from_the_hard_e_step():
    """On the smooth stand-in the outer filter loses under 0.02 nats per trial against the
    particle filter (measured 0.003); the hard E-step loses 16 times more (asserted: 5)."""
    from irc_torchrl.algorithms.fit import particle_check
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.8, "obs_sigma_w": 0.8}).double().unsqueeze(0)
    action_model, trials = _trials(1, 6, theta, 0.15, seed=5)
    nuisance = torch.full((1, 2), math.log(0.15), dtype=torch.float64)
    gap = {
        method: particle_check(
            InverseRationalLoss(MODEL, action_model, method=method),
            trials,
            theta,
            nuisance,
            n_particles=2000,
        )  # fmt: skip
        for method in ("marginal", "map")
    }
    for method, check in gap.items():  # what the approximation loses: particle minus its own
        own = InverseRationalLoss(MODEL, action_model, method=method)
        expected = check["particle_log_likelihood"] - own.log_likelihood(theta, nuisance, trials)
        torch.testing.assert_close(check["approximation_gap"], expected.detach())
    per_trial = {m: float(c["approximation_gap"].abs()) / 6 for m, c in gap.items()}
    assert per_trial["marginal"] < 0.02, per_trial
    assert per_trial["map"] > 5 * per_trial["marginal"], per_trial
    assert gap["marginal"]["min_effective_particles"] > 100


def test_the_score_check_finds_the_marginal_likelihood_calibrated_and_the_hard_e_step_not():
    """At 40 stand-in agents' true θ (40 trials each), one Fisher-scoring step in standard
    deviations is N(0, 1) for a nearly exact likelihood: the outer filter's pooled rms 0.95
    (asserted 0.8-1.2), 4% beyond ±1.96 (asserted ≤ 10%), every parameter's mean within 0.32
    (asserted 0.5, three standard errors); the hard E-step's rms 5.0 (asserted > 2× the
    marginal's). The same seed gives the same numbers; no draws is refused."""
    from irc_torchrl.algorithms.fit import score_check
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.sample((40,), generator=torch.Generator().manual_seed(3)).double()
    action_model, trials = _trials(40, 40, theta, 0.15, seed=11)
    nuisance = torch.full((40, 2), math.log(0.15), dtype=torch.float64)
    z = {
        method: score_check(
            InverseRationalLoss(MODEL, action_model, n_agents=40, method=method),
            trials,
            theta,
            nuisance,
        )
        for method in ("marginal", "map")
    }
    rms = {method: float(x.pow(2).mean().sqrt()) for method, x in z.items()}
    assert 0.8 < rms["marginal"] < 1.2, rms
    assert float((z["marginal"].abs() > 1.96).double().mean()) <= 0.10
    assert z["marginal"].mean(0).abs().max() < 0.5, z["marginal"].mean(0)
    assert rms["map"] > 2 * rms["marginal"], rms
    loss = InverseRationalLoss(MODEL, action_model, n_agents=3, method="marginal")
    few = trials[:3, :5]
    again = [score_check(loss, few, theta[:3], nuisance[:3], seed=1) for _ in range(2)]
    assert torch.equal(*again)
    with pytest.raises(ValueError, match="draws: expected an integer ≥ 1"):
        score_check(loss, few, theta[:3], nuisance[:3], draws=0)


def test_actions_far_outside_the_predictive_leave_the_gradient_a_true_slope():
    """Random actions scored with a motor noise 100 times too small put innovations hundreds of
    standard deviations out; each moves the latent's mean at most ``_INNOVATION_GATE`` sd, so
    over 100 steps the likelihood stays smooth and its gradient agrees with finite differences
    (measured −3.261e8 both; ungated, autograd read 2.0e16 for g_v and the differences −8.4e13,
    changing with the step: the iterated updates had made the value chaotic)."""
    from irc_torchrl.algorithms.ensemble import load_ensemble_policy
    from irc_torchrl.envs.firefly2d import Firefly2DEnv
    from irc_torchrl.modules.actor_critic import censored_action_model

    actor, _, _ = load_ensemble_policy("firefly2d")
    model = Firefly2DModel(max_steps=100)
    theta = model.theta_space.default().unsqueeze(0)
    g = torch.Generator().manual_seed(0)
    env = Firefly2DEnv(model, batch_size=(1, 1), theta=theta, seed=0)
    td, states, actions = env.reset(), [], []
    for _ in range(100):
        forward, turn = (
            0.1 + 0.9 * torch.rand(1, 1, generator=g),
            2 * torch.rand(1, 1, generator=g) - 1,
        )
        td["action"] = torch.stack([forward, turn], -1)
        states.append(td["state"])
        actions.append(td["action"])
        td = env.step(td)["next"]
    state, action = (torch.stack(x, 2)[0].double() for x in (states, actions))
    target, theta = td["target"][0].double(), theta.double()
    action_model = censored_action_model(actor, model)
    nuisance = torch.full((1, 2), math.log(1e-3), dtype=torch.float64)

    def log_likelihood(th):
        logp = marginal_filter(
            model, action_model, th, nuisance, state, action, target, theta, beliefs=False
        )[0]
        return logp.sum()

    at = theta.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(log_likelihood(at), at)
    assert torch.isfinite(grad).all()
    j = model.theta_space.index("g_v")
    with torch.no_grad():
        for h in (1e-8, 1e-10):
            e = torch.zeros_like(theta)
            e[0, j] = h
            fd = (log_likelihood(theta + e) - log_likelihood(theta - e)) / (2 * h)
            assert float(fd) == pytest.approx(float(grad[0, j]), rel=0.01), (h, float(fd))


class _PersistentVelocity(Firefly2DModel):
    """The 2D task with velocities that persist (``v' = 0.6 v + g a``): the agent's believed
    velocity carries its earlier observations' noise on, as the outer covariance must."""

    def transition(self, state, action, theta):
        carried = torch.nn.functional.pad(0.6 * state[..., 3:], (3, 0))
        return super().transition(state, action, theta) + carried

    def transition_jacobian(self, state, action, theta):
        jac = super().transition_jacobian(state, action, theta)
        jac[..., 3, 3] += 0.6
        jac[..., 4, 4] += 0.6
        return jac


class _LinearPolicy(torch.nn.Module):
    """An actor linear in the believed velocities (features 5-6) and the time (feature 13)."""

    def forward(self, features):
        v, w, time = features[..., 5], features[..., 6], features[..., 13]
        return torch.stack([0.7 - 0.2 * v + time, 0.1 - 0.5 * w - 2 * time], -1)


def test_the_outer_filter_is_exact_where_the_actions_are_linear_gaussian_in_the_noise():
    """A linear actor on the believed velocities and time, velocities that persist, and an
    agent that takes its observations for less noisy than the world makes them: its velocity
    belief is linear in the world's observation noise, the actions jointly Gaussian, and their
    likelihood a closed form. Both moment rules give it within 1e-6 nats per trial (measured
    2e-9 and 2e-15), for trials cut short by the mask too; none stops or is clipped."""
    from torch.distributions import MultivariateNormal

    from irc_torchrl.objectives.marginal import MOMENT_RULES

    model, n, motor = _PersistentVelocity(), 4, 0.1
    noise = {"sigma_v": 0.4, "sigma_w": 0.3}
    agent = SPACE.from_dict({**noise, "obs_sigma_v": 0.3, "obs_sigma_w": 0.25}).double()
    world = SPACE.from_dict({**noise, "obs_sigma_v": 0.7, "obs_sigma_w": 0.5}).double()
    action_model, state, action, target = _simulate(
        agent, motor, n, 0, world=world, model=model, policy=_LinearPolicy()
    )
    assert action.abs().max() < 0.9 and action[..., 0].min() > model.stop_threshold
    theta_b, world_b = agent.expand(n, -1), world.expand(n, -1)

    def outputs(seen_noise):
        """The actor's outputs along the recorded trials, the agent seeing the world's
        observation of each next state plus ``seen_noise`` ``[n, T - 1, 2]``."""
        mean, cov = model.initial_belief(state[:, 0], target, theta_b)
        out = []
        for t in range(T):
            features = model.belief_features(mean, cov, target, torch.full((n, 1), t), theta_b)
            out.append(action_model.actor(features))
            if t + 1 < T:
                seen = model.observe(state[:, t + 1], world_b) + seen_noise[:, t]
                mean, cov = ekf_step(model, mean, cov, action[:, t], seen, theta_b)
        return torch.stack(out, 1)

    zero = torch.zeros(n, T - 1, 2, dtype=torch.float64)
    predicted = outputs(zero)
    jac = torch.autograd.functional.jacobian(outputs, zero, vectorize=True)  # [n, T, 2, n, T-1, 2]
    drawn = torch.randn(zero.shape, generator=torch.Generator().manual_seed(1), dtype=zero.dtype)
    linear = predicted + torch.einsum("itajsb,jsb->ita", jac, drawn)
    torch.testing.assert_close(outputs(drawn), linear, rtol=0, atol=1e-12)  # the premise
    world_var = model.observation_cov(state[:, 0], world_b).diagonal(dim1=-2, dim2=-1)
    length = torch.tensor([10, 7, 4, 10])
    exact = []
    for i, steps in enumerate(length.tolist()):
        m = jac[i, :steps, :, i].reshape(2 * steps, 2 * (T - 1))
        cov = m @ torch.diag(world_var[i].repeat(T - 1)) @ m.mT
        cov = cov + motor**2 * torch.eye(2 * steps, dtype=torch.float64)
        gaussian = MultivariateNormal(predicted[i, :steps].reshape(-1), cov)
        exact.append(gaussian.log_prob(action[i, :steps].reshape(-1)))
    mask = torch.arange(T) < length.unsqueeze(-1)
    padded = state.masked_fill(~mask.unsqueeze(-1), torch.nan)
    nuisance = torch.full((n, 2), math.log(motor), dtype=torch.float64)
    for moments in MOMENT_RULES:
        logp = marginal_filter(
            model, action_model, theta_b, nuisance, padded, action, target, world_b, mask,
            moments=moments,
        )[0]  # fmt: skip
        torch.testing.assert_close(logp.sum(-1), torch.stack(exact), rtol=0, atol=1e-6)


def test_a_gaussian_sum_weighs_its_components_by_bayes_rule():
    """Each component of the Gaussian sum is filtered on its own: the sum's per-step scores
    chain to ``log (1/M) Σ_m Π_t p_m(a_t | a_<t)``, and its recovered belief at every step is
    the components' mixture under their posterior weights (mean, the agent's covariance, and
    the outer covariance with the components' spread about the mean), to round-off."""
    from irc_torchrl.objectives.marginal import _cubature, _outer_pass, _Recorded

    action_model, theta, nuisance, state, action, target = _stand_in_trials(0.8, sharpness=6.0)
    n, m, start, ds = 6, 8, 5, 5
    theta_b = theta.expand(n, -1)
    recorded = _Recorded(
        MODEL, action_model, _cubature, theta_b, nuisance, state, action, target, theta_b,
        None, True,
    )  # fmt: skip
    # a mixture at step 5: the hard E-step's belief, its components spread about it at random
    mean, cov = MODEL.initial_belief(state[:, 0], target, theta_b)
    for t in range(start):
        seen = MODEL.observe(state[:, t + 1], theta_b)
        mean, cov = ekf_step(MODEL, mean, cov, action[:, t], seen, theta_b)
    g = torch.Generator().manual_seed(0)
    means = mean.unsqueeze(1) + 0.1 * torch.randn(n, m, ds, generator=g, dtype=torch.float64)
    root = 0.05 * torch.randn(n, m, ds, ds, generator=g, dtype=torch.float64)
    mixture = (means, cov.unsqueeze(1).expand(n, m, ds, ds), root @ root.mT)
    begin, count = torch.full((n,), start), torch.full((n,), T - start)
    together, _ = _outer_pass(recorded, begin, count, *mixture)
    rows = torch.arange(n).repeat_interleave(m)
    fields = ("theta", "nuisance", "state", "action", "target", "task_theta")
    alone = recorded._replace(**{f: getattr(recorded, f)[rows] for f in fields})
    apart, _ = _outer_pass(
        alone, begin[rows], count[rows], *(x.flatten(0, 1).unsqueeze(1) for x in mixture)
    )
    k = T - start
    logp, mean_m, cov_m, outer_m = (x.view(n, m, T, *x.shape[2:])[:, :, :k] for x in apart[:4])
    joint = logp.cumsum(-1)  # log Π_{s ≤ t} p_m(a_s | a_<s)
    torch.testing.assert_close(
        together[0][:, :k].cumsum(-1), joint.logsumexp(1) - math.log(m), rtol=0, atol=1e-10
    )
    weight = joint.softmax(1)[..., None]
    recovered = (weight * mean_m).sum(1)
    spread = (mean_m - recovered.unsqueeze(1)).unsqueeze(-1)
    weight = weight.unsqueeze(-1)
    torch.testing.assert_close(together[1][:, :k], recovered)
    torch.testing.assert_close(together[2][:, :k], (weight * cov_m).sum(1))
    torch.testing.assert_close(together[3][:, :k], (weight * (outer_m + spread @ spread.mT)).sum(1))


def test_the_gaussian_sum_has_the_mean_and_covariance_of_the_gaussian_it_splits():
    """The equally weighted components' means average to the latent's mean, and their spread
    about it plus the covariance each keeps is its covariance (to the factor's jitter), a
    rank-deficient one too; each keeps the agent's own covariance."""
    from irc_torchrl.objectives.marginal import _split

    g = torch.Generator().manual_seed(0)
    n, m, ds = 3, 16, 5
    mean = torch.randn(n, 1, ds, generator=g, dtype=torch.float64)
    root = torch.randn(n, 1, ds, ds, generator=g, dtype=torch.float64)
    root[0, 0, :, 2:] = 0  # rank 2: actions that pin the latent down along three directions
    outer = root @ root.mT
    cov = outer.flip(0) + torch.eye(ds, dtype=torch.float64)
    means, covs, kept = _split(mean, cov, outer, m)
    torch.testing.assert_close(means.mean(1), mean[:, 0], rtol=0, atol=1e-12)
    spread = means - mean
    between = spread.mT @ spread / m
    torch.testing.assert_close(between + kept[:, 0], outer[:, 0], rtol=0, atol=1e-9)
    assert torch.equal(kept, kept[:, :1].expand_as(kept))
    assert torch.equal(covs, cov.expand(n, m, ds, ds))


def test_where_the_world_observes_without_noise_the_marginal_estimator_is_the_hard_e_step():
    """With the world's observation noise at zero (its floor; read from the world's θ,
    ``senses="world"``) the recorded states fix the agent's belief: the marginal estimator's
    likelihood is the hard E-step's within 1e-4 nats per trial (measured 4e-6; 0.04-0.29
    apart at the agent's noise), and it recovers the same beliefs, the agent's own covariance
    and no uncertainty about the mean, trials cut short by the mask included."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.6, "sigma_v": 0.3}).double().unsqueeze(0)
    action_model, trials = _trials(1, 4, theta, 0.15, seed=3)
    quiet = SPACE.from_dict({"obs_sigma_v": 0.0, "obs_sigma_w": 0.0, "sigma_v": 0.3}).double()
    trials["task_theta"] = quiet.expand_as(trials["task_theta"]).clone()
    trials["mask"][0, 1, 6:] = False
    nuisance = torch.full((1, 2), math.log(0.15), dtype=torch.float64)
    per_trial, beliefs = {}, {}
    for method in ("map", "marginal"):
        loss = InverseRationalLoss(MODEL, action_model, senses="world", method=method)
        per_trial[method] = loss.log_likelihood(theta, nuisance, trials, per_trial=True)
        beliefs[method] = loss.recovered_beliefs(theta, nuisance, trials)[trials["mask"]]
    torch.testing.assert_close(per_trial["marginal"], per_trial["map"], rtol=0, atol=1e-4)
    exact, marginal = beliefs["map"]["belief"], beliefs["marginal"]["belief"]
    torch.testing.assert_close(marginal["mean"], exact["mean"], rtol=0, atol=1e-5)
    torch.testing.assert_close(marginal["cov"], exact["cov"], rtol=0, atol=1e-8)
    assert (exact["mean_cov"] == 0).all() and marginal["mean_cov"].abs().max() < 1e-6


@pytest.mark.parametrize("world", ["known", "shared"])
@pytest.mark.parametrize("method", ["map", "marginal"])
def test_each_agent_of_a_batch_is_scored_under_its_own_theta_and_nuisance(method, world):
    """Agents are independent rows: two agents with their own θ, motor noise and trials of
    different lengths score, and have their beliefs recovered, as each alone does; under
    each other's θ or nuisance they score otherwise."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = torch.cat(
        [
            SPACE.from_dict({"obs_sigma_v": 0.6, "sigma_v": 0.3}).double().unsqueeze(0),
            SPACE.from_dict({"obs_sigma_v": 0.3, "g_v": 1.4, "goal_radius": 0.25}).double()[None],
        ]
    )
    action_model, trials = _trials(2, 3, theta, 0.15, seed=3)
    trials["mask"][1, 0, 5:] = False
    nuisance = torch.tensor([[0.15, 0.2], [0.1, 0.25]], dtype=torch.float64).log()
    loss = InverseRationalLoss(MODEL, action_model, n_agents=2, world=world, method=method)
    both = loss.log_likelihood(theta, nuisance, trials, per_trial=True)
    recovered = loss.recovered_beliefs(theta, nuisance, trials)["belief", "mean"]
    one = InverseRationalLoss(MODEL, action_model, world=world, method=method)
    for i in range(2):
        agent = (theta[i : i + 1], nuisance[i : i + 1], trials[i : i + 1])
        torch.testing.assert_close(both[i], one.log_likelihood(*agent, per_trial=True)[0])
        alone = one.recovered_beliefs(*agent)["belief", "mean"][0]
        torch.testing.assert_close(recovered[i], alone)
    for other in ((theta.flip(0), nuisance), (theta, nuisance.flip(0))):
        assert (loss.log_likelihood(*other, trials, per_trial=True) - both).abs().min() > 1e-2


@pytest.mark.parametrize("method", ["map", "marginal"])
def test_in_a_shared_world_the_drawn_data_hold_drawn_transitions_too(method):
    """Fisher scoring's draws in a shared world include the next states: beside the drawn
    actions (the known world's, with the same seed) they add the log-density of next states
    drawn from ``N(f(s_t, a_t), Q)``, whose mean over the 27 transitions is
    ``Σ −½ (d + log det 2πQ)`` = 452 nats with sd ``√(27 d / 2)`` = 8.2; asserted within 4 sd
    (measured 466 and 462; draws without the transitions add 0)."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    theta = SPACE.from_dict({"obs_sigma_v": 0.6, "sigma_v": 0.3}).double().unsqueeze(0)
    action_model, trials = _trials(1, 3, theta, 0.15, seed=3)
    nuisance = torch.full((1, 2), math.log(0.15), dtype=torch.float64)
    drawn = {}
    for world in ("known", "shared"):
        loss = InverseRationalLoss(MODEL, action_model, world=world, method=method)
        generator = torch.Generator().manual_seed(0)
        drawn[world] = loss.log_likelihood_and_draws(theta, nuisance, trials, generator)[1]
    moves = drawn["shared"] - drawn["known"]
    state, action = trials["state"][0, :, :-1], trials["action"][0, :, :-1]
    cov = MODEL.process_cov(state, action, theta)
    d = MODEL.state_dim
    expected = -0.5 * (d + torch.logdet(2 * math.pi * cov)).sum(-1)
    sd = math.sqrt(d / 2 * cov.shape[0] * cov.shape[1])
    assert (moves.sum() - expected.sum()).abs() < 4 * sd, float(moves.sum())


def test_a_fixed_parameter_holds_its_value_and_the_free_ones_their_coordinates():
    """With ``theta_space.fix(g_v=1.3)`` the loss's θ holds g_v at 1.3 (not the task's default
    1.2) whatever the free coordinates, which set every other parameter, and the loss is the
    likelihood at that θ."""
    from irc_torchrl.objectives.inverse import InverseRationalLoss

    action_model, trials = _trials(1, 2, SPACE.default().double().unsqueeze(0), 0.15, seed=3)
    space = SPACE.fix(g_v=1.3)
    held = InverseRationalLoss(MODEL, action_model, theta_space=space)
    with torch.no_grad():
        held.theta_free.add_(0.3)
    theta = held.theta().detach()
    assert (theta[:, SPACE.index("g_v")] == 1.3).all()
    free = space.free_mask
    torch.testing.assert_close(SPACE.to_unconstrained(theta)[:, free], held.theta_free.detach())
    full = InverseRationalLoss(MODEL, action_model)
    at_theta = full.log_likelihood(theta, held.nuisance.detach(), trials)
    torch.testing.assert_close(held(trials)["loss_nll"].detach(), -at_theta.sum())
