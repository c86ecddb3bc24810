"""The EKF belief on the 2D firefly task: exactness, calibration, robustness, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats
from torchrl.data import Unbounded
from torchrl.envs import TransformedEnv

from irc_torchrl.envs import EKFBelief, Firefly2DEnv, Firefly2DModel, TaskModel, ekf_step
from irc_torchrl.envs.belief import ekf_predict, joseph_update
from irc_torchrl.envs.firefly2d import NOISE_FLOOR
from irc_torchrl.theta import Parameter, ThetaSpace

torch.set_num_threads(1)
MODEL = Firefly2DModel()
SPACE = MODEL.theta_space
DT = 0.1


# --- an independent reference, written from the equations in plain numpy -------------------
def reference_ekf(theta, actions, observations):
    """EKF for (x, y, φ, v, ω) with velocities set by the action and observed with noise."""
    g_v, g_w, s_v, s_w, o_v, o_w, s_pos = (float(theta[i]) for i in range(7))
    f2 = NOISE_FLOOR**2
    q = np.diag([s_pos**2 + f2, s_pos**2 + f2, f2, s_v**2 + f2, s_w**2 + f2])
    r = np.diag([o_v**2 + f2, o_w**2 + f2])
    h = np.zeros((2, 5))
    h[0, 3] = h[1, 4] = 1.0
    m, p = np.zeros(5), f2 * np.eye(5)
    means, covs = [], []
    for a, o in zip(actions, observations, strict=True):
        x, y, phi, v, w = m
        big_f = np.eye(5)
        big_f[3, 3] = big_f[4, 4] = 0.0
        big_f[0, 2], big_f[0, 3] = -v * math.sin(phi) * DT, math.cos(phi) * DT
        big_f[1, 2], big_f[1, 3] = v * math.cos(phi) * DT, math.sin(phi) * DT
        big_f[2, 4] = DT
        m = np.array(
            [
                x + v * math.cos(phi) * DT,
                y + v * math.sin(phi) * DT,
                phi + w * DT,
                g_v * a[0],
                g_w * a[1],
            ]
        )
        p = big_f @ p @ big_f.T + q
        s = h @ p @ h.T + r
        k = p @ h.T @ np.linalg.inv(s)
        m = m + k @ (o - h @ m)
        p = (np.eye(5) - k @ h) @ p
        means.append(m)
        covs.append(p)
    return np.array(means), np.array(covs)


def run_filter(model, theta, actions, observations, dtype=torch.float64):
    """Our filter over ``[*B, T, ...]`` actions and observations, from the initial belief."""
    theta = theta.to(dtype)
    state = torch.zeros(*actions.shape[:-2], model.state_dim, dtype=dtype)
    mean, cov = model.initial_belief(state, None, theta)
    means, covs = [], []
    for t in range(actions.shape[-2]):
        mean, cov = ekf_step(
            model, mean, cov, actions[..., t, :].to(dtype), observations[..., t, :].to(dtype), theta
        )
        means.append(mean)
        covs.append(cov)
    return torch.stack(means, -2), torch.stack(covs, -3)


def env_rollout(n, steps, seed, theta=None, task_theta=None):
    """A rollout of the filtered env under uniform random actions, never stopping."""
    env = TransformedEnv(
        Firefly2DEnv(batch_size=(n,), theta=theta, task_theta=task_theta, seed=seed, model=MODEL),
        EKFBelief(MODEL),
    )
    gen = torch.Generator().manual_seed(seed)

    def policy(td):
        u = torch.rand(n, 2, generator=gen)
        return td.set("action", torch.stack([0.2 + 0.8 * u[:, 0], 2 * u[:, 1] - 1], -1))

    return env.rollout(steps, policy, break_when_any_done=False)


def test_filter_matches_numpy_reference_along_env_trajectories():
    td = env_rollout(6, 40, seed=3)
    theta = td["theta"][:, 0]
    actions, observations = td["action"], td["next", "observation"]
    ours_mean, ours_cov = td["next", "belief", "mean"], td["next", "belief", "cov"]
    ref64 = run_filter(MODEL, theta, actions, observations)
    for b in range(6):
        ref_mean, ref_cov = reference_ekf(
            theta[b].double().numpy(), actions[b].double().numpy(), observations[b].double().numpy()
        )
        np.testing.assert_allclose(ref64[0][b].numpy(), ref_mean, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(ref64[1][b].numpy(), ref_cov, rtol=1e-9, atol=1e-12)
        # the env's float32 filter agrees to float32 precision
        np.testing.assert_allclose(ours_mean[b].numpy(), ref_mean, rtol=1e-3, atol=1e-4)
        np.testing.assert_allclose(ours_cov[b].numpy(), ref_cov, rtol=1e-3, atol=1e-5)


class LinearModel(TaskModel):
    """A linear-Gaussian model (2D constant-velocity tracking, position observed)."""

    state_dim, observation_dim, target_dim, max_steps = 4, 2, 2, 50
    action_spec = Unbounded(shape=(2,))
    theta_space = ThetaSpace([Parameter("q", 0.01, 1.0, 0.1), Parameter("r", 0.01, 1.0, 0.3)])
    a = torch.tensor(
        [[1.0, 0, 0.1, 0], [0, 1, 0, 0.1], [0, 0, 0.9, 0], [0, 0, 0, 0.9]], dtype=torch.float64
    )
    b = torch.tensor([[0.0, 0], [0, 0], [0.1, 0], [0, 0.1]], dtype=torch.float64)
    c = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0]], dtype=torch.float64)

    def initial_state(self, theta, generator):
        raise NotImplementedError

    def transition(self, state, action, theta):
        return state @ self.a.T + action @ self.b.T

    def process_cov(self, state, action, theta):
        return theta[..., 0, None, None] ** 2 * torch.eye(4, dtype=state.dtype)

    def observe(self, state, theta):
        return state @ self.c.T

    def observation_cov(self, state, theta):
        return theta[..., 1, None, None] ** 2 * torch.eye(2, dtype=state.dtype)

    stops = reward = initial_belief = belief_reward = belief_features = initial_state
    belief_feature_dim = 0


def test_linear_special_case_is_the_exact_kalman_filter():
    model, rng = LinearModel(), np.random.default_rng(0)
    theta = torch.tensor([0.3, 0.5], dtype=torch.float64)
    a, b, c = model.a.numpy(), model.b.numpy(), model.c.numpy()
    q, r = 0.09 * np.eye(4), 0.25 * np.eye(2)
    m, p = rng.normal(size=4), np.diag(rng.uniform(0.1, 1.0, size=4))
    mean, cov = torch.tensor(m), torch.tensor(p)
    for _ in range(30):
        u, y = rng.normal(size=2), rng.normal(size=2)
        m, p = a @ m + b @ u, a @ p @ a.T + q
        gain = p @ c.T @ np.linalg.inv(c @ p @ c.T + r)
        m, p = m + gain @ (y - c @ m), (np.eye(4) - gain @ c) @ p
        mean, cov = ekf_step(model, mean, cov, torch.tensor(u), torch.tensor(y), theta)
        np.testing.assert_allclose(mean.numpy(), m, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(cov.numpy(), p, rtol=1e-10, atol=1e-12)


def test_analytic_jacobians_match_torch_func():
    gen = torch.Generator().manual_seed(0)
    state = torch.randn(3, 4, 5, generator=gen, dtype=torch.float64) * 2
    action = 2 * torch.rand(3, 4, 2, generator=gen, dtype=torch.float64) - 1
    theta = SPACE.free().sample((3, 4), generator=gen, dtype=torch.float64)
    analytic = MODEL.transition_jacobian(state, action, theta)
    auto = TaskModel.transition_jacobian(MODEL, state, action, theta)
    torch.testing.assert_close(analytic, auto, rtol=1e-12, atol=1e-12)
    # the terms that broke earlier implementations are there
    assert (analytic[..., 0, 3] != 0).all() and (analytic[..., 0, 2] != 0).all()
    assert (analytic[..., 2, 4] == DT).all()
    torch.testing.assert_close(
        MODEL.observation_jacobian(state, theta),
        TaskModel.observation_jacobian(MODEL, state, theta),
    )


def test_velocity_observations_reach_position_through_the_jacobian():
    """Position integrates the filtered velocity: an observed speed moves the position
    estimate one step later, and precise observations leave less position uncertainty
    (a Jacobian without ∂x/∂v would give neither)."""
    zero, one = torch.zeros(5, dtype=torch.float64), torch.tensor([1.0, 0.0], dtype=torch.float64)

    def two_steps(obs_sigma_v):
        theta = SPACE.from_dict({"obs_sigma_v": obs_sigma_v, "sigma_v": 0.8}).double()
        mean, cov = MODEL.initial_belief(zero, None, theta)
        seen = torch.tensor([1.5, 0.0], dtype=torch.float64)  # faster than g_v a_v = 1.2
        mean, cov = ekf_step(MODEL, mean, cov, one, seen, theta)
        return ekf_step(MODEL, mean, cov, one, None, theta)

    (mean_sharp, cov_sharp), (mean_blur, cov_blur) = two_steps(0.05), two_steps(1.6)
    assert mean_sharp[0] > 0.145 and mean_blur[0] < 0.13  # x ≈ dt·v̂
    assert cov_sharp[0, 0] < 0.05 * cov_blur[0, 0]


def nees(td, t):
    """Normalised estimation error squared of the belief at step ``t`` of a rollout."""
    err = (td["next", "state"][:, t] - td["next", "belief", "mean"][:, t]).double()
    cov = td["next", "belief", "cov"][:, t].double()
    return (err.unsqueeze(-2) @ torch.linalg.solve(cov, err.unsqueeze(-1))).squeeze()


@pytest.mark.parametrize(
    ("theta", "steps", "tol_mean", "tol_cover"),
    [(SPACE.default(), (9, 19, 39), 0.04, 0.015), (None, (4, 9), 0.04, 0.015)],
    ids=["default-theta", "prior"],
)
def test_nees_is_chi_squared_when_agent_and_task_agree(theta, steps, tol_mean, tol_cover):
    """NEES over 3000 trials (seed 0) ~ χ²(5): its mean within ``tol_mean`` of 5 (3.4 Monte-Carlo
    standard errors) and the χ²(5) 95% quantile covering 95% ± ``tol_cover`` (3.7 s.e.).

    Over the whole prior the heading's uncertainty grows without bound (heading is never
    observed) and the EKF's linearisation makes it overconfident late in long trials at the
    largest angular noise (mean NEES 5.5 at step 30, 5.9 at step 40): there we test early steps.
    """
    td = env_rollout(3000, max(steps) + 1, seed=0, theta=theta)
    for t in steps:
        value = nees(td, t)
        assert abs(value.mean().item() / 5 - 1) < tol_mean, (t, value.mean().item())
        coverage = (value < stats.chi2.ppf(0.95, 5)).double().mean().item()
        assert abs(coverage - 0.95) < tol_cover, (t, coverage)


def test_nees_detects_a_wrong_agent_model():
    """The same test fails when the agent underestimates its noise (the test can fail)."""
    task = SPACE.from_dict({"sigma_v": 0.6, "sigma_w": 0.5, "obs_sigma_v": 1.0, "obs_sigma_w": 1.0})
    agent = SPACE.from_dict(
        {"sigma_v": 0.1, "sigma_w": 0.1, "obs_sigma_v": 0.1, "obs_sigma_w": 0.1}
    )
    td = env_rollout(500, 20, seed=1, theta=agent, task_theta=task)
    assert nees(td, -1).mean().item() > 10


def corner_thetas(dtype):
    """θ at the all-low corner (every noise zero), the all-high corner and an alternating one."""
    low, high = SPACE.low(dtype), SPACE.high(dtype)
    return torch.stack([low, high, torch.where(torch.arange(len(SPACE)) % 2 == 0, low, high)])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_long_episodes_keep_covariance_symmetric_pd(dtype):
    gen = torch.Generator().manual_seed(0)
    theta = torch.cat(
        [corner_thetas(dtype), SPACE.free().sample((61,), generator=gen, dtype=dtype)]
    )
    mean, cov = MODEL.initial_belief(torch.zeros(64, 5, dtype=dtype), None, theta)
    for t in range(1000):
        action = 2 * torch.rand(64, 2, generator=gen, dtype=dtype) - 1
        if (t // 50) % 2 == 0:
            action[:8, 0] = 1.0  # stretches at full speed
        obs = mean[:, 3:] + torch.randn(64, 2, generator=gen, dtype=dtype)
        mean, cov = ekf_step(MODEL, mean, cov, action, obs, theta)
        assert mean.dtype == cov.dtype == dtype
        assert torch.isfinite(mean).all() and torch.isfinite(cov).all()
        assert torch.equal(cov, cov.mT)
        assert (torch.linalg.eigvalsh(cov.double()) > 0).all(), t


@settings(
    max_examples=12, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    u=st.lists(st.floats(0.0, 1.0), min_size=9, max_size=9),
    seed=st.integers(0, 2**16),
    n=st.sampled_from([1, 3]),
)
def test_fuzz_rollouts_stay_finite_pd_and_in_spec(u, seed, n):
    theta = SPACE.denormalise(2 * torch.tensor(u) - 1)
    env = TransformedEnv(
        Firefly2DEnv(batch_size=(n,), theta=theta, seed=seed, model=MODEL), EKFBelief(MODEL)
    )
    gen = torch.Generator().manual_seed(seed)
    td = env.rollout(
        150,
        lambda td: td.set("action", 2 * torch.rand(n, 2, generator=gen) - 1),
        break_when_any_done=False,
    )
    spec = env.full_observation_spec
    for key in spec.keys(True, True):
        value = td["next", key]
        assert torch.isfinite(value.float()).all(), key
        assert spec[key].is_in(value[:, 0]) and spec[key].is_in(value[:, -1]), key
    cov = td["next", "belief", "cov"].double()
    assert (torch.linalg.eigvalsh(cov) > 0).all()


def test_belief_is_differentiable_in_theta_and_matches_finite_differences():
    gen = torch.Generator().manual_seed(0)
    actions = 2 * torch.rand(2, 15, 2, generator=gen, dtype=torch.float64) - 1
    observations = torch.randn(2, 15, 2, generator=gen, dtype=torch.float64)
    weights = torch.randn(2, 15, 5 + 25, generator=gen, dtype=torch.float64)
    theta0 = SPACE.from_dict({"sigma_pos": 0.05}).double()

    def loss(theta):
        mean, cov = run_filter(MODEL, theta.expand(2, -1), actions, observations)
        return (torch.cat([mean, cov.flatten(-2)], -1) * weights).sum()

    assert torch.autograd.gradcheck(loss, (theta0.clone().requires_grad_(True),))
    theta = theta0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(theta), theta)
    assert torch.isfinite(grad).all()
    assert (grad[:7] != 0).all()  # every dynamics and noise parameter moves the belief


def test_float32_and_float64_filters_agree():
    td = env_rollout(4, 30, seed=5)
    args = td["theta"][:, 0], td["action"], td["next", "observation"]
    mean32, cov32 = run_filter(MODEL, *args, dtype=torch.float32)
    mean64, cov64 = run_filter(MODEL, *args, dtype=torch.float64)
    assert mean32.dtype == torch.float32 and mean64.dtype == torch.float64
    torch.testing.assert_close(mean32.double(), mean64, rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(cov32.double(), cov64, rtol=1e-3, atol=1e-5)


def test_bad_inputs_give_clear_errors():
    with pytest.raises(ValueError, match="theta: g_v=5 is outside its space"):
        Firefly2DEnv(theta=SPACE.default().index_put((torch.tensor(0),), torch.tensor(5.0)))
    with pytest.raises(ValueError, match=r"task_theta: expected shape \[\.\.\., 9\]"):
        Firefly2DEnv(task_theta=torch.zeros(3))
    env = TransformedEnv(Firefly2DEnv(batch_size=(2,)), EKFBelief(MODEL))
    td = env.reset()
    with pytest.raises(ValueError, match="action: expected finite values"):
        env.step(td.set("action", torch.tensor([[0.5, float("nan")], [0.5, 0.0]])))
    with pytest.raises(ValueError, match=r"action: expected shape \[2, 2\]"):
        env.step(td.set("action", torch.zeros(2, 3)))
    with pytest.raises(ValueError, match="action: expected values within the bounds"):
        env.step(td.set("action", torch.full((2, 2), 1.5)))
    with pytest.raises(ValueError, match="theta: obs_sigma_v=-1"):
        env.reset(theta=SPACE.default().index_put((torch.tensor(4),), torch.tensor(-1.0)))
    # a θ edited in the TensorDict between steps: refused before the world or the belief moves
    td = env.reset().set("action", torch.zeros(2, 2))
    for key, message in (
        ("theta", "theta: g_w=-1 is outside its space"),
        ("task_theta", "task_theta: g_w=-1 is outside its space"),
    ):
        edited = td.clone()
        edited[key][1, 1] = -1.0
        with pytest.raises(ValueError, match=message):
            env.step(edited)
    edited = td.clone().set("theta", torch.full((2, 9), float("nan")))
    with pytest.raises(ValueError, match="theta: g_v=nan is outside its space"):
        env.step(edited)
    with pytest.raises(ValueError, match=r"task_theta: expected shape \[2, 9\], got \[2, 8\]"):
        env.step(td.clone().set("task_theta", torch.zeros(2, 8)))
    assert torch.equal(env.step(td.clone())["next", "theta"], td["theta"])  # in its space: steps


def test_the_joseph_update_is_the_error_covariance_for_any_gain():
    """For a gain that is not Kalman's, ``joseph_update``'s covariance is still that of the
    updated mean's error (200 000 Monte-Carlo draws, within 3% of the largest entry; the
    shortcut ``(I − KH) Σ`` is off by the whole largest entry there), and ``A = I − KH`` is
    the map from the prior mean to the updated one that the outer filter carries its
    covariance through."""
    gen = torch.Generator().manual_seed(0)
    root = torch.randn(4, 4, generator=gen, dtype=torch.float64)
    cov = root @ root.T + 0.5 * torch.eye(4, dtype=torch.float64)
    jac = torch.randn(2, 4, generator=gen, dtype=torch.float64)
    noise = torch.tensor([[0.5, 0.1], [0.1, 0.3]], dtype=torch.float64)
    kalman = cov @ jac.T @ torch.linalg.inv(jac @ cov @ jac.T + noise)
    gain = kalman + 0.3 * torch.randn(4, 2, generator=gen, dtype=torch.float64)
    mean = torch.randn(4, generator=gen, dtype=torch.float64)
    n = 200_000
    draw = torch.randn(n, 6, generator=gen, dtype=torch.float64)
    state = mean + draw[:, :4] @ torch.linalg.cholesky(cov).T
    observed = state @ jac.T + draw[:, 4:] @ torch.linalg.cholesky(noise).T
    residual = observed - mean @ jac.T
    updated, post, a = joseph_update(mean, cov, gain, jac, noise, residual)
    error = state - updated
    empirical = error.T @ error / n
    assert (post - empirical).abs().max() < 0.03 * empirical.abs().max()
    torch.testing.assert_close(post, post.T, rtol=0, atol=0)
    assert torch.linalg.eigvalsh(post).min() > 0
    # A is ∂(updated mean)/∂(prior mean) with the observation held
    moved = torch.func.jacrev(
        lambda m: joseph_update(m, cov, gain, jac, noise, observed[0] - jac @ m)[0]
    )(mean)
    torch.testing.assert_close(a, moved, rtol=1e-12, atol=1e-12)
    # at Kalman's gain it is the textbook (I − KH) Σ
    _, optimal, _ = joseph_update(mean, cov, kalman, jac, noise, residual[0])
    eye = torch.eye(4, dtype=torch.float64)
    torch.testing.assert_close(optimal, (eye - kalman @ jac) @ cov, rtol=1e-9, atol=1e-12)


def test_the_predicted_covariance_is_exactly_symmetric():
    """``F Σ Fᵀ + Q`` in float32 leaves its halves unequal by rounding; a predict-only step
    (the 1D task's every step) is never symmetrised later, and a Cholesky reads one triangle."""
    generator = torch.Generator().manual_seed(0)
    model = Firefly2DModel()
    theta = model.theta_space.sample((256,), generator=generator)
    root = torch.randn(256, 5, 5, generator=generator)
    cov = root @ root.mT + 0.1 * torch.eye(5)
    cov = 0.5 * (cov + cov.mT)
    mean = torch.randn(256, 5, generator=generator)
    action = torch.rand(256, 2, generator=generator) * 2 - 1
    _, predicted = ekf_predict(model, mean, cov, action, theta)
    assert torch.equal(predicted, predicted.mT)
