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

from irc_torchrl.checks import count
from irc_torchrl.envs.belief import BeliefFeatures
from irc_torchrl.envs.model import TaskModel, continuous_actions
from irc_torchrl.modules.likelihood import CensoredGaussianActionModel

__all__ = [
    "ACTIVATIONS",
    "ACTOR_DTYPES",
    "FeaturePolicy",
    "censored_action_model",
    "make_actor",
    "make_critic",
]

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


def _continuous_actions(model: TaskModel, maker: str) -> int:
    """The action dimension of a task with continuous actions ``[da]``, else a one-line error."""
    spec = model.action_spec
    if not continuous_actions(spec):
        raise TypeError(
            f"model: {maker} needs continuous actions [da], got {type(spec).__name__} actions of "
            f"shape {list(spec.shape)} (a discrete task learns a Q: train_factorised_q)"
        )
    return spec.shape[-1]


def _widths(hidden: Sequence[int]) -> list[int]:
    """The hidden layers' widths, each a positive integer (a width of 0 builds no layer)."""
    if isinstance(hidden, str) or not hasattr(hidden, "__iter__"):
        raise ValueError(f"hidden: expected a list of layer widths, got {hidden!r}")
    return [count("hidden", width) for width in hidden]


def _float32_network(mlp: MLP) -> MLP:
    """``mlp`` in float32, as the env's states are, whatever torch's default dtype; its inputs
    cast to its weights' dtype, so that a float64 action (TorchRL's exploration noise drawn in
    a float64 default) or a float64 env's belief reach it in what it computes in."""
    mlp = mlp.float()
    mlp.register_forward_pre_hook(_cast_to_weights)
    return mlp


def _cast_to_weights(module: nn.Module, inputs: tuple[torch.Tensor, ...]) -> tuple:
    """The inputs in the dtype of the weights the module runs with (float64 ones swapped in
    by :class:`FeaturePolicy`'s ``functional_call`` too; an MLP's first layer is linear)."""
    dtype = module[0].weight.dtype
    return tuple(x.to(dtype) for x in inputs)


def make_actor(
    model: TaskModel, hidden: Sequence[int] = (64, 64, 64), activation: str = "softplus"
) -> TensorDictSequential:
    """``π(b, θ)``: belief features → MLP → tanh squashed into the action bounds → ``action``."""
    spec = model.action_spec  # one environment's spec: the bounds without batch dimensions
    mlp = MLP(
        in_features=_feature_dim(model),
        out_features=_continuous_actions(model, "make_actor"),
        num_cells=_widths(hidden),
        activation_class=_activation(activation),
    )
    return TensorDictSequential(
        BeliefFeatures(model),
        Actor(_float32_network(mlp), in_keys=["features"], out_keys=["param"]),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
    )


def make_critic(
    model: TaskModel, hidden: Sequence[int] = (64, 64, 64), activation: str = "softplus"
) -> TensorDictSequential:
    """``Q(b, a, θ)``: belief features and action → MLP → ``state_action_value``."""
    mlp = MLP(
        in_features=_feature_dim(model) + _continuous_actions(model, "make_critic"),
        out_features=1,
        num_cells=_widths(hidden),
        activation_class=_activation(activation),
    )
    return TensorDictSequential(
        BeliefFeatures(model),
        ValueOperator(_float32_network(mlp), in_keys=["features", "action"]),
    )


#: the precisions :class:`FeaturePolicy` can run the network in, by their config names
ACTOR_DTYPES = {"float64": torch.float64, "float32": torch.float32}
#: a float32 network's backward clips the gradient reaching its output here: 3 layers of 64
#: units multiply it by far less than the 3e8 left to float32's largest value (3.4e38)
_FLOAT32_GRADIENT_LIMIT = 1e30


class FeaturePolicy(nn.Module):
    """The tensor path of a :func:`make_actor` actor: features ``[*B, df]`` → action ``[*B, da]``.

    The inverse objective differentiates the policy in its input (the belief), so it needs the
    network without the TensorDict plumbing; the weights are the actor's own (shared). The
    network runs in ``dtype`` (``None``: the input's, float64 in a fit). float32 takes a quarter
    to a third off a float64 fit, where the actor's matrix products are half of every pass, for an
    error of ~1e-4 nats in a 100-trial log-likelihood; the squashing to the action bounds runs
    in the input's dtype, which keeps a saturated action's distance to its bound exact. Its
    backward clips each gradient element reaching the float32 network at ±1e30, where float32
    would overflow to NaN (a nearly noise-free motor noise far from the actions: log L ≈ −1e10);
    every smaller gradient passes unchanged.
    """

    def __init__(self, actor: TensorDictSequential, dtype: torch.dtype | None = None) -> None:
        super().__init__()
        parts = list(getattr(actor, "module", ()))
        if len(parts) != 3 or not isinstance(parts[2], TanhModule):
            raise TypeError(
                "actor: expected make_actor's TensorDictSequential (features, MLP, TanhModule), "
                f"got {type(actor).__name__} of {len(parts)} module(s); pass the actor itself, "
                "not an exploration policy around it"
            )
        if dtype is not None and dtype not in ACTOR_DTYPES.values():
            raise ValueError(
                f"dtype: expected None or one of {list(ACTOR_DTYPES.values())}, got {dtype!r}"
            )
        _, net, squash = parts
        self.mlp = net.module
        self.dtype = dtype
        bounds = squash.spec[squash.out_keys[0]].space
        self.register_buffer("low", bounds.low.to(torch.float32))
        self.register_buffer("high", bounds.high.to(torch.float32))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """The actor's actions for ``features``, computed in this policy's dtype."""
        dtype, inner = features.dtype, self.dtype or features.dtype
        weights = {k: v.to(inner) for k, v in self.mlp.named_parameters()}
        pre = torch.func.functional_call(self.mlp, weights, (features.to(inner),)).to(dtype)
        if inner == torch.float32 and pre.requires_grad:
            pre.register_hook(
                lambda grad: grad.clamp(-_FLOAT32_GRADIENT_LIMIT, _FLOAT32_GRADIENT_LIMIT)
            )
        half = (self.high - self.low).to(dtype) / 2
        return self.low.to(dtype) + half + half * torch.tanh(pre)


def censored_action_model(
    actor: TensorDictSequential,
    model: TaskModel,
    actor_dtype: str = "float64",
    motor_noise: float = 0.1,
    lapse: float = 0.0,
    fit_lapse: bool = False,
) -> CensoredGaussianActionModel:
    """Algorithm 2's action model around a trained actor: its output plus censored Gaussian
    motor noise within the task's action bounds (and lapses at rate ``lapse``, or fitted from
    there with ``fit_lapse``), the network run in ``actor_dtype`` (a name of
    :data:`ACTOR_DTYPES`) inside the float64 likelihood."""
    if actor_dtype not in ACTOR_DTYPES:
        raise ValueError(f"actor_dtype: expected one of {list(ACTOR_DTYPES)}, got {actor_dtype!r}")
    bounds = model.action_spec.space
    policy = FeaturePolicy(actor, ACTOR_DTYPES[actor_dtype])
    return CensoredGaussianActionModel(
        policy, bounds.low, bounds.high, motor_noise, lapse=lapse, fit_lapse=fit_lapse
    )
