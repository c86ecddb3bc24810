"""The inverse objective (Algorithm 2): the likelihood of an agent's actions under candidate θ.

For each candidate θ the agent's belief is re-run along the recorded trials with the same
filter the agent used (:func:`~irc_torchrl.envs.belief.ekf_step`), fed to the frozen policy
through the action model, and the recorded actions are scored. Where the agent's model is the
world's (``world="shared"``) the recorded state transitions are scored too.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.objectives import LossModule

from irc_torchrl.checks import count, first_line
from irc_torchrl.data.trajectories import TRIAL_KEYS, validate_trials
from irc_torchrl.envs.belief import ekf_step
from irc_torchrl.envs.model import SENSES, TaskModel, continuous_actions, sensed_world
from irc_torchrl.envs.probe import check_model
from irc_torchrl.objectives.marginal import (
    FINAL_STEPS,
    MOMENT_RULES,
    check_mixture,
    marginal_filter,
    particle_log_likelihood,
)
from irc_torchrl.theta import ThetaSpace

__all__ = ["METHODS", "InverseRationalLoss"]

#: the estimators: the paper's hard E-step, and the agent's observations integrated out
METHODS = ("map", "marginal")


class InverseRationalLoss(LossModule):
    """Negative log-likelihood of held trials ``[n_agents, n_trials, T]`` under θ.

    θ to fit lives in ``theta_free`` (unconstrained coordinates of the free parameters, one
    row per agent); fixed parameters take their values from ``theta_space``. The nuisance
    parameters of the action model (e.g. ``log τ``) live in ``nuisance``.

    Args:
        model: the task.
        action_model: scores actions given belief features (by a frozen copy of its network).
        theta_space: which parameters are free; defaults to the model's.
        n_agents: how many agents are fitted at once (independent rows).
        world: ``"known"`` if the world's θ is the recorded ``task_theta`` (actions alone
            inform θ), ``"shared"`` if the agent's model is the world's: the world then runs
            under the candidate θ (its transitions count too, its observations' noise is the
            candidate's, the recorded ``task_theta`` is not read, though :meth:`forward`
            checks it as it checks every recorded field).
        senses: ``"agent"`` if the noise of the agent's observations is its own (the world's
            θ has the task's :attr:`~irc_torchrl.envs.model.TaskModel.sensory_names` from the
            candidate θ: the paper's O_θo, which no experimenter measures), ``"world"`` if it
            is the recorded ``task_theta``'s (a sensory noise measured apart).
        method: ``"map"``, the paper's hard E-step (the agent's observations at their most
            probable value), or ``"marginal"``, the agent's unseen observations integrated out
            by an outer filter over its belief (:mod:`~irc_torchrl.objectives.marginal`).
        moments: with ``"marginal"``, how the policy's output is predicted from the uncertain
            belief: ``"cubature"`` (sigma points; sees the policy bend within the belief's
            spread) or ``"linearised"`` (its tangent at the belief mean; cheaper, but one
            near-target step can cost a trial 100+ nats at the true θ).
        components: with ``"marginal"``, how many Gaussians the outer filter's latent splits
            into for each trial's last ``final_steps`` steps (1: one Gaussian throughout).
            Where the agent stops, its belief given the actions is far from Gaussian and one
            Gaussian mis-scores the stop by an amount that depends on θ.
        final_steps: how many of each trial's last steps the mixture scores.
    """

    @dataclass
    class _AcceptedKeys:
        state: str = "state"
        action: str = "action"
        target: str = "target"
        mask: str = "mask"
        task_theta: str = "task_theta"

    default_keys = _AcceptedKeys
    out_keys = ["loss_nll", "log_likelihood"]

    def __init__(
        self,
        model: TaskModel,
        action_model: nn.Module,
        theta_space: ThetaSpace | None = None,
        n_agents: int = 1,
        world: str = "known",
        senses: str = "agent",
        method: str = "map",
        moments: str = "cubature",
        components: int = 1,
        final_steps: int = FINAL_STEPS,
    ) -> None:
        super().__init__()
        check_model(model)
        n_agents = count("n_agents", n_agents)
        if world not in ("known", "shared"):
            raise ValueError(f"world: expected 'known' or 'shared', got {world!r}")
        if senses not in SENSES:
            raise ValueError(f"senses: expected one of {SENSES}, got {senses!r}")
        if method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
        if method == "marginal" and not hasattr(action_model, "assimilate"):
            raise ValueError(
                f"method: 'marginal' needs a continuous action model with `assimilate`, "
                f"got {type(action_model).__name__}"
            )
        if moments not in MOMENT_RULES:
            raise ValueError(f"moments: expected one of {MOMENT_RULES}, got {moments!r}")
        if not all(hasattr(action_model, name) for name in ("nuisance_init", "log_prob")):
            raise TypeError(
                "action_model: expected an action model with nuisance_init and log_prob (e.g. "
                f"CensoredGaussianActionModel around the policy), got {type(action_model).__name__}"
            )
        _check_action_model(model, action_model)
        self.method = method
        self.moments = moments
        check_mixture(model, components, final_steps)
        self.components, self.final_steps = components, final_steps
        self.model = model
        self.action_model = action_model
        self.theta_space = theta_space if theta_space is not None else model.theta_space
        if self.theta_space.names != model.theta_space.names:
            raise ValueError(
                f"theta_space: expected the task's parameters {model.theta_space.names}, "
                f"got {self.theta_space.names}"
            )
        self.world = world
        self.senses = senses
        free = self.theta_space.free_mask
        start = self.theta_space.to_unconstrained(self.theta_space.default(torch.float64))[free]
        self.theta_free = nn.Parameter(start.expand(n_agents, -1).clone())
        self.nuisance = nn.Parameter(
            action_model.nuisance_init.double().expand(n_agents, -1).clone()
        )
        # which nuisance coordinates the fit holds within bounds (none, unless the model says)
        dn = action_model.nuisance_init.numel()
        bounded = tuple(getattr(action_model, "nuisance_bounded", (False,) * dn))
        if len(bounded) != dn:
            raise ValueError(
                f"nuisance_bounded: expected one flag per nuisance parameter ({dn}), "
                f"got {len(bounded)}"
            )
        self._nuisance_bounded = bounded

    def _forward_value_estimator_keys(self, **kwargs: Any) -> None:
        """No value estimator: the objective is a likelihood, not a TD target."""

    @property
    def in_keys(self) -> list[str]:
        """The trial fields :meth:`forward` reads, under the keys :meth:`set_keys` gave them."""
        keys = self.tensor_keys
        return [keys.state, keys.action, keys.target, keys.mask, keys.task_theta]

    @property
    def parameter_names(self) -> list[str]:
        """Names of the fitted coordinates: free θ, then the nuisance parameters."""
        return [*self.theta_space.free_names, *self.action_model.nuisance_names]

    @property
    def bounded(self) -> torch.Tensor:
        """Which fitted coordinates are bounded logits, ``[p]``: every free θ, and the
        nuisance parameters the action model bounds (a fitted lapse rate)."""
        k = int(self.theta_space.free_mask.sum())
        flags = [True] * k + [bool(b) for b in self._nuisance_bounded]
        return torch.tensor(flags, device=self.theta_free.device)

    def theta(self, theta_free: torch.Tensor | None = None) -> torch.Tensor:
        """Full natural θ ``[n, d]`` from unconstrained free coordinates ``[n, d_free]``."""
        theta_free = self.theta_free if theta_free is None else theta_free
        space = self.theta_space
        full = space.default(theta_free.dtype, theta_free.device).expand(theta_free.shape[0], -1)
        u = space.to_unconstrained(full).clone()
        u[:, space.free_mask.to(theta_free.device)] = theta_free
        natural = space.from_unconstrained(u)
        return torch.where(space.free_mask.to(theta_free.device), natural, full)

    def log_likelihood(
        self,
        theta: torch.Tensor,
        nuisance: torch.Tensor,
        trials: TensorDictBase,
        per_trial: bool = False,
    ) -> torch.Tensor:
        """Log-likelihood of trials ``[n_agents, n_trials, T]``: per agent ``[n_agents]``.

        θ ``[n_agents, d]`` and the nuisance ``[n_agents, dn]`` may also be given per trial
        (``[n_agents, n_trials, ·]``); with ``per_trial`` each trial's own log-likelihood
        ``[n_agents, n_trials]`` is returned (what per-trial scores are made of). Neither θ
        nor the trials are checked here (the fit calls this for every row of every pass, and
        one row's NaN must not stop the others): :meth:`forward` and ``fit_theta`` check
        theirs, and a θ outside its space extrapolates the networks. The filter runs in θ's
        dtype: pass float64, as ``fit_theta`` does (float32 moved one agent's value by 1.65
        nats).
        """
        total, _ = self.log_likelihood_and_draws(theta, nuisance, trials)
        return total if per_trial else total.sum(1)

    def log_likelihood_and_draws(
        self,
        theta: torch.Tensor,
        nuisance: torch.Tensor,
        trials: TensorDictBase,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Per-trial log-likelihood ``[n_agents, n_trials]`` and, with ``generator``, the
        log-probability of data drawn from the model along the same filter (held fixed).

        The gradient of the second is a sampled score: its outer product summed over trials
        estimates the Fisher information (what ``fit_theta(curvature="fisher")`` steps with).
        """
        theta_b, nuisance_b, state, action, target, mask, task_theta = self._fields(
            theta, nuisance, trials
        )
        if self.method == "marginal":
            logp, *_, draws = marginal_filter(
                self.model, self.action_model, theta_b, nuisance_b, state, action.to(state.dtype),
                target, task_theta, mask, generator, self.moments, self.components,
                self.final_steps, beliefs=False,
            )  # fmt: skip
            total = torch.where(mask, logp, torch.zeros_like(logp)).sum(2)
            drawn = torch.where(mask, draws, torch.zeros_like(draws)).sum(2)
        else:
            total, drawn = self._map_log_likelihood(
                theta_b, nuisance_b, state, action, target, mask, task_theta, generator
            )
        if self.world == "shared":
            moved, moved_drawn = self._transition_log_likelihood(
                theta_b, state, action, mask, generator
            )
            total, drawn = total + moved, drawn + moved_drawn
        return total, drawn if generator is not None else None

    def particle_log_likelihood(
        self,
        theta: torch.Tensor,
        nuisance: torch.Tensor,
        trials: TensorDictBase,
        n_particles: int = 1000,
        seed: int = 0,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The likelihood both estimators approximate, per trial ``[n_agents, n_trials]``, by a
        particle filter (:func:`~irc_torchrl.objectives.marginal.particle_log_likelihood`),
        and each trial's smallest effective sample size.

        Compared with :meth:`log_likelihood` (``per_trial=True``) at θ̂ and nearby θ, it shows
        what the estimator's approximation costs on these trials, and whether that cost
        depends on θ (which biases θ̂). Needs a continuous action model.
        """
        if not hasattr(self.action_model, "assimilate"):
            raise ValueError(
                "particle_log_likelihood: needs a continuous action model, "
                f"got {type(self.action_model).__name__}"
            )
        theta_b, nuisance_b, state, action, target, mask, task_theta = self._fields(
            theta, nuisance, trials
        )
        generator = torch.Generator().manual_seed(seed)
        total, ess = particle_log_likelihood(
            self.model, self.action_model, theta_b, nuisance_b, state, action.to(state.dtype),
            target, task_theta, mask, n_particles, generator,
        )  # fmt: skip
        if self.world == "shared":
            total = total + self._transition_log_likelihood(theta_b, state, action, mask, None)[0]
        return total, ess

    def _fields(
        self, theta: torch.Tensor, nuisance: torch.Tensor, trials: TensorDictBase
    ) -> tuple[torch.Tensor, ...]:
        """The recorded fields in θ's dtype, and θ and the nuisance per trial.

        Steps after a trial's end may hold anything, NaN too: the filters run over them (their
        terms are dropped), and a NaN there would still poison the gradient (0 × NaN), so the
        state and action are zeroed there before anything reads them.
        """
        keys = self.tensor_keys
        dtype = theta.dtype
        mask = trials[keys.mask]
        state = trials[keys.state].to(dtype).masked_fill(~mask.unsqueeze(-1), 0)
        action = trials[keys.action]
        if action.is_floating_point():
            action = action.masked_fill(~mask.view(*mask.shape, *[1] * (action.ndim - 3)), 0)
        target = trials[keys.target][:, :, 0].to(dtype)
        theta_b, nuisance_b = (
            x if x.dim() == 3 else x.unsqueeze(1).expand(*state.shape[:2], -1)
            for x in (theta, nuisance)
        )
        # a shared world is the agent's own: the candidate θ runs it
        task_theta = (
            theta_b if self.world == "shared" else trials[keys.task_theta][:, :, 0].to(dtype)
        )
        task_theta = sensed_world(self.model, task_theta, theta_b, self.senses)
        return theta_b, nuisance_b, state, action, target, mask, task_theta

    def _map_log_likelihood(
        self,
        theta_b: torch.Tensor,
        nuisance_b: torch.Tensor,
        state: torch.Tensor,
        action: torch.Tensor,
        target: torch.Tensor,
        mask: torch.Tensor,
        task_theta: torch.Tensor,
        generator: torch.Generator | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The hard E-step: beliefs along the most probable observations, then the actions."""
        means, covs = self.beliefs(theta_b, state, action, target, task_theta)
        steps = torch.arange(state.shape[2], device=state.device).view(1, 1, -1, 1)
        features = self.model.belief_features(
            means, covs, target.unsqueeze(2), steps, theta_b.unsqueeze(2)
        )[mask]  # score only the recorded steps: trials end at different times
        nuisance = nuisance_b.unsqueeze(2).expand(*mask.shape, -1)[mask]
        scored = self.model.scored_actions(action, steps.expand(*mask.shape, 1))
        # a task that scores every component keeps the action model's own signature
        extra = () if scored is None else (scored[mask],)
        logp = self.action_model.log_prob(features, action[mask], nuisance, *extra)
        drawn = (
            self.action_model.log_prob_of_draw(features, nuisance, generator, *extra)
            if generator is not None
            else torch.zeros_like(logp)
        )
        per_trial = torch.zeros(2, *mask.shape, dtype=logp.dtype, device=state.device)
        per_trial = per_trial.masked_scatter(mask, torch.stack([logp, drawn]))
        return per_trial[0].sum(2), per_trial[1].sum(2)

    def recovered_beliefs(
        self, theta: torch.Tensor, nuisance: torch.Tensor, trials: TensorDictBase
    ) -> TensorDict:
        """The agent's belief at every recorded step under θ (e.g. θ̂), ``[A, n, T]``.

        ``("belief", "mean")`` and ``("belief", "cov")`` are the agent's belief; with
        ``method="marginal"`` the mean is its posterior mean given the actions so far and
        ``("belief", "mean_cov")`` says how well the actions pin it down (zero for ``map``).
        θ ``[A, d]`` and the nuisance ``[A, dn]`` (either may be per trial, ``[A, n, ·]``) and the
        trials are checked first (:meth:`checked`).
        """
        trials = self.checked(theta, nuisance, trials, per_trial=True)
        theta_b, nuisance_b, state, action, target, mask, task_theta = self._fields(
            theta, nuisance, trials
        )
        action = action.to(state.dtype)
        if self.method == "marginal":
            _, mean, cov, mean_cov, _ = marginal_filter(
                self.model, self.action_model, theta_b, nuisance_b, state, action, target,
                task_theta, mask, moments=self.moments, components=self.components,
                final_steps=self.final_steps,
            )  # fmt: skip
        else:
            mean, cov = self.beliefs(theta_b, state, action, target, task_theta)
            mean_cov = torch.zeros_like(cov)
        return TensorDict(
            {"belief": {"mean": mean, "cov": cov, "mean_cov": mean_cov}},
            batch_size=state.shape[:3],
        )

    def beliefs(
        self,
        theta_b: torch.Tensor,
        state: torch.Tensor,
        action: torch.Tensor,
        target: torch.Tensor,
        task_theta: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The agent's beliefs ``[A, n, T, ds]``, ``[A, n, T, ds, ds]`` at every recorded step.

        The filter runs under ``theta_b`` along the recorded actions; where the task has
        observations, the agent's are taken at their most probable value given the recorded
        state (the paper's hard E-step): the world's observation of it, under ``task_theta``
        (the world's θ, ``[A, n, d]``; default ``theta_b``, a world that is the agent's).
        """
        world = theta_b if task_theta is None else task_theta
        mean, cov = self.model.initial_belief(state[:, :, 0], target, theta_b)
        means, covs = [mean], [cov]
        for t in range(state.shape[2] - 1):
            observation = (
                self.model.observe(state[:, :, t + 1], world)
                if self.model.observation_dim
                else None
            )
            mean, cov = ekf_step(self.model, mean, cov, action[:, :, t], observation, theta_b)
            means.append(mean)
            covs.append(cov)
        return torch.stack(means, 2), torch.stack(covs, 2)

    def _transition_log_likelihood(
        self,
        theta_b: torch.Tensor,
        state: torch.Tensor,
        action: torch.Tensor,
        mask: torch.Tensor,
        generator: torch.Generator | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per trial ``Σ log N(s_{t+1}; f(s_t, a_t, θ), Q(θ))`` over consecutive valid steps,
        and the same for next states drawn from that Gaussian with ``generator`` (else 0)."""
        prev, nxt = state[:, :, :-1], state[:, :, 1:]
        theta_t = theta_b.unsqueeze(2).expand(*prev.shape[:3], -1)
        mean = self.model.transition(prev, action[:, :, :-1], theta_t)
        cov = self.model.process_cov(prev, action[:, :, :-1], theta_t)
        chol = torch.linalg.cholesky(cov)
        valid = mask[:, :, :-1] & mask[:, :, 1:]

        def log_prob(x: torch.Tensor) -> torch.Tensor:
            z = torch.linalg.solve_triangular(chol, (x - mean).unsqueeze(-1), upper=False)
            logp = -0.5 * (z.squeeze(-1) ** 2).sum(-1) - chol.diagonal(dim1=-2, dim2=-1).log().sum(
                -1
            )
            logp = logp - 0.5 * state.shape[-1] * math.log(2 * math.pi)
            return torch.where(valid, logp, torch.zeros_like(logp)).sum(2)

        if generator is None:
            return log_prob(nxt), state.new_zeros(valid.shape[:2])
        noise = torch.randn(
            nxt.shape, dtype=nxt.dtype, generator=generator, device=generator.device
        )
        noise = noise.to(nxt.device)
        drawn = (mean + (chol @ noise.unsqueeze(-1)).squeeze(-1)).detach()
        return log_prob(nxt), log_prob(drawn)

    def validate(self, trials: TensorDictBase) -> TensorDictBase:
        """``trials`` as ``[n_agents, n_trials, T]`` if well formed (:func:`validate_trials`),
        read under this loss's keys (:meth:`set_keys`), else a one-line error."""
        if not isinstance(trials, TensorDictBase):
            return validate_trials(trials, self.model)  # refused, naming the type
        present = trials.keys(include_nested=True)
        named = {name: getattr(self.tensor_keys, name) for name in TRIAL_KEYS}
        missing = [key for key in named.values() if key not in present]
        if missing:
            raise KeyError(
                f"trials: missing field(s) {missing}; this loss reads {list(named.values())} "
                "(set_keys names them)"
            )
        kept = {"step": trials.get("step")} if "step" in present else {}  # the env's counter
        validate_trials(  # under the default names, which its messages give
            TensorDict(
                {**{name: trials.get(key) for name, key in named.items()}, **kept},
                batch_size=trials.batch_size,
            ),
            self.model,
        )
        return trials if trials.ndim == 3 else trials.unsqueeze(0)

    def checked(
        self,
        theta: torch.Tensor,
        nuisance: torch.Tensor | None,
        trials: TensorDictBase,
        per_trial: bool = False,
    ) -> TensorDictBase:
        """``trials`` validated (:meth:`validate`) with θ ``[n_agents, d]`` inside its space and
        a finite nuisance ``[n_agents, dn]`` for them (with ``per_trial`` also one per trial,
        ``[n_agents, n_trials, ·]``; ``None``: the action model's initial one, nothing to
        check), else a one-line error naming the field."""
        trials = self.validate(trials)
        self._check_point(theta, nuisance, trials, per_trial)
        return trials

    def _check_point(
        self,
        theta: torch.Tensor,
        nuisance: torch.Tensor | None,
        trials: TensorDictBase,
        per_trial: bool = False,
    ) -> None:
        """:meth:`checked`'s check of θ and the nuisance for validated ``trials``."""
        n_agents, dn = trials.shape[0], self.action_model.nuisance_init.numel()

        def rows(x: torch.Tensor) -> tuple[int, ...]:
            """The leading dimensions ``x`` must have: per agent, or per trial where allowed."""
            return (n_agents, trials.shape[1]) if per_trial and x.ndim == 3 else (n_agents,)

        theta = self.theta_space.validate(theta, "theta")
        each = "per agent" + (" (or per trial)" if per_trial else "")
        if theta.shape != (*rows(theta), self.theta_space.dim):
            raise ValueError(
                f"theta: expected one θ {each}, {[*rows(theta), self.theta_space.dim]}, "
                f"got {list(theta.shape)}"
            )
        if nuisance is None:
            return
        if not isinstance(nuisance, torch.Tensor) or not nuisance.is_floating_point():
            raise TypeError(f"nuisance: expected a float tensor [{n_agents}, {dn}]")
        if nuisance.shape != (*rows(nuisance), dn):
            raise ValueError(
                f"nuisance: expected shape {[*rows(nuisance), dn]}, got {list(nuisance.shape)}"
            )
        if not torch.isfinite(nuisance).all():
            raise ValueError(
                "nuisance: expected finite values (the fit's coordinates), got NaN or inf"
            )

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        """``loss_nll`` of held trials ``[n_agents, n_trials, T]`` (one agent's may be
        ``[n_trials, T]``) and each agent's ``log_likelihood``; malformed trials, and a θ or
        nuisance an optimiser's step sent to NaN, are refused first (:meth:`checked`)."""
        n_agents = self.theta_free.shape[0]
        trials = self.validate(tensordict)
        if trials.shape[0] != n_agents:
            raise ValueError(
                f"trials: expected batch dims [{n_agents} agents, n_trials, T] (this loss's "
                f"n_agents), got {list(tensordict.batch_size)}"
            )
        theta = self.theta(self.theta_free)
        self._check_point(theta.detach(), self.nuisance.detach(), trials)
        log_likelihood = self.log_likelihood(theta, self.nuisance, trials)
        return TensorDict(
            loss_nll=-log_likelihood.sum(), log_likelihood=log_likelihood.detach(), batch_size=[]
        )


def _check_action_model(model: TaskModel, action_model: nn.Module) -> None:
    """Refuse, before any work, an action model whose network does not read this task's
    features into its actions (one trained on another task): it failed deep inside a fit.

    A copy on the CPU (where no index error is fatal, and a model built before ``.to(device)``
    moves its buffers scores as it will there) scores one point as the loss does: every
    discrete action (their probabilities must sum to one), or one continuous action (one
    log-probability, and a policy exposed as ``.actor`` giving the action's size)."""
    probe = copy.deepcopy(action_model).cpu()
    space = model.theta_space
    theta = space.normalise(space.default(torch.float64))
    features = torch.cat([theta.new_zeros(model.belief_feature_dim), theta]).unsqueeze(0)
    nuisance = probe.nuisance_init.to("cpu", torch.float64).unsqueeze(0)
    spec = model.action_spec
    continuous = continuous_actions(spec)
    n = spec.shape[-1] if continuous else spec.n
    expected = (
        f"actions [1, {n}]" if continuous else f"probabilities of its {n} actions summing to 1"
    )
    width = f"belief features [1, {features.shape[-1]}] in float64"
    try:
        with torch.no_grad():
            wrong = _probe(model, probe, features, nuisance, continuous, n)
    except (RuntimeError, KeyError, IndexError, TypeError, ValueError, AttributeError) as error:
        raise ValueError(
            f"action_model: expected a network that scores this task's ({model.name}) {width}, "
            f"got an error ({type(error).__name__}: {first_line(error)}); a network "
            "of another task, or of another dtype?"
        ) from None
    if wrong is not None:
        raise ValueError(
            f"action_model: expected a network that reads this task's ({model.name}) {width} "
            f"into {expected}, got {wrong}; a network trained on another task?"
        )


def _probe(
    model: TaskModel,
    action_model: nn.Module,
    features: torch.Tensor,
    nuisance: torch.Tensor,
    continuous: bool,
    n: int,
) -> str | None:
    """What :func:`_check_action_model` finds wrong at one point (``None``: nothing)."""
    cpu = features.device  # whatever the default device
    action = features.new_zeros(1, n) if continuous else torch.arange(n, device=cpu)
    step = torch.zeros(len(action), 1, dtype=torch.long, device=cpu)
    scored = model.scored_actions(action, step)
    extra = () if scored is None else (scored,)  # as the loss passes it
    if continuous:
        logp = action_model.log_prob(features, action, nuisance, *extra)
        policy = getattr(action_model, "actor", None)
        shape = list(policy(features).shape) if policy is not None else [1, n]
        if shape != [1, n]:
            return f"actions {shape}"
        return f"log-probabilities {list(logp.shape)}" if logp.shape != (1,) else None
    logp = action_model.log_prob(features.expand(n, -1), action, nuisance, *extra)
    mass = float(logp.exp().sum())  # NaN (a Q undefined there) is not judged
    return f"probabilities summing to {mass:.3g}" if abs(mass - 1) > 1e-3 else None
