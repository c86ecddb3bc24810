"""Tutorial: define your own task family and fit θ for it, without touching the library.

A task is written once, as a :class:`~irc_torchrl.envs.model.TaskModel` subclass in batched
torch ops (differentiable in θ). Here it is a 1D "reach and hold" task: a point mass at
position ``x`` with velocity ``v`` is pushed by a control ``a ∈ [-1, 1]`` towards a target
shown at the start, and should stay there until the time is up::

    x' = x + v dt                        (dt = 0.1 s, 40 steps)
    v' = v + g a dt + σ_v ε              the agent observes  o = v + σ_o ε  (not x)

Each step costs ``dt (e² + c a²)`` for the distance ``e`` to the target and the effort.
θ = (g, σ_v, σ_o, c); σ_v is held fixed (the experimenter measures the world's process noise).

What you write, as :class:`ReachModel` below does:

- the θ space (:class:`~irc_torchrl.theta.ThetaSpace`), the dimensions, ``max_steps``, ``dt``,
  the action spec, and the names and units of state, action and target;
- the world: ``initial_state``, ``transition`` and ``process_cov`` (Gaussian process noise),
  ``observe`` and ``observation_cov`` (Gaussian observation noise), ``stops``, ``reward``;
- the agent: ``initial_belief``, ``belief_reward`` (the paper's ``R_θ(b, a)``), and
  ``belief_features`` (what a policy reads, ending with the normalised θ; its arguments'
  batch dimensions broadcast, so expand before concatenating) with ``belief_feature_dim``.
  ``transition_jacobian`` and ``observation_jacobian`` are optional: by default ``torch.func``
  takes them (exact here, the task being linear); so is ``rate_limit``, the fastest speed a
  recording read by ``read_trials`` may show (by default 10× θ's largest bound in its unit,
  here a noise: :class:`ReachModel` bounds its speeds by its gain instead);
- a name (:attr:`~irc_torchrl.envs.model.TaskModel.name`), which its checkpoints carry, and
  optionally :meth:`~irc_torchrl.envs.model.TaskModel.succeeded` (this task has no success,
  only costs);
- a policy over the belief features. This one needs no training: with a linear world,
  Gaussian noise and quadratic costs the optimal control acts on the belief mean alone (LQG's
  separation principle), and :class:`LQGController` applies the continuous-time LQR gain of
  the agent's own ``g`` and ``c`` to it (near-optimal: the simulated task steps by ``dt`` and
  saturates at ±1, where the discrete-time gain on the distance is 10-16% lower). A
  hand-written policy goes into
  :class:`~irc_torchrl.modules.likelihood.CensoredGaussianActionModel` directly; an actor
  trained by Algorithm 1 (``train_ensemble(model=...)``, below) through
  ``censored_action_model``.

What you get, unchanged: :class:`~irc_torchrl.envs.task_env.TaskEnv` (a batched TorchRL env,
each element with its own θ), :class:`~irc_torchrl.envs.belief.EKFBelief` (the agent's filter
as a transform) and ``BeliefReward``, :func:`~irc_torchrl.algorithms.simulate.simulate_agents`
with motor noise, and Algorithm 2: :class:`~irc_torchrl.objectives.inverse.InverseRationalLoss`
and :func:`~irc_torchrl.algorithms.fit.fit_theta`, θ̂ with 95% intervals by both estimators,
and ``particle_check``, which measures what each estimator's likelihood loses against a
particle filter's. This script checks that the controller does the task, simulates three
agents whose internal model θ* differs from the world's (the world runs at the θ space's
defaults, recorded as ``task_theta``), and fits them both ways:

    python examples/define_your_task.py --out runs/own_task   # about 15 s on one core

``marginal`` (the agent's unseen observations integrated out) recovers θ* within its
intervals (35 of its 36 over seeds 0-3, 8 of 9 at seed 0), and its likelihood at θ* is the
particle filter's to a nat or two. ``map`` (the
paper's hard E-step: the observations at their most probable value) is twice as fast, but it
blames the agent's observation noise on its motor noise (fitted 10-85% high), its likelihood
at θ* falls tens to hundreds of nats below the particle filter's, and its intervals, narrower
than its bias, miss θ* for two to five of the nine parameters (seeds 0-3).

Algorithm 1 learns the policy instead, on this task as on the firefly's:
``train_ensemble(config, model=ReachModel())`` (DDPG from a uniform random warm-up, its
checkpoints, resume and evaluations the firefly's) and ``load_ensemble_policy(path, model=)``.
``--train-frames`` does it, compares the learned policy with the controller, and fits agents
that act by it::

    python examples/define_your_task.py --out runs/own_task --train-frames 200000  # ~2 min

(or from the command line, with the settings of :func:`ensemble_config`: ``irc train --model
examples/define_your_task.py:ReachModel --seed 0 ddpg.n_envs=32 ddpg.total_frames=200000
ddpg.anneal_frames=200000 ddpg.warmup_frames=2048 ddpg.buffer_size=100000
ddpg.batch_size=256 evaluation.n_theta=16 evaluation.trials_per_theta=8
evaluation.every=250``; then ``irc recover --model examples/define_your_task.py:ReachModel
--checkpoint runs/train/checkpoint.pt`` scores Algorithm 2 on 40 agents of this task, about
6 min on 2 cores).

At seed 0 the learned policy costs 1.23× the controller's over 16 θ (1.00-1.86×). It reads θ
otherwise than the optimum: its control turns on the effort cost a third as much (0.12 against
0.41) and on the observation noise, which the controller ignores (LQG's certainty equivalence).
Fitted with it, ``marginal`` holds the gains and observation noises of the three agents within
its intervals (5 of 6) and leaves the effort cost nearly the prior's range: Algorithm 2 recovers
what the rational policy reads.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import Compose, ExplorationType, TransformedEnv, set_exploration_type

from irc_torchrl.algorithms.ensemble import (
    DDPGConfig,
    EvaluationConfig,
    Firefly2DConfig,
    evaluate_policy,
    load_ensemble_policy,
    theta_grid,
    theta_sensitivity,
    train_ensemble,
)
from irc_torchrl.algorithms.fit import fit_theta, particle_check
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.data.files import write_json
from irc_torchrl.envs import BeliefFeatures, BeliefReward, EKFBelief, TaskEnv, TaskModel
from irc_torchrl.envs.model import ABSURD
from irc_torchrl.modules.actor_critic import censored_action_model
from irc_torchrl.modules.likelihood import CensoredGaussianActionModel
from irc_torchrl.objectives.inverse import METHODS, InverseRationalLoss
from irc_torchrl.theta import Parameter, ThetaSpace

#: std added to every noise and the initial belief's std, so every covariance is positive
#: definite (the position has no process noise of its own)
NOISE_FLOOR = 1e-3
#: the agents we simulate, each with its own internal model of gain, observation noise and
#: effort cost (the world runs at the θ space's defaults: 1.0, 0.05, 0.1)
TRUE_THETA = (
    {"g": 1.3, "obs_sigma": 0.05, "effort_cost": 0.05},
    {"g": 0.8, "obs_sigma": 0.2, "effort_cost": 0.2},
    {"g": 1.6, "obs_sigma": 0.1, "effort_cost": 0.3},
)
#: the agents' motor noise (one std of the control), fitted beside θ
MOTOR_NOISE = 0.1
#: particles of the reference likelihood each estimator's is compared with at θ*
PARTICLES = 1000


def reach_theta_space() -> ThetaSpace:
    """θ = (g, σ_v, σ_o, c); the world's process noise σ_v is held at its measured value."""
    return ThetaSpace(
        [
            Parameter("g", 0.5, 2.0, 1.0, "distance/s²", "acceleration at full control"),
            Parameter("sigma_v", 0.0, 0.1, 0.05, "distance/s", "process noise std of v"),
            Parameter("obs_sigma", 0.01, 0.3, 0.05, "distance/s", "observation noise std of v"),
            Parameter("effort_cost", 0.02, 0.5, 0.1, "distance²", "cost of a², in units of e²"),
        ],
        fixed={"sigma_v": 0.05},
    )


class ReachModel(TaskModel):
    """The reach-and-hold task (see the module docstring): linear, so its EKF is exact."""

    #: what its checkpoints are called (by default the class's name)
    name = "reach_and_hold"
    theta_space = reach_theta_space()
    state_dim, observation_dim, target_dim = 2, 1, 1
    max_steps = 40
    dt = 0.1
    action_spec = Bounded(-1.0, 1.0, shape=(1,), dtype=torch.float32)
    state_names, state_units = ("x", "v"), ("distance", "distance/s")
    action_names, target_names = ("a",), ("target_x",)
    #: how far away the target is, at most (either side)
    target_range = 1.0
    belief_feature_dim = 5

    def rate_limit(self, unit: str) -> float | None:
        """10× the speed of full control held for a whole trial at the largest gain: θ bounds
        this task's speeds through ``g`` (distance/s²), not through its noises (distance/s)."""
        if unit != "distance/s":
            return None
        return ABSURD * self.theta_space["g"].high * self.max_steps * self.dt

    # --- world ---------------------------------------------------------------------------
    def initial_state(
        self, theta: torch.Tensor, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """At rest at 0; the target uniform within ``target_range`` on either side."""
        kind = {"dtype": theta.dtype, "device": theta.device}
        u = torch.rand(*theta.shape[:-1], 1, generator=generator, **kind)
        return torch.zeros(*theta.shape[:-1], 2, **kind), self.target_range * (2 * u - 1)

    def transition(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        """The position integrates the velocity; the control accelerates by ``g``."""
        x, v = state[..., :1], state[..., 1:]
        push = self.parameter(theta, "g") * action.to(state.dtype) * self.dt
        return torch.cat(torch.broadcast_tensors(x + v * self.dt, v + push), -1)

    def process_cov(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        """Noise on the velocity only (and the floor on both)."""
        sigma_v = self.parameter(theta, "sigma_v")
        var = torch.cat([torch.zeros_like(sigma_v), sigma_v**2], -1) + NOISE_FLOOR**2
        batch = torch.broadcast_shapes(state.shape[:-1], var.shape[:-1])
        return torch.diag_embed(var.expand(*batch, 2))

    def observe(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """The agent senses its velocity."""
        return state[..., 1:]

    def observation_cov(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """``σ_o²`` (and the floor)."""
        var = self.parameter(theta, "obs_sigma") ** 2 + NOISE_FLOOR**2
        batch = torch.broadcast_shapes(state.shape[:-1], var.shape[:-1])
        return var.expand(*batch, 1).unsqueeze(-1)

    def stops(self, action: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """The agent holds until the time is up: no action ends a trial."""
        return torch.zeros_like(step, dtype=torch.bool)

    def cost(self, error2: torch.Tensor, action: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """``dt (e² + c a²)`` from the squared distance ``e²`` ``[*B, 1]``."""
        effort = self.parameter(theta, "effort_cost") * (action.to(theta.dtype) ** 2)
        return self.dt * (error2 + effort)

    def reward(
        self,
        state: torch.Tensor,
        target: torch.Tensor,
        action: torch.Tensor,
        stop: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        """Minus the cost at the true position."""
        return -self.cost((state[..., :1] - target) ** 2, action, theta)

    # --- agent ---------------------------------------------------------------------------
    def initial_belief(
        self, state: torch.Tensor, target: torch.Tensor, theta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The agent knows where it starts (up to the floor)."""
        eye = torch.eye(2, dtype=state.dtype, device=state.device)
        return state.clone(), (NOISE_FLOOR**2 * eye).expand(*state.shape, 2).clone()

    def belief_reward(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        target: torch.Tensor,
        action: torch.Tensor,
        stop: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        """Minus the expected cost: ``E[e²]`` is the believed distance² plus its variance."""
        return -self.cost((mean[..., :1] - target) ** 2 + cov[..., 0, :1], action, theta)

    def belief_features(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        target: torch.Tensor,
        step: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        """Believed distance and velocity, their stds, time; then the normalised θ."""
        std = torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(0).sqrt()
        parts = [
            mean[..., :1] - target,
            mean[..., 1:],
            std,
            step.to(mean.dtype) / self.max_steps,
            self.theta_space.normalise(theta),
        ]
        batch = torch.broadcast_shapes(*(p.shape[:-1] for p in parts))
        return torch.cat([p.expand(*batch, p.shape[-1]) for p in parts], -1)


class LQGController(nn.Module):
    """The agent's control from its belief features: ``a = -(ω² e + √2 ω v̂) / g`` with
    ``ω = √g / c^¼``, the LQR gain of ``ẍ = g a`` under the cost ``e² + c a²``.

    It reads the believed distance ``e`` and velocity ``v̂`` and the agent's own ``g`` and
    ``c`` (from the normalised θ at the end of the features); its muscles saturate at ±1.
    """

    def __init__(self, model: ReachModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """The commanded control ``[*B, 1]`` (unclipped: the world clips it to the bounds)."""
        model = self.model
        theta = model.theta_space.denormalise(features[..., model.belief_feature_dim :])
        gain, cost = model.parameter(theta, "g"), model.parameter(theta, "effort_cost")
        omega = gain.sqrt() / cost.sqrt().sqrt()
        error, velocity = features[..., :1], features[..., 1:2]
        return -(omega**2 * error + math.sqrt(2) * omega * velocity) / gain


def controller_policy(model: ReachModel) -> TensorDictSequential:
    """The controller as a TorchRL policy: belief → features → ``action``."""
    return TensorDictSequential(
        BeliefFeatures(model),
        TensorDictModule(LQGController(model), in_keys=["features"], out_keys=["action"]),
    )


def belief_returns(model: ReachModel, n_envs: int, seed: int) -> dict[str, dict[str, float]]:
    """The return the agent expects (``R_θ(b, a)`` summed) and its final distance to the
    target, acting with its controller or at random at the default θ: does the policy work?"""
    env = TransformedEnv(
        TaskEnv(model, batch_size=(n_envs,), theta=model.theta_space.default(), seed=seed),
        Compose(EKFBelief(model), BeliefReward(model)),
    )
    torch.manual_seed(seed)
    agent = motor_noise_policy(controller_policy(model), model.action_spec, MOTOR_NOISE)
    out = {}
    for name, policy in (("controller", agent), ("random", None)):
        env.set_seed(seed)  # the same targets for both
        with set_exploration_type(ExplorationType.RANDOM):
            rollout = env.rollout(model.max_steps, policy)
        distance = rollout["next", "state"][:, -1, :1] - rollout["target"][:, -1]
        out[name] = {
            "return": rollout["next", "reward"].sum(-2).mean().item(),
            "final_distance": distance.abs().mean().item(),
        }
    return out


def simulate(
    model: ReachModel, policy: TensorDictSequential, n_trials: int, seed: int
) -> tuple[torch.Tensor, TensorDict]:
    """Agents with :data:`TRUE_THETA` acting by ``policy`` with motor noise in the default world."""
    space = model.theta_space
    theta = torch.stack([space.from_dict(values) for values in TRUE_THETA])
    agent = motor_noise_policy(policy, model.action_spec, MOTOR_NOISE)
    return theta, simulate_agents(model, agent, theta, n_trials, space.default(), seed=seed)


def controller_action_model(model: ReachModel) -> CensoredGaussianActionModel:
    """Algorithm 2's action model of the controller: its control plus censored motor noise."""
    bounds = model.action_spec.space
    return CensoredGaussianActionModel(LQGController(model), bounds.low, bounds.high)


def fit_both(
    model: ReachModel,
    action_model: Callable[[], CensoredGaussianActionModel],
    theta: torch.Tensor,
    held: TensorDict,
    seed: int,
) -> dict[str, dict]:
    """θ̂ with intervals by each estimator (a fresh ``action_model()`` each), its fitted motor
    noise, its seconds, and what its likelihood at θ* loses against a particle filter's (nats
    per agent)."""
    truth = torch.full((len(theta), 1), math.log(MOTOR_NOISE))
    out = {}
    for method in METHODS:
        start = time.perf_counter()
        loss = InverseRationalLoss(model, action_model(), n_agents=len(theta), method=method)
        result = fit_theta(loss, held, n_starts=2, n_screen=16, seed=seed)
        seconds = time.perf_counter() - start
        check = particle_check(loss, held, theta, truth, PARTICLES, seed)
        out[method] = {
            "agents": [result.agent(i) for i in range(len(theta))],
            "motor_noise": result.nuisance[:, 0].exp().tolist(),
            "seconds": seconds,
            "gap_at_truth": (-check["approximation_gap"]).tolist(),
            "min_effective_particles": check["min_effective_particles"].tolist(),
        }
    return out


def report(model: ReachModel, truths: list[dict[str, float]], fits: dict[str, dict]) -> None:
    """Print θ̂ against θ* with the 95% intervals, then the motor noise and the gaps."""
    for method, fitted in fits.items():
        print(f"{method} ({fitted['seconds']:.0f} s):")
        print(f"  agent {'parameter':<12} {'θ*':>6} {'θ̂':>7}  95% interval")
        for i, (truth, agent) in enumerate(zip(truths, fitted["agents"], strict=True)):
            for name in model.theta_space.free_names:
                low, high = agent["ci_low"][name], agent["ci_high"][name]
                missed = "" if low <= truth[name] <= high else "  (misses θ*)"
                print(
                    f"  {i:<5} {name:<12} {truth[name]:>6.3f} {agent['theta_hat'][name]:>7.3f}"
                    f"  [{low:.3f}, {high:.3f}]{missed}"
                )
        noise = ", ".join(f"{x:.3f}" for x in fitted["motor_noise"])
        gaps = ", ".join(f"{x:+.1f}" for x in fitted["gap_at_truth"])
        print(f"  motor noise {noise} (θ*: {MOTOR_NOISE}); log L(θ*) − particle filter's: {gaps}")


def ensemble_config(frames: int, seed: int) -> Firefly2DConfig:
    """Algorithm 1's settings for this task: DDPG from a uniform random warm-up (the firefly's
    pursuit controller knows the firefly only), evaluated on 16 θ of the prior."""
    return Firefly2DConfig(
        seed=seed,
        ddpg=DDPGConfig(
            warmup_policy="random",
            n_envs=32,
            total_frames=frames,
            anneal_frames=frames,
            warmup_frames=2048,
            buffer_size=100_000,
            batch_size=256,
        ),
        evaluation=EvaluationConfig(n_theta=16, trials_per_theta=8, every=250),
    )


def compare_with_controller(
    model: ReachModel, actor: TensorDictSequential, seed: int
) -> dict[str, object]:
    """The learned policy against the controller on 16 θ of the prior (16 trials each, the same
    targets and noise for both): each θ's cost ratio, and how much each policy's control turns
    on each parameter of θ (what Algorithm 2 can read from it)."""
    thetas = theta_grid(model.theta_space, 16, seed)
    clip = TensorDictModule(partial(torch.clamp, min=-1.0, max=1.0), ["action"], ["action"])
    controller = TensorDictSequential(controller_policy(model), clip)
    scores = {
        name: evaluate_policy(model, policy, thetas, 16, seed)
        for name, policy in (("ensemble", actor), ("controller", controller))
    }
    ratio = torch.tensor(scores["ensemble"]["per_theta_return"]) / torch.tensor(
        scores["controller"]["per_theta_return"]
    )
    return {
        "cost_ratio": ratio.tolist(),
        "mean_cost": {name: -score["mean_return"] for name, score in scores.items()},
        "theta_sensitivity": {
            "ensemble": theta_sensitivity(model, actor, thetas, 16, seed),
            "controller": theta_sensitivity(model, controller, thetas, 16, seed),
        },
    }


def learn_and_fit(
    model: ReachModel, frames: int, n_trials: int, seed: int, out: Path
) -> dict[str, object]:
    """Algorithm 1 on this task, then Algorithm 2 with its policy: train the ensemble, compare
    it with the controller, reload it from its checkpoint, and fit agents that act by it."""
    start = time.perf_counter()
    trained = train_ensemble(
        ensemble_config(frames, seed), out=out / "ensemble", progress=False, model=model
    )
    seconds = time.perf_counter() - start
    comparison = compare_with_controller(model, trained.actor, seed)
    ratio = torch.tensor(comparison["cost_ratio"])
    print(
        f"ensemble ({frames} frames, {seconds:.0f} s): cost {ratio.mean():.2f}× the "
        f"controller's over 16 θ (from {ratio.min():.2f}× to {ratio.max():.2f}×)"
    )
    for name, turns in comparison["theta_sensitivity"]["ensemble"].items():
        own = comparison["theta_sensitivity"]["controller"][name]
        print(f"  control turns on {name:<12} {turns[0]:.3f} (the controller's {own[0]:.3f})")
    actor, model, _ = load_ensemble_policy(out / "ensemble" / "checkpoint.pt", model=model)
    fits = fit_learned(model, actor, n_trials, seed)
    return {"train_seconds": seconds, "best": trained.best, **comparison, **fits}


def fit_learned(
    model: ReachModel, actor: TensorDictSequential, n_trials: int, seed: int
) -> dict[str, dict]:
    """Agents with :data:`TRUE_THETA` acting by the learned ``actor``, fitted with it."""
    theta, trials = simulate(model, actor, n_trials, seed)
    held = trials.select("state", "action", "target", "mask", "task_theta")
    fits = fit_both(model, partial(censored_action_model, actor, model), theta, held, seed)
    report(model, [model.theta_space.to_dict(row) for row in theta], fits)
    return fits


def main() -> None:
    """Check the controller, simulate, fit by both estimators (and with ``--train-frames``,
    learn the policy and fit with it), write ``results.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/own_task", help="output folder")
    parser.add_argument("--trials", type=int, default=20, help="trials per agent")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--train-frames",
        type=int,
        default=0,
        help="learn the policy by Algorithm 1 over this many frames (200000: about 75 s) and "
        "fit agents acting by it too (0: the controller alone)",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    start = time.perf_counter()
    model = ReachModel()
    returns = belief_returns(model, 64, args.seed)
    for name, values in returns.items():
        print(
            f"{name:>10}: expected return {values['return']:.3f}, final distance to the "
            f"target {values['final_distance']:.3f}"
        )
    theta, trials = simulate(model, controller_policy(model), args.trials, args.seed)
    held = trials.select("state", "action", "target", "mask", "task_theta")  # what is recorded
    truths = [model.theta_space.to_dict(row) for row in theta]
    fits = fit_both(model, partial(controller_action_model, model), theta, held, args.seed)
    report(model, truths, fits)
    results = {"theta_true": truths, "returns": returns, **fits}
    if args.train_frames:
        out = Path(args.out)
        results["ensemble"] = learn_and_fit(model, args.train_frames, args.trials, args.seed, out)
    results["seconds"] = time.perf_counter() - start
    path = write_json(Path(args.out) / "results.json", results)
    print(f"wrote {path} ({results['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
