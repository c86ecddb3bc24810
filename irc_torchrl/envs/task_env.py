"""A batched TorchRL environment over any :class:`TaskModel`, every element with its own θ."""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase

from irc_torchrl.checks import resolve_device
from irc_torchrl.checks import seed as check_seed
from irc_torchrl.envs.model import TaskModel, action_in_spec
from irc_torchrl.envs.probe import check_model

__all__ = ["TaskEnv"]

#: how a NaN observation is named: the noise-free observation plus its noise's draw
_OBSERVED = "observe (with observation_cov's noise)"


class TaskEnv(EnvBase):
    """The world of a task: true state, target and noisy observations, stepped with ``task_theta``.

    Every batch element carries the agent's θ (``theta``) and the world's θ (``task_theta``).
    At each reset, ``theta`` is drawn from the prior unless it was given (to the constructor,
    held for every trial, or as a keyword, ``env.reset(theta=...)``, for one reset);
    ``task_theta`` equals ``theta`` unless given. A ``theta`` entry of the TensorDict passed to
    :meth:`reset` is not read: there it is the ending trial's, carried over by ``step_mdp``,
    and reading it would keep θ from being redrawn. The agent's belief is added by
    :class:`~irc_torchrl.envs.belief.EKFBelief`.

    Args:
        model: the task; ``None`` builds the subclass's ``model_class`` with its defaults.
        batch_size: leading batch dimensions (``()`` for one environment).
        theta: agent θ for every trial, ``[*batch_size, d]`` or ``[d]``; ``None`` draws from
            the prior.
        task_theta: world θ, likewise; ``None`` means equal to the agent's.
        device: where tensors live.
        seed: seed of the environment's generator; ``None`` draws one from torch's global
            generator (each env its own stream; :func:`torch.manual_seed` fixes them).
    """

    batch_locked = True
    #: the task a subclass stands for, built when no model is given
    model_class: type[TaskModel] | None = None

    def __init__(
        self,
        model: TaskModel | None = None,
        batch_size: Sequence[int] | torch.Size = (),
        theta: torch.Tensor | None = None,
        task_theta: torch.Tensor | None = None,
        device: torch.device | str | None = None,
        seed: int | None = None,
    ) -> None:
        device = None if device is None else resolve_device(str(device))
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        if model is None:
            if self.model_class is None:
                raise TypeError("model: TaskEnv needs a TaskModel (or use a task's env subclass)")
            model = self.model_class()
        check_model(model)
        self.model = model
        self.theta = None if theta is None else self._check_theta(theta, "theta")
        self.task_theta = (
            None if task_theta is None else self._check_theta(task_theta, "task_theta")
        )
        self._make_specs()
        self.rng = torch.Generator(device=self.device if self.device is not None else "cpu")
        self.set_seed(None if seed is None else check_seed("seed", seed))

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "__signature__" not in cls.__dict__:  # a subclass's own stands
            cls.__signature__ = _constructor_signature(cls)

    def _check_theta(self, theta: torch.Tensor, field: str) -> torch.Tensor:
        theta = torch.as_tensor(theta, dtype=torch.float32, device=self.device)
        self.model.theta_space.validate(theta, field)
        try:
            return theta.expand(*self.batch_size, self.model.theta_space.dim).clone()
        except RuntimeError:
            raise ValueError(
                f"{field}: expected shape [{self.model.theta_space.dim}] or "
                f"{[*self.batch_size, self.model.theta_space.dim]}, got {list(theta.shape)}"
            ) from None

    def _make_specs(self) -> None:
        m, batch, device = self.model, self.batch_size, self.device
        # the dtype the model computes in (the firefly tasks: float32 whatever torch's default),
        # read off one draw on the CPU (not on a default device of the caller's)
        with torch.device("cpu"):
            theta = m.theta_space.default().unsqueeze(0)
            dtype = m.initial_state(theta, torch.Generator().manual_seed(0))[0].dtype

        def real(*shape: int) -> Unbounded:
            return Unbounded(shape=(*batch, *shape), dtype=dtype, device=device)

        observation = {
            "theta": m.theta_space.spec(batch, device),
            "task_theta": m.theta_space.spec(batch, device),
            "state": real(m.state_dim),
            "target": real(m.target_dim),
            "step": Bounded(0, m.max_steps, shape=(*batch, 1), dtype=torch.int64, device=device),
        }
        if m.observation_dim:
            observation["observation"] = real(m.observation_dim)
        self.observation_spec = Composite(observation, shape=batch, device=device)
        self.action_spec = m.action_spec.expand(*batch, *m.action_spec.shape).to(device)
        self.reward_spec = real(1)
        self.done_spec = Composite(
            {
                key: Bounded(0, 1, shape=(*batch, 1), dtype=torch.bool, device=device)
                for key in ("done", "terminated", "truncated")
            },
            shape=batch,
            device=device,
        )

    def to(self, device: torch.device | str) -> TaskEnv:
        """Move the env with its fixed θ and its generator: draws are made where it lives (the
        generator moves as a new one seeded from the old, so a seed still fixes the draws)."""
        super().to(device)
        if self.rng.device != self.device:
            seed = int(torch.randint(2**62, (), generator=self.rng, device=self.rng.device))
            self.rng = torch.Generator(device=self.device).manual_seed(seed)
        self.theta, self.task_theta = (
            None if x is None else x.to(self.device) for x in (self.theta, self.task_theta)
        )
        return self

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:  # drawn from torch's global generator: torch.manual_seed sets it
            seed = int(torch.randint(2**62, (), dtype=torch.int64))
        self.rng.manual_seed(int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        space, batch = self.model.theta_space, self.batch_size
        theta = kwargs.get("theta")
        theta = self._check_theta(theta, "theta") if theta is not None else self.theta
        if theta is None:
            theta = space.sample(batch, generator=self.rng, device=self.device)
        task_theta = kwargs.get("task_theta")
        if task_theta is not None:
            task_theta = self._check_theta(task_theta, "task_theta")
        else:
            task_theta = self.task_theta
        if task_theta is None:
            task_theta = theta
        state, target = self.model.initial_state(task_theta, self.rng)
        fresh = {
            "theta": theta,
            "task_theta": task_theta,
            "state": state,
            "target": target,
            "step": torch.zeros(*batch, 1, dtype=torch.int64, device=self.device),
        }
        made = {"initial_state": torch.cat([state, target], -1)}
        if self.model.observation_dim:
            fresh["observation"] = made[_OBSERVED] = self._observe(state, task_theta)
        self._check_finite(made, task_theta)
        # TorchRL keeps the rows that a partial reset (``_reset``) leaves alone
        return TensorDict(fresh, batch_size=batch, device=self.device)

    def _sample_noise(self, cov: torch.Tensor) -> torch.Tensor:
        """A draw from ``N(0, cov)`` for a PSD ``cov`` (a zero variance gives zero noise)."""
        jitter = 1e-12 * torch.eye(cov.shape[-1], dtype=torch.float64, device=cov.device)
        chol = torch.linalg.cholesky(cov.to(torch.float64) + jitter).to(cov.dtype)
        eps = torch.randn(
            *cov.shape[:-1], 1, generator=self.rng, device=cov.device, dtype=cov.dtype
        )
        return (chol @ eps).squeeze(-1)

    def _observe(self, state: torch.Tensor, task_theta: torch.Tensor) -> torch.Tensor:
        noise = self._sample_noise(self.model.observation_cov(state, task_theta))
        return self.model.observe(state, task_theta) + noise

    def _check_step_inputs(
        self, action: torch.Tensor, theta: torch.Tensor, task_theta: torch.Tensor
    ) -> None:
        """Raise a one-line error unless ``action`` has the spec's shape and in-bound values
        and both θ lie in their space: a θ edited in the TensorDict between steps is refused
        as the constructor and ``reset`` refuse it, before the world or the belief moves."""
        spec, space = self.action_spec, self.model.theta_space
        if action.shape != spec.shape:
            raise ValueError(f"action: expected shape {list(spec.shape)}, got {list(action.shape)}")
        expected = torch.Size((*self.batch_size, space.dim))
        for field, value in (("theta", theta), ("task_theta", task_theta)):
            if value.shape != expected:
                raise ValueError(
                    f"{field}: expected shape {list(expected)}, got {list(value.shape)}"
                )
        inside = ~(space.outside(theta) | space.outside(task_theta)).any()
        # one sync for all three (a comparison fails on NaN too)
        if bool(action_in_spec(spec, action).all() & inside):
            return
        space.validate(theta, "theta")
        space.validate(task_theta, "task_theta")
        if action.is_floating_point() and not torch.isfinite(action).all():
            raise ValueError("action: expected finite values, got NaN or inf")
        raise ValueError(
            f"action: expected values within the bounds of the {type(spec).__name__} action "
            f"spec, got values in [{action.min().item()}, {action.max().item()}]"
        )

    def _check_finite(self, outputs: dict[str, torch.Tensor], task_theta: torch.Tensor) -> None:
        """Refuse ``outputs`` (by the task's method that made each) holding NaN or inf, at a θ
        the constructor's probe did not try: named here, before the NaN reaches a belief and
        an action, with the world's θ of the first element it hit."""
        finite = {
            method: torch.isfinite(out).reshape(*self.batch_size, -1).all(-1)
            for method, out in outputs.items()
        }
        if bool(torch.stack(list(finite.values())).all()):  # one sync for all of them
            return
        method, ok = next((method, ok) for method, ok in finite.items() if not bool(ok.all()))
        theta = self.model.theta_space.format(task_theta[~ok][0].cpu().to(torch.float32))
        raise ValueError(
            f"model.{method}: NaN or inf at the world's θ ({theta}); expected finite values for "
            "every θ in its space and every action"
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        m = self.model
        state, action, step = tensordict["state"], tensordict["action"], tensordict["step"]
        task_theta, target = tensordict["task_theta"], tensordict["target"]
        self._check_step_inputs(action, tensordict["theta"], task_theta)
        stop = m.stops(action, step)
        reward = m.reward(state, target, action, stop, task_theta)
        next_state = m.transition(state, action, task_theta)
        next_state = next_state + self._sample_noise(m.process_cov(state, action, task_theta))
        made = {"transition (with process_cov's noise)": next_state, "reward": reward}
        next_step = step + 1
        timeout = next_step >= m.max_steps
        out = {
            "theta": tensordict["theta"],
            "task_theta": task_theta,
            "state": next_state,
            "target": target,
            "step": next_step.clamp_max(m.max_steps),
            "reward": reward,
            "done": stop | timeout,
            "terminated": stop | timeout,
            "truncated": timeout & ~stop,
        }
        if m.observation_dim:
            out["observation"] = made[_OBSERVED] = self._observe(next_state, task_theta)
        self._check_finite(made, task_theta)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)


def _constructor_signature(cls: type[TaskEnv]) -> inspect.Signature:
    """The constructor's arguments, for ``help`` and ``inspect``: TorchRL's env metaclass
    would show every env as ``(*args, **kwargs)``."""
    signature = inspect.signature(cls.__init__)
    parameters = list(signature.parameters.values())[1:]
    return signature.replace(parameters=parameters, return_annotation=inspect.Signature.empty)


TaskEnv.__signature__ = _constructor_signature(TaskEnv)
