"""One probe of a task's methods before anything runs them.

A :class:`~irc_torchrl.envs.model.TaskModel` of the user's own is called by the env, the belief
filter and the inverse deep inside their loops, where a wrong shape fails as torch's error (or,
broadcast, not at all) and a θ dropped from autograd fits "not identified" without a word.
:func:`check_model` calls each method once at the θ space's default, on a batch of two, and
refuses what it returns in one line naming the method and the expected form.
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
_STEPS = (1e-2, 1e-3)


def check_model(model: TaskModel) -> None:
    """Refuse a task whose methods return the wrong shape, dtype or values at the default θ,
    or whose outputs move with a θ parameter autograd cannot see (every method must be
    differentiable in θ: the inverse backpropagates through them)."""
    check_action_spec(model)
    # on the CPU, where θ's default lives, and with gradients even where the caller has none
    with torch.device("cpu"), torch.inference_mode(False), torch.enable_grad():
        _Probe(model).run()


class _Probe:
    """The inputs of one probe (a first step taken from the initial state, so that velocities
    and beliefs are not all zero) and the checks of what each method returns."""

    def __init__(self, model: TaskModel) -> None:
        self.model = model
        space = model.theta_space
        theta = space.default().expand(_BATCH, -1)
        state, target = self.pair(
            "initial_state", (model.state_dim,), (model.target_dim,), theta,
            torch.Generator().manual_seed(0),
        )  # fmt: skip
        self.dtype = state.dtype
        if not self.dtype.is_floating_point:
            raise ValueError(
                f"model.initial_state: expected a floating-point state, got {self.dtype}"
            )
        self.theta = theta.to(self.dtype)
        self.target = target
        self.action = _probe_action(model, self.dtype)
        self.step = torch.ones(_BATCH, 1, dtype=torch.int64)
        self.state = self.tensor("transition", (model.state_dim,), state, self.action, self.theta)

    def run(self) -> None:
        m, ds, do = self.model, self.model.state_dim, self.model.observation_dim
        state, action, theta, target = self.state, self.action, self.theta, self.target
        self.stop = self.tensor("stops", (1,), action, self.step, dtype=torch.bool)
        self.tensor("transition", (ds,), state, action, theta)
        self.covariance("process_cov", ds, state, action, theta)
        self.tensor("observe", (do,), state, theta, hint=_OBSERVE if do else "")
        self.covariance("observation_cov", do, state, theta)
        self.reward("reward", state, target, action, self.stop, theta)
        mean, cov = self.pair("initial_belief", (ds,), (ds, ds), state, target, theta)
        self.symmetric("initial_belief", cov)
        self.mean, self.cov = mean + 0.1, cov  # off the target: features of a belief that moved
        self.reward("belief_reward", self.mean, cov, target, action, self.stop, theta)
        features = (m.belief_feature_dim + m.theta_space.dim,)
        self.tensor("belief_features", features, self.mean, cov, target, self.step, theta)
        self.broadcast_features()
        self.tensor("transition_jacobian", (ds, ds), state, action, theta, hint=_JACOBIAN)
        if do:
            self.tensor("observation_jacobian", (do, ds), state, theta, hint=_JACOBIAN)
        self.differentiable()

    # --- what a method returns -------------------------------------------------------------
    def call(self, name: str, *args: object, hint: str = "") -> object:
        try:
            return getattr(self.model, name)(*args)
        except (RuntimeError, TypeError, ValueError, IndexError) as error:
            shapes = ", ".join(str(list(a.shape)) for a in args if isinstance(a, torch.Tensor))
            raise ValueError(
                f"model.{name}: failed on inputs {shapes} at the default θ "
                f"({first_line(error)}){hint}"
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
        expected = [_BATCH, *shape]
        if not isinstance(out, torch.Tensor) or list(out.shape) != expected:
            got = list(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ValueError(
                f"model.{name}: expected [*B, {', '.join(map(str, shape))}] ({expected} for "
                f"inputs of batch [{_BATCH}]), got {got}{hint}"
            )
        self.check_values(name, out, dtype or self.dtype)
        return out

    def check_values(self, name: str, out: torch.Tensor, dtype: torch.dtype) -> None:
        if out.dtype != dtype:
            raise ValueError(
                f"model.{name}: expected {dtype} (the dtype of initial_state's state), got "
                f"{out.dtype}"
            )
        if out.is_floating_point() and not torch.isfinite(out).all():
            raise ValueError(
                f"model.{name}: NaN or inf at the default θ "
                f"({_shown(self.model, self.theta[0])}); expected finite values "
                "for every θ in its space"
            )

    def pair(
        self, name: str, first: tuple[int, ...], second: tuple[int, ...], *args: object
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``model.name(*args)``, refused unless two tensors ``[*B, *first]``, ``[*B, *second]``."""
        out = self.call(name, *args)
        shapes = [list(o.shape) for o in out] if isinstance(out, tuple | list) else None
        expected = [[_BATCH, *first], [_BATCH, *second]]
        if shapes != expected or not all(isinstance(o, torch.Tensor) for o in out):
            got = shapes if shapes is not None else type(out).__name__
            raise ValueError(
                f"model.{name}: expected a pair of tensors {expected} for inputs of batch "
                f"[{_BATCH}], got {got}"
            )
        for o in out:
            self.check_values(name, o, getattr(self, "dtype", o.dtype))
        return out[0], out[1]

    def covariance(self, name: str, dim: int, *args: object) -> None:
        self.symmetric(name, self.tensor(name, (dim, dim), *args))

    def symmetric(self, name: str, cov: torch.Tensor) -> None:
        """Refuse a covariance that is not symmetric positive semi-definite."""
        scale = float(cov.abs().max()) if cov.numel() else 0.0
        cov = cov.double()
        if not torch.allclose(cov, cov.mT, atol=1e-6 * max(scale, 1.0), rtol=0):
            raise ValueError(f"model.{name}: expected a symmetric covariance, got {cov[0]}")
        if cov.numel() and float(torch.linalg.eigvalsh(cov).min()) < -1e-6 * max(scale, 1.0):
            raise ValueError(
                f"model.{name}: expected a positive semi-definite covariance, got eigenvalues "
                f"{torch.linalg.eigvalsh(cov[0]).tolist()}"
            )

    def reward(self, name: str, *args: object) -> None:
        """A reward ``[*B, 1]`` (or ``[*B]``, which TorchRL reshapes)."""
        out = self.call(name, *args)
        if not isinstance(out, torch.Tensor) or list(out.shape) not in ([_BATCH, 1], [_BATCH]):
            got = list(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise ValueError(
                f"model.{name}: expected a reward [*B, 1] ([{_BATCH}, 1] for inputs of batch "
                f"[{_BATCH}]), got {got}"
            )
        self.check_values(name, out, self.dtype)

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

    # --- differentiable in θ ----------------------------------------------------------------
    def differentiable(self) -> None:
        """Refuse a method whose output moves with a θ parameter to first order (a finite
        difference) while autograd finds no gradient to it (a ``.detach()``, ``.item()``,
        ``float()``): the inverse would call that parameter "not identified"."""
        m, s, a, t, st = self.model, self.state, self.action, self.target, self.step
        mean, cov, stop = self.mean, self.cov, self.stop

        def lift(x: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
            """``x`` beside θ rows ``[n, B, d]``: one call scores every finite difference."""
            return x.expand(*theta.shape[:-2], *x.shape)

        methods: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
            "transition": lambda th: m.transition(lift(s, th), lift(a, th), th),
            "process_cov": lambda th: m.process_cov(lift(s, th), lift(a, th), th),
            "observe": lambda th: m.observe(lift(s, th), th),
            "observation_cov": lambda th: m.observation_cov(lift(s, th), th),
            "initial_belief": lambda th: m.initial_belief(lift(s, th), lift(t, th), th)[1],
            "belief_reward": lambda th: m.belief_reward(
                *(lift(x, th) for x in (mean, cov, t, a, stop)), th
            ),
            "belief_features": lambda th: m.belief_features(
                *(lift(x, th) for x in (mean, cov, t, st)), th
            )[..., : m.belief_feature_dim],
        }
        shifted = self.shifted()
        for name, method in methods.items():
            theta = self.theta.clone().requires_grad_(True)
            out = method(theta)
            if not out.numel():
                continue
            weight = torch.linspace(0.5, 1.5, out.numel(), dtype=out.dtype).view_as(out)
            value = (weight * out).sum()
            grad = None  # an output without a graph (θ unused, or detached) has no gradient
            if value.requires_grad:
                (grad,) = torch.autograd.grad(value, theta, allow_unused=True)
            unseen = (grad == 0).all(0) if grad is not None else torch.ones(m.theta_space.dim)
            with torch.no_grad():
                moved = (weight * method(shifted)).flatten(1).sum(1)
            moved = (moved[1:] - moved[0]).view(len(_STEPS), -1)  # [step, parameter]
            noise = 1e-5 * (1 + abs(float(value.detach())))
            first_order = (moved[1].abs() > noise) & (moved[0].abs() < 30 * moved[1].abs())
            for i in (unseen.bool() & first_order).nonzero().flatten().tolist():
                raise ValueError(
                    f"model.{name}: its output moves with θ parameter "
                    f"{m.theta_space.names[i]!r} (a finite difference) but carries no gradient "
                    "to it (autograd); expected every method differentiable in θ (no "
                    ".detach(), .item() or float() of θ)"
                )

    def shifted(self) -> torch.Tensor:
        """θ rows ``[1 + len(_STEPS) · d, B, d]``: the default, then each parameter moved by each
        of :data:`_STEPS` of its range, into the range."""
        space, theta = self.model.theta_space, self.theta.detach()
        low, high = space.low(self.dtype), space.high(self.dtype)
        rows = [theta]
        for fraction in _STEPS:
            step = fraction * (high - low)
            step = torch.where(theta[0] + step <= high, step, -step)
            rows += [
                theta + step[i] * torch.eye(space.dim, dtype=self.dtype)[i]
                for i in range(space.dim)
            ]
        return torch.stack(rows)


def _probe_action(model: TaskModel, dtype: torch.dtype) -> torch.Tensor:
    """An action of every batch element, inside the spec and off its centre (a gain times a
    zero action would hide the gain): index 1 of a discrete action, three quarters of the way
    up a bounded box, 0.5 where unbounded."""
    spec = model.action_spec
    if isinstance(spec, Categorical):
        return torch.full((_BATCH,), min(1, spec.n - 1), dtype=spec.dtype)
    low, high = spec.space.low.to(dtype), spec.space.high.to(dtype)
    bounded = torch.isfinite(high - low) & (high - low < torch.finfo(torch.float32).max)
    action = torch.where(bounded, low + 0.75 * (high - low), torch.full_like(low, 0.5))
    return action.expand(_BATCH, -1).to(spec.dtype)


def _shown(model: TaskModel, theta: torch.Tensor) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in model.theta_space.to_dict(theta).items())


_OBSERVE = " (a task with observations, observation_dim > 0, overrides observe and observation_cov)"
_JACOBIAN = (
    "; write the method in batched torch ops, without a Python branch on a tensor's value, or "
    "override it with an analytic Jacobian"
)
