"""The agent's belief as a latent state: the action likelihood with its observations integrated.

An experimenter sees the states and actions but not the agent's noisy observations, so the
agent's belief mean ``z_t`` is unknown to them: it is driven by observation noise and read out
through the actions. Given the agent's θ, its belief covariance ``P_t`` is fixed by the filter
and ``z_t`` moves linearly in that noise (to first order)::

    z_{t+1} = f(z_t, a_t) + K_{t+1} (h(s_{t+1}) + v_{t+1} - h(f(z_t, a_t))),   v ~ N(0, R_world)
    a_t     = clip(π(z_t, P_t, θ) + ε_t),                                   ε ~ N(0, σ_m²)

An outer Kalman filter over ``z`` gives ``log p(a_{0:T} | s_{0:T}, θ)`` with the agent's
observations integrated out; the policy's output and its covariance with ``z`` come from a
cubature rule over ``z``'s spread (an unscented-style filter; or, cheaper, from the actor
linearised at the current estimate, as exact inverse LQG is in the linear case); and
``E[z_t | actions so far]``, the agent's belief as recovered from its behaviour. With the
outer covariance held at zero this reduces to the hard E-step (observations at their most
probable value, ``method="map"``).

:func:`particle_log_likelihood` estimates the same likelihood without the Gaussian outer
approximation (a particle filter over whole simulated agents): not differentiable and far
costlier, it is the reference that measures what the outer filter loses on given trials.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch.func import vjp, vmap

from irc_torchrl.envs.belief import ekf_gain, ekf_predict, ekf_step, joseph_update
from irc_torchrl.envs.model import TaskModel
from irc_torchrl.modules.likelihood import CensoredGaussianActionModel, gaussian_log_prob_of_draw

__all__ = ["MOMENT_RULES", "marginal_filter", "particle_log_likelihood"]

#: how the policy's output moments over the uncertain belief are computed
MOMENT_RULES = ("cubature", "linearised")
#: variance added to the outer covariance before its Cholesky factor (it starts at zero)
_JITTER = 1e-10
#: how many particles (trials × particles) one chunk of :func:`particle_log_likelihood` holds
_PARTICLE_BUDGET = 2**18


def marginal_filter(
    model: TaskModel,
    action_model: CensoredGaussianActionModel,
    theta: torch.Tensor,
    nuisance: torch.Tensor,
    state: torch.Tensor,
    action: torch.Tensor,
    target: torch.Tensor,
    task_theta: torch.Tensor,
    mask: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    moments: str = "cubature",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Run the outer filter along recorded trials ``[*B, T]``.

    Args:
        theta: the agent's θ, ``[*B, d]``; ``task_theta`` the world's (its observation noise
            drives the agent's belief).
        nuisance: the action model's log motor-noise std, ``[*B, da]``.
        state, action: recorded, ``[*B, T, ds]`` and ``[*B, T, da]``.
        target: ``[*B, dt]``.
        mask: the recorded steps ``[*B, T]``; a trial is filtered up to its last recorded step
            only (trials of a dataset differ in length), later outputs are zero.
        generator: if given, each step also scores an action drawn from its predictive
            distribution (:func:`~irc_torchrl.modules.likelihood.gaussian_log_prob_of_draw`).
        moments: one of :data:`MOMENT_RULES`, how the policy's output over the uncertain
            belief is predicted (a cubature rule, or the tangent at the mean).

    Returns:
        per-step ``log p(a_t | a_{<t}, s)`` ``[*B, T]``; the recovered belief mean
        ``E[z_t | a_{≤t}]`` ``[*B, T, ds]``; the agent's own belief covariance ``P_t``
        ``[*B, T, ds, ds]``; the uncertainty of the recovered mean ``[*B, T, ds, ds]``; and
        per step the log-probability of the drawn action ``[*B, T]`` (zeros without
        ``generator``).
    """
    if moments not in MOMENT_RULES:
        raise ValueError(f"moments: expected one of {MOMENT_RULES}, got {moments!r}")
    batch, steps = state.shape[:-2], state.shape[-2]
    flat = batch.numel()
    ds = model.state_dim
    if mask is None:
        length = torch.full((flat,), steps, device=state.device)
    else:
        recorded = torch.arange(1, steps + 1, device=state.device) * mask.reshape(flat, steps)
        length = recorded.amax(-1)
    # longest trials first: the trials still running at step t are a prefix of the rows
    order = length.argsort(descending=True, stable=True)
    running = length[order].unsqueeze(0) > torch.arange(steps, device=state.device)[:, None]
    running = running.sum(-1).tolist()
    theta, nuisance, target, task_theta = (
        x.reshape(flat, x.shape[-1])[order] for x in (theta, nuisance, target, task_theta)
    )
    state, action = state.reshape(flat, steps, ds)[order], action.reshape(flat, steps, -1)[order]
    mean, cov = model.initial_belief(state[:, 0], target, theta)
    outer = torch.zeros_like(cov)  # the agent starts from a belief the experimenter knows
    predict = _cubature if moments == "cubature" else _linearised

    def policy(z, p, tg, step, th):
        return action_model.actor(model.belief_features(z, p, tg, step, th))

    logps, means, covs, outers, draws = [], [], [], [], []
    for t in range(steps):
        n = running[t]
        if n == 0:
            break
        mean, cov, outer = mean[:n], cov[:n], outer[:n]
        step = torch.full((n, 1), t, dtype=torch.long, device=state.device)
        predicted = predict(policy, mean, outer, cov, target[:n], step, theta[:n])
        scored = model.scored_actions(action[:n, t], step)
        logp, shift, outer, (m, var) = action_model.assimilate(
            *predicted, outer, action[:n, t], nuisance[:n], scored
        )
        if generator is not None:
            draws.append(gaussian_log_prob_of_draw(m, var, generator, scored))
        mean = mean + shift
        logps.append(logp)
        means.append(mean)
        covs.append(cov)
        outers.append(outer)
        if t + 1 == steps or running[t + 1] == 0:
            break
        # the agent's filter, linearised at the recovered mean
        a_t, th = action[:n, t], theta[:n]
        jac_f = model.transition_jacobian(mean, a_t, th)
        prior, prior_cov = ekf_predict(model, mean, cov, a_t, th)
        gain, jac_h, agent_noise = ekf_gain(model, prior, prior_cov, th)
        residual = model.observe(state[:n, t + 1], th) - model.observe(prior, th)
        mean, cov, a = joseph_update(prior, prior_cov, gain, jac_h, agent_noise, residual)
        world_noise = model.observation_cov(state[:n, t + 1], task_theta[:n])
        outer = (a @ jac_f) @ outer @ (a @ jac_f).mT + gain @ world_noise @ gain.mT
        outer = 0.5 * (outer + outer.mT)

    unsort = order.argsort()

    def stack(xs):
        padded = [torch.cat([x, x.new_zeros(flat - len(x), *x.shape[1:])]) for x in xs]
        padded += [padded[0].new_zeros(padded[0].shape)] * (steps - len(padded))
        out = torch.stack(padded, 1)[unsort]
        return out.reshape(*batch, steps, *out.shape[2:])

    draws = stack(draws) if draws else torch.zeros_like(stack(logps))
    return stack(logps), stack(means), stack(covs), stack(outers), draws


@torch.no_grad()
def particle_log_likelihood(
    model: TaskModel,
    action_model: CensoredGaussianActionModel,
    theta: torch.Tensor,
    nuisance: torch.Tensor,
    state: torch.Tensor,
    action: torch.Tensor,
    target: torch.Tensor,
    task_theta: torch.Tensor,
    mask: torch.Tensor | None = None,
    n_particles: int = 1000,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``log p(a_{0:T} | s_{0:T}, θ)`` per trial by a bootstrap particle filter, ``[*B]``.

    Each particle is one agent: it draws its observations from the world's noise given the
    recorded states, runs its own filter (linearised at its own belief) and is weighted by the
    recorded action; the particles are then resampled (systematically). The estimate of the
    likelihood (not of its log) is unbiased and exact as ``n_particles`` grows, with no
    Gaussian approximation of the agent's belief; what :func:`marginal_filter` loses against
    it is the cost of that approximation, large where the policy switches within the belief's
    spread. Arguments as for :func:`marginal_filter`.

    Returns:
        the log-likelihood estimate ``[*B]`` and the smallest effective sample size of the
        weights over the trial's steps ``[*B]`` (near 1: too few particles for that trial).
    """
    if n_particles < 1:
        raise ValueError(f"n_particles: expected an integer ≥ 1, got {n_particles}")
    generator = generator if generator is not None else torch.Generator().manual_seed(0)
    batch, steps = state.shape[:-2], state.shape[-2]
    flat = batch.numel()
    mask = (
        torch.ones(*batch, steps, dtype=torch.bool, device=state.device) if mask is None else mask
    )
    rows = (
        x.reshape(flat, *x.shape[len(batch) :])
        for x in (theta, nuisance, state, action, target, task_theta, mask)
    )
    size = max(1, _PARTICLE_BUDGET // n_particles)
    parts = [
        _particle_chunk(model, action_model, *chunk, n_particles, generator)
        for chunk in zip(*(x.split(size) for x in rows), strict=True)
    ]
    log_likelihood, ess = (torch.cat(x).reshape(batch) for x in zip(*parts, strict=True))
    return log_likelihood, ess


def _particle_chunk(
    model: TaskModel,
    action_model: CensoredGaussianActionModel,
    theta: torch.Tensor,
    nuisance: torch.Tensor,
    state: torch.Tensor,
    action: torch.Tensor,
    target: torch.Tensor,
    task_theta: torch.Tensor,
    mask: torch.Tensor,
    n: int,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`particle_log_likelihood` for rows ``[B]`` (trials), ``n`` particles each."""
    b, steps = mask.shape
    device, dtype = state.device, state.dtype

    def per_particle(x: torch.Tensor) -> torch.Tensor:
        return x.repeat_interleave(n, 0)

    theta_p, nuisance_p, target_p, world_p = map(
        per_particle, (theta, nuisance, target, task_theta)
    )
    mean, cov = model.initial_belief(per_particle(state[:, 0]), target_p, theta_p)
    total = torch.zeros(b, dtype=dtype, device=device)
    ess = torch.full((b,), float(n), dtype=dtype, device=device)
    offset = torch.arange(b, device=device).unsqueeze(-1) * n
    for t in range(steps):
        live = mask[:, t]
        if not live.any():
            break
        step = torch.full((b * n, 1), t, dtype=torch.long, device=device)
        a_t = per_particle(action[:, t])
        features = model.belief_features(mean, cov, target_p, step, theta_p)
        scored = model.scored_actions(a_t, step)
        extra = () if scored is None else (scored,)
        logw = action_model.log_prob(features, a_t, nuisance_p, *extra).view(b, n)
        logw = torch.where(live.unsqueeze(-1), logw, torch.zeros_like(logw))
        total = total + logw.logsumexp(-1) - math.log(n)
        weight = torch.softmax(logw, -1)
        ess = torch.where(live, torch.minimum(ess, 1 / (weight**2).sum(-1)), ess)
        if t + 1 == steps or not mask[:, t + 1].any():
            break
        # systematic resampling: one uniform per trial
        u = torch.rand(b, 1, dtype=dtype, generator=generator).to(device)
        grid = (u + torch.arange(n, dtype=dtype, device=device)) / n
        pick = torch.searchsorted(weight.cumsum(-1), grid).clamp_max(n - 1)
        pick = (pick + offset).reshape(-1)
        mean, cov = mean[pick], cov[pick]
        # each particle's own observation of the next recorded state, and its own filter;
        # trials that have ended stay put (their padding is never read)
        keep = per_particle(mask[:, t + 1]).unsqueeze(-1)
        nxt = torch.where(keep, per_particle(state[:, t + 1]), torch.zeros_like(mean))
        observation = None
        if model.observation_dim:
            root = torch.linalg.cholesky(model.observation_cov(nxt, world_p))
            noise = torch.randn(b * n, root.shape[-1], 1, dtype=dtype, generator=generator)
            observation = model.observe(nxt, theta_p) + (root @ noise.to(device)).squeeze(-1)
        moved = ekf_step(model, mean, cov, a_t, observation, theta_p)
        mean = torch.where(keep, moved[0], mean)
        cov = torch.where(keep.unsqueeze(-1), moved[1], cov)
    return total, ess


def _linearised(
    policy: Callable[..., torch.Tensor], z: torch.Tensor, outer: torch.Tensor, *args: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of ``π`` over ``N(z, outer)``, with the policy linearised at the mean ``z``."""
    out, jac = _rowwise_jacobian(policy, z, *args)
    cross = outer @ jac.mT
    return out, cross, jac @ cross


def _cubature(
    policy: Callable[..., torch.Tensor], z: torch.Tensor, outer: torch.Tensor, *args: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of ``π`` over ``N(z, outer)``: the mean, the covariance with the latent and the
    covariance of ``π``, by the spherical cubature rule (2 dz points at ±√dz standard
    deviations).

    Unlike the linearisation, it sees how the policy bends within the belief's spread: near
    the target the steering flips with the believed bearing, and a tangent at the mean
    predicts the action with a confidence the agent's own uncertainty does not support.
    """
    n, dz = z.shape
    eye = torch.eye(dz, dtype=z.dtype, device=z.device)
    root = torch.linalg.cholesky(outer + _JITTER * eye)
    offsets = math.sqrt(dz) * torch.cat([root.mT, -root.mT], 1)  # [n, 2 dz, dz]
    points = (z.unsqueeze(1) + offsets).reshape(n * 2 * dz, dz)
    out = policy(points, *(a.repeat_interleave(2 * dz, 0) for a in args)).view(n, 2 * dz, -1)
    mean = out.mean(1)
    spread = out - mean.unsqueeze(1)
    return mean, offsets.mT @ spread / (2 * dz), spread.mT @ spread / (2 * dz)


def _rowwise_jacobian(
    fn: Callable[..., torch.Tensor], z: torch.Tensor, *args: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``fn(z, *args)`` ``[n, m]`` and its Jacobian in ``z`` per row, ``[n, m, dz]``.

    Rows are independent, so one reverse pass per output dimension (``m`` is the action's
    size, 2 here) gives every row's Jacobian: several times cheaper than forward mode over
    the belief's dimensions under ``vmap``, and differentiable in ``args`` (θ).
    """
    out, pullback = vjp(lambda x: fn(x, *args), z)
    basis = torch.eye(out.shape[-1], dtype=out.dtype, device=out.device)
    (jac,) = vmap(pullback)(basis.unsqueeze(1).expand(-1, *out.shape))
    return out, jac.movedim(0, 1)
