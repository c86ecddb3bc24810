"""Algorithm 1 for discrete actions: one factorised Q over the whole θ prior.

Rounds of TorchRL rollouts (θ drawn from the prior every trial, random actions first, then
ε-greedy on the current Q) feed least-squares fitted Q-iteration on the paper's factorised
basis. The targets use the agent's expected reward under its belief (``BeliefReward``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import EGreedyModule, QValueModule

from irc_torchrl.algorithms.runtime import float32_default
from irc_torchrl.checks import check_fields, positive, resolve_device
from irc_torchrl.envs.belief import BeliefFeatures, BeliefReward, EKFBelief
from irc_torchrl.envs.model import TaskModel
from irc_torchrl.envs.task_env import TaskEnv
from irc_torchrl.modules.factorised_q import FactorisedQ, regressors

__all__ = ["QIterationConfig", "make_q_policy", "train_factorised_q", "FittedQIteration"]


@dataclass
class QIterationConfig:
    """Settings of :func:`train_factorised_q`."""

    #: parallel environments, each with its own θ drawn from the prior per trial
    n_envs: int = 512
    #: rounds of collection, each followed by a fit on all the data so far; the first round
    #: acts uniformly at random, the later ones ε-greedily on the last fit's Q
    rounds: int = 4
    #: batched env steps per round (trials end and restart within them)
    steps_per_round: int = 60
    #: Bellman backups per fit, each a least-squares regression from Q = 0
    sweeps: int = 40
    #: discount of the backups (1: undiscounted, as the task's trials end)
    gamma: float = 1.0
    #: ridge penalty per sample of each action's regression (keeps a design of few samples
    #: invertible)
    ridge: float = 1e-4
    #: probability of a random action in the rounds after the first
    epsilon: float = 0.3
    #: sizes of the random bases over the belief features (φ) and over normalised θ (ψ),
    #: each with its constant; Q has ``n_actions × n_belief_basis × n_theta_basis`` weights
    n_belief_basis: int = 64
    n_theta_basis: int = 16
    #: spread of the bases' random input weights (larger: finer detail, less smoothing)
    belief_scale: float = 3.0
    theta_scale: float = 1.5

    def validate(self) -> QIterationConfig:
        """Return ``self`` if every field is usable, else raise a one-line error naming it."""
        check_fields(self, "q_iteration.")
        sizes = ("n_envs", "rounds", "steps_per_round", "sweeps", "n_belief_basis")
        # without a ridge a design of few samples is singular
        scales = ("n_theta_basis", "belief_scale", "theta_scale", "ridge")
        positive(**{f"q_iteration.{name}": getattr(self, name) for name in sizes + scales})
        if not 0 < self.gamma <= 1:
            raise ValueError(f"config: q_iteration.gamma must lie in (0, 1], got {self.gamma}")
        if not 0 <= self.epsilon <= 1:
            raise ValueError(f"config: q_iteration.epsilon must lie in [0, 1], got {self.epsilon}")
        return self


def make_q_policy(model: TaskModel, q: FactorisedQ, epsilon: float = 0.0) -> TensorDictSequential:
    """A TorchRL policy acting greedily (or ε-greedily) on ``q`` from the belief."""
    modules = [
        BeliefFeatures(model),
        TensorDictModule(q, in_keys=["features"], out_keys=["action_value"]),
        QValueModule(spec=model.action_spec, action_space="categorical"),
    ]
    if epsilon > 0:
        modules.append(EGreedyModule(model.action_spec, eps_init=epsilon, eps_end=epsilon))
    return TensorDictSequential(*modules)


class FittedQIteration:
    """Least-squares Q-iteration for a :class:`FactorisedQ`, with data added in rounds.

    ``Q`` is linear in ``φ(b) ⊗ ψ(θ)`` for each action, so each action's ridge-regularised Gram
    matrix is accumulated as data arrive and inverted once per fit; a sweep (one Bellman
    backup) is then a few matrix products.
    """

    def __init__(self, q: FactorisedQ, gamma: float, ridge: float) -> None:
        self.q, self.gamma, self.ridge = q, gamma, ridge
        size = q.weight.shape[1] * q.weight.shape[2]
        self.device = q.weight.device
        self.gram = torch.zeros(q.n_actions, size, size, dtype=torch.float64, device=self.device)
        self.data: TensorDict | None = None

    def _bases(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            phi = self.q.phi(features[..., : self.q.belief_dim])
            return phi.double(), self.q.psi(features[..., self.q.belief_dim :]).double()

    def add(self, batch: TensorDict) -> None:
        """Add transitions: features, action, reward, next_features and terminated."""
        phi, psi = self._bases(batch["features"])
        next_phi, next_psi = self._bases(batch["next_features"])
        for a in range(self.q.n_actions):
            for chunk in torch.split((batch["action"] == a).nonzero().squeeze(-1), 4096):
                x = regressors(phi[chunk], psi[chunk])
                self.gram[a] += x.T @ x
        new = TensorDict(
            action=batch["action"],
            reward=batch["reward"].reshape(-1).double(),
            alive=(~batch["terminated"].reshape(-1)).double(),
            phi=phi,
            psi=psi,
            next_phi=next_phi,
            next_psi=next_psi,
            batch_size=batch.batch_size,
        )
        self.data = new if self.data is None else torch.cat([self.data, new])

    def fit(self, sweeps: int) -> None:
        """Run ``sweeps`` Bellman backups from ``Q = 0`` and write the weights into ``q``."""
        d, (n_actions, k, m) = self.data, self.q.weight.shape
        eye = torch.eye(k * m, dtype=torch.float64, device=self.device)
        per_action = []
        for a in range(n_actions):
            rows = (d["action"] == a).nonzero().squeeze(-1)
            gram = self.gram[a] + self.ridge * max(len(rows), 1) * eye
            inverse = torch.cholesky_inverse(torch.linalg.cholesky(gram))
            per_action.append((rows, d["phi"][rows], d["psi"][rows], inverse))
        weight = torch.zeros(n_actions, k, m, dtype=torch.float64, device=self.device)
        for _ in range(sweeps):
            next_q = ((d["next_phi"] @ weight) * d["next_psi"]).sum(-1)
            target = d["reward"] + self.gamma * d["alive"] * next_q.max(0).values
            for a, (rows, phi, psi, inverse) in enumerate(per_action):
                rhs = (phi * target[rows].unsqueeze(-1)).T @ psi
                weight[a] = (inverse @ rhs.reshape(-1)).reshape(k, m)
        self.q.weight.data.copy_(weight)


def train_factorised_q(
    model: TaskModel,
    config: QIterationConfig | None = None,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
    device: torch.device | str = "cpu",
) -> FactorisedQ:
    """Learn ``Q(b, a, θ)`` over the θ prior (the paper's Algorithm 1 with a factorised basis)
    on ``device``, where the returned Q lives.

    ``config``: the settings (``None``: :class:`QIterationConfig`'s defaults); ``seed`` fixes
    the bases, the environments and the exploration, so the same seed gives the same Q;
    ``progress(done, total)`` is called after each round.
    """
    config = (config if config is not None else QIterationConfig()).validate()
    device = resolve_device(str(device))
    # ε-greedy draws from the global generator, in the default dtype
    with float32_default(), torch.random.fork_rng():
        torch.manual_seed(seed)
        env = TransformedEnv(
            TaskEnv(model, batch_size=(config.n_envs,), device=device, seed=seed),
            Compose(EKFBelief(model), BeliefReward(model)),
        )
        q = FactorisedQ(
            model.belief_feature_dim,
            model.theta_space.dim,
            int(model.action_spec.n),
            config.n_belief_basis,
            config.n_theta_basis,
            config.belief_scale,
            config.theta_scale,
            seed=seed,
        ).to(device)
        features = BeliefFeatures(model)
        solver = FittedQIteration(q, config.gamma, config.ridge)
        for round_ in range(config.rounds):
            with torch.device(device):  # TorchRL's modules are built on the default device
                policy = None if round_ == 0 else make_q_policy(model, q, config.epsilon)
            with torch.no_grad():
                rollout = env.rollout(
                    config.steps_per_round, policy, break_when_any_done=False
                ).reshape(-1)
            solver.add(
                TensorDict(
                    features=features(rollout.clone())["features"],
                    action=rollout["action"],
                    reward=rollout["next", "reward"],
                    next_features=features(rollout["next"].clone())["features"],
                    terminated=rollout["next", "terminated"],
                    batch_size=rollout.batch_size,
                )
            )
            solver.fit(config.sweeps)
            if progress is not None:
                progress(round_ + 1, config.rounds)
    return q
