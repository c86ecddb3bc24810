"""Simulated agents: rational under their own θ, acting in a world whose θ may differ.

Trials come out in the held-trajectory layout of the design (``[n_agents, n_trials, T]`` with
``state``, ``action``, ``target``, ``mask``, ``task_theta``), plus the ground truth an
experimenter never has: ``theta`` and the agent's ``belief``.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import TensorSpec
from torchrl.envs import ExplorationType, TransformedEnv, set_exploration_type
from torchrl.modules import AdditiveGaussianModule, ProbabilisticActor

from irc_torchrl import checks
from irc_torchrl.algorithms.runtime import float32_default
from irc_torchrl.checks import count, positive_number
from irc_torchrl.envs.belief import BeliefFeatures, EKFBelief
from irc_torchrl.envs.model import TaskModel
from irc_torchrl.envs.task_env import TaskEnv
from irc_torchrl.modules.lapse import Lapse

__all__ = ["boltzmann_policy", "motor_noise_policy", "simulate_agents", "first_trial_mask"]


def boltzmann_policy(
    model: TaskModel, q_network: torch.nn.Module, temperature: float
) -> TensorDictSequential:
    """A TorchRL policy sampling actions from ``softmax(Q(b, ·, θ) / temperature)``."""
    temperature = positive_number("temperature", temperature)
    return TensorDictSequential(
        BeliefFeatures(model),
        ProbabilisticActor(
            TensorDictModule(
                lambda f: q_network(f) / temperature, in_keys=["features"], out_keys=["logits"]
            ),
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
            spec=model.action_spec,
        ),
    )


def motor_noise_policy(
    actor: TensorDictSequential,
    spec: TensorSpec,
    motor_noise: float | torch.Tensor,
    lapse: float | torch.Tensor = 0.0,
) -> TensorDictSequential:
    """A continuous actor plus Gaussian motor noise, clipped to ``spec``'s bounds, and with
    probability ``lapse`` per action dimension an action unrelated to the belief
    (:class:`~irc_torchrl.modules.lapse.Lapse`).

    This is the agent the inverse objective's
    :class:`~irc_torchrl.modules.likelihood.CensoredGaussianActionModel` describes; the noise
    is TorchRL's :class:`~torchrl.modules.AdditiveGaussianModule` at a constant scale.
    ``motor_noise`` is one standard deviation, or a tensor of them broadcasting against the
    action (e.g. ``[n_agents, 1, da]`` for :func:`simulate_agents`: each agent's fitted noise);
    ``lapse`` likewise (``[n_agents, 1, 1]``). :func:`simulate_agents` takes one per agent,
    not per trial: an agent the inverse objective describes has one noise and one lapse rate.
    """
    # on the CPU, as TorchRL's module draws its noise there before moving it to the action
    std = torch.as_tensor(motor_noise, dtype=torch.float32, device="cpu")
    if not (torch.isfinite(std).all() and (std > 0).all()):
        raise ValueError(f"motor_noise: expected positive standard deviations, got {motor_noise}")
    noise = AdditiveGaussianModule(
        spec, sigma_init=1.0, sigma_end=1.0, annealing_num_steps=1, device="cpu"
    )
    noise.std = std  # the module's noise scale, per action where it is a tensor
    noise.mean = torch.zeros((), dtype=torch.float32, device="cpu")  # TorchRL: default dtype
    if not torch.as_tensor(lapse, device="cpu").any():
        return TensorDictSequential(actor, noise)
    return TensorDictSequential(actor, noise, Lapse(spec, lapse))


def _check_per_agent(policy: TensorDictSequential | None, shape: tuple[int, ...]) -> None:
    """Refuse a motor noise or lapse that is not one value per agent (``shape``: ``[n_agents,
    1, *action]``), before the rollout: ``[n_agents, da]`` would spread over trials instead, or
    fail inside TorchRL's noise module."""
    if not isinstance(policy, torch.nn.Module):
        return
    for module in policy.modules():
        if isinstance(module, AdditiveGaussianModule):
            name, value = "motor_noise", module.std
        elif isinstance(module, Lapse):
            name, value = "lapse", module.lapse
        else:
            continue
        try:
            fits = torch.broadcast_shapes(value.shape, shape) == shape
        except RuntimeError:
            fits = False
        if not fits:
            raise ValueError(
                f"{name}: expected one value per agent, broadcasting against {list(shape)} "
                f"(agents, trials, action), got shape {list(value.shape)}"
            )


def first_trial_mask(done: torch.Tensor) -> torch.Tensor:
    """Steps up to and including the first ``done`` of each row of ``done [..., T]``: a
    rollout's first trial per env, as held trials' ``mask`` (a rollout's ``done`` is
    ``[..., T, 1]``: squeeze it)."""
    if done.dtype != torch.bool:
        raise TypeError(f"done: expected a bool tensor [..., T], got {done.dtype}")
    before = torch.cumsum(done.long(), -1) - done.long()
    return before == 0


def simulate_agents(
    model: TaskModel,
    policy: TensorDictSequential | None,
    theta: torch.Tensor,
    n_trials: int,
    task_theta: torch.Tensor | None = None,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> TensorDict:
    """Run ``n_trials`` trials for each agent θ (``[n_agents, d]``) and return held trials.

    Args:
        policy: a TorchRL policy reading the belief (e.g. :func:`boltzmann_policy`);
            ``None`` acts at random.
        task_theta: the world's θ, ``[d]`` or ``[n_agents, d]``; ``None``: each agent's own.
        progress: called as ``progress(steps_done, max_steps)`` after each time step (all
            trials advance together).

    Returns:
        Held trials ``[n_agents, n_trials, max_steps]`` on θ's device: ``state``, ``action``,
        ``target``, ``task_theta`` (the world's θ), ``theta`` (the agent's), ``belief``
        (``mean`` and ``cov``: what the agent believed before each action, which the inverse
        recovers) and ``mask`` (each trial's steps, up to and including its stop; the steps
        after it are not read).
    """
    space = model.theta_space
    theta = space.validate(theta, "theta")
    if theta.ndim != 2:
        raise ValueError(f"theta: expected [n_agents, {space.dim}], got {list(theta.shape)}")
    n_agents = theta.shape[0]
    batch = (n_agents, count("n_trials", n_trials))
    _check_per_agent(policy, (n_agents, 1, *model.action_spec.shape))
    seed = checks.seed("seed", seed)
    world = None
    if task_theta is not None:
        world = space.validate(task_theta, "task_theta")
        if world.shape not in ((space.dim,), (n_agents, space.dim)):
            raise ValueError(
                f"task_theta: expected [{space.dim}] or [{n_agents}, {space.dim}] (one per "
                f"agent), got {list(world.shape)}"
            )
        world = world.expand(n_agents, -1).unsqueeze(1).expand(*batch, -1)
    env = TransformedEnv(
        TaskEnv(
            model,
            batch_size=batch,
            theta=theta.unsqueeze(1).expand(*batch, -1),
            task_theta=world,
            device=theta.device,
            seed=seed,
        ),
        EKFBelief(model),
    )
    done = itertools.count(1)
    callback = None if progress is None else lambda *_: progress(next(done), model.max_steps)
    explore = set_exploration_type(ExplorationType.RANDOM)
    with float32_default(), torch.random.fork_rng(), torch.no_grad(), explore:
        torch.manual_seed(seed)
        rollout = env.rollout(model.max_steps, policy, callback, break_when_any_done=False)
    if progress is not None:  # rollout calls back between steps, not after the last
        progress(model.max_steps, model.max_steps)
    keys = ["state", "action", "target", "task_theta", "theta", "belief"]
    trials = rollout.select(*keys)
    trials["mask"] = first_trial_mask(rollout["next", "done"].squeeze(-1))
    return trials
