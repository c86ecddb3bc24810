"""The task model: one description of a POMDP family, shared by env, belief filter and inverse.

A task is written once as a :class:`TaskModel`: θ space, transition ``f(s, a, θ)`` with
Gaussian process noise, observation ``h(s, θ)`` with Gaussian observation noise, the initial
state and belief, the stop rule, and the reward. The environment steps the world with the
task's θ, :class:`~irc_torchrl.envs.belief.EKFBelief` runs the agent's belief with the agent's
θ, and the inverse objective re-runs that filter under candidate θ.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import torch
from torchrl.data import Categorical, TensorSpec

from irc_torchrl.theta import ThetaSpace

__all__ = [
    "ABSURD",
    "SENSES",
    "TaskModel",
    "action_in_spec",
    "bounded_box",
    "check_action_spec",
    "continuous_actions",
    "own_theta_space",
    "sensed_world",
]

#: a recorded rate this many times the largest gain of its unit in the θ space is taken as a
#: unit mistake (:meth:`TaskModel.rate_limit`'s default)
ABSURD = 10.0
#: where the noise of the agent's observations comes from: its own θ (the paper's; no
#: experimenter measures it), or the recorded world's θ
SENSES = ("agent", "world")


class TaskModel(abc.ABC):
    """A parameterised POMDP with Gaussian noise, written in batched torch ops.

    All methods take tensors with arbitrary leading batch dimensions ``*B`` and must be
    differentiable in ``theta`` (the inverse objective backpropagates through them).
    """

    #: the θ space of the family (and its prior)
    theta_space: ThetaSpace
    #: dimensions of the latent state, the agent's observation and the target
    state_dim: int
    observation_dim: int
    target_dim: int
    #: the longest trial, in steps
    max_steps: int
    #: the action spec of one environment (no batch dimensions)
    action_spec: TensorSpec
    #: seconds per step (a recording is resampled to this grid); tasks without a clock use 1.0
    dt: float = 1.0
    #: names of the state's components, in order, and the unit of each (the trajectory schema)
    state_names: tuple[str, ...]
    state_units: tuple[str, ...]
    #: names of the action's components (one name for a discrete action's integer index)
    action_names: tuple[str, ...]
    #: names of the target's components, in the state's distance units
    target_names: tuple[str, ...]
    #: the task's name, which its checkpoints carry (a class that names none and inherits
    #: none a base named: the class's name)
    name: str
    #: θ parameters of the agent's senses (e.g. its observation noise): with ``senses="agent"``
    #: (:func:`sensed_world`) the world draws the agent's observations under the agent's own
    #: values of these, as the paper's O_θo does, since no experimenter measures them
    sensory_names: tuple[str, ...] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" in cls.__dict__:
            cls._named = True
        elif not getattr(cls, "_named", False):  # a name a base gave itself is inherited
            cls.name = cls.__name__

    def parameter(self, theta: torch.Tensor, name: str) -> torch.Tensor:
        """One parameter of θ ``[*B, d]`` as ``[*B, 1]`` (a KeyError listing the names else)."""
        i = self.theta_space.index(name)
        return theta[..., i : i + 1]

    # --- world ---------------------------------------------------------------------------
    @abc.abstractmethod
    def initial_state(
        self, theta: torch.Tensor, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Draw ``(state, target)`` for a batch of trials with task parameters ``theta``."""

    @abc.abstractmethod
    def transition(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        """The noise-free next state ``f(s, a, θ)``."""

    @abc.abstractmethod
    def process_cov(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        """Covariance ``[*B, ds, ds]`` of the process noise added to ``f(s, a, θ)``."""

    def observe(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """The noise-free observation ``h(s, θ)``; tasks without observations keep the default."""
        return state.new_zeros(*state.shape[:-1], 0)

    def observation_cov(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """Covariance ``[*B, do, do]`` of the observation noise."""
        return state.new_zeros(*state.shape[:-1], 0, 0)

    @abc.abstractmethod
    def stops(self, action: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """Whether ``action`` taken at ``step`` ends the trial by stopping, ``[*B, 1]`` bool."""

    def scored_actions(self, action: torch.Tensor, step: torch.Tensor) -> torch.Tensor | None:
        """Which components of ``action`` an inverse scores, ``[*B, da]`` bool; ``None``: all.

        A component with no consequence (it moves nothing, ends nothing) says little about the
        agent's model and, for a subject, is not controlled; leaving it out of the likelihood
        is ignorable, since which components are left out depends on recorded data only.
        """
        return None

    @abc.abstractmethod
    def reward(
        self,
        state: torch.Tensor,
        target: torch.Tensor,
        action: torch.Tensor,
        stop: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        """The reward ``[*B, 1]`` the world pays for ``action`` taken in ``state``."""

    def succeeded(
        self, state: torch.Tensor, target: torch.Tensor, stop: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor | None:
        """Whether a trial that ends in ``state`` (by stopping where ``stop``) did the task,
        ``[*B, 1]`` bool, judged by the world's ``theta``; ``None`` (the default): the task
        has no success, and evaluations score its return alone."""
        return None

    # --- agent ---------------------------------------------------------------------------
    @abc.abstractmethod
    def initial_belief(
        self, state: torch.Tensor, target: torch.Tensor, theta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The agent's belief ``(mean, cov)`` at the start of a trial (the target is seen)."""

    @abc.abstractmethod
    def belief_reward(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        target: torch.Tensor,
        action: torch.Tensor,
        stop: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        """The reward the agent expects under its Gaussian belief: the paper's ``R_θ(b, a)``."""

    @abc.abstractmethod
    def belief_features(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        target: torch.Tensor,
        step: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        """What the actor and critic read: belief features, then normalised θ, ``[*B, df]``.

        The arguments' batch dimensions broadcast, and need not match: the inverse's hard
        E-step passes the beliefs at every step ``[A, n, T, ·]`` beside each trial's target and
        θ ``[A, n, 1, ·]`` and the step ``[1, 1, T, 1]``, so expand the parts to their common
        batch shape before concatenating them (:func:`~irc_torchrl.envs.probe.check_model` checks
        it when an env or an inverse is built).
        """

    @property
    @abc.abstractmethod
    def belief_feature_dim(self) -> int:
        """How many leading entries of :meth:`belief_features` describe the belief."""

    # --- recordings ----------------------------------------------------------------------
    def rate_limit(self, unit: str) -> float | None:
        """The fastest rate in ``unit`` (``"distance/s"``, ``"rad/s"``) a recording of this task
        may show before the readers take it for a unit mistake (``None``: not checked).

        By default :data:`ABSURD` times the largest θ bound in ``unit`` (a gain: the top speed),
        per-step units counted per second. Override it where θ does not bound the task's speeds
        so (its only parameter in ``distance/s`` a noise, say).
        """
        per_step = unit.replace("/s", "/step")
        highs = [p.high for p in self.theta_space.parameters if p.unit == unit]
        highs += [p.high / self.dt for p in self.theta_space.parameters if p.unit == per_step]
        return ABSURD * max(highs) if highs else None

    # --- Jacobians (override with analytic forms; tests check them against torch.func) ---
    def transition_jacobian(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        """``∂f/∂s``, ``[*B, ds, ds]``, by ``jacrev`` under ``vmap``."""
        return _batched_jacobian(lambda s, a, th: self.transition(s, a, th), state, action, theta)

    def observation_jacobian(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """``∂h/∂s``, ``[*B, do, ds]``, by ``jacrev`` under ``vmap``."""
        return _batched_jacobian(lambda s, th: self.observe(s, th), state, theta)


def _batched_jacobian(
    fn: Callable[..., torch.Tensor], state: torch.Tensor, *args: torch.Tensor
) -> torch.Tensor:
    """Jacobian of ``fn`` with respect to its first argument, for every batch element."""
    batch = state.shape[:-1]
    flat = [state.reshape(-1, state.shape[-1])]
    flat += [
        a.expand(*batch, *a.shape[len(batch) :]).reshape(-1, *a.shape[len(batch) :]) for a in args
    ]
    jac = torch.func.vmap(torch.func.jacrev(fn, argnums=0))(*flat)
    return jac.reshape(*batch, *jac.shape[1:])


def sensed_world(
    model: TaskModel, task_theta: torch.Tensor, theta: torch.Tensor, senses: str = "agent"
) -> torch.Tensor:
    """The world's θ ``task_theta`` ``[*B, d]`` with the task's :attr:`~TaskModel.sensory_names`
    taken from the agent's ``theta`` (broadcast, cast to the world's dtype and device): the
    world whose observations of the agent are as noisy as the agent's senses are by its own
    θ; with ``senses="world"`` (:data:`SENSES`), ``task_theta`` as it is.
    :class:`~irc_torchrl.envs.task_env.TaskEnv` and :func:`simulate_agents` take the world
    they are given: pass them this one for agents whose senses are their own."""
    if senses == "world" or not model.sensory_names:
        return task_theta
    own = torch.zeros(model.theta_space.dim, dtype=torch.bool, device=task_theta.device)
    own[[model.theta_space.index(name) for name in model.sensory_names]] = True
    return torch.where(own, theta.to(task_theta), task_theta)


def action_in_spec(spec: TensorSpec, action: torch.Tensor, slack: float = 0.0) -> torch.Tensor:
    """Per-step validity ``[..]`` of ``action`` (``[..]`` discrete, ``[.., da]`` continuous).

    ``slack`` (a fraction of each bound's range) tolerates round-off in recorded files. An
    ``Unbounded`` spec (its box the dtype's extremes) admits every finite action.
    """
    if isinstance(spec, Categorical):
        integral = (
            action == action.round()
            if action.is_floating_point()
            else torch.ones_like(action, dtype=torch.bool)
        )
        return integral & (action >= 0) & (action < spec.n)
    low, high = spec.space.low.to(action.device), spec.space.high.to(action.device)
    if slack:  # an unbounded box's range overflows to inf, and 0 × inf would refuse everything
        margin = slack * (high - low)
        low, high = low - margin, high + margin
    return ((action >= low) & (action <= high)).all(-1)


def bounded_box(low: torch.Tensor, high: torch.Tensor) -> bool:
    """Whether action bounds are a box of their own, not an ``Unbounded`` spec's (the dtype's
    extremes): a lapse is uniform over the box, which those leave without a usable width."""
    extreme = torch.finfo(torch.float32).max
    return bool((low.abs() < extreme).all() and (high.abs() < extreme).all())


def continuous_actions(spec: TensorSpec) -> bool:
    """Whether a task's action spec is a vector of continuous actions ``[da]`` (else discrete)."""
    return len(spec.shape) == 1 and spec.dtype.is_floating_point


def check_action_spec(model: TaskModel) -> None:
    """Refuse a task whose actions are neither one index among ``n`` (``Categorical(n)``) nor a
    vector of continuous actions ``[da]``, the two kinds the env, the data and the inverse read
    (a ``OneHot`` or a matrix of actions failed deep inside a rollout)."""
    spec = model.action_spec
    if (isinstance(spec, Categorical) and not spec.shape) or continuous_actions(spec):
        return
    raise ValueError(
        f"model.action_spec: expected Categorical(n) (one index per step) or a floating-point "
        f"spec of shape [da], got {type(spec).__name__} of {spec.dtype}, shape "
        f"{list(spec.shape)} (task {model.name!r})"
    )


def own_theta_space(space: ThetaSpace | None, default: Callable[[], ThetaSpace]) -> ThetaSpace:
    """``space`` (other bounds or priors of a task's parameters), or the task's ``default()``
    where ``None``; a space of other parameters is refused: the task's equations read them."""
    expected = default()
    if space is None:
        return expected
    if space.names != expected.names:
        raise ValueError(f"theta_space: expected parameters {expected.names}, got {space.names}")
    return space
