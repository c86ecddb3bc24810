"""Action likelihood models: proper distributions, censoring at the bounds, gradients."""

import math

import pytest
import torch

from irc_torchrl.modules.likelihood import (
    LAPSE_MAX,
    BoltzmannActionModel,
    CensoredGaussianActionModel,
)


class Affine(torch.nn.Module):
    """A fixed actor: tanh of a linear map, like a bounded DDPG actor."""

    def __init__(self, weight):
        super().__init__()
        self.weight = torch.nn.Parameter(weight)

    def forward(self, features):
        return torch.tanh(features @ self.weight.to(features.dtype))


def _model(motor_noise=0.3, lapse=0.0, fit_lapse=False):
    weight = torch.tensor([[1.5, -0.5], [0.3, 2.0]], dtype=torch.float64)
    low, high = -torch.ones(2), torch.ones(2)
    return CensoredGaussianActionModel(
        Affine(weight), low, high, motor_noise, lapse=lapse, fit_lapse=fit_lapse
    )


@pytest.mark.parametrize("lapse, fit_lapse", [(0.0, False), (0.05, False), (0.05, True)])
def test_censored_gaussian_is_a_distribution_with_point_masses_at_the_bounds(lapse, fit_lapse):
    """Interior density integrates with the two tail masses to 1 (per dimension, grid 1e-4),
    with or without lapses, held or fitted (at its start)."""
    model = _model(lapse=lapse, fit_lapse=fit_lapse)
    features = torch.tensor([[0.4, 0.9]], dtype=torch.float64)
    nuisance = model.nuisance_init.double()
    grid = torch.linspace(-1 + 1e-4, 1 - 1e-4, 20001, dtype=torch.float64)
    mean = model.actor(features)[0]
    for dim in range(2):
        # the other dimension sits at its mean, where its density is 1 / (σ √(2π))
        action = torch.full((len(grid), 2), mean[1 - dim].item(), dtype=torch.float64)
        action[:, dim] = grid
        joint = model.log_prob(features.expand(len(grid), -1), action, nuisance).exp()
        peak = math.exp(-math.log(0.3) - 0.5 * math.log(2 * math.pi))
        other_density = (1 - lapse) * peak + lapse / 4  # the lapse's density: 1 / (2 × width 2)
        interior = torch.trapezoid(joint / other_density, grid)
        edge = action[:2].clone()
        edge[0, dim], edge[1, dim] = -1.0, 1.0
        masses = model.log_prob(features.expand(2, -1), edge, nuisance).exp() / other_density
        assert abs(interior.item() + masses.sum().item() - 1) < 1e-3


def test_a_clipped_action_scores_the_tail_probability():
    model = _model(motor_noise=0.2)
    features = torch.tensor([[0.5, 0.1]], dtype=torch.float64)
    nuisance = model.nuisance_init.double()
    mean = model.actor(features)[0]
    action = torch.tensor([[1.0, mean[1].item()]], dtype=torch.float64)
    expected = torch.special.log_ndtr((mean[0] - 1) / 0.2) + (
        -math.log(0.2) - 0.5 * math.log(2 * math.pi)
    )
    assert torch.allclose(model.log_prob(features, action, nuisance), expected.reshape(1))


def test_log_prob_is_differentiable_in_features_and_noise():
    model = _model()
    features = torch.randn(5, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    features.requires_grad_(True)
    nuisance = model.nuisance_init.double().clone().requires_grad_(True)
    action = torch.tensor([[-1.0, 0.2], [0.3, 1.0], [0.0, 0.0], [0.99, -0.99], [1.0, -1.0]])
    torch.autograd.gradcheck(
        lambda f, n: model.log_prob(f, action.double(), n), (features, nuisance)
    )


def test_a_fitted_lapse_rate_is_a_bounded_nuisance_scored_as_a_held_one():
    """The rate's coordinate is a logit scaled to (0, LAPSE_MAX): at its start the model
    scores every action as with that rate held, the rate moves the score smoothly
    (gradcheck), and a start outside (0, LAPSE_MAX) is refused."""
    held, fitted = _model(lapse=0.05), _model(lapse=0.05, fit_lapse=True)
    assert fitted.nuisance_names[-1] == "logit_lapse" and fitted.nuisance_bounded == (
        False,
        False,
        True,
    )
    features = torch.randn(5, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    action = torch.tensor([[-1.0, 0.2], [0.3, 1.0], [0.0, 0.0], [0.99, -0.99], [1.0, -1.0]])
    action = action.double()
    start = fitted.nuisance_init.double()
    torch.testing.assert_close(fitted.lapse_rate(start), torch.tensor(0.05, dtype=torch.float64))
    torch.testing.assert_close(
        fitted.log_prob(features, action, start),
        held.log_prob(features, action, held.nuisance_init.double()),
    )
    for u, rate in ((-40.0, 0.0), (40.0, LAPSE_MAX)):
        edge = torch.cat([start[:2], torch.tensor([u], dtype=torch.float64)])
        assert abs(fitted.lapse_rate(edge).item() - rate) < 1e-12
        assert torch.isfinite(fitted.log_prob(features, action, edge)).all()
    torch.autograd.gradcheck(
        lambda n: fitted.log_prob(features, action, n), (start.clone().requires_grad_(True),)
    )
    for bad in (0.0, LAPSE_MAX, 0.7):
        with pytest.raises(ValueError, match=r"lapse: expected the fitted rate's start in"):
            _model(lapse=bad, fit_lapse=True)


def test_boltzmann_probabilities_sum_to_one_and_sharpen_with_temperature():
    q = torch.nn.Linear(3, 3).double()
    model = BoltzmannActionModel(q, temperature=1.0)
    features = torch.randn(4, 3, dtype=torch.float64)
    actions = torch.arange(3).expand(4, 3)
    for log_tau in (0.0, -2.0):
        nuisance = torch.tensor([log_tau], dtype=torch.float64)
        logp = torch.stack(
            [model.log_prob(features, actions[:, a], nuisance) for a in range(3)], -1
        )
        assert torch.allclose(logp.exp().sum(-1), torch.ones(4, dtype=torch.float64))
    best = q(features).argmax(-1)
    cold = model.log_prob(features, best, torch.tensor([-4.0], dtype=torch.float64)).exp()
    warm = model.log_prob(features, best, torch.tensor([0.0], dtype=torch.float64)).exp()
    assert (cold >= warm).all()


def test_a_lapse_caps_what_an_unexplained_action_costs():
    """An action 3 units from the policy's output costs ~50 nats per dimension without a
    lapse; with lapse ε it costs at most -log(ε/4), and an action at the output loses only
    about ε."""
    features = torch.tensor([[0.4, 0.9]], dtype=torch.float64)
    plain, robust = _model(motor_noise=0.1), _model(motor_noise=0.1, lapse=1e-3)
    nuisance = plain.nuisance_init.double()
    mean = plain.actor(features)
    far = mean - 3 * mean.sign() * 0.3  # inside the bounds, 9 noise sd away
    assert plain.log_prob(features, far, nuisance) < -70
    cap = 2 * math.log(1e-3 / 4)
    assert robust.log_prob(features, far, nuisance) > cap - 1e-6
    gap = plain.log_prob(features, mean, nuisance) - robust.log_prob(features, mean, nuisance)
    assert 0 < gap < 2.1e-3


def test_a_lapse_keeps_an_unexplained_action_from_moving_the_belief():
    """The outer filter's update: a typical action moves the latent input as without a lapse,
    an action the prediction cannot explain leaves it (nearly) where it was; the covariance
    stays symmetric positive definite."""
    dz = 3
    torch.manual_seed(0)
    root = torch.randn(dz, dz, dtype=torch.float64)
    cov = 1e-3 * (root @ root.T) + 1e-4 * torch.eye(dz, dtype=torch.float64)
    jac = torch.randn(2, dz, dtype=torch.float64)
    mean = torch.tensor([0.1, -0.2], dtype=torch.float64)
    cross, cov_action = cov @ jac.T, jac @ cov @ jac.T
    nuisance = torch.full((2,), math.log(0.1), dtype=torch.float64)
    plain, robust = _model(), _model(lapse=1e-3)
    sd = (cov_action.diagonal() + 0.01).sqrt()  # the predictive sd: spread and motor noise
    typical, wild = mean + 0.5 * sd, mean + 8 * sd * torch.tensor([-1.0, 1.0])
    assert wild.abs().max() < 0.95  # inside the bounds
    moved = {}
    for name, model in (("plain", plain), ("robust", robust)):
        for kind, action in (("typical", typical), ("wild", wild)):
            _, shift, post, _ = model.assimilate(mean, cross, cov_action, cov, action, nuisance)
            assert torch.linalg.eigvalsh(post).min() > 0
            torch.testing.assert_close(post, post.T)
            moved[name, kind] = shift.norm()
    torch.testing.assert_close(
        moved["robust", "typical"], moved["plain", "typical"], rtol=0.02, atol=0
    )
    assert moved["robust", "wild"] < 0.05 * moved["plain", "wild"], moved


@pytest.mark.parametrize("sds_out", [3.0, 40.0, 6.6e3])
def test_an_action_clipped_far_in_the_tail_conditions_the_input_as_the_tail_says(sds_out):
    """A clipped action ``sds_out`` predictive sds beyond the predicted mean: the input's
    variance along the action shrinks by the truncated normal's factor 1 - λ(λ - α)
    (λ = φ(α)/Φ(-α); for large α, λ - α = 1/α - 2/α³ + ...), stays positive, and the log
    probability is the tail's. Thousands of sds out the direct exp(-α²/2 - log Φ(-α)) gave a
    factor past 1: a negative variance, then NaN."""
    dz, cov_y, noise = 2, 1e-6, 1e-10
    cov = cov_y * torch.eye(dz, dtype=torch.float64)
    cross = torch.zeros(dz, 2, dtype=torch.float64)
    cross[0, 0] = cov_y  # y_0 = z_0; y_1 does not depend on z
    cov_action = torch.diag(torch.tensor([cov_y, cov_y], dtype=torch.float64))
    nuisance = torch.full((2,), 0.5 * math.log(noise), dtype=torch.float64)
    alpha = torch.tensor(sds_out, dtype=torch.float64)
    std = math.sqrt(cov_y + noise)
    mean = torch.tensor([1.0 - sds_out * std, 0.0], dtype=torch.float64)
    action = torch.tensor([1.0, 0.0], dtype=torch.float64)
    logp, _, post, _ = _model().assimilate(mean, cross, cov_action, cov, action, nuisance)
    if sds_out < 8:
        tail_mass = 0.5 * math.erfc(sds_out / 2**0.5)
        mills = math.exp(-0.5 * sds_out**2) / math.sqrt(2 * math.pi) / tail_mass
    else:  # where doubles cannot hold Φ(-α) directly: the asymptotic series
        mills = sds_out + 1 / sds_out - 2 / sds_out**3 + 10 / sds_out**5 - 74 / sds_out**7
    factor = 1 - mills * (mills - sds_out)  # the variance left, as a fraction of Var(y)
    kept = cov_y - cov_y**2 / (cov_y + noise) * (1 - factor)
    torch.testing.assert_close(
        post[0, 0], torch.tensor(kept, dtype=torch.float64), rtol=1e-6, atol=0
    )
    assert post[0, 0] > 0 and torch.isfinite(logp)
    interior = -0.5 * math.log(2 * math.pi * (cov_y + noise))  # the second action, at its mean
    tail = torch.special.log_ndtr(-alpha)
    torch.testing.assert_close(logp, tail + interior, rtol=1e-9, atol=0)


def test_draws_for_fisher_scoring_lapse_and_carry_the_lapse_rates_information():
    """Fisher scoring's draws from a predictive N(0, 0.3²) under a fitted lapse (ε = 0.2,
    bounds ±1): the lapse coordinate's scores average to zero, and their mean square is the
    mixture's Fisher information (by quadrature), within 3% over 200 000 draws."""
    model = _model(lapse=0.2, fit_lapse=True)
    n = 200_000
    mean, var = torch.zeros(n, 2, dtype=torch.float64), torch.full((n, 2), 0.09).double()
    nuisance = model.nuisance_init.double().expand(n, -1).clone().requires_grad_(True)
    generator = torch.Generator().manual_seed(0)
    logp = model.log_prob_of_gaussian_draw(mean, var, nuisance, generator)
    (score,) = torch.autograd.grad(logp.sum(), nuisance)
    score = score[:, -1]  # the predictive's variance is given: only the rate is scored here
    assert score.mean().abs() < 4 * score.std() / math.sqrt(n)
    grid = torch.linspace(-2, 2, 400_001, dtype=torch.float64)
    normal = torch.exp(-0.5 * grid**2 / 0.09) / math.sqrt(2 * math.pi * 0.09)
    mixture = 0.8 * normal + 0.2 / 4
    information = torch.trapezoid((0.25 - normal) ** 2 / mixture, grid)  # in ε, per dimension
    slope = 0.2 * (1 - 0.2 / LAPSE_MAX)  # dε/du of the scaled logit
    expected = 2 * information * slope**2
    assert abs((score**2).mean().item() / expected.item() - 1) < 0.03


def test_draws_from_a_wide_predictive_at_a_bound_have_scores_of_mean_zero():
    """A predictive N(1, 0.6²) on the upper bound sends Gaussian draws beyond the lapse's
    support ([-2, 2]): scored there by the Gaussian alone, the scores of the mean, the
    variance and the lapse rate each average to zero (within 4 standard errors, 200 000
    draws of 2 dimensions; measured 0.1, 1.3 and 0.4, where scoring the lapse's density
    everywhere gave 34, 56 and 45)."""
    model = _model(lapse=0.2, fit_lapse=True)
    n = 200_000
    mean = torch.ones(n, 2, dtype=torch.float64, requires_grad=True)
    var = torch.full((n, 2), 0.36, dtype=torch.float64, requires_grad=True)
    nuisance = model.nuisance_init.double().expand(n, -1).clone().requires_grad_(True)
    logp = model.log_prob_of_gaussian_draw(mean, var, nuisance, torch.Generator().manual_seed(1))
    scores = torch.autograd.grad(logp.sum(), (mean, var, nuisance))
    for score in (scores[0].flatten(), scores[1].flatten(), scores[2][:, -1]):
        assert score.mean().abs() < 4 * score.std() / math.sqrt(len(score))


@pytest.mark.parametrize("kind", ["censored", "boltzmann"])
def test_an_action_model_scores_by_a_frozen_copy_and_leaves_the_callers_network_trainable(kind):
    """Building an action model must not freeze the network a user is still training (a
    DDPG step would then silently do nothing), nor follow its later updates."""
    network = Affine(torch.tensor([[1.5, -0.5], [0.3, 2.0]], dtype=torch.float64))
    if kind == "censored":
        model = CensoredGaussianActionModel(network, -torch.ones(2), torch.ones(2))
        held = model.actor
    else:
        model = BoltzmannActionModel(network)
        held = model.q_network
    features = torch.tensor([[0.4, 0.9]], dtype=torch.float64)
    before = held(features)
    assert network.weight.requires_grad and not held.weight.requires_grad
    network(features).sum().backward()
    with torch.no_grad():
        network.weight -= network.weight.grad  # the caller's training step
    assert not torch.equal(network(features), before)
    assert torch.equal(held(features), before)


def test_feature_policy_names_what_it_needs_when_given_an_exploration_policy():
    from tensordict.nn import TensorDictSequential
    from torchrl.modules import AdditiveGaussianModule

    from irc_torchrl.envs.firefly2d import Firefly2DModel
    from irc_torchrl.modules.actor_critic import FeaturePolicy, make_actor

    model = Firefly2DModel()
    actor = make_actor(model, hidden=(8,))
    explore = TensorDictSequential(actor, AdditiveGaussianModule(model.action_spec))
    with pytest.raises(TypeError, match="pass the actor itself, not an exploration policy"):
        FeaturePolicy(explore)
    assert FeaturePolicy(actor).mlp is actor.module[1].module  # the actor's own network


def test_assimilating_interior_actions_is_the_joint_gaussian_conditioning():
    """Without lapses and with every action inside the bounds, the sequence of scalar updates
    is the exact joint one for a linear policy: ``log N(a; ŷ, S)`` with ``S = JPJᵀ + D``, the
    Kalman shift and covariance of the input, and each dimension's predictive given the ones
    before it; an unscored dimension neither scores nor moves anything."""
    gen = torch.Generator().manual_seed(0)
    root = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    cov = 0.05 * root @ root.T + 0.01 * torch.eye(3, dtype=torch.float64)
    jac = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    mean = torch.tensor([0.1, -0.3], dtype=torch.float64)
    action = torch.tensor([0.4, -0.6], dtype=torch.float64)
    noise = torch.tensor([0.2, 0.3], dtype=torch.float64)
    cross, cov_action = cov @ jac.T, jac @ cov @ jac.T
    model = _model()
    out = model.assimilate(mean, cross, cov_action, cov, action, noise.log())
    s = cov_action + torch.diag(noise**2)
    gain = cross @ torch.linalg.inv(s)
    joint = torch.distributions.MultivariateNormal(mean, s).log_prob(action)
    conditional_mean = mean[1] + s[1, 0] / s[0, 0] * (action[0] - mean[0])
    conditional_var = s[1, 1] - s[1, 0] ** 2 / s[0, 0]
    expected = (
        joint,
        gain @ (action - mean),
        cov - gain @ cross.T,
        (torch.stack([mean[0], conditional_mean]), torch.stack([s[0, 0], conditional_var])),
    )
    torch.testing.assert_close(out, expected, rtol=1e-10, atol=1e-12)
    for i in range(2):  # one dimension scored: that one alone, conditioned on nothing else
        scored = torch.arange(2) == i
        out = model.assimilate(mean, cross, cov_action, cov, action, noise.log(), scored)
        alone = torch.distributions.Normal(mean[i], s[i, i].sqrt()).log_prob(action[i])
        shift = cross[:, i] * (action[i] - mean[i]) / s[i, i]
        post = cov - cross[:, i, None] * cross[:, i] / s[i, i]
        torch.testing.assert_close(out[:3], (alone, shift, post), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("lapse", [0.0, 0.2])
@pytest.mark.parametrize("action", [0.3, 1.0, -1.0], ids=["interior", "upper", "lower"])
def test_assimilating_one_action_gives_the_exact_posterior_moments(action, lapse):
    """One action dimension of a linear policy, inside or clipped at either bound, with or
    without lapses: ``log p(a)`` and the mean and covariance of the input given the action
    are those of the exact posterior (a Tobit tail, a lapse mixture), by quadrature on an
    801² grid (to 1e-7)."""
    model = CensoredGaussianActionModel(
        torch.nn.Identity(), -torch.ones(1), torch.ones(1), 0.3, lapse=lapse
    )
    prior = torch.tensor([0.2, -0.1], dtype=torch.float64)
    cov = torch.tensor([[0.09, 0.03], [0.03, 0.04]], dtype=torch.float64)
    weight, offset = torch.tensor([1.0, 0.8], dtype=torch.float64), 0.1  # y = w·z + c
    mean = (weight @ prior + offset).reshape(1)
    cross, cov_action = (cov @ weight).reshape(2, 1), (weight @ cov @ weight).reshape(1, 1)
    a = torch.tensor([action], dtype=torch.float64)
    logp, shift, post, _ = model.assimilate(
        mean, cross, cov_action, cov, a, model.nuisance_init.double()
    )
    # the exact posterior on a grid over the whitened input
    g = torch.linspace(-8, 8, 801, dtype=torch.float64)
    g = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    z = prior + g @ torch.linalg.cholesky(cov).T
    density = torch.exp(-0.5 * (g**2).sum(-1)) / (2 * math.pi) * (16 / 800) ** 2
    y = z @ weight + offset
    if action == 1.0:
        likely = torch.special.ndtr((y - 1) / 0.3)
    elif action == -1.0:
        likely = torch.special.ndtr((-1 - y) / 0.3)
    else:
        likely = torch.exp(-0.5 * ((action - y) / 0.3) ** 2) / (0.3 * math.sqrt(2 * math.pi))
    lapsed = 0.25  # the lapse's mass at a bound, and its density inside: 1 / (2 × width 2)
    joint = density * ((1 - lapse) * likely + lapse * lapsed)
    evidence = joint.sum()
    centre = (joint @ z) / evidence
    spread = ((z - centre).T * joint) @ (z - centre) / evidence
    torch.testing.assert_close(logp, evidence.log(), rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(shift, centre - prior, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(post, spread, rtol=1e-7, atol=1e-9)


def test_draws_for_fisher_scoring_carry_the_motor_noises_information():
    """Scores of the log motor noise from the model's own draws: mean zero and mean square 2
    per dimension (a Gaussian's information on ``log σ``), within 4% over 200 000 draws (the
    standard error is 0.8%)."""
    model = _model(motor_noise=0.3)
    n = 200_000
    gen = torch.Generator().manual_seed(0)
    features = torch.randn(n, 2, generator=gen, dtype=torch.float64)
    nuisance = model.nuisance_init.double().expand(n, -1).clone().requires_grad_(True)
    logp = model.log_prob_of_draw(features, nuisance, gen)
    (score,) = torch.autograd.grad(logp.sum(), nuisance)
    assert (score.mean(0).abs() < 4 * score.std(0) / math.sqrt(n)).all()
    torch.testing.assert_close(
        (score**2).mean(0), torch.full((2,), 2.0, dtype=torch.float64), rtol=0.04, atol=0
    )


def _actor_with_bounds(low, high, hidden=(8,), activation="softplus"):
    """A small 2D actor whose action spec has the given (non-symmetric) bounds, seed 0."""
    from torchrl.data import Bounded

    from irc_torchrl.envs.firefly2d import Firefly2DModel
    from irc_torchrl.modules.actor_critic import make_actor

    model = Firefly2DModel()
    model.action_spec = Bounded(torch.tensor(low), torch.tensor(high), shape=(2,))
    torch.manual_seed(0)
    return make_actor(model, hidden=hidden, activation=activation), model


def test_actor_and_feature_policy_squash_into_the_specs_own_bounds():
    """Both paths map the network's output p to ``low + (high − low)(1 + tanh p)/2`` of the
    spec's bounds, here [0, 2] × [−2, 0.5], not [−1, 1]; features are wide enough to come
    within 0.05 of every bound."""
    from tensordict import TensorDict

    from irc_torchrl.modules.actor_critic import FeaturePolicy

    actor, model = _actor_with_bounds([0.0, -2.0], [2.0, 0.5])
    low, high = torch.tensor([0.0, -2.0]), torch.tensor([2.0, 0.5])
    mlp = actor.module[1].module
    g = torch.Generator().manual_seed(1)
    features = 20 * torch.randn(256, mlp[0].in_features, generator=g)
    expected = low + (high - low) * (1 + torch.tanh(mlp(features))) / 2
    torch.testing.assert_close(FeaturePolicy(actor)(features), expected)
    squashed = actor.module[2](actor.module[1](TensorDict(features=features, batch_size=[256])))
    torch.testing.assert_close(squashed["action"], expected)
    assert (expected >= low).all() and (expected <= high).all()
    assert ((expected - low).abs().min(0).values < 0.05).all()
    assert ((expected - high).abs().min(0).values < 0.05).all()


def test_a_float32_feature_policy_runs_its_network_in_float32_and_answers_in_float64():
    """``dtype=float32`` rounds the network (float64 input) to float32 and squashes its output
    in float64, as does ``censored_action_model(..., "float32")``; ``"float64"`` keeps float64
    throughout (the two differ by float32 rounding: between 1e-9 and 1e-4)."""
    from irc_torchrl.modules.actor_critic import FeaturePolicy, censored_action_model

    actor, model = _actor_with_bounds([-1.0, -1.0], [1.0, 1.0])
    mlp = actor.module[1].module
    features = torch.randn(64, mlp[0].in_features, dtype=torch.float64)
    out = FeaturePolicy(actor, torch.float32)(features)
    assert out.dtype == torch.float64
    expected = torch.tanh(mlp(features.float()).double())
    torch.testing.assert_close(out, expected, atol=1e-12, rtol=0)
    exact = FeaturePolicy(actor)(features)
    assert exact.dtype == torch.float64
    assert 1e-9 < (out - exact).abs().max() < 1e-4
    for name, reference in (("float32", out), ("float64", exact)):
        scored = censored_action_model(actor, model, name).actor(features)
        torch.testing.assert_close(scored, reference, atol=1e-12, rtol=0)


def test_censored_action_model_starts_from_the_motor_noise_it_is_given():
    """``motor_noise`` is where the fit starts: the initial nuisance is its log per dimension."""
    from irc_torchrl.modules.actor_critic import censored_action_model

    actor, model = _actor_with_bounds([-1.0, -1.0], [1.0, 1.0])
    action_model = censored_action_model(actor, model, motor_noise=0.3)
    noise = action_model.motor_noise(action_model.nuisance_init)
    torch.testing.assert_close(noise, torch.full((2,), 0.3))


def test_actor_and_critic_use_the_activation_they_are_given():
    """The networks are built with the named activation (here ``tanh``), not the default."""
    from irc_torchrl.modules.actor_critic import make_critic

    actor, model = _actor_with_bounds([-1.0, -1.0], [1.0, 1.0], hidden=(8, 8), activation="tanh")
    critic = make_critic(model, hidden=(8, 8), activation="tanh")
    for network in (actor, critic):
        kinds = {type(m) for m in network.modules()}
        assert torch.nn.Tanh in kinds and torch.nn.Softplus not in kinds


def test_an_unbounded_action_space_scores_and_differentiates_as_the_plain_gaussian():
    """A task with an ``Unbounded`` action spec has the dtype's extremes for bounds: no action
    is clipped, the score is the Gaussian density, and its gradients (map's ``log_prob`` and
    marginal's ``assimilate``) are finite (an unread tail term far out once made them NaN)."""
    big = torch.finfo(torch.float32).max
    bounds = big * torch.ones(2)
    model = CensoredGaussianActionModel(Affine(torch.eye(2, dtype=torch.float64)), -bounds, bounds)
    features = torch.tensor([[0.4, -0.2]], dtype=torch.float64, requires_grad=True)
    nuisance = model.nuisance_init.double().clone().requires_grad_(True)
    action = torch.tensor([[0.5, -3.0]], dtype=torch.float64)
    logp = model.log_prob(features, action, nuisance)
    std = model.motor_noise(nuisance)
    expected = torch.distributions.Normal(model.actor(features), std).log_prob(action).sum(-1)
    torch.testing.assert_close(logp, expected, rtol=1e-12, atol=1e-12)
    (gradient,) = torch.autograd.grad(logp.sum(), features, create_graph=True)
    (curvature,) = torch.autograd.grad(gradient.sum(), nuisance)
    assert torch.isfinite(gradient).all() and torch.isfinite(curvature).all()
    cov = 0.1 * torch.eye(2, dtype=torch.float64)
    mean = features[0].tanh()
    out = model.assimilate(mean, cov, cov, cov, action[0], nuisance)
    assert all(torch.isfinite(g).all() for g in torch.autograd.grad(out[0], (features, nuisance)))
