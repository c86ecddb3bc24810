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

Where the agent stops, the policy switches within the latent's spread and its posterior given
the actions is far from Gaussian; ``components`` splits the latent into a Gaussian sum for
each trial's last ``final_steps`` steps (measured on the 40-agent 2D recovery: the error in
``log L(θ̂) − log L(θ*)`` against the particle filter falls from a mean 15.5 to 5.9 nats per
agent with 16 components, for about six times the fitting time).

:func:`particle_log_likelihood` estimates the same likelihood without the Gaussian outer
approximation (a particle filter over whole simulated agents): not differentiable and far
costlier, it is the reference that measures what the outer filter loses on given trials.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch.func import vjp, vmap

from irc_torchrl.checks import count
from irc_torchrl.envs.belief import ekf_gain, ekf_predict, ekf_step, joseph_update, symmetrise
from irc_torchrl.envs.model import TaskModel
from irc_torchrl.modules.likelihood import CensoredGaussianActionModel

__all__ = [
    "FINAL_STEPS",
    "MOMENT_RULES",
    "check_mixture",
    "marginal_filter",
    "particle_log_likelihood",
]

#: how the policy's output moments over the uncertain belief are computed
MOMENT_RULES = ("cubature", "linearised")
#: variance added to the outer covariance before its Cholesky factor (it starts at zero)
_JITTER = 1e-10
#: how many of each trial's last steps a mixture scores by default
FINAL_STEPS = 4
#: under a mixture, a component's mean sits at this fraction of the latent's spread (it keeps
#: the rest of the covariance as its own)
_SPLIT_SPREAD = 0.9
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
    components: int = 1,
    final_steps: int = FINAL_STEPS,
    beliefs: bool = True,
) -> tuple[torch.Tensor | None, ...]:
    """Run the outer filter along recorded trials ``[*B, T]``.

    Args:
        theta: the agent's θ, ``[*B, d]``; ``task_theta`` the world's (its observation noise
            drives the agent's belief).
        nuisance: the action model's nuisance, ``[*B, dn]``: log motor-noise stds, then
            ``logit_lapse`` when the rate is fitted.
        state, action: recorded, ``[*B, T, ds]`` and ``[*B, T, da]``.
        target: ``[*B, dt]``.
        mask: the recorded steps ``[*B, T]``; a trial is filtered up to its last recorded step
            only (trials of a dataset differ in length), later outputs are zero.
        generator: if given, each step also scores an action drawn from its predictive
            distribution (``action_model.log_prob_of_gaussian_draw``, lapses included;
            under a mixture, from its moment-matched Gaussian).
        moments: one of :data:`MOMENT_RULES`, how the policy's output over the uncertain
            belief is predicted (a cubature rule, or the tangent at the mean).
        components: above 1, the outer Gaussian splits into that many narrower ones (a
            Gaussian sum with the same mean and covariance) ``final_steps`` steps before each
            trial's end: there the agent stops or creeps on, its belief given the actions is
            far from Gaussian, and one Gaussian mis-scores the stop by a θ-dependent amount.
        final_steps: how many of each trial's last steps the mixture scores.
        beliefs: also return the beliefs at every step; a fit needs the likelihood alone,
            and without them a pass neither gathers nor reorders ``[*B, T, ds, ds]`` tensors.

    Returns:
        per-step ``log p(a_t | a_{<t}, s)`` ``[*B, T]``; the recovered belief mean
        ``E[z_t | a_{≤t}]`` ``[*B, T, ds]``; the agent's own belief covariance ``P_t``
        ``[*B, T, ds, ds]`` (under a mixture, its posterior average); the uncertainty of the
        recovered mean ``[*B, T, ds, ds]`` (these three ``None`` without ``beliefs``); and
        per step the log-probability of the drawn action ``[*B, T]`` (zeros without
        ``generator``).
    """
    if moments not in MOMENT_RULES:
        raise ValueError(f"moments: expected one of {MOMENT_RULES}, got {moments!r}")
    check_mixture(model, components, final_steps)
    batch, steps = state.shape[:-2], state.shape[-2]
    flat = batch.numel()
    ds = model.state_dim
    if mask is None:
        length = torch.full((flat,), steps, device=state.device)
    else:
        steps_in = torch.arange(1, steps + 1, device=state.device) * mask.reshape(flat, steps)
        length = steps_in.amax(-1)
    # longest trials first: the trials still running at any step are a prefix of the rows
    order = length.argsort(descending=True, stable=True)
    length = length[order]
    theta, nuisance, target, task_theta = (
        x.reshape(flat, x.shape[-1])[order] for x in (theta, nuisance, target, task_theta)
    )
    state, action = state.reshape(flat, steps, ds)[order], action.reshape(flat, steps, -1)[order]
    recorded = _Recorded(
        model, action_model, _cubature if moments == "cubature" else _linearised,
        theta, nuisance, state, action, target, task_theta, generator, beliefs,
    )  # fmt: skip
    mean, cov = model.initial_belief(state[:, 0], target, theta)
    # the agent starts from a belief the experimenter knows
    start = (mean.unsqueeze(1), cov.unsqueeze(1), torch.zeros_like(cov).unsqueeze(1))
    split = length if components == 1 else torch.minimum(length, (length - final_steps).clamp(1))
    outputs, carried = _outer_pass(
        recorded, torch.zeros_like(split), split, *start, carry=components > 1
    )
    rest = length - split
    mixed = int((rest > 0).sum())  # a prefix of the rows
    if components > 1 and mixed:
        mixture = _split(*(x[:mixed] for x in carried), components)
        late, _ = _outer_pass(recorded, split, rest[:mixed], *mixture)
        # the mixture's steps take their places after each trial's first ``split`` steps
        later = torch.arange(late[0].shape[1], device=state.device)
        row, offset = (later < rest.unsqueeze(-1)).nonzero(as_tuple=True)
        outputs = [
            None if head is None else head.index_put((row, split[row] + offset), tail[row, offset])
            for head, tail in zip(outputs, late, strict=True)
        ]
    unsort = order.argsort()
    return tuple(
        None if x is None else x[unsort].reshape(*batch, steps, *x.shape[2:]) for x in outputs
    )


def check_mixture(model: TaskModel, components: int, final_steps: int) -> None:
    """Refuse a mixture that cannot match the latent's covariance, or scores no step."""
    if components != 1 and components <= model.state_dim:
        raise ValueError(
            f"components: expected 1 or more than the belief's {model.state_dim} dimensions, "
            f"got {components}"
        )
    count("components", components)
    count("final_steps", final_steps)


class _Recorded(NamedTuple):
    """What every step of the outer filter reads: the task, the rule, the sorted trials."""

    model: TaskModel
    action_model: CensoredGaussianActionModel
    predict: Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]
    theta: torch.Tensor
    nuisance: torch.Tensor
    state: torch.Tensor
    action: torch.Tensor
    target: torch.Tensor
    task_theta: torch.Tensor
    generator: torch.Generator | None
    beliefs: bool


def _outer_pass(
    recorded: _Recorded,
    start: torch.Tensor,
    count: torch.Tensor,
    mean: torch.Tensor,
    cov: torch.Tensor,
    outer: torch.Tensor,
    carry: bool = False,
) -> tuple[list[torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None]:
    """Filter ``count`` steps of each trial from step ``start`` (rows with ``count``
    non-increasing), each trial's latent a mixture of ``M`` equally weighted Gaussians.

    Args:
        mean, cov, outer: per trial and component, the agent's belief mean and covariance
            and the outer covariance of that mean, ``[n, M, ds(, ds)]``.
        carry: also carry each trial's mixture on to the step after its last.

    Returns:
        the five per-step outputs of :func:`marginal_filter` at the steps after ``start``
        (rows sorted, ``[n, T, ...]``), and with ``carry`` the carried mixture
        (``[n, M, ...]``).
    """
    model, action_model, predict, theta, nuisance, state, action, target, task_theta = recorded[:9]
    generator, beliefs = recorded.generator, recorded.beliefs
    n_rows, m = mean.shape[:2]
    steps, ds = state.shape[1], state.shape[2]
    step_index = torch.arange(int(count.max()), device=count.device)
    running = [int(n) for n in (count.unsqueeze(-1) > step_index).sum(0)]
    log_weight = torch.full((n_rows, m), -math.log(m), dtype=mean.dtype, device=mean.device)

    def components(x: torch.Tensor) -> torch.Tensor:
        return x if m == 1 else x.repeat_interleave(m, 0)

    def policy(
        z: torch.Tensor, p: torch.Tensor, tg: torch.Tensor, step: torch.Tensor, th: torch.Tensor
    ) -> torch.Tensor:
        return action_model.actor(model.belief_features(z, p, tg, step, th))

    logps, means, covs, outers, draws = [], [], [], [], []
    finished = [tuple(x[running[0] if running else 0 :] for x in (mean, cov, outer))]
    for k, n in enumerate(running):
        rows = torch.arange(n, device=state.device)
        t = start[:n] + k
        mean, cov, outer, log_weight = mean[:n], cov[:n], outer[:n], log_weight[:n]
        z, p, o = (x.flatten(0, 1) for x in (mean, cov, outer))
        step = t.unsqueeze(-1)
        a_t, th = action[rows, t], theta[:n]
        scored = model.scored_actions(a_t, step)
        *predicted, o = predict(policy, z, o, p, *map(components, (target[:n], step, th)))
        logp, shift, o, drawn = action_model.assimilate(
            *predicted, o, components(a_t), components(nuisance[:n]),
            None if scored is None else components(scored),
        )  # fmt: skip
        z = z + shift
        if m == 1:
            logps.append(logp)
            if beliefs:
                means.append(z)
                covs.append(p)
                outers.append(o)
        else:
            # the predictive is the mixture's; actions are drawn from its moments
            weight = log_weight.exp().unsqueeze(-1)
            a_mean, a_var = (x.view(n, m, -1) for x in drawn)
            drawn_mean = (weight * a_mean).sum(1)
            drawn = drawn_mean, (weight * (a_var + (a_mean - drawn_mean.unsqueeze(1)) ** 2)).sum(1)
            joint = log_weight + logp.view(n, m)  # the weights are normalised: Σ exp = 1
            logps.append(joint.logsumexp(-1))
            log_weight = joint.log_softmax(-1)
            if beliefs:
                weight = log_weight.exp()[..., None, None]
                z_m, o_m = z.view(n, m, ds, 1), o.view(n, m, ds, ds)
                recovered = (weight * z_m).sum(1)
                spread = z_m - recovered.unsqueeze(1)
                means.append(recovered.squeeze(-1))
                covs.append((weight * cov).sum(1))
                outers.append((weight * (o_m + spread @ spread.mT)).sum(1))
        if generator is not None:
            draws.append(
                action_model.log_prob_of_gaussian_draw(*drawn, nuisance[:n], generator, scored)
            )
        below = running[k + 1] if k + 1 < len(running) else 0
        if not (below or carry):
            break
        # the agent's filter, linearised at each component's recovered mean, to the next step
        nxt = components(state[rows, (t + 1).clamp_max(steps - 1)])
        carried = _propagate(
            model, z, p, o, components(a_t), nxt, components(th), components(task_theta[:n])
        )
        mean, cov, outer = (x.view(n, m, *x.shape[1:]) for x in carried)
        finished.append(tuple(x[below:] for x in (mean, cov, outer)))

    def stack(xs: list[torch.Tensor]) -> torch.Tensor | None:
        if not xs:
            return None
        padded = [torch.cat([x, x.new_zeros(n_rows - len(x), *x.shape[1:])]) for x in xs]
        padded += [padded[0].new_zeros(padded[0].shape)] * (steps - len(padded))
        return torch.stack(padded, 1)

    draws = stack(draws) if draws else torch.zeros_like(stack(logps))
    carried = (
        tuple(torch.cat(parts) for parts in zip(*reversed(finished), strict=True))
        if carry
        else None
    )
    return [stack(logps), stack(means), stack(covs), stack(outers), draws], carried


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
    count("n_particles", n_particles)
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
        u = torch.rand(b, 1, dtype=dtype, generator=generator, device=generator.device)
        u = u.to(device)
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
            noise = torch.randn(
                b * n, root.shape[-1], 1, dtype=dtype, generator=generator, device=generator.device
            )
            observation = model.observe(nxt, world_p) + (root @ noise.to(device)).squeeze(-1)
        moved = ekf_step(model, mean, cov, a_t, observation, theta_p)
        mean = torch.where(keep, moved[0], mean)
        cov = torch.where(keep.unsqueeze(-1), moved[1], cov)
    return total, ess


def _propagate(
    model: TaskModel,
    mean: torch.Tensor,
    cov: torch.Tensor,
    outer: torch.Tensor,
    action: torch.Tensor,
    next_state: torch.Tensor,
    theta: torch.Tensor,
    task_theta: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The agent's filter to the next recorded state, linearised at the recovered mean, and the
    outer covariance carried through it (the world's observation noise moves the mean). The
    world observes the state under its own θ; the agent predicts that under its θ."""
    jac_f = model.transition_jacobian(mean, action, theta)
    prior, prior_cov = ekf_predict(model, mean, cov, action, theta)
    gain, jac_h, agent_noise = ekf_gain(model, prior, prior_cov, theta)
    residual = model.observe(next_state, task_theta) - model.observe(prior, theta)
    mean, cov, a = joseph_update(prior, prior_cov, gain, jac_h, agent_noise, residual)
    world_noise = model.observation_cov(next_state, task_theta)
    outer = (a @ jac_f) @ outer @ (a @ jac_f).mT + gain @ world_noise @ gain.mT
    return mean, cov, symmetrise(outer)


def _split(
    mean: torch.Tensor, cov: torch.Tensor, outer: torch.Tensor, m: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One Gaussian latent per trial ``[n, 1, ...]`` as ``m`` equally weighted narrower ones
    with the same mean and covariance: their means at :data:`_SPLIT_SPREAD` times whitened
    quasi-random offsets of its spread, each keeping the rest of the covariance."""
    n, _, ds = mean.shape
    root = _covariance_root(outer[:, 0])
    offsets = _whitened_normal(m, ds).to(mean)
    means = mean + _SPLIT_SPREAD * (root.unsqueeze(1) @ offsets.unsqueeze(-1)).squeeze(-1)
    kept = (1 - _SPLIT_SPREAD**2) * outer
    return means, cov.expand(n, m, ds, ds), kept.expand(n, m, ds, ds)


def _covariance_root(cov: torch.Tensor) -> torch.Tensor:
    """A lower-triangular ``L`` with ``L Lᵀ ≈ cov``, also where round-off left ``cov`` slightly
    indefinite: an action nearly noise-free in the latent (tiny motor noise) conditions the
    outer covariance to rank deficiency, and those rows are loaded just past their lowest
    eigenvalue (a constant shift, so the gradient still flows through the factor). A row the
    task's methods made NaN keeps a NaN root: its likelihood is NaN, the other rows' are not."""
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    root, info = torch.linalg.cholesky_ex(cov + _JITTER * eye)
    finite = torch.isfinite(cov).all(-1).all(-1)
    if not finite.all():  # (only then: the backward pass of every other call stays as it was)
        root = torch.where(finite[..., None, None], root, torch.nan)
    failed = (info > 0) & finite
    if failed.any():
        low = torch.linalg.eigvalsh(cov[failed].detach())[..., 0]
        scale = cov[failed].detach().diagonal(dim1=-2, dim2=-1).amax(-1)
        shift = _JITTER + (-low).clamp_min(0) + 1e-12 * scale
        loaded = cov[failed] + 2 * shift[..., None, None] * eye
        root = root.masked_scatter(failed[..., None, None], torch.linalg.cholesky(loaded))
    return root


def _whitened_normal(m: int, d: int) -> torch.Tensor:
    """``m`` fixed points in ``d`` dimensions with mean exactly 0 and covariance exactly I:
    scrambled Sobol points through the normal quantile, centred and whitened."""
    u = torch.quasirandom.SobolEngine(d, scramble=True, seed=0).draw(m, dtype=torch.float64)
    x = torch.special.ndtri(u.clamp(1e-6, 1 - 1e-6))
    x = x - x.mean(0)
    root = torch.linalg.cholesky(x.mT @ x / m)
    return torch.linalg.solve_triangular(root, x.mT, upper=False).mT


def _linearised(
    policy: Callable[..., torch.Tensor], z: torch.Tensor, outer: torch.Tensor, *args: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of ``π`` over ``N(z, outer)``, with the policy linearised at the mean ``z``
    (and ``outer`` itself, the covariance they are exact for)."""
    out, jac = _rowwise_jacobian(policy, z, *args)
    cross = outer @ jac.mT
    return out, cross, jac @ cross, outer


def _cubature(
    policy: Callable[..., torch.Tensor], z: torch.Tensor, outer: torch.Tensor, *args: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of ``π`` over ``N(z, outer)``: the mean, the covariance with the latent and the
    covariance of ``π``, by the spherical cubature rule (2 dz points at ±√dz standard
    deviations); and the covariance the points span (``outer`` loaded by the factor's jitter),
    from which the action's update must subtract so that the outer covariance stays positive
    (subtracted from the unloaded one, a nearly noise-free action drove it negative and on to
    overflow within a trial).

    Unlike the linearisation, it sees how the policy bends within the belief's spread: near
    the target the steering flips with the believed bearing, and a tangent at the mean
    predicts the action with a confidence the agent's own uncertainty does not support.
    """
    n, dz = z.shape
    root = _covariance_root(outer)
    offsets = math.sqrt(dz) * torch.cat([root.mT, -root.mT], 1)  # [n, 2 dz, dz]
    points = (z.unsqueeze(1) + offsets).reshape(n * 2 * dz, dz)
    out = policy(points, *(a.repeat_interleave(2 * dz, 0) for a in args)).view(n, 2 * dz, -1)
    mean = out.mean(1)
    spread = out - mean.unsqueeze(1)
    return mean, offsets.mT @ spread / (2 * dz), spread.mT @ spread / (2 * dz), root @ root.mT


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
