"""Lapses: simulated as the action model scores them, and what they protect a fit from."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import ExplorationType, set_exploration_type

from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.fit import BOUND, _clamp_bounded, _pin_bounds, _pinned, fit_theta
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.envs.model import sensed_world
from irc_torchrl.modules import Lapse
from irc_torchrl.modules.actor_critic import censored_action_model
from irc_torchrl.objectives.inverse import InverseRationalLoss

SPEC = Firefly2DModel().action_spec  # bounds [-1, 1] in both dimensions


def _lapsed(lapse: float, n: int, seed: int) -> torch.Tensor:
    torch.manual_seed(seed)
    td = TensorDict({"action": torch.full((n, 2), 0.3)}, [n])
    return Lapse(SPEC, lapse)(td)["action"]


def test_lapses_come_at_their_rate_from_the_distribution_the_action_model_scores():
    """With n = 200 000 action dimensions, sd of the lapse fraction 0.0007; of the mass at a
    bound among the lapsed 0.002."""
    action = _lapsed(0.1, 100_000, seed=0)
    lapsed = action != 0.3
    assert abs(lapsed.double().mean().item() - 0.1) < 0.004
    drawn = action[lapsed]
    # uniform over [-2, 2], clipped to [-1, 1]: a quarter at each bound, a flat half inside
    assert abs((drawn == 1).double().mean().item() - 0.25) < 0.01
    assert abs((drawn == -1).double().mean().item() - 0.25) < 0.01
    inside = drawn[(drawn > -1) & (drawn < 1)]
    counts = torch.histc(inside, bins=4, min=-1, max=1) / len(drawn)
    torch.testing.assert_close(
        counts, torch.full((4,), 0.125, dtype=counts.dtype), atol=0.008, rtol=0
    )


def test_lapses_repeat_with_the_seed_and_stay_off_when_acting_greedily():
    assert torch.equal(_lapsed(0.2, 1000, seed=3), _lapsed(0.2, 1000, seed=3))
    assert not torch.equal(_lapsed(0.2, 1000, seed=3), _lapsed(0.2, 1000, seed=4))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert (_lapsed(0.5, 1000, seed=0) == 0.3).all()
    assert (_lapsed(0.0, 1000, seed=0) == 0.3).all()


@pytest.mark.parametrize(
    "lapse, shown",
    [(-0.1, "-0.1"), (1.0, "1"), (math.nan, "nan"), (torch.tensor([[0.1], [1.0]]), "1")],
)
def test_a_lapse_outside_zero_to_one_is_refused(lapse, shown):
    with pytest.raises(
        ValueError, match=rf"lapse: expected probabilities in \[0, 1\), got {shown}$"
    ):
        Lapse(SPEC, lapse)


def test_a_lapse_over_unbounded_actions_is_refused():
    """A lapse is uniform over the action bounds: an ``Unbounded`` spec (the dtype's extremes)
    has none, in the simulated agent and in the scored action model alike; lapse 0 is kept."""
    from torchrl.data import Unbounded

    from irc_torchrl.modules.likelihood import CensoredGaussianActionModel

    with pytest.raises(TypeError, match=r"^spec: expected a bounded action spec .* unbounded"):
        Lapse(Unbounded(shape=(2,)), 0.1)
    bound = torch.finfo(torch.float32).max * torch.ones(2)
    with pytest.raises(ValueError, match=r"^lapse: a lapse is uniform over the action bounds"):
        CensoredGaussianActionModel(torch.nn.Identity(), -bound, bound, lapse=0.05)
    assert CensoredGaussianActionModel(torch.nn.Identity(), -bound, bound).lapse == 0.0
    box = torch.ones(2)
    assert CensoredGaussianActionModel(torch.nn.Identity(), -box, box, lapse=0.05).lapse == 0.05


def test_per_agent_rates_that_do_not_fit_the_action_are_refused():
    td = TensorDict({"action": torch.zeros(2, 2)}, [2])
    for shape in ((3, 1), (2, 2, 2)):
        with pytest.raises(ValueError, match=r"lapse: expected rates broadcasting against the"):
            Lapse(SPEC, torch.full(shape, 0.1))(td)
    # placed before the policy: no action to act on ("NoneType has no attribute shape")
    with pytest.raises(KeyError, match="action: Lapse acts on the policy's action; none is set"):
        Lapse(SPEC, 0.1)(TensorDict({}, [2]))


def test_a_lapse_keeps_the_marginal_gradient_finite_where_the_policy_cannot_act_so():
    """Agents forced to drive on (a_v ≥ 0.4, never stopping) for all 60 steps of a trial:
    actions the policy cannot produce. Without a lapse the outer filter explains the steering
    by a belief settled on the target, where the bearing turns on millimetres, and the
    gradient of log L explodes (measured: a largest |∂ log L/∂θ| over the free parameters of
    6.0e11 over 8 agents × 3 trials, each sensing as noisily as its θ says); with lapse = 0.01
    it is 2.5e6 (agent 5, the noisiest senses, obs σ 0.77 and 1.15; the others at most 3.9e4).
    In the default world's senses (obs σ 0.4 and 0.3, which the test used to simulate) the
    same was 1.2e11 and 2.0e4."""
    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    theta = space.sample((8,), generator=torch.Generator().manual_seed(0))
    drive_on = TensorDictModule(
        lambda a: torch.cat([a[..., :1].clamp_min(0.4), a[..., 1:]], -1), ["action"], ["action"]
    )
    policy = TensorDictSequential(motor_noise_policy(actor, model.action_spec, 0.1), drive_on)
    world = sensed_world(model, space.default().expand(8, -1), theta)  # their senses, their own
    trials = simulate_agents(model, policy, theta, 3, world, seed=1)
    assert trials["mask"].all()  # every trial runs its 60 steps
    held = trials.select("state", "action", "target", "mask", "task_theta")
    largest = {}
    for lapse in (0.0, 0.01):
        action_model = censored_action_model(actor, model, "float32", lapse=lapse)
        loss = InverseRationalLoss(model, action_model, n_agents=8, method="marginal")
        at = theta.double().requires_grad_(True)
        nuisance = action_model.nuisance_init.double().expand(8, -1)
        log_likelihood = loss.log_likelihood(at, nuisance, held)
        (grad,) = torch.autograd.grad(log_likelihood.sum(), at)
        assert torch.isfinite(log_likelihood).all() and torch.isfinite(grad).all()
        largest[lapse] = grad[:, space.free_mask].abs().max().item()
    assert largest[0.0] > 1e8
    assert largest[0.01] < 1e7


def test_agents_that_lapse_are_fitted_with_their_motor_noise_only_by_a_lapse_model():
    """2 agents × 40 trials lapsing at 5%, every parameter free, 8 iterations (no fit has
    converged by then; at 30, one of the four). Measured (seeds below): the fitted motor noise
    0.091–0.103 with the lapse in the model, 0.27–0.39 without (the Gaussian widens to absorb
    the lapses; 0.091–0.104 and 0.25–0.39 after 12 iterations, the same to 0.001 and 0.01
    after 30), the gains within 0.9% with the lapse; at 8 agents × 100 trials the
    noise parameters' median errors fall from 9–22% to 1–4% and 100% of the fits converge
    against 75%."""
    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    theta = space.sample((2,), generator=torch.Generator().manual_seed(2))
    policy = motor_noise_policy(actor, model.action_spec, 0.1, lapse=0.05)
    held = simulate_agents(model, policy, theta, 40, space.default(), seed=3).select(
        "state", "action", "target", "mask", "task_theta"
    )
    noise = {}
    for lapse in (0.0, 0.05):
        action_model = censored_action_model(actor, model, "float32", lapse=lapse)
        loss = InverseRationalLoss(
            model, action_model, n_agents=2, senses="world", method="marginal"
        )
        result = fit_theta(
            loss, held, max_iter=8, seed=0, n_screen=8, n_starts=1, curvature="bfgs"
        )
        noise[lapse] = action_model.motor_noise(result.nuisance)
        if lapse:
            gains = [space.index("g_v"), space.index("g_w")]
            error = (result.theta_hat[:, gains] - theta[:, gains]).abs() / theta[:, gains]
            assert (error < 0.05).all()
    assert (noise[0.05] - 0.1).abs().max() < 0.015
    assert (noise[0.0] > 0.18).all()


def test_a_fitted_lapse_rate_finds_each_agents_own():
    """4 agents × 40 trials, two lapsing at 10% and two never (per-agent rates in one
    simulation), every parameter free and the rate fitted from 0.01 for 20 iterations.
    Measured (seeds below): the lapsing agents' rates 0.093 and 0.095 with 95% intervals
    [0.074, 0.116] and [0.078, 0.116]; the others on the rate's floor, 0.0012; every motor
    noise 0.097–0.111 (0.094, 0.096 and 0.097–0.104 after 30 iterations)."""
    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    theta = space.sample((4,), generator=torch.Generator().manual_seed(2))
    rate = torch.tensor([0.1, 0.1, 0.0, 0.0]).view(-1, 1, 1)
    policy = motor_noise_policy(actor, model.action_spec, 0.1, lapse=rate)
    held = simulate_agents(model, policy, theta, 40, space.default(), seed=3).select(
        "state", "action", "target", "mask", "task_theta"
    )
    action_model = censored_action_model(actor, model, "float32", lapse=0.01, fit_lapse=True)
    loss = InverseRationalLoss(model, action_model, n_agents=4, senses="world", method="marginal")
    result = fit_theta(loss, held, max_iter=20, seed=0, n_screen=8, n_starts=1, curvature="bfgs")
    fitted = action_model.lapse_rate(result.nuisance)
    low, high = map(action_model.lapse_rate, result.nuisance_intervals(loss.bounded[-3:]))
    assert ((fitted[:2] - 0.1).abs() < 0.03).all()
    assert ((low[:2] < 0.1) & (0.1 < high[:2])).all()
    # held on the fit's bound (the rate's floor), whose interval reaches down to 0
    assert (result.nuisance[2:, -1] == -BOUND).all() and (low[2:] == 0).all()
    assert (high[2:] > fitted[2:]).all()
    assert ((action_model.motor_noise(result.nuisance) - 0.1).abs() < 0.02).all()


def test_the_fit_holds_any_bounded_coordinate_within_its_bounds():
    """The fit's bound logic follows a mask, not "the first k": a bounded coordinate at
    ±BOUND whose gradient points out is pinned (gradient zeroed, curvature decoupled) and
    clamped; an unbounded one anywhere is left alone."""
    bounded = torch.tensor([True, False, True])
    params = torch.tensor([[BOUND, 9.0, -BOUND], [BOUND, 9.0, 0.0]], dtype=torch.float64)
    g = torch.tensor([[-1.0, 1.0, 1.0], [1.0, -1.0, 1.0]], dtype=torch.float64)
    # descent is −g: row 0 leans out on both bounded ends, row 1 on neither
    assert _pinned(params, g, bounded).tolist() == [[True, False, True], [False, False, False]]
    h, g_kept = _pin_bounds(params, torch.ones(2, 3, 3, dtype=torch.float64), g, bounded)
    assert g_kept[0].tolist() == [0.0, 1.0, 0.0] and torch.equal(g_kept[1], g[1])
    assert h[0].tolist() == [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    assert torch.equal(h[1], torch.ones(3, 3, dtype=torch.float64))
    clamped = _clamp_bounded(params * 2, bounded)
    assert clamped.tolist() == [[BOUND, 18.0, -BOUND], [BOUND, 18.0, 0.0]]


def test_an_action_model_says_which_nuisance_is_bounded_or_none_is():
    """A user's action model without ``nuisance_bounded`` fits every nuisance unbounded; one
    whose flags do not match its nuisance, or a non-bool ``fit_lapse``, is a clear error."""
    actor, model, _ = load_ensemble_policy("firefly2d")
    k = len(model.theta_space.free_names)
    fitted = censored_action_model(actor, model, lapse=0.01, fit_lapse=True)
    loss = InverseRationalLoss(model, fitted)
    assert loss.bounded.tolist() == [True] * k + [False, False, True]
    plain = censored_action_model(actor, model)
    del plain.nuisance_bounded  # as a model written without it
    assert InverseRationalLoss(model, plain).bounded.tolist() == [True] * k + [False, False]
    plain.nuisance_bounded = (False,)
    with pytest.raises(ValueError, match=r"nuisance_bounded: expected one flag per nuisance"):
        InverseRationalLoss(model, plain)
    with pytest.raises(TypeError, match=r"fit_lapse: expected a bool, got 2"):
        censored_action_model(actor, model, lapse=0.01, fit_lapse=2)
