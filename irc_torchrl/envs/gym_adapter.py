"""The 2D firefly task behind gymnasium's API, for users of other RL libraries.

:class:`Firefly2DGymEnv` wraps one ``TransformedEnv(Firefly2DEnv(), EKFBelief)`` and reads
:class:`BeliefFeatures`: the world, its random stream, its input checks and the filter are the
very objects the TorchRL pipeline runs, so the two cannot drift apart. The observation is the
feature vector (belief features, then normalised θ); θ is drawn from the prior at every reset
unless given to the constructor or as ``reset(options={"theta": ..., "task_theta": ...})``.
Registered as ``irc_torchrl/Firefly2D-v0``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torchrl.envs import TransformedEnv

from irc_torchrl.envs.belief import BeliefFeatures, EKFBelief
from irc_torchrl.envs.firefly2d import Firefly2DEnv, Firefly2DModel

__all__ = ["GYM_ID", "Firefly2DGymEnv", "register_gym"]

GYM_ID = "irc_torchrl/Firefly2D-v0"


class Firefly2DGymEnv(gym.Env):
    """One 2D firefly trial at a time with the gymnasium API; features are the observation.

    Args:
        theta: the agent's θ (``{name: value}`` or a ``[d]`` tensor) for every trial;
            ``None`` draws it from the prior at each reset.
        task_theta: the world's θ likewise; ``None`` means equal to the agent's.
        model: the task (default: :class:`Firefly2DModel` with its defaults).
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        theta: Mapping[str, float] | torch.Tensor | None = None,
        task_theta: Mapping[str, float] | torch.Tensor | None = None,
        model: Firefly2DModel | None = None,
    ) -> None:
        if model is not None and not isinstance(model, Firefly2DModel):
            raise TypeError(f"model: expected a Firefly2DModel, got {type(model).__name__}")
        self.model = model if model is not None else Firefly2DModel()
        space = self.model.theta_space
        self._theta = None if theta is None else self._as_theta(theta, "theta")
        self._task_theta = None if task_theta is None else self._as_theta(task_theta, "task_theta")
        # seeded at the first reset (gymnasium's way), not from torch's global generator
        base = Firefly2DEnv(model=self.model, seed=0)
        self.env = TransformedEnv(base, EKFBelief(self.model))
        self.features = BeliefFeatures(self.model)
        dim = self.model.belief_feature_dim + space.dim
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(dim,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self._td = None

    def _as_theta(self, theta: Mapping[str, float] | torch.Tensor, field: str) -> torch.Tensor:
        space = self.model.theta_space
        if isinstance(theta, Mapping):
            return space.from_dict(theta, field=field)
        return space.validate(torch.as_tensor(theta, dtype=torch.float32), field)

    def _observation(self) -> np.ndarray:
        return self.features(self._td)["features"].detach().numpy().astype(np.float32)

    def _info(self) -> dict[str, Any]:
        td = self._td
        return {
            "state": td["state"].numpy().copy(),
            "target": td["target"].numpy().copy(),
            "theta": td["theta"].numpy().copy(),
            "task_theta": td["task_theta"].numpy().copy(),
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a trial; ``seed`` reseeds the world's generator, ``options`` may hold θ."""
        super().reset(seed=seed)
        if seed is not None or self._td is None:  # unseeded first reset: gymnasium's entropy
            self.env.set_seed(int(self.np_random.integers(2**31)))
        options = options or {}
        unknown = sorted(set(options) - {"theta", "task_theta"})
        if unknown:
            raise ValueError(f"options: unknown key(s) {unknown}; expected 'theta', 'task_theta'")
        kwargs = {}
        for field, default in (("theta", self._theta), ("task_theta", self._task_theta)):
            value = options.get(field, default)
            if value is not None:
                kwargs[field] = self._as_theta(value, field)
        self._td = self.env.reset(**kwargs)
        return self._observation(), self._info()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Take ``action = (a_v, a_ω)`` in ``[-1, 1]²``. At the time limit both ``terminated``
        and ``truncated`` are true (the TorchRL env's flags)."""
        if self._td is None:
            raise RuntimeError("Firefly2DGymEnv.step: call reset() first")
        action = torch.as_tensor(np.asarray(action, dtype=np.float32))
        self._td["action"] = action
        td = self.env.step(self._td)
        reward = float(td["next", "reward"])
        # the time limit is part of the task (the step is a feature and no reward follows it),
        # so a timeout terminates, as in the TorchRL env: a learner must not bootstrap there
        terminated = bool(td["next", "terminated"])
        truncated = bool(td["next", "truncated"])
        self._td = td["next"].exclude("reward", "done", "terminated", "truncated")
        return self._observation(), reward, terminated, truncated, self._info()


def register_gym() -> None:
    """Register :class:`Firefly2DGymEnv` with gymnasium as ``irc_torchrl/Firefly2D-v0`` (once)."""
    if GYM_ID not in gym.registry:
        gym.register(id=GYM_ID, entry_point="irc_torchrl.envs.gym_adapter:Firefly2DGymEnv")
