"""Tutorial: assemble an IRC experiment from its parts in a plain TorchRL loop (2D firefly task).

Algorithm 1 (learn one policy over the θ prior) is ordinary TorchRL: a batched
``Firefly2DEnv`` whose every element draws its own θ, the agent's belief kept by the
``EKFBelief`` transform, the reward it expects under that belief (``BeliefReward``), a
``Collector``, a replay buffer, ``DDPGLoss`` and ``SoftUpdate``. Algorithm 2 (infer an agent's θ)
is a TorchRL ``LossModule`` too: ``InverseRationalLoss`` holds θ as parameters, and any torch
optimiser can step it. Both run at toy sizes here (seconds); ``irc train`` and ``irc fit`` are
the full versions (irc_torchrl/algorithms/ensemble.py and recordings.py).

    python examples/assemble_in_torchrl.py --out runs/assemble
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import AdditiveGaussianModule
from torchrl.objectives import DDPGLoss, SoftUpdate, ValueEstimators

from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.simulate import motor_noise_policy, simulate_agents
from irc_torchrl.envs import BeliefReward, EKFBelief, Firefly2DEnv, Firefly2DModel
from irc_torchrl.envs.model import sensed_world
from irc_torchrl.modules.actor_critic import FeaturePolicy, make_actor, make_critic
from irc_torchrl.modules.likelihood import CensoredGaussianActionModel
from irc_torchrl.objectives.inverse import InverseRationalLoss


def train_ddpg(n_envs: int, batches: int, updates_per_batch: int, seed: int) -> dict:
    """A few DDPG updates over the θ prior; the losses and how far the target networks moved."""
    torch.manual_seed(seed)
    model = Firefly2DModel()
    # every environment draws its own θ (agent = world here) at each trial; the agent's belief
    # under that θ is ("belief", "mean"/"cov"), and the reward is the one it expects
    env = TransformedEnv(
        Firefly2DEnv(model=model, batch_size=(n_envs,), seed=seed),
        Compose(EKFBelief(model), BeliefReward(model)),
    )
    actor = make_actor(model, hidden=(32, 32))  # belief features and θ -> action in [-1, 1]²
    critic = make_critic(model, hidden=(32, 32))
    explore = TensorDictSequential(
        actor, AdditiveGaussianModule(model.action_spec, sigma_init=0.3, sigma_end=0.3)
    )
    frames_per_batch = n_envs * 8
    collector = Collector(
        env,
        explore,
        frames_per_batch=frames_per_batch,
        total_frames=frames_per_batch * batches,
        # the policy keeps no state between steps (the belief is the env's), so the collector
        # needs no InitTracker (TorchRL's check asks for one for this policy, and warns)
        auto_register_policy_transforms=False,
    )
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100_000), batch_size=128)
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.98)
    target_update = SoftUpdate(loss, tau=0.05)
    optimiser = torch.optim.Adam(loss.parameters(), lr=1e-3)
    before = [p.clone() for p in loss.target_value_network_params.values(True, True)]
    history = []
    for batch in collector:
        # the features are recomputed from the belief by the networks; keep the belief only
        buffer.extend(batch.exclude("features", ("next", "features")).reshape(-1))
        for _ in range(updates_per_batch):
            losses = loss(buffer.sample())
            (losses["loss_actor"] + losses["loss_value"]).backward()
            optimiser.step()
            optimiser.zero_grad()
            target_update.step()
            history.append({k: losses[k].item() for k in ("loss_actor", "loss_value")})
    collector.shutdown()
    after = loss.target_value_network_params.values(True, True)
    moved = sum((a - b).abs().sum().item() for a, b in zip(after, before, strict=True))
    return {"updates": len(history), "losses": history, "target_moved": moved}


def fit_with_adam(n_agents: int, n_trials: int, steps: int, seed: int) -> dict:
    """Simulate agents with the shipped policy, then step their θ with Adam on the IRC loss."""
    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    theta = space.sample((n_agents,), generator=torch.Generator().manual_seed(seed))
    policy = motor_noise_policy(actor, model.action_spec, motor_noise=0.1)
    world = sensed_world(model, space.default(), theta)  # each senses as its θ says
    trials = simulate_agents(model, policy, theta, n_trials, world, seed=seed)
    held = trials.select("state", "action", "target", "mask", "task_theta")  # what is recorded
    low, high = model.action_spec.space.low, model.action_spec.space.high
    action_model = CensoredGaussianActionModel(FeaturePolicy(actor), low, high)
    loss = InverseRationalLoss(model, action_model, n_agents=n_agents, method="map")
    # θ lives in unconstrained coordinates (loss.theta_free), the motor noise in loss.nuisance
    optimiser = torch.optim.Adam([loss.theta_free, loss.nuisance], lr=0.05)
    nll = []
    for _ in range(steps):
        out = loss(held)
        out["loss_nll"].backward()
        optimiser.step()
        optimiser.zero_grad()
        nll.append(out["loss_nll"].item())
    # fit_theta (Algorithm 2) does this properly: Newton steps, several starts, 95% intervals
    return {"nll": nll, "theta": space.to_dict(loss.theta().detach()[0].float())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/assemble", help="output folder")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)

    ddpg = train_ddpg(n_envs=16, batches=3, updates_per_batch=4, seed=args.seed)
    first, last = ddpg["losses"][0], ddpg["losses"][-1]
    print(
        f"DDPG: {ddpg['updates']} updates, loss_value {first['loss_value']:.4g} -> "
        f"{last['loss_value']:.4g}, loss_actor {first['loss_actor']:.4g} -> "
        f"{last['loss_actor']:.4g}, target networks moved by {ddpg['target_moved']:.4g}"
    )
    inverse = fit_with_adam(n_agents=2, n_trials=5, steps=10, seed=args.seed)
    print(f"IRC: negative log-likelihood {inverse['nll'][0]:.1f} -> {inverse['nll'][-1]:.1f}")
    finite = all(math.isfinite(v) for row in ddpg["losses"] for v in row.values())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(
        json.dumps({"ddpg": ddpg, "inverse": inverse, "finite": finite}, indent=2)
    )
    print(f"wrote {out / 'results.json'}")


if __name__ == "__main__":
    main()
