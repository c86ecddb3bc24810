"""The 2D "catching fireflies" task: steer to a target seen once, by noisy optic flow, then stop.

State ``s = (x, y, φ, v, ω)``: position, heading, forward and angular velocity. Action
``a = (a_v, a_ω) ∈ [-1, 1]²``. With ``dt = 0.1 s`` the world moves as (anchors' convention:
the action *sets* the velocities, position and heading integrate them)::

    x' = x + v cos φ dt + σ_pos ε_x        v' = g_v a_v + σ_v ε_v
    y' = y + v sin φ dt + σ_pos ε_y        ω' = g_ω a_ω + σ_ω ε_ω
    φ' = φ + ω dt

Position integrates the *previous* velocity, whose estimate the last observation refined:
observations reach position through ``∂x/∂v``, ``∂x/∂φ`` and ``∂φ/∂ω`` in the prediction
(the update's gain on position is zero by construction, since a freshly set velocity says
nothing about where the agent already is).

The agent observes its velocities (optic flow), ``o = (v, ω) + (σᵒ_v ε, σᵒ_ω ε)``. The target is
seen only at the start: it lies ``target_distance`` ahead within ``±target_angle`` of the
initial heading, and the agent knows its start pose. The trial ends when the agent stops
(``a_v < stop_threshold`` at ``step ≥ min_steps``) or after ``max_steps``: the forward control
alone decides (not ``‖a‖ ≤ 0.1`` as in the anchors), so from ``min_steps`` on any negative
``a_v`` stops (no reversing) and a stop's turning control moves nothing. The observation noise
is the agent's senses' (``sensory_names``): the world draws it under the agent's own θ where a
recovery or fit says ``senses="agent"``.

θ (natural units; ``σ`` are noise standard deviations):

==============  ==========  ===========  ================================================
name            range       unit         meaning
==============  ==========  ===========  ================================================
g_v             0.8 – 1.6   distance/s   forward gain (top speed)
g_w             0.6 – 1.4   rad/s        angular gain
sigma_v         0 – 0.8     distance/s   process noise on v (up to half the top gain)
sigma_w         0 – 0.7     rad/s        process noise on ω
obs_sigma_v     0 – 1.6     distance/s   observation noise on v (up to 1× the gain)
obs_sigma_w     0 – 1.4     rad/s        observation noise on ω
sigma_pos       0 – 0.1     distance     position process noise per step (fixed at 0)
goal_radius     0.2 – 0.5   distance     stopping within it is rewarded
effort_cost     0 – 0.1     reward       cost per step of ``‖a‖²``
==============  ==========  ===========  ================================================

The noise ranges are wide on purpose (ANCHORS.md: noise below 0.2 of the gain makes the task
too easy for behaviour to say anything about θ). The seed paper's 3-parameter variant (two
gains and one position noise) is :func:`seed_paper_theta_space`.

Every noise variance gets ``NOISE_FLOOR²`` added (in the world and in the filter alike), and
the initial belief covariance is ``NOISE_FLOOR² I``, so the belief covariance is positive
definite for every θ, zero noises included.

Rewards: on stopping, the world pays ``reward_value`` if the *true* position is inside the
goal radius (what an experimenter rewards); the agent's :meth:`Firefly2DModel.belief_reward`
is ``reward_value`` times the probability *under its belief* of being inside (the paper's
``R_θ(b, a)``, an exact radial integral with a fixed angular quadrature). Both subtract
``effort_cost ‖a‖²`` at every step. The two agree in expectation when θ is the task's.
"""

from __future__ import annotations

import math

import torch
from torchrl.data import Bounded

from irc_torchrl.checks import count, positive_number, real
from irc_torchrl.envs.model import TaskModel, own_theta_space
from irc_torchrl.envs.task_env import TaskEnv
from irc_torchrl.theta import Parameter, ThetaSpace

__all__ = [
    "Firefly2DEnv",
    "Firefly2DModel",
    "NOISE_FLOOR",
    "disc_probability",
    "firefly2d_theta_space",
    "seed_paper_theta_space",
]

#: std (natural units) added in quadrature to every noise, and the initial belief's std
NOISE_FLOOR = 1e-3

X, Y, PHI, V, W = range(5)


def _batch(*shapes: torch.Size) -> torch.Size:
    """The broadcast of batch shapes, skipping ``torch.broadcast_shapes`` (slow) when equal."""
    return shapes[0] if all(s == shapes[0] for s in shapes) else torch.broadcast_shapes(*shapes)


def firefly2d_theta_space() -> ThetaSpace:
    """The 2D task's θ: gains, process and observation noise, goal radius, effort cost."""
    return ThetaSpace(
        [
            Parameter("g_v", 0.8, 1.6, 1.2, "distance/s", "forward gain"),
            Parameter("g_w", 0.6, 1.4, 1.0, "rad/s", "angular gain"),
            Parameter("sigma_v", 0.0, 0.8, 0.2, "distance/s", "process noise std of v"),
            Parameter("sigma_w", 0.0, 0.7, 0.15, "rad/s", "process noise std of ω"),
            Parameter("obs_sigma_v", 0.0, 1.6, 0.4, "distance/s", "observation noise std of v"),
            Parameter("obs_sigma_w", 0.0, 1.4, 0.3, "rad/s", "observation noise std of ω"),
            Parameter(
                "sigma_pos", 0.0, 0.1, 0.0, "distance", "position process noise std per step"
            ),
            Parameter("goal_radius", 0.2, 0.5, 0.35, "distance", "radius rewarded on stopping"),
            Parameter("effort_cost", 0.0, 0.1, 0.02, "reward", "cost per step of ‖a‖²"),
        ],
        fixed={"sigma_pos": 0.0},
    )


def seed_paper_theta_space() -> ThetaSpace:
    """The seed paper's variant: free ``g_v``, ``g_w`` and ``sigma_pos``; no velocity noise."""
    space = firefly2d_theta_space()
    rest = {n: space[n].default for n in space.names if n not in ("g_v", "g_w", "sigma_pos")}
    return space.free().fix(**{**rest, "sigma_v": 0.0, "sigma_w": 0.0})


def disc_probability(
    mean: torch.Tensor, cov: torch.Tensor, radius: torch.Tensor, n_angles: int = 64
) -> torch.Tensor:
    """``P(‖p‖ < radius)`` for ``p ~ N(mean, cov)`` in 2D, ``[*B, 1]``.

    Writing ``p = mean + ρ L u(α)`` (``L`` the Cholesky factor, ``ρ`` Rayleigh), each ray
    meets the disc on an interval ``[ρ₁, ρ₂]`` whose probability is exact
    (``e^{-ρ₁²/2} - e^{-ρ₂²/2}``); the angle ``α`` is averaged on fixed, evenly spaced nodes.
    Smooth in all inputs, and accurate for any covariance scale.
    """
    chol = torch.linalg.cholesky(cov)
    alpha = (torch.arange(n_angles, dtype=mean.dtype, device=mean.device) + 0.5) * (
        2 * math.pi / n_angles
    )
    u = torch.stack([alpha.cos(), alpha.sin()])  # [2, n]
    w = chol @ u  # [*B, 2, n]: ray directions in the plane
    a = (w * w).sum(-2)  # ‖w‖², [*B, n]
    b = (mean.unsqueeze(-1) * w).sum(-2)  # μ·w
    c = (mean * mean).sum(-1, keepdim=True) - radius**2  # ‖μ‖² - r²
    disc = b * b - a * c
    root = disc.clamp_min(torch.finfo(mean.dtype).tiny).sqrt()
    lo = ((-b - root) / a).clamp_min(0)
    hi = ((-b + root) / a).clamp_min(0)
    mass = torch.exp(-0.5 * lo * lo) - torch.exp(-0.5 * hi * hi)
    return torch.where(disc > 0, mass, torch.zeros_like(mass)).mean(-1, keepdim=True)


class Firefly2DModel(TaskModel):
    """The 2D task (see the module docstring). Analytic Jacobians; any batch shape and dtype."""

    state_dim = 5
    observation_dim = 2
    target_dim = 2
    dt = 0.1
    #: position (distance units), heading (rad), forward (distance/s) and angular (rad/s) velocity
    state_names = ("x", "y", "heading", "v", "w")
    state_units = ("distance", "distance", "rad", "distance/s", "rad/s")
    #: dimensionless controls in [-1, 1], scaled by the gains ``g_v``, ``g_w``
    action_names = ("a_v", "a_w")
    target_names = ("target_x", "target_y")
    name = "firefly2d"
    #: the optic flow's noise is the agent's own: no experimenter measures it
    sensory_names = ("obs_sigma_v", "obs_sigma_w")

    def __init__(
        self,
        theta_space: ThetaSpace | None = None,
        max_steps: int = 60,
        min_steps: int = 3,
        stop_threshold: float = 0.1,
        target_distance: tuple[float, float] = (1.0, 3.0),
        target_angle: float = math.pi / 4,
        reward_value: float = 10.0,
    ) -> None:
        self.theta_space = own_theta_space(theta_space, firefly2d_theta_space)
        self.max_steps = count("max_steps", max_steps)
        self.min_steps = count("min_steps", min_steps, least=0)  # 0: may stop at once
        if self.min_steps > self.max_steps:
            raise ValueError(f"min_steps: expected at most max_steps={max_steps}, got {min_steps}")
        self.stop_threshold = real("stop_threshold", stop_threshold)
        if not -1 < self.stop_threshold < 1:
            raise ValueError(
                f"stop_threshold: expected a forward control in (-1, 1), got {stop_threshold}"
            )
        expected = f"target_distance: expected (nearest, farthest), got {target_distance}"
        if len(target_distance) != 2:
            raise ValueError(expected)
        lo, hi = (positive_number("target_distance", d) for d in target_distance)
        if lo > hi:
            raise ValueError(expected)
        self.target_distance = (lo, hi)
        self.target_angle = real("target_angle", target_angle)
        if not 0 <= self.target_angle <= math.pi:
            raise ValueError(f"target_angle: expected an angle in [0, π], got {target_angle}")
        self.reward_value = positive_number("reward_value", reward_value)
        self.action_spec = Bounded(-1.0, 1.0, shape=(2,), dtype=torch.float32)

    # --- world ---------------------------------------------------------------------------
    def initial_state(
        self, theta: torch.Tensor, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        batch, kw = theta.shape[:-1], {"dtype": theta.dtype, "device": theta.device}
        u = torch.rand(*batch, 2, generator=generator, **kw)
        lo, hi = self.target_distance
        distance = lo + (hi - lo) * u[..., :1]
        angle = self.target_angle * (2 * u[..., 1:] - 1)
        target = torch.cat([distance * angle.cos(), distance * angle.sin()], -1)
        return torch.zeros(*batch, self.state_dim, **kw), target

    def transition(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        x, y, phi, v, w = state.unbind(-1)
        dt = self.dt
        pose = torch.stack([x + v * phi.cos() * dt, y + v * phi.sin() * dt, phi + w * dt], -1)
        gains = torch.cat([self.parameter(theta, "g_v"), self.parameter(theta, "g_w")], -1)
        velocity = gains * action.to(state.dtype)
        batch = _batch(pose.shape[:-1], velocity.shape[:-1])
        return torch.cat([pose.expand(*batch, 3), velocity.expand(*batch, 2)], -1)

    def transition_jacobian(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        phi, v = state[..., PHI], state[..., V]
        batch = _batch(state.shape[:-1], theta.shape[:-1], action.shape[:-1])
        jac = torch.zeros(*batch, 5, 5, dtype=state.dtype, device=state.device)
        dt = self.dt
        jac[..., X, X] = 1
        jac[..., Y, Y] = 1
        jac[..., PHI, PHI] = 1
        jac[..., X, PHI] = -v * phi.sin() * dt
        jac[..., X, V] = phi.cos() * dt
        jac[..., Y, PHI] = v * phi.cos() * dt
        jac[..., Y, V] = phi.sin() * dt
        jac[..., PHI, W] = dt
        return jac

    def process_cov(
        self, state: torch.Tensor, action: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        pos = self.parameter(theta, "sigma_pos") ** 2
        vel = (
            torch.cat([self.parameter(theta, "sigma_v"), self.parameter(theta, "sigma_w")], -1) ** 2
        )
        var = torch.cat([pos, pos, torch.zeros_like(pos), vel], -1) + NOISE_FLOOR**2
        return torch.diag_embed(var.expand(*_batch(state.shape[:-1], var.shape[:-1]), 5))

    def observe(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        return state[..., V : W + 1]

    def observation_jacobian(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        batch = _batch(state.shape[:-1], theta.shape[:-1])
        jac = torch.zeros(*batch, 2, 5, dtype=state.dtype, device=state.device)
        jac[..., 0, V] = 1
        jac[..., 1, W] = 1
        return jac

    def observation_cov(self, state: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        std = torch.cat(
            [self.parameter(theta, "obs_sigma_v"), self.parameter(theta, "obs_sigma_w")], -1
        )
        var = std**2 + NOISE_FLOOR**2
        return torch.diag_embed(var.expand(*_batch(state.shape[:-1], var.shape[:-1]), 2))

    def stops(self, action: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        return (action[..., :1] < self.stop_threshold) & (step >= self.min_steps)

    def scored_actions(self, action: torch.Tensor, step: torch.Tensor) -> torch.Tensor | None:
        """On stopping, the angular control moves nothing: only the stop itself is scored.

        It matters: at the target the bearing, and with it the actor's angular output, turns
        on millimetres of belief, so this one component would dominate the likelihood.
        """
        stop = self.stops(action, step)
        return torch.cat([torch.ones_like(stop), ~stop], -1)

    def effort(self, action: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """The effort cost ``effort_cost ‖a‖²`` of one step, ``[*B, 1]``."""
        effort = (action.to(theta.dtype) ** 2).sum(-1, keepdim=True)
        return self.parameter(theta, "effort_cost") * effort

    def reward(
        self,
        state: torch.Tensor,
        target: torch.Tensor,
        action: torch.Tensor,
        stop: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        success = self.succeeded(state, target, stop, theta)
        return self.reward_value * success.to(state.dtype) - self.effort(action, theta)

    def succeeded(
        self, state: torch.Tensor, target: torch.Tensor, stop: torch.Tensor, theta: torch.Tensor
    ) -> torch.Tensor:
        """Stopped inside the goal: what the world rewards."""
        distance = (state[..., :2] - target).norm(dim=-1, keepdim=True)
        return stop & (distance < self.parameter(theta, "goal_radius"))

    # --- agent ---------------------------------------------------------------------------
    def initial_belief(
        self, state: torch.Tensor, target: torch.Tensor, theta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        eye = torch.eye(self.state_dim, dtype=state.dtype, device=state.device)
        return state.clone(), (NOISE_FLOOR**2 * eye).expand(*state.shape, self.state_dim).clone()

    def belief_reward(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        target: torch.Tensor,
        action: torch.Tensor,
        stop: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        p = disc_probability(
            mean[..., :2] - target, cov[..., :2, :2], self.parameter(theta, "goal_radius")
        )
        return self.reward_value * stop.to(p.dtype) * p - self.effort(action, theta)

    belief_feature_dim = 14

    def belief_features(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        target: torch.Tensor,
        step: torch.Tensor,
        theta: torch.Tensor,
    ) -> torch.Tensor:
        """Egocentric target, distance, bearing, velocities, uncertainty, time; then θ.

        Positions are in units of the farthest target; velocities in units of the agent's
        gains; position uncertainty in the heading frame (std ahead, std aside, correlation).
        """
        phi = mean[..., PHI : PHI + 1]
        cos, sin = phi.cos(), phi.sin()
        rel = target - mean[..., :2]
        ahead = cos * rel[..., :1] + sin * rel[..., 1:]
        aside = -sin * rel[..., :1] + cos * rel[..., 1:]
        distance = torch.sqrt(ahead**2 + aside**2 + 1e-12)
        # the position block of the covariance, rotated into the heading frame
        c_xx, c_xy, c_yy = cov[..., X, X : X + 1], cov[..., X, Y : Y + 1], cov[..., Y, Y : Y + 1]
        var_ahead = cos**2 * c_xx + 2 * sin * cos * c_xy + sin**2 * c_yy
        var_aside = sin**2 * c_xx - 2 * sin * cos * c_xy + cos**2 * c_yy
        cov_aa = sin * cos * (c_yy - c_xx) + (cos**2 - sin**2) * c_xy
        std_ahead, std_aside = var_ahead.clamp_min(0).sqrt(), var_aside.clamp_min(0).sqrt()
        corr = cov_aa / (std_ahead * std_aside).clamp_min(NOISE_FLOOR**2)
        g_v, g_w = self.parameter(theta, "g_v"), self.parameter(theta, "g_w")
        diag = torch.diagonal(cov, dim1=-2, dim2=-1)[..., PHI:].clamp_min(0).sqrt()
        scale = self.target_distance[1]
        parts = [
            ahead / scale, aside / scale, distance / scale,
            aside / distance, ahead / distance,  # sin and cos of the bearing
            mean[..., V : V + 1] / g_v, mean[..., W : W + 1] / g_w,
            std_ahead / scale, std_aside / scale, corr,
            diag[..., :1], diag[..., 1:2] / g_v, diag[..., 2:3] / g_w,
            step.to(mean.dtype) / self.max_steps,
            self.theta_space.normalise(theta),
        ]  # fmt: skip
        batch = _batch(*(p.shape[:-1] for p in parts))
        return torch.cat([p.expand(*batch, p.shape[-1]) for p in parts], -1)


class Firefly2DEnv(TaskEnv):
    """:class:`TaskEnv` over :class:`Firefly2DModel` (see there for the task)."""

    model_class = Firefly2DModel
