"""Algorithm 1 on continuous-action tasks: one θ-conditioned DDPG policy over the whole θ prior.

A TorchRL ``Collector`` steps a batched :class:`~irc_torchrl.envs.task_env.TaskEnv` (the 2D
firefly task by default, or any continuous-action task of the user's own) whose every element
draws its θ from the prior at each trial; :class:`EKFBelief` keeps the agent's
belief under that θ and :class:`BeliefReward` pays the reward the agent expects under its
belief (the paper's ``R_θ(b, a)``). Transitions go to a ``TensorDictReplayBuffer``;
``DDPGLoss`` (n-step targets through ``MultiStepTransform``, 5 steps by default; ``TD3Loss``
optionally; target networks moved by ``SoftUpdate``) trains an actor and a critic that both
read the belief features and θ. Exploration is additive Gaussian noise annealed over frames.
A fixed θ grid evaluates the greedy policy on the world's reward, and the best policy by
evaluation is kept (learning curves are not monotone).

A *specialist* is the same algorithm over a θ space with every parameter fixed
(``theta_fixed``): the premise of the method is that the ensemble matches it.

A task of the user's own (``train_ensemble(model=...)``) trains the same way from a uniform
random warm-up (the pursuit controller that seeds the firefly's buffer knows that task only);
its evaluations score the world's return, and the success rate where the task defines one
(:meth:`~irc_torchrl.envs.model.TaskModel.succeeded`).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import shutil
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, EnvBase, MultiStepTransform, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import AdditiveGaussianModule
from torchrl.objectives import DDPGLoss, LossModule, SoftUpdate, TD3Loss, ValueEstimators

import irc_torchrl
from irc_torchrl.algorithms.runtime import resolve_device, torch_settings
from irc_torchrl.algorithms.simulate import first_trial_mask
from irc_torchrl.checkpoint import load_checkpoint, save_checkpoint
from irc_torchrl.checks import check_fields, count, first_line, non_negative, one_of, real
from irc_torchrl.checks import positive as check_positive
from irc_torchrl.checks import seed as check_seed
from irc_torchrl.data.files import write_json, write_text
from irc_torchrl.envs.belief import BeliefReward, EKFBelief
from irc_torchrl.envs.firefly2d import Firefly2DModel, firefly2d_theta_space
from irc_torchrl.envs.model import TaskModel, bounded_box, continuous_actions
from irc_torchrl.envs.task_env import TaskEnv
from irc_torchrl.modules.actor_critic import ACTIVATIONS, make_actor, make_critic
from irc_torchrl.modules.pursuit import BeliefPursuit
from irc_torchrl.theta import ThetaSpace

__all__ = [
    "DDPGConfig",
    "EvaluationConfig",
    "Firefly2DConfig",
    "TrainResult",
    "config_from_dict",
    "evaluate_policy",
    "critic_slices",
    "load_ensemble_critic",
    "load_ensemble_policy",
    "make_model",
    "stop_sharpness",
    "theta_grid",
    "theta_sensitivity",
    "train_ensemble",
]

TASK = Firefly2DModel.name
#: the entries of its checkpoint a resumed run reads (besides the config and θ space)
RESUME_ENTRIES = (
    "loss",
    "optimiser_actor",
    "optimiser_critic",
    "exploration",
    "best_actor",
    "counters",
    "history",
    "best",
    "rng",
)


@dataclass
class DDPGConfig:
    """Settings of the DDPG learner in :func:`train_ensemble`."""

    #: parallel environments, each with its own θ
    n_envs: int = 64
    #: batched env steps per collector batch; frames per batch = n_envs × steps_per_batch
    steps_per_batch: int = 4
    #: gradient updates per collector batch (one per batched step by default)
    updates_per_batch: int = 4
    #: training length, in env frames (one frame = one step of one environment) of the
    #: exploring policy (the pursuit warm-up's come on top); with the pre-activation penalty
    #: seeds 0 and 1 declined after about 450k of 768k frames
    total_frames: int = 384_000
    #: frames collected before the first update: by ``warmup_policy`` at the start of a run,
    #: by the current policy after a resume (the replay buffer is not checkpointed)
    warmup_frames: int = 10_240
    #: "pursuit": the belief-pursuit controller plus ``warmup_sigma`` noise (puts rewarded
    #: stops in the buffer: uniform random actions stop within 3 steps and never reach a
    #: target, so the sparse stop reward is never seen); "random": uniform actions
    warmup_policy: str = "pursuit"
    warmup_sigma: float = 0.3
    #: with the pursuit warm-up: gradient steps of behaviour cloning (the actor imitates the
    #: controller on the warm-up beliefs), then of critic-only learning, before DDPG proper.
    #: 2000 (the default) leave a clone that never stops (0% success on seeds 0-2), so DDPG
    #: discovers the task itself (with pre_activation_weight=0 seed 0 did, 1 and 2 not);
    #: 6000 give a clone at 87-88% (above the controller), which DDPG then drives to stopping
    #: at once (docs/benchmarks.md)
    clone_updates: int = 2000
    critic_updates: int = 1000
    #: with the pursuit warm-up: weight of a behaviour-cloning term in the actor's loss
    #: (as TD3+BC; 0: off). It keeps the actor near the controller where the critic is wrong
    #: about other actions: with 2 (held) all 3 seeds reach 80%, and from a 6000-update clone
    #: stay at 80-88% without passing it. bc_updates > 0 anneals it linearly to 0 over
    #: that many DDPG updates; 0 holds it for the whole run (annealed runs collapsed when
    #: the weight reached 0). Off by default: the shipped checkpoint is trained without it
    bc_weight: float = 0.0
    bc_updates: int = 0
    #: weight of the mean square of the actor's pre-tanh output in its loss (rlkit's DDPG
    #: ``policy_pre_activation_weight``): it keeps the squashed actions off the flat ends of
    #: tanh, where the critic's gradient no longer moves them. Without it seeds 1 and 2 stay
    #: at 0% success (seed 1's actor with every pre-tanh output beyond ±3); with 0.01 seeds
    #: 0-6 all discover the task (best 79-85%, docs/benchmarks.md)
    pre_activation_weight: float = 0.01
    #: weight of a spatial smoothness term in the actor's loss (CAPS, Mysore et al. 2021): the
    #: mean squared change of the actions when the belief mean moves by Gaussian noise of std
    #: ``smoothness_sigma`` (state units). A policy that switches from going to stopping within
    #: the spread of the agent's belief makes Algorithm 2's likelihood a cusp there. With
    #: gamma=0.99, 10 and 0.05 made that likelihood nearly exact (9.5 nats per agent from a
    #: particle filter's, against 68-81) but the stop then says less of θ: errors on the noises
    #: 2-3× the shipped policy's, success 80.9% (docs/benchmarks.md); 0: off
    smoothness_weight: float = 0.0
    smoothness_sigma: float = 0.05
    buffer_size: int = 200_000
    batch_size: int = 512
    hidden: list[int] = field(default_factory=lambda: [64, 64, 64])
    activation: str = "softplus"
    lr_actor: float = 1e-4
    #: the actor's learning rate during behaviour cloning (lr_actor takes over after it).
    #: With clone_updates=6000 and lr_actor=1e-5 DDPG still drops the clone within 500
    #: updates but comes back above 80% within 3000-6000 (seeds 0-4), within 1000-2000 with
    #: lr_critic=3e-3 too (seeds 0-4, ending at 88-90%); at 1e-4 (seeds 0, 1) and 3e-5
    #: (seed 1) it never does
    lr_clone: float = 1e-4
    #: 3e-3 alone lifts seeds 0-2 to 88-89% success (above the pursuit floor) and the
    #: specialist ratios to 0.90-1.02, but that policy's actions turn less on θ and the
    #: inverse's errors on the noises triple (docs/benchmarks.md); the shipped policy is 1e-3's
    lr_critic: float = 1e-3
    #: gradient norm clip of each network (0 disables)
    max_grad_norm: float = 10.0
    #: the discount of the critic's targets (a policy is scored undiscounted). 0.99 gave seed 3
    #: a policy returning 1.00-1.19 of its specialists at the benchmark's 5 θ (0.98: 0.70 at
    #: the noisiest) but a steeper stop, which the inverse's outer filter approximates worse:
    #: on irc recover's default draw its errors on the noises are 1.4-2.1× the shipped
    #: policy's (docs/benchmarks.md); the shipped policy is 0.98's
    gamma: float = 0.98
    #: "ddpg" (TorchRL's DDPGLoss) or "td3" (TD3Loss: twin critics, the smaller one's target,
    #: the target action smoothed by policy_noise clipped at noise_clip)
    loss: str = "ddpg"
    policy_noise: float = 0.2
    noise_clip: float = 0.5
    #: critic updates per actor update (TD3 delays the actor by 2)
    policy_delay: int = 1
    #: n-step TD targets (TorchRL's MultiStepTransform): the sparse stop reward reaches the
    #: start of a trial n times sooner than with one-step targets
    n_steps: int = 5
    tau: float = 0.005
    #: std of the additive Gaussian exploration noise, annealed linearly over anneal_frames
    sigma_init: float = 0.15
    sigma_end: float = 0.05
    anneal_frames: int = 512_000
    #: collector processes (1: in this process; more: a MultiSyncCollector)
    collector_workers: int = 1


@dataclass
class EvaluationConfig:
    """The fixed θ set on which :func:`evaluate_policy` scores the greedy policy."""

    #: θ points, a Latin hypercube over the free parameters
    n_theta: int = 64
    trials_per_theta: int = 8
    #: evaluate every this many gradient updates (and at the end)
    every: int = 500
    #: seed of the θ grid and of the evaluation trials (common to every evaluation)
    seed: int = 12345


@dataclass
class Firefly2DConfig:
    """Algorithm 1 on the 2D firefly task (``irc train --config configs/firefly2d.yaml``), or on
    a task of the user's own (``train_ensemble(model=...)``, ``irc train --model``)."""

    task: str = TASK
    #: seed 3 trained the shipped policy (of seeds 0-6 reaching 80%, the one that stops most
    #: gently, by stop_sharpness: the smaller the drop, the smoother the inverse's likelihood)
    seed: int = 3
    #: torch threads; small networks run fastest on one thread per process
    threads: int = 1
    #: flush denormal floats to zero (they made early CPU runs 5-10× slower)
    flush_denormal: bool = True
    #: torch device to train on, e.g. "cpu" or "cuda:0" (the checkpoint loads anywhere)
    device: str = "cpu"
    #: θ parameters held fixed beyond the task's own ({name: value}); all fixed = a specialist
    theta_fixed: dict = field(default_factory=dict)
    #: write a checkpoint every this many gradient updates (at the end of the batch that
    #: reaches them, so a resume misses none of its updates) and at the end
    checkpoint_every: int = 1000
    #: "csv", "tensorboard" (when installed) or "none"
    logger: str = "csv"
    ddpg: DDPGConfig = field(default_factory=DDPGConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)

    def validate(self, model: TaskModel | None = None, fresh: bool = True) -> Firefly2DConfig:
        """Return ``self`` if every field is usable, else raise a one-line error naming it.

        ``model`` is the task of the user's own the config trains (``None``: the 2D firefly).
        ``fresh``: the config starts a run from scratch; a resumed run (or a checkpoint's
        config read back) runs no pursuit warm-up, so that warm-up's length is not checked.
        """
        check_fields(self)
        d, e = self.ddpg, self.evaluation
        if model is None and self.task != TASK:
            raise ValueError(
                f"config: task must be {TASK!r} (a task of your own is given as a model), "
                f"got {self.task!r}"
            )
        if model is not None and self.task != model.name:
            raise ValueError(f"config: task must be the model's, {model.name!r}, got {self.task!r}")
        positive = {
            "threads": self.threads,
            "checkpoint_every": self.checkpoint_every,
            "ddpg.n_envs": d.n_envs,
            "ddpg.steps_per_batch": d.steps_per_batch,
            "ddpg.updates_per_batch": d.updates_per_batch,
            "ddpg.total_frames": d.total_frames,
            "ddpg.buffer_size": d.buffer_size,
            "ddpg.warmup_frames": d.warmup_frames,
            "ddpg.batch_size": d.batch_size,
            "ddpg.anneal_frames": d.anneal_frames,
            "ddpg.collector_workers": d.collector_workers,
            "ddpg.n_steps": d.n_steps,
            "ddpg.policy_delay": d.policy_delay,
            "ddpg.lr_actor": d.lr_actor,
            "ddpg.lr_clone": d.lr_clone,
            "ddpg.lr_critic": d.lr_critic,
            "evaluation.n_theta": e.n_theta,
            "evaluation.trials_per_theta": e.trials_per_theta,
            "evaluation.every": e.every,
        }
        check_positive(**positive)
        non_negative(
            **{
                "ddpg.clone_updates": d.clone_updates,
                "ddpg.critic_updates": d.critic_updates,
                "ddpg.bc_weight": d.bc_weight,
                "ddpg.bc_updates": d.bc_updates,
                "ddpg.pre_activation_weight": d.pre_activation_weight,
                "ddpg.smoothness_weight": d.smoothness_weight,
                "ddpg.smoothness_sigma": d.smoothness_sigma,
                "ddpg.policy_noise": d.policy_noise,
                "ddpg.noise_clip": d.noise_clip,
                "ddpg.sigma_init": d.sigma_init,
                "ddpg.sigma_end": d.sigma_end,
                "ddpg.warmup_sigma": d.warmup_sigma,
            }
        )
        if d.sigma_end > d.sigma_init:
            raise ValueError(
                f"config: ddpg.sigma_end={d.sigma_end} must not exceed "
                f"ddpg.sigma_init={d.sigma_init} (the exploration noise anneals down)"
            )
        for name, value in {"ddpg.gamma": d.gamma, "ddpg.tau": d.tau}.items():
            if not 0 < value <= 1:
                raise ValueError(f"config: {name} must lie in (0, 1], got {value}")
        if d.buffer_size < d.batch_size:
            raise ValueError(
                f"config: ddpg.buffer_size={d.buffer_size} must hold a batch, "
                f"ddpg.batch_size={d.batch_size}"
            )
        try:
            device = torch.device(self.device)
        except (RuntimeError, TypeError):
            raise ValueError(
                f"config: device must name a torch device such as 'cpu' or 'cuda:0', "
                f"got {self.device!r}"
            ) from None
        if device.type not in ("cpu", "cuda"):
            raise ValueError(
                f"config: device must be 'cpu' or a 'cuda' device (the task's filter runs in "
                f"float64), got {self.device!r}"
            )
        if d.collector_workers > 1 and device.type != "cpu":
            raise ValueError(
                f"config: ddpg.collector_workers must be 1 on {device} (collector processes "
                f"share CPU cores), got {d.collector_workers}"
            )
        if d.n_envs % d.collector_workers:
            raise ValueError(
                f"config: ddpg.n_envs={d.n_envs} must be a multiple of "
                f"ddpg.collector_workers={d.collector_workers}"
            )
        if not d.hidden or any(h <= 0 for h in d.hidden):  # ints: check_fields saw to it
            raise ValueError(f"config: ddpg.hidden must list positive widths, got {d.hidden}")
        if not 0 <= d.max_grad_norm < math.inf:
            raise ValueError(
                f"config: ddpg.max_grad_norm must be ≥ 0 and finite (0: no clipping), "
                f"got {d.max_grad_norm}"
            )
        one_of("ddpg.activation", d.activation, sorted(ACTIVATIONS))
        one_of("ddpg.loss", d.loss, ("ddpg", "td3"))
        one_of("ddpg.warmup_policy", d.warmup_policy, ("pursuit", "random"))
        if d.bc_weight > 0 and d.warmup_policy != "pursuit":
            raise ValueError(
                f"config: ddpg.bc_weight clones the pursuit controller, which "
                f"ddpg.warmup_policy={d.warmup_policy!r} does not run; expected 0, "
                f"got {d.bc_weight}"
            )
        if fresh:
            _check_warmup(d)
        one_of("logger", self.logger, ("csv", "tensorboard", "none"))
        if model is None:
            make_model(self)  # theta_fixed: unknown names and out-of-range values
        return self


def _check_warmup(d: DDPGConfig) -> None:
    """Refuse a pursuit warm-up too short for the clone and critic updates that learn from it:
    it collects whole batches (of at most ``buffer_size`` frames in all), and the n-step
    transform passes on no transition until each environment has taken ``n_steps`` steps."""
    if d.warmup_policy != "pursuit" or d.clone_updates + d.critic_updates == 0:
        return
    least = d.n_steps // d.steps_per_batch * d.n_envs * d.steps_per_batch + 1
    collected = {"ddpg.warmup_frames": d.warmup_frames, "ddpg.buffer_size": d.buffer_size}
    for name, value in collected.items():
        if value < least:
            raise ValueError(
                f"config: {name} must be at least {least} with ddpg.clone_updates or "
                f"ddpg.critic_updates (the pursuit warm-up collects whole batches of "
                f"ddpg.steps_per_batch={d.steps_per_batch} steps and passes on n-step "
                f"transitions once past ddpg.n_steps={d.n_steps}), got {value}"
            )


def _check_trainable(config: Firefly2DConfig, model: TaskModel) -> None:
    """Refuse to train a model given to :func:`train_ensemble` with settings it cannot train
    with (the θ space is the model's; the pursuit warm-up knows the 2D firefly only), or a
    model whose actions DDPG's actor cannot produce."""
    if config.theta_fixed:
        raise ValueError(
            f"config: theta_fixed builds the firefly2d task's θ space; for a model given, fix "
            f"them in its own (ThetaSpace(..., fixed=...)), got {config.theta_fixed}"
        )
    if config.ddpg.warmup_policy == "pursuit" and not isinstance(model, Firefly2DModel):
        raise ValueError(
            f"config: ddpg.warmup_policy='pursuit' runs the firefly2d task's pursuit "
            f"controller; expected 'random' for task {model.name!r}"
        )
    spec = model.action_spec
    if not continuous_actions(spec) or not bounded_box(spec.space.low, spec.space.high):
        raise ValueError(
            f"model.action_spec: expected a bounded box of continuous actions, shape [n] (the "
            f"actor squashes into it), got {type(spec).__name__} of {spec.dtype}, shape "
            f"{list(spec.shape)}"
        )
    theta = model.theta_space.default().expand(2, -1)
    state, target = model.initial_state(theta, torch.Generator().manual_seed(0))
    step = torch.zeros(2, 1, dtype=torch.int64)
    _succeeded(model, state, target, model.stops(spec.zero((2,)).cpu(), step), theta)


def _succeeded(
    model: TaskModel,
    state: torch.Tensor,
    target: torch.Tensor,
    stop: torch.Tensor,
    theta: torch.Tensor,
) -> torch.Tensor | None:
    """``model.succeeded``, refused unless None or a bool of ``stop``'s shape."""
    success = model.succeeded(state, target, stop, theta)
    if success is not None and (success.shape != stop.shape or success.dtype != torch.bool):
        raise ValueError(
            f"model.succeeded: expected None or bool {list(stop.shape)}, as model.stops gives, "
            f"got {success.dtype} {list(success.shape)}"
        )
    return success


def _on_device(model: TaskModel, device: torch.device) -> TaskModel:
    """``model`` with its action spec on ``device`` (a copy where it moves): the actor's
    squashing and the exploration noise read their bounds from it."""
    if torch.device(model.action_spec.device or "cpu") == device:
        return model
    model = copy.copy(model)
    model.action_spec = model.action_spec.to(device)
    return model


def _check_model(model: Any) -> TaskModel | None:
    """``model`` if it is a task model or None, else a one-line refusal."""
    if isinstance(model, type) and issubclass(model, TaskModel):
        raise ValueError(
            f"model: got the class {model.__name__}; pass an instance, {model.__name__}()"
        )
    if model is not None and not isinstance(model, TaskModel):
        raise ValueError(f"model: expected a TaskModel, got {type(model).__name__}")
    return model


def config_from_dict(data: Mapping[str, Any]) -> Firefly2DConfig:
    """Rebuild a :class:`Firefly2DConfig` from its plain-dict form (checkpoints, summaries)."""
    data = dict(data)
    return Firefly2DConfig(
        **{k: v for k, v in data.items() if k not in ("ddpg", "evaluation")},
        ddpg=DDPGConfig(**data.get("ddpg", {})),
        evaluation=EvaluationConfig(**data.get("evaluation", {})),
    )


def make_model(config: Firefly2DConfig) -> Firefly2DModel:
    """The task of ``config``: the 2D firefly over its θ space with ``theta_fixed`` held."""
    try:
        fixed = {k: real(k, v) for k, v in config.theta_fixed.items()}
        space = firefly2d_theta_space().fix(**fixed)
    except KeyError as error:
        raise ValueError(f"config: theta_fixed: {error.args[0]}") from None
    except ValueError as error:
        raise ValueError(f"config: theta_fixed: {error}") from None
    return Firefly2DModel(theta_space=space)


def make_train_env(
    model: TaskModel, n_envs: int, seed: int, device: torch.device | str = "cpu"
) -> EnvBase:
    """The training world: θ from the prior per trial, the EKF belief, the belief reward."""
    env = TaskEnv(model=model, batch_size=(n_envs,), seed=seed, device=device)
    return TransformedEnv(env, Compose(EKFBelief(model), BeliefReward(model)))


def theta_grid(space: ThetaSpace, n: int, seed: int) -> torch.Tensor:
    """``n`` θ covering the prior: a Latin hypercube over the free parameters, ``[n, d]``.

    Each free parameter's range is cut into ``n`` equal strata and every stratum is used once,
    at a random point, in a random pairing with the other parameters' strata (fixed seed).
    """
    generator = torch.Generator().manual_seed(check_seed("seed", seed))
    n = count("n", n)
    theta = space.default().expand(n, space.dim).clone()
    low, high = space.low(), space.high()
    for i, name in enumerate(space.names):
        if name in space.fixed:
            continue
        strata = torch.randperm(n, generator=generator, device="cpu").float()
        u = (strata + torch.rand(n, generator=generator, device="cpu")) / n
        theta[:, i] = low[i] + u * (high[i] - low[i])
    return theta


@torch.no_grad()
def evaluate_policy(
    model: TaskModel,
    policy: Callable[[TensorDictBase], TensorDictBase],
    thetas: torch.Tensor,
    trials_per_theta: int = 8,
    seed: int = 12345,
) -> dict[str, Any]:
    """Score ``policy`` (greedy) on one trial per environment, ``trials_per_theta`` per θ.

    The world pays its own reward (on the firefly task, the true position inside the goal on
    stopping, minus effort), not the agent's expected one: this is what an experimenter would
    score. Every call with the same ``seed`` faces the same θ and first targets, and the same
    noise until a row's trial ends: the rows share one random stream, which that row's reset
    then moves on, so later noise depends on when the policy stops (a difference of noise, not
    of bias).

    Returns:
        ``success_rate``, ``mean_return``, ``mean_length`` (steps), and per θ
        ``per_theta_success`` and ``per_theta_return`` (lists, in the order of ``thetas``);
        both success entries are None for a task without success
        (:meth:`~irc_torchrl.envs.model.TaskModel.succeeded`).
    """
    rollout, alive = _first_trials(model, policy, thetas, trials_per_theta, seed)
    batch = rollout.shape[0]
    last = alive.sum(-1) - 1
    returns = (rollout["next", "reward"].squeeze(-1) * alive).sum(-1)
    end = rollout[torch.arange(batch, device=last.device), last]
    stop = model.stops(end["action"], end["step"])
    success = _succeeded(model, end["state"], end["target"], stop, end["task_theta"])
    n_theta = thetas.shape[0]
    if success is not None:
        success = success.squeeze(-1).float()
    return {
        "success_rate": None if success is None else float(success.mean()),
        "mean_return": float(returns.mean()),
        "mean_length": float((last + 1).float().mean()),
        "per_theta_success": (
            None
            if success is None
            else success.reshape(n_theta, trials_per_theta).mean(-1).tolist()
        ),
        "per_theta_return": returns.reshape(n_theta, trials_per_theta).mean(-1).tolist(),
    }


@torch.no_grad()
def theta_sensitivity(
    model: TaskModel,
    policy: Callable[[TensorDictBase], TensorDictBase],
    thetas: torch.Tensor,
    trials_per_theta: int = 8,
    seed: int = 12345,
) -> dict[str, list[float]]:
    """How much ``policy``'s action turns on each free θ parameter, at the beliefs it visits.

    Algorithm 2 reads θ from the actions, so a parameter the policy ignores is seen only
    through the belief filter. Per free parameter: the mean absolute change of each action
    dimension when the policy's θ (its input only; the belief held) moves from the lower to
    the upper end of that parameter's range, over every step of the greedy trials of
    :func:`evaluate_policy` (same ``thetas``, ``trials_per_theta`` and ``seed``).

    Returns:
        ``{name: [change of a_0, change of a_1, ...]}`` for each free parameter.
    """
    rollout, alive = _first_trials(model, policy, thetas, trials_per_theta, seed)
    return _sensitivity(model, policy, rollout, alive)


def _sensitivity(
    model: TaskModel,
    policy: Callable[[TensorDictBase], TensorDictBase],
    rollout: TensorDictBase,
    alive: torch.Tensor,
) -> dict[str, list[float]]:
    visited = rollout[alive].exclude("next")  # what the policy reads at each step
    space = model.theta_space
    change = {}
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for name in space.free_names:
            actions = []
            for end in (space[name].low, space[name].high):
                moved = visited.clone()
                moved["theta"][..., space.index(name)] = end
                actions.append(policy(moved)["action"])
            change[name] = (actions[1] - actions[0]).abs().mean(0).tolist()
    return change


@torch.no_grad()
def stop_sharpness(
    model: Firefly2DModel,
    policy: Callable[[TensorDictBase], TensorDictBase],
    thetas: torch.Tensor,
    trials_per_theta: int = 8,
    seed: int = 12345,
) -> dict[str, float | None]:
    """How abruptly ``policy`` stops: its greedy forward control the step before a stop and at
    it, over the first trials of :func:`evaluate_policy` (same arguments) that end by a stop.

    Algorithm 2 scores a stop by its forward control; a policy that switches from going to
    stopping within the spread of the agent's belief makes the likelihood a cusp there
    (docs/recovery2d.md). Returns the fraction of trials that stop and the mean ``a_v_before``,
    ``a_v_stop`` and ``drop`` (their difference); the means are None where no trial stops
    (``a_v_before`` and ``drop``: where no stop has a step before it, ``min_steps=0``).
    """
    rollout, alive = _first_trials(model, policy, thetas, trials_per_theta, seed)
    return _sharpness(model, rollout, alive)


def _sharpness(
    model: Firefly2DModel, rollout: TensorDictBase, alive: torch.Tensor
) -> dict[str, float | None]:
    last = alive.sum(-1) - 1  # the last step of each row's first trial
    rows = torch.arange(last.shape[0], device=last.device)
    action, step = rollout["action"][rows, last], rollout["step"][rows, last]
    stopped = model.stops(action, step).squeeze(-1)
    # a stop on a trial's first step (min_steps = 0) has no step before it: index -1 would
    # read the rollout's last step, in a later trial
    paired = stopped & (last > 0)
    before = rollout["action"][rows, (last - 1).clamp_min(0)][paired, 0]

    def mean(x: torch.Tensor) -> float | None:
        return float(x.mean()) if x.numel() else None

    return {
        "stopped": float(stopped.float().mean()),
        "a_v_before": mean(before),
        "a_v_stop": mean(action[stopped, 0]),
        "drop": mean(before - action[paired, 0]),
    }


@torch.no_grad()
def _policy_report(
    model: TaskModel,
    policy: Callable[[TensorDictBase], TensorDictBase],
    thetas: torch.Tensor,
    trials_per_theta: int,
    seed: int,
) -> dict[str, dict]:
    """:func:`theta_sensitivity` and, on the 2D firefly task (its stop is a forward control),
    :func:`stop_sharpness`, from one set of greedy trials."""
    rollout, alive = _first_trials(model, policy, thetas, trials_per_theta, seed)
    report = {"theta_sensitivity": _sensitivity(model, policy, rollout, alive)}
    if isinstance(model, Firefly2DModel):
        report["stop_sharpness"] = _sharpness(model, rollout, alive)
    return report


def _first_trials(
    model: TaskModel,
    policy: Callable[[TensorDictBase], TensorDictBase],
    thetas: torch.Tensor,
    trials_per_theta: int,
    seed: int,
) -> tuple[TensorDictBase, torch.Tensor]:
    """Greedy rollouts of ``policy``, ``trials_per_theta`` rows per θ: ``[N, T]``, and which
    steps belong to each row's first trial ``[N, T]`` (the timeout makes every row end)."""
    space = model.theta_space
    space.validate(thetas, "thetas")
    if thetas.ndim != 2 or thetas.shape[0] == 0:
        raise ValueError(f"thetas: expected shape [n ≥ 1, {space.dim}], got {list(thetas.shape)}")
    count("trials_per_theta", trials_per_theta)
    batch = thetas.shape[0] * trials_per_theta
    theta = thetas.float().repeat_interleave(trials_per_theta, 0)
    env = TransformedEnv(
        TaskEnv(model=model, batch_size=(batch,), theta=theta, seed=seed, device=thetas.device),
        EKFBelief(model),
    )
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(model.max_steps, policy, break_when_any_done=False)
    return rollout, first_trial_mask(rollout["next", "done"].squeeze(-1))


@dataclass
class TrainResult:
    """What :func:`train_ensemble` returns."""

    #: the best policy by evaluation (greedy: run it under ``ExplorationType.DETERMINISTIC``)
    actor: TensorDictSequential
    #: the critic at the end of training
    critic: TensorDictSequential
    model: TaskModel
    config: Firefly2DConfig
    #: one row per evaluation: frames, updates, cpu_s, train_cpu_s, success_rate, ...
    history: list[dict[str, Any]]
    #: the evaluation of the kept (best) policy
    best: dict[str, Any]
    frames: int
    updates: int
    checkpoint: Path | None


class _Logger:
    """TorchRL's CSV (or TensorBoard) logger under ``out``; does nothing without ``out``."""

    #: the experiment's name: TorchRL's loggers write under ``out/logs/NAME``
    NAME = "train"

    def __init__(self, kind: str, out: Path | None) -> None:
        self.logger = None
        if out is None or kind == "none":
            return
        if kind == "tensorboard":
            try:
                from torchrl.record.loggers import TensorboardLogger

                self.logger = TensorboardLogger(self.NAME, log_dir=str(out / "logs"))
                return
            except ImportError as error:  # TensorBoard absent: CSV, as documented
                warnings.warn(
                    f"logger='tensorboard': TensorBoard is not installed ({first_line(error)}); "
                    f"writing CSV logs to {out / 'logs'} instead",
                    stacklevel=4,
                )
        from torchrl.record.loggers import CSVLogger

        self.logger = CSVLogger(self.NAME, log_dir=str(out / "logs"))

    def log(self, values: Mapping[str, float], step: int) -> None:
        if self.logger is not None:
            for name, value in values.items():
                self.logger.log_scalar(name, float(value), step=step)


def _progress_bar(enabled: bool, total: int, initial: int):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="frame", unit_scale=True, desc="train")


def train_ensemble(
    config: Firefly2DConfig | None = None,
    out: str | Path | None = None,
    resume: str | Path | None = None,
    progress: bool = True,
    seed: int | None = None,
    model: TaskModel | None = None,
) -> TrainResult:
    """Train one θ-conditioned DDPG policy over the θ prior (Algorithm 1).

    Args:
        config: the settings (default: the embedded default of :class:`Firefly2DConfig`).
        out: folder for ``checkpoint.pt`` (at the end of the batch whose updates reach each
            multiple of ``checkpoint_every``, and at the end),
            ``config.yaml``, ``summary.json`` and the logger's files; ``None`` writes nothing.
        resume: a checkpoint to continue from. Networks, optimisers, exploration noise,
            counters and RNG states are restored; the replay buffer and the trials in flight
            are not (the buffer is refilled with ``warmup_frames`` from the current policy).
            The config is the run's: a warning names every setting that differs from the
            checkpoint's (but ``ddpg.total_frames`` and ``device``), learning rates and noise
            bounds included; other networks than the checkpoint's are refused.
        progress: show a progress bar with the current success rate (the return, for a task
            without success).
        seed: overrides ``config.seed``.
        model: a continuous-action task of the user's own (``None``: the 2D firefly task of
            ``config``); on another device than the config's, a copy gets its action spec
            moved there. The config's ``task`` becomes its
            :attr:`~irc_torchrl.envs.model.TaskModel.name`, which the checkpoint carries;
            ``theta_fixed`` must be empty, and ``ddpg.warmup_policy`` ``"random"`` unless the
            model is the 2D firefly's (the pursuit warm-up knows that task only). With
            ``collector_workers > 1`` the model goes to the collector processes, so its class
            must be importable there.

    Deterministic for a seed and a single collector process: nothing depends on wall time.
    """
    config = dataclasses.replace(config if config is not None else Firefly2DConfig())
    if seed is not None:
        config.seed = int(seed)
    if _check_model(model) is not None:
        config.task = model.name
    config.validate(model, fresh=resume is None)
    if model is not None:
        _check_trainable(config, model)
    device = resolve_device(config.device)
    model = _on_device(model, device) if model is not None else None
    out = Path(out) if out is not None else None
    with torch_settings(config.threads, config.flush_denormal), torch.random.fork_rng():
        return _train(config, model, device, out, resume, progress)


def _train(
    config: Firefly2DConfig,
    model: TaskModel | None,
    device: torch.device,
    out: Path | None,
    resume: str | Path | None,
    progress: bool,
) -> TrainResult:
    d, e = config.ddpg, config.evaluation
    torch.manual_seed(config.seed)
    with torch.device(device):  # TorchRL's modules and specs are built on the default device
        model = make_model(config) if model is None else model
        actor = make_actor(model, d.hidden, d.activation)
        critic = make_critic(model, d.hidden, d.activation)
        noise = AdditiveGaussianModule(
            model.action_spec,
            sigma_init=d.sigma_init,
            sigma_end=d.sigma_end,
            annealing_num_steps=d.anneal_frames,
        )
        loss, critic_params, value_key, value_loss = _make_loss(model, actor, critic, d)
        loss.make_value_estimator(ValueEstimators.TD0, gamma=d.gamma)
        target_update = SoftUpdate(loss, tau=d.tau)
    explore = TensorDictSequential(actor, noise)
    opt_actor = torch.optim.Adam(loss.actor_network_params.values(True, True), lr=d.lr_actor)
    opt_critic = torch.optim.Adam(critic_params.values(True, True), lr=d.lr_critic)
    thetas = theta_grid(model.theta_space, e.n_theta, e.seed).to(device)

    frames, updates, history, best = 0, 0, [], None
    # frames the pursuit warm-up collected: beyond total_frames, which counts the frames of the
    # exploring policy (a resumed run's budget must not spend them a second time)
    seeded = 0
    best_actor = {k: v.clone() for k, v in actor.state_dict().items()}
    env_seed = config.seed
    if resume is not None:
        ckpt = load_checkpoint(
            resume, task=model.name, theta_space=model.theta_space, required=RESUME_ENTRIES
        )
        _check_networks(ckpt, d)
        _check_budget(ckpt, d)
        _restore(loss, ckpt, "loss")
        _restore(opt_actor, ckpt, "optimiser_actor")
        _restore(opt_critic, ckpt, "optimiser_critic")
        _restore(noise, ckpt, "exploration")
        _apply_schedule(ckpt, config, opt_actor, opt_critic, noise)
        _check_fit(actor, ckpt, "best_actor", ckpt["best_actor"])
        best_actor = ckpt["best_actor"]
        counters = ckpt["counters"]
        frames, updates = int(counters["frames"]), int(counters["updates"])
        seeded = int(counters.get("warmup_frames", 0))  # absent from older checkpoints
        history, best = list(ckpt["history"]), ckpt["best"]
        # a fresh world stream for the trials after the resume, derived from the counters
        env_seed = config.seed + 7919 * (updates + 1)
        torch.set_rng_state(ckpt["rng"]["torch"])
        if device.type == "cuda":  # a run from the CPU has no GPU stream: one from the counters
            if "cuda" in ckpt["rng"]:
                torch.cuda.set_rng_state(ckpt["rng"]["cuda"], device)
            else:
                torch.cuda.manual_seed(env_seed)
        trained_on = str(ckpt["config"].get("device", "cpu"))
        if trained_on.split(":")[0] != device.type:
            warnings.warn(
                f"resume: {ckpt['path']} was trained on {trained_on}; continuing on {device} "
                "(the config's device)",
                stacklevel=3,
            )

    frames_per_batch = d.n_envs * d.steps_per_batch
    remaining = max(d.total_frames + seeded - frames, 0)
    remaining = math.ceil(remaining / frames_per_batch) * frames_per_batch
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(d.buffer_size, device=device), batch_size=d.batch_size
    )
    if out is not None and resume is None:  # an earlier run's rows would run on into this one's
        shutil.rmtree(out / "logs" / _Logger.NAME, ignore_errors=True)
    logger = _Logger(config.logger, out)
    bar = _progress_bar(progress, d.total_frames, frames - seeded)
    cpu0 = time.process_time() - (history[-1]["cpu_s"] if history else 0.0)
    eval_cpu = history[-1]["cpu_s"] - history[-1]["train_cpu_s"] if history else 0.0
    checkpoint_path = out / "checkpoint.pt" if out is not None else None
    settings = yaml.safe_dump(dataclasses.asdict(config), sort_keys=False)
    if checkpoint_path is not None and (resume is not None or not checkpoint_path.exists()):
        write_text(out / "config.yaml", settings)  # else with this run's first checkpoint

    def state() -> dict[str, Any]:
        return {
            "loss": loss.state_dict(),
            "actor": actor.state_dict(),
            "best_actor": best_actor,
            "optimiser_actor": opt_actor.state_dict(),
            "optimiser_critic": opt_critic.state_dict(),
            "exploration": noise.state_dict(),
            "counters": {"frames": frames, "updates": updates, "warmup_frames": seeded},
            "rng": {"torch": torch.get_rng_state(), **_device_rng_state(device)},
            "history": history,
            "best": best,
        }

    def checkpoint() -> None:
        """The checkpoint, with the config it was trained by; an earlier run's summary goes
        with the checkpoint it described (until this run's own replaces it)."""
        if checkpoint_path is not None:
            save_checkpoint(
                checkpoint_path,
                task=model.name,
                theta_space=model.theta_space,
                config=dataclasses.asdict(config),
                state=state(),
            )
            write_text(out / "config.yaml", settings)
            if resume is None:
                (out / "summary.json").unlink(missing_ok=True)

    def evaluate() -> None:
        nonlocal best, best_actor, eval_cpu
        start = time.process_time()
        metrics = evaluate_policy(model, actor, thetas, e.trials_per_theta, e.seed)
        eval_cpu += time.process_time() - start
        cpu = time.process_time() - cpu0
        row = {"frames": frames, "updates": updates, "cpu_s": cpu, "train_cpu_s": cpu - eval_cpu}
        row.update({k: v for k, v in metrics.items() if not k.startswith("per_theta")})
        history.append(row)
        logged = {k: v for k, v in row.items() if k not in ("frames", "updates") and v is not None}
        logger.log(logged, frames)
        if best is None or metrics["mean_return"] > best["mean_return"]:
            best = {**metrics, "frames": frames, "updates": updates}
            best_actor = {k: v.clone() for k, v in actor.state_dict().items()}
        if bar is not None and metrics["success_rate"] is not None:
            bar.set_postfix(
                success=f"{metrics['success_rate']:.0%}", best=f"{best['success_rate']:.0%}"
            )
        elif bar is not None:
            bar.set_postfix(ret=f"{metrics['mean_return']:.3g}", best=f"{best['mean_return']:.3g}")

    warmup = min(d.warmup_frames, d.buffer_size)
    teacher = BeliefPursuit(model) if d.warmup_policy == "pursuit" else None
    if resume is None and teacher is not None:
        with torch.device(device):
            jitter = AdditiveGaussianModule(
                model.action_spec, sigma_init=d.warmup_sigma, sigma_end=d.warmup_sigma
            )
        seeding = TensorDictSequential(teacher, jitter)
        warmup_collector = _make_collector(config, model, seeding, env_seed + 1, warmup, False)
        warmup_steps = MultiStepTransform(d.n_steps, d.gamma)
        for batch in warmup_collector:
            frames += batch.numel()
            seeded += batch.numel()
            _extend(buffer, warmup_steps, batch)
        warmup_collector.shutdown()
        _pretrain(loss, value_loss, teacher, buffer, opt_actor, opt_critic, target_update, d)
        evaluate()  # the clone is a candidate too: DDPG may degrade it before it improves on it
    random_start = resume is None and d.warmup_policy == "random"
    collector = _make_collector(config, model, explore, env_seed, remaining, random_start)
    multi_step = MultiStepTransform(d.n_steps, d.gamma)
    for batch in collector if remaining else ():
        new_frames = batch.numel()
        frames += new_frames
        _extend(buffer, multi_step, batch)
        _anneal(noise, new_frames)
        if bar is not None:
            bar.update(new_frames)
        if len(buffer) < warmup:
            continue
        before = updates
        for _ in range(d.updates_per_batch):
            sample = buffer.sample()
            losses = loss(sample)
            total = losses[value_key]
            if (updates + 1) % d.policy_delay == 0:  # the actor moves every policy_delay steps
                total = total + losses["loss_actor"]
                weight = d.bc_weight * (1.0 - updates / d.bc_updates if d.bc_updates else 1.0)
                if teacher is not None and weight > 0:
                    total = total + weight * _clone_loss(loss.actor_network, teacher, sample)
                if d.pre_activation_weight > 0:
                    penalty = _pre_activation_penalty(loss.actor_network, sample)
                    total = total + d.pre_activation_weight * penalty
                if d.smoothness_weight > 0:
                    jitter = _smoothness_loss(loss.actor_network, sample, d.smoothness_sigma)
                    total = total + d.smoothness_weight * jitter
            total.backward()
            if d.max_grad_norm > 0:
                for group in (opt_actor, opt_critic):
                    torch.nn.utils.clip_grad_norm_(group.param_groups[0]["params"], d.max_grad_norm)
            opt_actor.step()
            opt_critic.step()
            opt_actor.zero_grad()
            opt_critic.zero_grad()
            target_update.step()
            updates += 1
            if updates % 100 == 0:
                logger.log({k: losses[k].item() for k in ("loss_actor", value_key)}, frames)
            if updates % e.every == 0:
                evaluate()
        # at the end of the batch whose updates reach a multiple of checkpoint_every: its
        # frames are counted, so a run resumed from mid-batch would skip the batch's rest
        if updates // config.checkpoint_every > before // config.checkpoint_every:
            checkpoint()
        collector.update_policy_weights_()
    collector.shutdown()
    if bar is not None:
        bar.close()
    if not history or history[-1]["updates"] != updates:
        evaluate()
    checkpoint()
    actor.load_state_dict(best_actor)
    if out is not None:
        write_json(
            out / "summary.json",
            {
                "command": "train",
                "task": model.name,
                "seed": config.seed,
                "version": irc_torchrl.__version__,
                "frames": frames,
                "updates": updates,
                "best": best,
                "history": history,
                "theta_grid": thetas.tolist(),
                "theta_names": model.theta_space.names,
                # what Algorithm 2 can read from the kept policy's actions, and how abruptly
                # it stops (one set of greedy trials for both)
                **_policy_report(model, actor, thetas, e.trials_per_theta, e.seed),
            },
        )
    return TrainResult(
        actor, critic, model, config, history, best, frames, updates, checkpoint_path
    )


def _device_rng_state(device: torch.device) -> dict[str, torch.Tensor]:
    """The random state of ``device`` beside the CPU's (exploration noise is drawn there)."""
    return {"cuda": torch.cuda.get_rng_state(device)} if device.type == "cuda" else {}


def _make_loss(
    model: TaskModel, actor: TensorDictSequential, critic: TensorDictSequential, d: DDPGConfig
) -> tuple[LossModule, TensorDictBase, str, Callable[[TensorDictBase], tuple]]:
    """TorchRL's DDPG or TD3 loss over ``actor`` and ``critic``: the loss, the critic's
    parameters (TD3's twin copies stacked), the key of the critic's loss in its output, and
    the loss's method that computes that term alone (for critic-only steps)."""
    if d.loss == "td3":
        loss = TD3Loss(
            actor,
            critic,
            action_spec=model.action_spec,
            num_qvalue_nets=2,
            policy_noise=d.policy_noise,
            noise_clip=d.noise_clip,
        )
        return loss, loss.qvalue_network_params, "loss_qvalue", loss.value_loss
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    return loss, loss.value_network_params, "loss_value", loss.loss_value


def _pretrain(
    loss: LossModule,
    value_loss: Callable[[TensorDictBase], tuple],
    teacher: TensorDictModuleBase,
    buffer: TensorDictReplayBuffer,
    opt_actor: torch.optim.Optimizer,
    opt_critic: torch.optim.Optimizer,
    target_update: SoftUpdate,
    d: DDPGConfig,
) -> None:
    """Clone ``teacher`` into the actor, then fit the critic to that actor, on the buffer."""
    _set_lr(opt_actor, d.lr_clone)
    for _ in range(d.clone_updates):
        _clone_loss(loss.actor_network, teacher, buffer.sample()).backward()
        opt_actor.step()
        opt_actor.zero_grad()
    _set_lr(opt_actor, d.lr_actor)
    with warnings.catch_warnings():  # re-initialising the targets on purpose: they lag the clone
        warnings.simplefilter("ignore", UserWarning)
        target_update.init_()
    for _ in range(d.critic_updates):
        value_loss(buffer.sample())[0].backward()
        opt_critic.step()
        opt_critic.zero_grad()
        target_update.step()


def _anneal(noise: AdditiveGaussianModule, frames: int) -> None:
    """``noise.step(frames)`` bit for bit, in float32 NumPy: TorchRL's loops over the frames
    with a few tensor ops each (7.7 ms of a 256-frame batch on the CPU, against 0.5 ms)."""
    with torch.no_grad():
        rate = ((noise.sigma_init - noise.sigma_end) / noise.annealing_num_steps).cpu().numpy()
        sigma, end = noise.sigma.cpu().numpy(), noise.sigma_end.cpu().numpy()
        for _ in range(frames):  # each step rounds to float32, as TorchRL's copy into σ
            sigma = np.maximum(end, sigma - rate).astype(np.float32)
        noise.sigma.copy_(torch.from_numpy(np.asarray(sigma)))  # from the CPU, any default


def _set_lr(optimiser: torch.optim.Optimizer, lr: float) -> None:
    for group in optimiser.param_groups:
        group["lr"] = lr


def _clone_loss(
    actor: TensorDictModuleBase, teacher: TensorDictModuleBase, batch: TensorDictBase
) -> torch.Tensor:
    """Mean squared distance of the actor's actions from the teacher's on ``batch``'s beliefs."""
    # the teacher saturates at the bounds, where tanh has no finite preimage
    target = teacher(batch.clone())["action"].clamp(-0.97, 0.97)
    return (actor(batch.clone())["action"] - target).pow(2).mean()


def _pre_activation_penalty(actor: TensorDictModuleBase, batch: TensorDictBase) -> torch.Tensor:
    """Mean square of the actor's pre-tanh outputs (``param``) on ``batch``'s beliefs."""
    return actor(batch.clone())["param"].pow(2).mean()


def _smoothness_loss(
    actor: TensorDictModuleBase, batch: TensorDictBase, sigma: float
) -> torch.Tensor:
    """Mean squared change of the actor's actions when the belief mean moves by Gaussian noise
    of std ``sigma`` (its covariance and θ held): CAPS's spatial term, over the very latent
    whose spread Algorithm 2's outer filter integrates."""
    moved = batch.clone()
    mean = moved["belief", "mean"]
    moved["belief", "mean"] = mean + sigma * torch.randn_like(mean)
    return (actor(batch.clone())["action"] - actor(moved)["action"]).pow(2).sum(-1).mean()


def _extend(
    buffer: TensorDictReplayBuffer, multi_step: MultiStepTransform, batch: TensorDictBase
) -> None:
    """Store a collector batch ``[n_envs, steps]`` as n-step transitions (features recomputed).

    ``MultiStepTransform`` moves ``next`` to the end of each window but leaves the end-of-trial
    flags at the window's first step, so a window that reaches a stop would bootstrap from the
    terminal state (values then grow past any reward). The flags ride along under other names
    and are put back from the window's end.
    """
    batch = batch.exclude("features", "param", ("next", "features"))
    for key in ("done", "terminated", "truncated"):
        batch["next", f"window_{key}"] = batch["next", key]
    batch = multi_step.inv(batch)
    if batch is None:  # the first n_steps frames of each env wait for their future
        return
    for key in ("done", "terminated", "truncated"):
        batch["next", key] = batch["next"].pop(f"window_{key}")
    buffer.extend(batch.reshape(-1))


def _make_collector(
    config: Firefly2DConfig,
    model: TaskModel,
    policy: TensorDictModuleBase,
    seed: int,
    total_frames: int,
    random_start: bool,
):
    """A ``Collector`` (or ``MultiSyncCollector`` over processes) over the training world."""
    d, device = config.ddpg, torch.device(config.device)
    workers = d.collector_workers
    common = {
        "frames_per_batch": d.n_envs * d.steps_per_batch,
        "total_frames": max(total_frames, d.n_envs * d.steps_per_batch),
        "init_random_frames": d.warmup_frames if random_start else 0,
        "auto_register_policy_transforms": False,  # no state between steps: no InitTracker
        "device": device,  # where the policy runs and the batches are stored
    }
    if workers == 1:
        collector = Collector(make_train_env(model, d.n_envs, seed, device), policy, **common)
    else:
        makers = [
            partial(make_train_env, model, d.n_envs // workers, seed + 104729 * i, device)
            for i in range(workers)
        ]
        collector = MultiSyncCollector(makers, policy, **common)
    collector.set_seed(seed)
    return collector


def _check_networks(ckpt: Mapping[str, Any], d: DDPGConfig) -> None:
    """Refuse to resume a checkpoint whose networks the config would build differently."""
    saved = ckpt["config"].get("ddpg", {})
    for name in ("hidden", "activation", "loss"):
        if name in saved and saved[name] != getattr(d, name):
            raise ValueError(
                f"resume: checkpoint {ckpt['path']} has ddpg.{name}={saved[name]!r}, the config "
                f"{getattr(d, name)!r}; resume with the checkpoint's settings"
            )


def _check_budget(ckpt: Mapping[str, Any], d: DDPGConfig) -> None:
    """Warn where a checkpoint has already trained for the config's budget: the resumed run
    trains nothing and only writes what it restored again."""
    counters = ckpt["counters"]
    trained = int(counters["frames"]) - int(counters.get("warmup_frames", 0))
    if trained >= d.total_frames:
        warnings.warn(
            f"resume: {ckpt['path']} has trained {trained} frames, ddpg.total_frames is "
            f"{d.total_frames}: nothing left to train (a larger ddpg.total_frames trains on)",
            stacklevel=4,
        )


#: the settings a resumed run may change without a word: its budget is why it is resumed, and
#: another device has a warning of its own
RESUMED_FREELY = ("ddpg.total_frames", "device")


def _apply_schedule(
    ckpt: Mapping[str, Any],
    config: Firefly2DConfig,
    opt_actor: torch.optim.Optimizer,
    opt_critic: torch.optim.Optimizer,
    noise: AdditiveGaussianModule,
) -> None:
    """Give the restored optimisers and noise the config's rates and noise bounds (the config
    a resumed run writes is the one it runs), warning of every setting that differs from the
    checkpoint's (the evaluation grid the kept policy was chosen on, the seed, the rates)."""
    saved, now = _flat(ckpt["config"]), _flat(dataclasses.asdict(config))
    changed = [
        f"{key}: {saved[key]} → {value}"
        for key, value in now.items()
        if key in saved and saved[key] != value and key not in RESUMED_FREELY
    ]
    if changed:
        warnings.warn(
            f"resume: continuing {ckpt['path']} with the config's {'; '.join(changed)}",
            stacklevel=4,
        )
    d = config.ddpg
    _set_lr(opt_actor, d.lr_actor)
    _set_lr(opt_critic, d.lr_critic)
    noise.sigma_init.fill_(d.sigma_init)
    noise.sigma_end.fill_(d.sigma_end)
    noise.sigma.clamp_(d.sigma_end, d.sigma_init)


def _flat(settings: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A config's plain-dict form as ``{"ddpg.lr_actor": 1e-4, ...}``."""
    flat = {}
    for key, value in settings.items():
        if isinstance(value, Mapping) and value:
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _restore(target: Any, ckpt: Mapping[str, Any], entry: str, weights: Any = None) -> None:
    """``target.load_state_dict`` of the checkpoint's ``entry`` (or of ``weights``, taken from
    it), a module's checked first by :func:`_check_fit`; a refusal is a ValueError naming both."""
    weights = ckpt[entry] if weights is None else weights
    if isinstance(target, torch.nn.Module):
        _check_fit(target, ckpt, entry, weights)
    try:
        target.load_state_dict(weights)
    except (RuntimeError, ValueError, KeyError, TypeError) as error:
        raise _misfit(ckpt, entry, first_line(error)) from None


def _check_fit(module: torch.nn.Module, ckpt: Mapping[str, Any], entry: str, weights: Any) -> None:
    """Refuse ``weights`` (the checkpoint's ``entry``, or taken from it) whose names or shapes
    are not exactly ``module``'s: TorchRL's losses load missing, extra and broadcastable
    weights without a word, and a kept policy is only loaded after training."""
    if not isinstance(weights, Mapping):
        raise _misfit(ckpt, entry, f"a {type(weights).__name__}, not a state dict")
    expected = module.state_dict()
    missing = [name for name in expected if name not in weights]
    extra = [name for name in weights if name not in expected]
    if missing or extra:
        what, names = ("missing", missing) if missing else ("unexpected", extra)
        raise _misfit(ckpt, entry, f"{len(names)} weight(s) {what}, e.g. {names[0]!r}")
    for name, value in expected.items():
        shape = getattr(weights[name], "shape", None)
        if shape != value.shape:
            found = list(shape) if shape is not None else type(weights[name]).__name__
            raise _misfit(ckpt, entry, f"{name} is {found}, the network's {list(value.shape)}")


def _misfit(ckpt: Mapping[str, Any], entry: str, problem: str) -> ValueError:
    return ValueError(
        f"checkpoint {ckpt['path']}: entry {entry} does not fit the networks its config builds "
        f"({problem}); expected the weights irc train saved with that config"
    )


def _load(
    source: str | Path, required: Sequence[str], model: TaskModel | None = None
) -> tuple[Firefly2DConfig, TaskModel, dict[str, Any]]:
    """A checkpoint holding the entries ``required``: its config and task model (``model``,
    or the 2D firefly of its config), the θ space checked against that model's."""
    task = TASK if _check_model(model) is None else model.name
    ckpt = load_checkpoint(source, task=task, required=required)
    try:
        config = config_from_dict(ckpt["config"]).validate(model, fresh=False)
    except (TypeError, ValueError) as error:
        raise ValueError(
            f"checkpoint {ckpt['path']}: entry config is not a config irc train writes ({error})"
        ) from None
    whose = "its own config's" if model is None else "the model's"
    model = make_model(config) if model is None else model
    difference = model.theta_space.difference(ThetaSpace.from_config(ckpt["theta_space"]))
    if difference:
        raise ValueError(
            f"checkpoint {ckpt['path']}: theta_space does not match {whose} θ space "
            f"({difference}, the checkpoint's first)"
        )
    return config, model, ckpt


def _caller_rng_kept(device: torch.device) -> contextlib.AbstractContextManager:
    """Networks built to be overwritten by a checkpoint draw their initial weights here without
    advancing the caller's random stream (loading a policy moved every later unseeded draw)."""
    return torch.random.fork_rng(devices=[device] if device.type == "cuda" else [])


def load_ensemble_policy(
    source: str | Path = TASK, device: torch.device | str = "cpu", model: TaskModel | None = None
) -> tuple[TensorDictSequential, TaskModel, dict[str, Any]]:
    """The kept (best-by-evaluation) policy of a checkpoint: ``(actor, model, checkpoint)``.

    ``source`` is a path or the name of a packaged checkpoint (default: the shipped one); the
    actor and the model (its action spec) are built on ``device``, whatever torch's default
    device is, the actor in float32 whatever its default dtype. ``model``: the task of the
    user's own the checkpoint was trained on, built on ``device`` (its name and θ space are
    checked); ``None``: the 2D firefly task.
    """
    device = resolve_device(str(device))
    with torch.device(device):
        config, model, ckpt = _load(source, ("best_actor",), model)
        with _caller_rng_kept(device):
            actor = make_actor(model, config.ddpg.hidden, config.ddpg.activation)
    _restore(actor, ckpt, "best_actor")
    return actor.requires_grad_(False), model, ckpt


def load_ensemble_critic(
    source: str | Path = TASK, device: torch.device | str = "cpu", model: TaskModel | None = None
) -> tuple[TensorDictSequential, TensorDictSequential, TaskModel]:
    """A checkpoint's critic and the actor it values, both at its last update.

    Returns ``(critic, actor, model)``; the critic is ``Q(b, a, θ)`` of that actor (the kept
    policy may be an earlier one). ``device`` and ``model`` as in :func:`load_ensemble_policy`.
    """
    if isinstance(device, TaskModel):  # the second argument was the model before `device`
        raise TypeError(
            "device: got a TaskModel; load_ensemble_critic's arguments are (source, device, "
            "model), as load_ensemble_policy's: pass it as model=..."
        )
    device = resolve_device(str(device))
    with torch.device(device):
        config, model, ckpt = _load(source, ("actor", "loss"), model)
        hidden, activation = config.ddpg.hidden, config.ddpg.activation
        with _caller_rng_kept(device):
            actor = make_actor(model, hidden, activation)
            critic = make_critic(model, hidden, activation)
    _restore(actor, ckpt, "actor")
    # DDPG's critic, or the first of TD3's twin copies (stacked along a leading dimension)
    twin = config.ddpg.loss == "td3"
    prefix = "qvalue_network_params." if twin else "value_network_params."
    weights = {
        k[len(prefix) :]: v[0] if twin else v
        for k, v in ckpt["loss"].items()
        if k.startswith(prefix)
    }
    _restore(critic, ckpt, "loss", weights)
    return critic.requires_grad_(False), actor.requires_grad_(False), model


@torch.no_grad()
def critic_slices(
    model: Firefly2DModel,
    critic: TensorDictSequential,
    actor: TensorDictSequential,
    theta: torch.Tensor,
    n: int = 41,
) -> dict[str, Any]:
    """Slices of ``Q(b, a; θ)`` for the paper's Fig. 1B on the 2D task.

    The agent stands at the origin heading along +x, at rest, certain of where it is, at the
    first step where it may stop. ``value``: ``Q(b, π(b); θ)`` for the target at each point of
    an ``n × n`` grid (ahead, aside). ``q_far`` / ``q_near``: ``Q`` over the action square for a
    target ahead-left at mid distance / at the agent's feet, with ``π(b)`` as ``pi_far`` /
    ``pi_near``. Distances are in the task's units. Evaluated where the critic is; returned on
    the CPU.
    """
    theta = model.theta_space.validate(theta, "theta")
    if theta.shape != (model.theta_space.dim,):
        raise ValueError(
            f"theta: expected one θ [{model.theta_space.dim}], got {list(theta.shape)}"
        )
    n = count("n", n)
    device = next(critic.parameters()).device
    with torch.device(device):
        out = _critic_slices(model, critic, actor, theta.to(device), n)
    return {k: v.cpu() if isinstance(v, torch.Tensor) else v for k, v in out.items()}


def _critic_slices(
    model: Firefly2DModel,
    critic: TensorDictSequential,
    actor: TensorDictSequential,
    theta: torch.Tensor,
    n: int,
) -> dict[str, Any]:
    """:func:`critic_slices` on the default device, once its inputs are checked."""
    far = float(model.target_distance[1])
    ahead = torch.linspace(-0.25 * far, far, n)
    aside = torch.linspace(-0.6 * far, 0.6 * far, n)
    targets = torch.stack(torch.meshgrid(ahead, aside, indexing="ij"), -1).reshape(-1, 2)
    action = torch.linspace(-1.0, 1.0, n)
    actions = torch.stack(torch.meshgrid(action, action, indexing="ij"), -1).reshape(-1, 2)

    def beliefs(target: torch.Tensor) -> TensorDictBase:
        batch = target.shape[0]
        mean = torch.zeros(batch, model.state_dim)
        mean, cov = model.initial_belief(mean, target, theta.expand(batch, -1))
        return TensorDict(
            {
                "belief": {"mean": mean, "cov": cov},
                "target": target,
                "step": torch.full((batch, 1), model.min_steps, dtype=torch.int64),
                "theta": theta.float().expand(batch, -1),
            },
            batch_size=[batch],
        )

    def q(td: TensorDictBase, action: torch.Tensor) -> torch.Tensor:
        return critic(td.set("action", action))["state_action_value"].squeeze(-1)

    grid = beliefs(targets)
    value = q(grid, actor(grid.clone())["action"]).reshape(n, n)
    out: dict[str, Any] = {"ahead": ahead, "aside": aside, "action": action, "value": value}
    for name, target in (("far", [0.6 * far, 0.25 * far]), ("near", [0.0, 0.0])):
        one = beliefs(torch.tensor([target]))
        out[f"pi_{name}"] = actor(one.clone())["action"][0]
        out[f"q_{name}"] = q(one.expand(actions.shape[0]).clone(), actions).reshape(n, n)
        out[f"target_{name}"] = target
    out["goal_radius"] = float(theta[model.theta_space.index("goal_radius")])
    out["stop_threshold"] = model.stop_threshold
    return out
