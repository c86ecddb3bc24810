"""One probe of a task's methods before anything runs them.

A :class:`~irc_torchrl.envs.model.TaskModel` of the user's own is called by the env, the belief
filter and the inverse deep inside their loops, where a wrong shape fails as torch's error (or,
broadcast, not at all) and a θ dropped from autograd fits "not identified" without a word.
:func:`check_model` calls each method once on a batch of two, and refuses what it returns in
one line naming the method and the expected form.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torchrl.data import Categorical

from irc_torchrl.checks import first_line
from irc_torchrl.envs.model import TaskModel, check_action_spec

__all__ = ["check_model"]

#: the probe's batch: two elements, so that a method mixing them up shows
_BATCH = 2
#: finite-difference steps, as fractions of a parameter's range: an output that moves ten times
#: as far for the larger one depends on the parameter to first order
_STEPS = (1e-1, 1e-2)
#: where in each parameter's range θ's gradients are checked: inside it, off the default (a
#: bound, often, where a σ² or a clamp has no slope)
_INSIDE = 0.37
#: an output moves where its change exceeds this many of its dtype's round-off of its size
_ROUND_OFF = 1e2

Method = Callable[[torch.Tensor], torch.Tensor]


def check_model(model: TaskModel) -> None:
    """Refuse a task whose methods return the wrong shape, dtype or values at the default θ,
    or whose outputs move with a θ parameter autograd cannot see (every method must be
    differentiable in θ: the inverse backpropagates through them)."""
    if not isinstance(model, TaskModel):
        raise TypeError(f"model: expected a TaskModel, got {type(model).__name__}")
    check_action_spec(model)
    names = model.theta_space.names
    sensory = model.sensory_names
    if not isinstance(sensory, tuple) or not all(name in names for name in sensory):
        raise ValueError(
            f"model.sensory_names: expected a tuple of θ parameter names from {names}, "
            f"got {sensory!r}"
        )
    # on the CPU, where θ's default lives, and with gradients even where the caller has none
    with torch.device("cpu"), torch.inference_mode(False), torch.enable_grad():
        probe = _Probe(model)
        probe.returns()
        probe.differentiable()


class _Probe:
    """The probe's inputs: a first step taken from the initial state, so that velocities and
    beliefs are not all zero; one element stopping, one not."""

    def __init__(self, model: TaskModel) -> None:
        self.model = model
        theta = model.theta_space.default().expand(_BATCH, -1)
        generator = torch.Generator().manual_seed(0)
        start = self.call("initial_state", theta, generator)
        self.paired("initial_state", start, (model.state_dim,), (model.target_dim,))
        self.dtype = start[0].dtype
        if not self.dtype.is_floating_point:
            raise ValueError(
                f"model.initial_state: expected a floating-point state, got {self.dtype}"
            )
        state, self.target = self.pair(
            "initial_state", start, (model.state_dim,), (model.target_dim,)
        )
        self.theta = theta.to(self.dtype)
        self.action = _probe_action(model, self.dtype)
        self.step = torch.ones(_BATCH, 1, dtype=torch.int64)
        self.stop = torch.tensor([[False], [True]])
        self.state = self.tensor("transition", (model.state_dim,), state, self.action, self.theta)

    # --- what each method returns ------------------------------------------------------------
    def returns(self) -> None:
        """Check every method's shape, dtype and values at the default θ."""
        m, ds, do = self.model, self.model.state_dim, self.model.observation_dim
        state, action, theta, target = self.state, self.action, self.theta, self.target
        self.tensor("stops", (1,), action, self.step, dtype=torch.bool)
        self.tensor("transition", (ds,), state, action, theta)
        self.covariance("process_cov", ds, state, action, theta)
        self.tensor("observe", (do,), state, theta, hint=_OBSERVE if do else "")
        self.covariance("observation_cov", do, state, theta)
        self.reward("reward", state, target, action, self.stop, theta)
        belief = self.call("initial_belief", state, target, theta)
        mean, cov = self.pair("initial_belief", belief, (ds,), (ds, ds))
        self.symmetric("initial_belief", cov)
        # the first belief moved and a little less certain; the second, stopping, so uncertain
        # (a std of about the target's distance) that what a stop is paid for moves with θ
        spread = torch.tensor([[0.01], [1.0 + float(target.abs().max()) ** 2]], dtype=self.dtype)
        self.mean = mean + torch.tensor([[0.1], [0.0]], dtype=self.dtype)
        self.cov = cov + spread[..., None] * torch.eye(ds, dtype=self.dtype)
        self.reward("belief_reward", self.mean, self.cov, target, action, self.stop, theta)
        features = (m.belief_feature_dim + m.theta_space.dim,)
        self.tensor("belief_features", features, self.mean, self.cov, target, self.step, theta)
        self.broadcast_features()
        self.tensor("transition_jacobian", (ds, ds), state, action, theta, hint=_JACOBIAN)
        if do:
            self.tensor("observation_jacobian", (do, ds), state, theta, hint=_JACOBIAN)

    def call(self, name: str, *args: object, hint: str = "") -> object:
        """``model.name(*args)``, its failure refused in one line naming it."""
        try:
            return getattr(self.model, name)(*args)
        except (RuntimeError, TypeError, ValueError, IndexError) as error:
            shapes = ", ".join(str(list(a.shape)) for a in args if isinstance(a, torch.Tensor))
            raise ValueError(
                f"model.{name}: failed on CPU inputs {shapes} ({first_line(error)}){hint}"
            ) from error

    def tensor(
        self,
        name: str,
        shape: tuple[int, ...],
        *args: object,
        dtype: torch.dtype | None = None,
        hint: str = "",
    ) -> torch.Tensor:
        """``model.name(*args)``, refused unless a finite ``[*B, *shape]`` tensor of ``dtype``
        (the state's by default)."""
        out = self.call(name, *args, hint=hint)
        self.shaped(name, out, shape, hint)
        self.values(name, out, dtype or self.dtype)
        return out

    def shaped(self, name: str, out: object, shape: tuple[int, ...], hint: str = "") -> None:
        """Refuse ``out`` unless a tensor ``[*B, *shape]``."""
        expected = [_BATCH, *shape]
        if not isinstance(out, torch.Tensor) or list(out.shape) != expected:
            raise ValueError(
                f"model.{name}: expected [*B, {', '.join(map(str, shape))}] ({expected} for "
                f"inputs of batch [{_BATCH}]), got {_shape_of(out)}{hint}"
            )

    def values(self, name: str, out: torch.Tensor, dtype: torch.dtype) -> None:
        """Refuse ``out`` of another dtype than ``dtype``, or NaN or inf in it."""
        if out.dtype != dtype:
            raise ValueError(
                f"model.{name}: expected {dtype} (the dtype of initial_state's state), got "
                f"{out.dtype}"
            )
        if out.is_floating_point() and not torch.isfinite(out).all():
            raise ValueError(
                f"model.{name}: NaN or inf at the default θ "
                f"({self.model.theta_space.format(self.theta[0])}); expected finite values "
                "for every θ in its space"
            )

    def pair(
        self, name: str, out: object, first: tuple[int, ...], second: tuple[int, ...]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``out``, refused unless two finite tensors ``[*B, *first]``, ``[*B, *second]`` of
        the state's dtype."""
        self.paired(name, out, first, second)
        for part in out:
            self.values(name, part, self.dtype)
        return out[0], out[1]

    def paired(
        self, name: str, out: object, first: tuple[int, ...], second: tuple[int, ...]
    ) -> None:
        """Refuse ``out`` unless two tensors ``[*B, *first]``, ``[*B, *second]``."""
        expected = [[_BATCH, *first], [_BATCH, *second]]
        if not isinstance(out, tuple | list) or len(out) != 2:
            raise ValueError(
                f"model.{name}: expected a pair of tensors {expected} for inputs of batch "
                f"[{_BATCH}], got {_shape_of(out)}"
            )
        for part, shape in zip(out, (first, second), strict=True):
            self.shaped(name, part, shape)

    def covariance(self, name: str, dim: int, *args: object) -> None:
        """``model.name(*args)``, refused unless a symmetric PSD ``[*B, dim, dim]``."""
        self.symmetric(name, self.tensor(name, (dim, dim), *args))

    def symmetric(self, name: str, cov: torch.Tensor) -> None:
        """Refuse a covariance that is not symmetric positive semi-definite."""
        if not cov.numel():
            return
        scale = max(float(cov.abs().max()), 1.0)
        cov = cov.double()
        if not torch.allclose(cov, cov.mT, atol=1e-6 * scale, rtol=0):
            raise ValueError(f"model.{name}: expected a symmetric covariance, got {cov[0]}")
        eigenvalues = torch.linalg.eigvalsh(cov)
        if float(eigenvalues.min()) < -1e-6 * scale:
            raise ValueError(
                f"model.{name}: expected a positive semi-definite covariance, got eigenvalues "
                f"{eigenvalues[0].tolist()}"
            )

    def reward(self, name: str, *args: object) -> None:
        """A finite reward ``[*B, 1]`` (or ``[*B]``, which TorchRL reshapes)."""
        out = self.call(name, *args)
        if not isinstance(out, torch.Tensor) or list(out.shape) not in ([_BATCH, 1], [_BATCH]):
            raise ValueError(
                f"model.{name}: expected a reward [*B, 1] ([{_BATCH}, 1] for inputs of batch "
                f"[{_BATCH}]), got {_shape_of(out)}"
            )
        self.values(name, out, self.dtype)

    def broadcast_features(self) -> None:
        """Refuse ``belief_features`` that need their arguments' batch shapes to match: the hard
        E-step passes beliefs per step beside each trial's target and θ."""
        m, steps = self.model, 2
        ds, dim = m.state_dim, m.theta_space.dim
        mean = self.mean[:1].expand(steps, ds).reshape(1, 1, steps, ds)
        cov = self.cov[:1].expand(steps, ds, ds).reshape(1, 1, steps, ds, ds)
        target = self.target[:1].view(1, 1, 1, -1)
        step = torch.arange(steps).view(1, 1, steps, 1)
        theta = self.theta[:1].view(1, 1, 1, -1)
        expected = [1, 1, steps, m.belief_feature_dim + dim]
        try:
            shape = list(m.belief_features(mean, cov, target, step, theta).shape)
        except RuntimeError as error:
            shape = f"an error ({first_line(error)})"
        if shape != expected:
            raise ValueError(
                f"model.belief_features: expected features {expected} from beliefs "
                f"[1, 1, {steps}, {ds}] beside a target and θ [1, 1, 1, ·] and steps "
                f"[1, 1, {steps}, 1] (batch dimensions that broadcast), got {shape}"
            )

    # --- differentiable in θ -----------------------------------------------------------------
    def differentiable(self) -> None:
        """Refuse a method whose output moves with a θ parameter to first order (a finite
        difference) while autograd finds no gradient to it (a ``.detach()``, ``.item()``,
        ``float()``): the inverse would call that parameter "not identified". Checked at a
        θ inside the range (:data:`_INSIDE`), where neither a bound nor a kink hides a slope."""
        space = self.model.theta_space
        low, high = space.low(self.dtype), space.high(self.dtype)
        inside = (low + _INSIDE * (high - low)).expand(_BATCH, -1)
        for name, method in self.methods().items():
            for i in _unseen(method, inside, high - low):
                raise ValueError(
                    f"model.{name}: its output moves with θ parameter {space.names[i]!r} (a "
                    "finite difference) but carries no gradient to it (autograd); expected "
                    "every method differentiable in θ (no .detach(), .item() or float() of θ)"
                )

    def methods(self) -> dict[str, Method]:
        """Each method that reads θ as a function of θ rows ``[*n, B, d]`` alone (the other
        inputs expanded beside them), its failures named."""
        m, s, a, t = self.model, self.state, self.action, self.target
        b = (self.mean, self.cov, t)
        methods = {
            "transition": lambda th: m.transition(*_lift(th, s, a), th),
            "process_cov": lambda th: m.process_cov(*_lift(th, s, a), th),
            "observe": lambda th: m.observe(*_lift(th, s), th),
            "observation_cov": lambda th: m.observation_cov(*_lift(th, s), th),
            "initial_belief": lambda th: m.initial_belief(*_lift(th, s, t), th)[1],
            "belief_reward": lambda th: m.belief_reward(*_lift(th, *b, a, self.stop), th),
            "belief_features": lambda th: m.belief_features(*_lift(th, *b, self.step), th)[
                ..., : m.belief_feature_dim
            ],
        }
        return {name: self.named(name, method) for name, method in methods.items()}

    def named(self, name: str, method: Method) -> Method:
        """``method`` with its failure refused in one line naming ``model.name``."""

        def called(theta: torch.Tensor) -> torch.Tensor:
            try:
                return method(theta)
            except (RuntimeError, TypeError, ValueError, IndexError) as error:
                raise ValueError(
                    f"model.{name}: failed on θ rows {list(theta.shape)} beside its other "
                    f"inputs, expanded to them ({first_line(error)}); expected batched torch "
                    "ops over any leading dimensions"
                ) from error

        return called


def _lift(theta: torch.Tensor, *inputs: torch.Tensor) -> list[torch.Tensor]:
    """``inputs`` ``[B, ·]`` expanded beside θ rows ``[*n, B, d]``."""
    return [x.expand(*theta.shape[:-2], *x.shape) for x in inputs]


def _unseen(method: Method, theta: torch.Tensor, width: torch.Tensor) -> list[int]:
    """The parameters ``method``'s output moves with to first order at ``theta`` while autograd
    gives it no gradient to them."""
    theta = theta.clone().requires_grad_(True)
    out = method(theta)
    if not out.numel():
        return []
    weight = torch.linspace(0.5, 1.5, out.numel(), dtype=out.dtype).view_as(out)
    value = (weight * out).sum()
    unseen = torch.ones(theta.shape[-1], dtype=torch.bool)
    if value.requires_grad:  # an output without a graph (θ unused, or detached) has none
        (grad,) = torch.autograd.grad(value, theta, allow_unused=True)
        unseen = (grad == 0).all(0) if grad is not None else unseen
    with torch.no_grad():
        rows = _shifted(theta.detach(), width)
        moved = (weight * method(rows)).flatten(1).sum(1)
        floor = _ROUND_OFF * torch.finfo(out.dtype).eps * float((weight * out).abs().sum())
    moved = (moved[1:] - moved[0]).view(len(_STEPS), -1)  # [step, parameter]
    first_order = (moved[1].abs() > floor) & (moved[0].abs() < 30 * moved[1].abs())
    return (unseen & first_order).nonzero().flatten().tolist()


def _shifted(theta: torch.Tensor, width: torch.Tensor) -> torch.Tensor:
    """θ rows ``[1 + len(_STEPS) · d, B, d]``: ``theta``, then each parameter moved up by each
    of :data:`_STEPS` of its range ``width``."""
    eye = torch.eye(theta.shape[-1], dtype=theta.dtype)
    moved = [theta + fraction * width[i] * eye[i] for fraction in _STEPS for i in range(len(eye))]
    return torch.stack([theta, *moved])


def _probe_action(model: TaskModel, dtype: torch.dtype) -> torch.Tensor:
    """Two actions, one per batch element, inside the spec and off its centre (a gain times a
    zero action would hide the gain): indices 1 and the last of a discrete action; three
    quarters and a quarter of the way up a bounded box; 0.5 and -0.5 where unbounded."""
    spec = model.action_spec
    if isinstance(spec, Categorical):
        return torch.tensor([min(1, spec.n - 1), spec.n - 1], dtype=spec.dtype)
    # on the CPU, where the probe runs: a model built on a GPU (load_ensemble_policy, irc train
    # --device) has its spec there
    low, high = (x.to("cpu", dtype) for x in (spec.space.low, spec.space.high))
    bounded = torch.isfinite(high - low) & (high - low < torch.finfo(torch.float32).max)
    up = torch.tensor([[0.75], [0.25]], dtype=dtype)
    action = torch.where(bounded, low + up * (high - low), 2 * up - 1)
    return action.to(spec.dtype)


def _shape_of(out: object) -> str:
    """What a method returned, for a message: a tensor's shape, a pair's shapes, or its type."""
    if isinstance(out, torch.Tensor):
        return str(list(out.shape))
    if isinstance(out, tuple | list):
        return "(" + ", ".join(_shape_of(part) for part in out) + ")"
    return type(out).__name__


_OBSERVE = " (a task with observations, observation_dim > 0, overrides observe and observation_cov)"
_JACOBIAN = (
    "; write the method in batched torch ops, without a Python branch on a tensor's value, or "
    "override it with an analytic Jacobian"
)
