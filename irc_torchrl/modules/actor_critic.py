"""The θ-conditioned actor and critic of Algorithm 1 on continuous-action tasks.

Both start with :class:`~irc_torchrl.envs.belief.BeliefFeatures`, so they read the belief, the
target, the step and θ straight from the environment's TensorDict; TorchRL's ``DDPGLoss`` can
then recompute features on next states without any extra plumbing. The paper's shape is three
hidden layers of 64 units with softplus activations.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.modules import MLP, Actor, TanhModule, ValueOperator

from irc_torchrl.envs.belief import BeliefFeatures
from irc_torchrl.envs.model import TaskModel

__all__ = ["ACTIVATIONS", "FeaturePolicy", "make_actor", "make_critic"]

#: activations a config may name
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "softplus": nn.Softplus,
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "elu": nn.ELU,
}


def _activation(name: str) -> type[nn.Module]:
    if name not in ACTIVATIONS:
        raise ValueError(f"activation: expected one of {sorted(ACTIVATIONS)}, got {name!r}")
    return ACTIVATIONS[name]


def _feature_dim(model: TaskModel) -> int:
    return model.belief_feature_dim + model.theta_space.dim


def make_actor(
    model: TaskModel, hidden: Sequence[int] = (64, 64, 64), activation: str = "softplus"
) -> TensorDictSequential:
    """``π(b, θ)``: belief features → MLP → tanh squashed into the action bounds → ``action``."""
    spec = model.action_spec  # one environment's spec: the bounds without batch dimensions
    mlp = MLP(
        in_features=_feature_dim(model),
        out_features=spec.shape[-1],
        num_cells=list(hidden),
        activation_class=_activation(activation),
    )
    return TensorDictSequential(
        BeliefFeatures(model),
        Actor(mlp, in_keys=["features"], out_keys=["param"]),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
    )


def make_critic(
    model: TaskModel, hidden: Sequence[int] = (64, 64, 64), activation: str = "softplus"
) -> TensorDictSequential:
    """``Q(b, a, θ)``: belief features and action → MLP → ``state_action_value``."""
    mlp = MLP(
        in_features=_feature_dim(model) + model.action_spec.shape[-1],
        out_features=1,
        num_cells=list(hidden),
        activation_class=_activation(activation),
    )
    return TensorDictSequential(
        BeliefFeatures(model),
        ValueOperator(mlp, in_keys=["features", "action"]),
    )


class FeaturePolicy(nn.Module):
    """The tensor path of a :func:`make_actor` actor: features ``[*B, df]`` → action ``[*B, da]``.

    The inverse objective differentiates the policy in its input (the belief), so it needs the
    network without the TensorDict plumbing; the weights are the actor's own (shared), cast to
    the input's dtype on the fly.
    """

    def __init__(self, actor: TensorDictSequential) -> None:
        super().__init__()
        _, net, squash = actor.module
        self.mlp = net.module
        bounds = squash.spec[squash.out_keys[0]].space
        self.register_buffer("low", torch.as_tensor(bounds.low, dtype=torch.float32))
        self.register_buffer("high", torch.as_tensor(bounds.high, dtype=torch.float32))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        dtype = features.dtype  # the inverse runs in float64; the actor's weights stay as they are
        weights = {k: v.to(dtype) for k, v in self.mlp.named_parameters()}
        half = (self.high - self.low).to(dtype) / 2
        squashed = torch.tanh(torch.func.functional_call(self.mlp, weights, (features,)))
        return self.low.to(dtype) + half + half * squashed
