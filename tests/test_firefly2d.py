"""The 2D firefly task: θ space, specs, resets, seeding, dynamics, stop rule and rewards."""

from __future__ import annotations

import inspect
import math
import pydoc

import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from irc_torchrl.envs import (
    BeliefFeatures,
    BeliefReward,
    EKFBelief,
    Firefly2DEnv,
    Firefly2DModel,
    firefly2d_theta_space,
    seed_paper_theta_space,
)
from irc_torchrl.envs.firefly1d import Firefly1DEnv
from irc_torchrl.envs.firefly2d import NOISE_FLOOR, disc_probability
from irc_torchrl.envs.task_env import TaskEnv
from irc_torchrl.theta import ThetaSpace

torch.set_num_threads(1)
MODEL = Firefly2DModel()
SPACE = MODEL.theta_space


def filtered(batch_size=(), **kwargs):
    return TransformedEnv(Firefly2DEnv(batch_size=batch_size, **kwargs), EKFBelief(MODEL))


def test_theta_space_names_ranges_and_seed_paper_variant():
    space = firefly2d_theta_space()
    assert space.names == [
        "g_v",
        "g_w",
        "sigma_v",
        "sigma_w",
        "obs_sigma_v",
        "obs_sigma_w",
        "sigma_pos",
        "goal_radius",
        "effort_cost",
    ]
    assert space.free_names == [n for n in space.names if n != "sigma_pos"]
    # wide noise: observation noise up to the gain, process noise up to half of it
    assert space["obs_sigma_v"].high >= space["g_v"].high
    assert space["sigma_v"].high >= 0.5 * space["g_v"].high
    paper = seed_paper_theta_space()
    assert paper.free_names == ["g_v", "g_w", "sigma_pos"]
    draws = paper.sample((100,), generator=torch.Generator().manual_seed(0))
    assert (draws[:, paper.index("sigma_w")] == 0).all() and draws[:, 6].std() > 0
    td = Firefly2DEnv(batch_size=(8,), model=Firefly2DModel(theta_space=paper)).reset()
    assert (td["theta"][:, paper.index("sigma_v")] == 0).all()
    with pytest.raises(ValueError, match="theta_space: expected parameters"):
        Firefly2DModel(theta_space=ThetaSpace(space.parameters[:3]))


@pytest.mark.parametrize("batch_size", [(), (5,), (2, 3)])
@pytest.mark.parametrize("with_filter", [False, True])
def test_check_env_specs(batch_size, with_filter):
    env = filtered(batch_size) if with_filter else Firefly2DEnv(batch_size=batch_size)
    check_env_specs(env, seed=0)
    td = env.rollout(5, break_when_any_done=False)
    assert td["state"].shape == (*batch_size, 5, 5)
    if with_filter:
        assert td["next", "belief", "cov"].shape == (*batch_size, 5, 5, 5)


def test_envs_show_their_constructors_arguments_not_the_metaclass_catch_all():
    class Extended(Firefly2DEnv):
        def __init__(self, horizon: int = 3, **kwargs) -> None:
            super().__init__(**kwargs)

    names = ["model", "batch_size", "theta", "task_theta", "device", "seed"]
    for env in (TaskEnv, Firefly1DEnv, Firefly2DEnv):
        assert list(inspect.signature(env).parameters) == names
    assert list(inspect.signature(Extended).parameters) == ["horizon", "kwargs"]
    assert "Firefly2DEnv(model: " in pydoc.plain(pydoc.render_doc(Firefly2DEnv))  # help()


def test_initial_belief_knows_the_start_pose_with_a_pd_floor():
    td = filtered((4,)).reset()
    assert torch.equal(td["belief", "mean"], td["state"])
    assert torch.equal(td["state"], torch.zeros(4, 5))
    torch.testing.assert_close(td["belief", "cov"], NOISE_FLOOR**2 * torch.eye(5).expand(4, 5, 5))
    distance = td["target"].norm(dim=-1)
    assert (distance >= 1.0).all() and (distance <= 3.0).all()
    assert (td["target"][:, 0] > 0).all()  # ahead of the start heading


def test_theta_and_task_theta():
    theta = SPACE.default()
    task = SPACE.from_dict({"g_v": 0.8})
    env = Firefly2DEnv(batch_size=(3,), theta=theta, task_theta=task)
    td = env.reset()
    assert torch.equal(td["theta"], theta.expand(3, -1)) and torch.equal(
        td["task_theta"], task.expand(3, -1)
    )
    # the world moves with the task's gain: v' = 0.8 a_v exactly up to the noise floor
    env = Firefly2DEnv(
        batch_size=(3,),
        theta=theta,
        task_theta=SPACE.from_dict({"g_v": 0.8, "sigma_v": 0.0, "sigma_w": 0.0}),
    )
    td = env.step(env.reset().set("action", torch.tensor([[1.0, 0.0]] * 3)))
    torch.testing.assert_close(td["next", "state"][:, 3], torch.full((3,), 0.8), atol=1e-2, rtol=0)
    # without a task θ, each reset draws θ from the prior and the task's equals the agent's
    td = Firefly2DEnv(batch_size=(64,)).reset()
    assert torch.equal(td["theta"], td["task_theta"])
    assert td["theta"][:, 0].std() > 0.1
    # per-reset θ through reset kwargs
    td = Firefly2DEnv(batch_size=(2,)).reset(theta=task)
    assert torch.equal(td["theta"], task.expand(2, -1))


def test_partial_reset_only_touches_the_masked_rows():
    env = filtered((4,), seed=0)
    td = env.rollout(6, lambda td: td.set("action", torch.tensor([[1.0, 0.5]] * 4)))
    last = td[:, -1]["next"].clone()
    reset = torch.tensor([[True], [False], [True], [False]])
    out = env.reset(last.clone().set("_reset", reset))
    keep = ~reset.squeeze(-1)
    for key in ["theta", "state", "target", "step", ("belief", "mean"), ("belief", "cov")]:
        assert torch.equal(out[key][keep], last[key][keep]), key
    assert (out["step"][~keep] == 0).all() and (out["state"][~keep] == 0).all()
    assert not torch.equal(out["theta"][~keep], last["theta"][~keep])
    torch.testing.assert_close(
        out["belief", "cov"][~keep], NOISE_FLOOR**2 * torch.eye(5).expand(2, 5, 5)
    )


def test_rollout_resets_the_belief_of_stopped_trials_only():
    env = filtered((2,), seed=0)
    action = torch.tensor([[1.0, 0.3], [0.0, 0.3]])  # the second stops at min_steps
    td = env.rollout(8, lambda td: td.set("action", action), break_when_any_done=False)
    t = MODEL.min_steps
    assert td["next", "done"][:, t].squeeze(-1).tolist() == [False, True]
    after = td[:, t + 1]
    assert after["step"].squeeze(-1).tolist() == [t + 1, 0]
    assert torch.equal(after["belief", "mean"][1], torch.zeros(5))
    assert torch.equal(after["belief", "mean"][0], td["next", "belief", "mean"][0, t])


def test_seeding_reproduces_rollouts():
    def run(seed):
        env = filtered((3,), seed=seed)
        return env.rollout(
            20, lambda td: td.set("action", torch.full((3, 2), 0.7)), break_when_any_done=False
        )

    a, b, c = run(1), run(1), run(2)
    assert torch.equal(a["next", "belief", "cov"], b["next", "belief", "cov"])
    assert torch.equal(a["next", "state"], b["next", "state"])
    assert not torch.equal(a["next", "state"], c["next", "state"])


def test_noise_free_dynamics_integrate_velocities():
    theta = SPACE.from_dict({"g_v": 1.0, "g_w": 1.0}).double()
    state = torch.tensor([1.0, 2.0, math.pi / 2, 0.5, -0.4], dtype=torch.float64)
    nxt = MODEL.transition(state, torch.tensor([0.3, 0.6], dtype=torch.float64), theta)
    expected = torch.tensor([1.0, 2.0 + 0.05, math.pi / 2 - 0.04, 0.3, 0.6], dtype=torch.float64)
    torch.testing.assert_close(nxt, expected)
    cov = MODEL.process_cov(state, None, SPACE.from_dict({"sigma_v": 0.3, "sigma_pos": 0.05}))
    torch.testing.assert_close(
        torch.diagonal(cov),
        torch.tensor([0.05**2, 0.05**2, 0.0, 0.3**2, SPACE["sigma_w"].default ** 2])
        + NOISE_FLOOR**2,
    )


def test_world_noise_has_the_task_variance():
    """Velocity noise and observation noise have the task θ's std (5000 draws, 4% tolerance)."""
    task = SPACE.from_dict({"sigma_v": 0.5, "sigma_w": 0.2, "obs_sigma_v": 0.8, "obs_sigma_w": 0.3})
    env = Firefly2DEnv(batch_size=(5000,), theta=SPACE.default(), task_theta=task, seed=0)
    td = env.step(env.reset().set("action", torch.full((5000, 2), 0.5)))
    state, obs = td["next", "state"], td["next", "observation"]
    torch.testing.assert_close(state[:, 3:].std(0), torch.tensor([0.5, 0.2]), rtol=0.04, atol=0)
    torch.testing.assert_close(
        (obs - state[:, 3:]).std(0), torch.tensor([0.8, 0.3]), rtol=0.04, atol=0
    )


def test_stop_rule_and_time_limit():
    step = torch.tensor([[0], [2], [3], [3], [10]])
    action = torch.tensor([[0.0, 0], [0.0, 0], [0.0, 1], [0.5, 0], [-1.0, 0]])
    assert MODEL.stops(action, step).squeeze(-1).tolist() == [False, False, True, False, True]
    env = Firefly2DEnv(batch_size=(2,))
    td = env.rollout(
        100,
        lambda td: td.set("action", torch.tensor([[1.0, 0.0], [0.0, 0.0]])),
        break_when_any_done=True,
    )
    assert td.shape[-1] == MODEL.min_steps + 1  # the second env stops at min_steps
    assert td["next", "terminated"][1, -1] and not td["next", "truncated"][1, -1]
    td = Firefly2DEnv(batch_size=(1,)).rollout(
        100, lambda td: td.set("action", torch.tensor([[1.0, 0.0]]))
    )
    assert td.shape[-1] == MODEL.max_steps
    assert td["next", "truncated"][0, -1] and td["next", "done"][0, -1]


def test_world_reward_on_the_true_state():
    theta = SPACE.from_dict({"goal_radius": 0.3, "effort_cost": 0.05})
    target = torch.tensor([[1.0, 1.0]] * 3)
    state = torch.tensor([[1.2, 1.0, 0, 0, 0], [1.4, 1.0, 0, 0, 0], [1.2, 1.0, 0, 0, 0]])
    stop = torch.tensor([[True], [True], [False]])
    action = torch.tensor([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]])
    reward = MODEL.reward(state, target, action, stop, theta)
    torch.testing.assert_close(reward.squeeze(-1), torch.tensor([10.0, 0.0, -0.1]))


def monte_carlo_disc(mean, cov, radius, n=400_000, seed=0):
    z = torch.randn(
        n, *mean.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64
    )
    p = mean + (torch.linalg.cholesky(cov) @ z.unsqueeze(-1)).squeeze(-1)
    return (p.norm(dim=-1) < radius.squeeze(-1)).double().mean(0)


def test_disc_probability_matches_monte_carlo():
    """Against 400k Monte-Carlo draws (s.e. ≤ 0.0008): absolute error < 0.004 at every
    scale, from near-point beliefs to beliefs much wider than the goal, anisotropic ones too."""
    gen = torch.Generator().manual_seed(1)
    mean = torch.randn(40, 2, generator=gen, dtype=torch.float64) * 0.4
    scale = torch.logspace(-3, 0.3, 40, dtype=torch.float64).view(-1, 1, 1)
    root = torch.randn(40, 2, 2, generator=gen, dtype=torch.float64)
    cov = scale**2 * (root @ root.mT + 0.05 * torch.eye(2, dtype=torch.float64))
    radius = 0.2 + 0.3 * torch.rand(40, 1, generator=gen, dtype=torch.float64)
    ours = disc_probability(mean, cov, radius).squeeze(-1)
    mc = monte_carlo_disc(mean, cov, radius)
    assert (ours - mc).abs().max() < 0.004
    assert ours.min() < 0.01 and ours.max() > 0.99  # the cases span the whole range
    # a point belief: the indicator of the true position
    point = disc_probability(
        torch.tensor([[0.1, 0.0], [0.5, 0.0]]),
        1e-12 * torch.eye(2).expand(2, 2, 2),
        torch.tensor([[0.3], [0.3]]),
    )
    torch.testing.assert_close(point.squeeze(-1), torch.tensor([1.0, 0.0]))


def test_disc_probability_is_smooth_in_its_inputs():
    """Finite-difference gradient check in float64, belief centre inside and outside the goal."""
    cov = torch.tensor([[[0.04, 0.01], [0.01, 0.02]]] * 2, dtype=torch.float64)
    for centre in ([0.1, -0.05], [0.45, 0.2]):
        mean = torch.tensor([centre, centre], dtype=torch.float64, requires_grad=True)
        radius = torch.tensor([[0.3], [0.4]], dtype=torch.float64, requires_grad=True)
        root = cov.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(
            lambda m, c, r: disc_probability(m, c @ c.mT, r), (mean, root, radius)
        )


def test_belief_reward_is_the_world_reward_in_expectation():
    theta = SPACE.from_dict({"goal_radius": 0.3, "effort_cost": 0.05}).double()
    mean = torch.tensor([[1.1, 0.9, 0.3, 0.5, 0.0]], dtype=torch.float64)
    root = torch.randn(5, 5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    cov = (0.1 * root @ root.T + 1e-3 * torch.eye(5, dtype=torch.float64)).unsqueeze(0)
    target, action = torch.tensor([[1.0, 1.0]], dtype=torch.float64), torch.tensor([[0.0, 0.6]])
    stop = torch.tensor([[True]])
    expected = MODEL.belief_reward(mean, cov, target, action, stop, theta)
    z = torch.randn(200_000, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    states = mean + z @ torch.linalg.cholesky(cov[0]).T
    world = MODEL.reward(states, target, action, stop, theta).mean()
    assert abs(expected.item() - world.item()) < 0.03  # s.e. of the MC mean ≈ 0.01
    moving = MODEL.belief_reward(mean, cov, target, action, ~stop, theta)
    torch.testing.assert_close(moving, torch.tensor([[-0.05 * 0.36]], dtype=torch.float64))


def test_belief_reward_transform_and_features_in_a_rollout():
    env = filtered((8,), seed=0).append_transform(BeliefReward(MODEL))
    check_env_specs(env, seed=0)
    features = BeliefFeatures(MODEL)
    gen = torch.Generator().manual_seed(0)
    td = env.rollout(
        60,
        lambda td: features(td).set("action", 2 * torch.rand(8, 2, generator=gen) - 1),
        break_when_any_done=False,
    )
    dim = MODEL.belief_feature_dim + SPACE.dim
    assert td["features"].shape == (8, 60, dim) and torch.isfinite(td["features"]).all()
    assert torch.isfinite(td["next", "reward"]).all()
    stopped = td["next", "terminated"] & ~td["next", "truncated"]
    assert stopped.any()
    assert (td["next", "reward"][~stopped] <= 0).all()  # moving only costs


def test_belief_features_geometry():
    theta = SPACE.default().double()
    # heading +90°: a target straight north is straight ahead
    mean = torch.tensor([1.0, 1.0, math.pi / 2, 0.6, 0.5], dtype=torch.float64)
    cov = torch.diag(torch.tensor([0.04, 0.01, 0.09, 0.16, 0.25], dtype=torch.float64))
    f = MODEL.belief_features(
        mean, cov, torch.tensor([1.0, 2.5], dtype=torch.float64), torch.tensor([6]), theta
    )
    assert f.shape == (MODEL.belief_feature_dim + SPACE.dim,)
    expected = [
        1.5 / 3,
        0.0,
        1.5 / 3,
        0.0,
        1.0,
        0.6 / 1.2,
        0.5 / 1.0,
        0.1 / 3,
        0.2 / 3,
        0.0,
        0.3,
        0.4 / 1.2,
        0.5 / 1.0,
        6 / MODEL.max_steps,
    ]
    torch.testing.assert_close(f[:14], torch.tensor(expected, dtype=torch.float64))
    torch.testing.assert_close(f[14:], SPACE.normalise(theta))
    # batched and broadcast over θ
    f = MODEL.belief_features(
        mean.expand(2, 3, 5),
        cov.expand(2, 3, 5, 5),
        torch.zeros(2, 3, 2, dtype=torch.float64),
        torch.zeros(2, 3, 1, dtype=torch.int64),
        theta,
    )
    assert f.shape == (2, 3, MODEL.belief_feature_dim + SPACE.dim)


def test_works_with_a_torchrl_collector():
    def make_env():
        return filtered((4,), seed=0).append_transform(BeliefReward(MODEL))

    actor = torch.nn.Sequential(
        torch.nn.Linear(MODEL.belief_feature_dim + SPACE.dim, 2), torch.nn.Tanh()
    )
    policy = TensorDictSequential(
        BeliefFeatures(MODEL), TensorDictModule(actor, in_keys=["features"], out_keys=["action"])
    )
    collector = Collector(
        make_env,
        policy,
        frames_per_batch=40,
        total_frames=80,
        auto_register_policy_transforms=False,
    )
    batches = list(collector)
    collector.shutdown()
    assert [b.shape for b in batches] == [torch.Size([4, 10])] * 2
    assert torch.isfinite(batches[-1]["next", "belief", "cov"]).all()


def test_the_belief_reward_is_the_goal_probability_under_the_belief_the_action_was_chosen_at():
    """``BeliefReward`` scores a stop, as the world does, at the belief and step before the
    action: a stop at ``min_steps`` inside the goal (under the belief it was chosen at; the
    filter's next belief has left it) pays, the same action a step earlier only costs effort."""
    env = filtered((2,), seed=0).append_transform(BeliefReward(MODEL))
    theta = SPACE.from_dict({"g_v": 1.6, "goal_radius": 0.2, "effort_cost": 0.05})
    td = env.reset(theta=theta)
    pose = torch.tensor([1.1, 0.0, 0.0, 1.6, 0.0])  # inside the goal, leaving it at full speed
    td["target"] = torch.tensor([[1.0, 0.0]] * 2)
    td["state"] = pose.expand(2, 5).clone()
    td["belief", "mean"] = pose.expand(2, 5).clone()
    td["belief", "cov"] = 0.03**2 * torch.eye(5).expand(2, 5, 5).clone()
    td["step"] = torch.tensor([[MODEL.min_steps], [MODEL.min_steps - 1]])
    td["action"] = torch.tensor([[0.0, 0.5]] * 2)  # a stop, where stopping is allowed
    out = env.step(td)
    effort = 0.05 * 0.25
    inside = disc_probability(
        td["belief", "mean"][:1, :2] - td["target"][:1],
        td["belief", "cov"][:1, :2, :2],
        torch.tensor([[0.2]]),
    )
    assert inside.item() > 0.99
    expected = torch.stack([10 * inside[0] - effort, torch.tensor([-effort])])
    torch.testing.assert_close(out["next", "reward"], expected)
    assert out["next", "terminated"].squeeze(-1).tolist() == [True, False]
    # the belief after the step says the agent has left: scoring it would not pay
    after = out["next", "belief"]
    left = disc_probability(
        after["mean"][:1, :2] - td["target"][:1], after["cov"][:1, :2, :2], torch.tensor([[0.2]])
    )
    assert left.item() < 0.5


def test_belief_features_are_the_target_and_position_uncertainty_in_the_heading_frame():
    """At any heading and full position covariance, the egocentric features are those of the
    rotated frame: target ``R(-φ)(target - p)``, and std ahead, std aside and correlation of
    ``R(-φ) C R(-φ)ᵀ`` (the correlation a true one, in [-1, 1])."""
    gen = torch.Generator().manual_seed(0)
    n = 64
    mean = torch.randn(n, 5, generator=gen, dtype=torch.float64)
    mean[:, 2] = 2 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64) - math.pi
    root = torch.randn(n, 5, 5, generator=gen, dtype=torch.float64)
    cov = 0.1 * root @ root.mT + 1e-3 * torch.eye(5, dtype=torch.float64)
    target = 2 * torch.randn(n, 2, generator=gen, dtype=torch.float64)
    theta = SPACE.default().double()
    f = MODEL.belief_features(mean, cov, target, torch.zeros(n, 1, dtype=torch.int64), theta)
    c, s = mean[:, 2].cos(), mean[:, 2].sin()
    turn = torch.stack([torch.stack([c, s], -1), torch.stack([-s, c], -1)], -2)  # R(-φ)
    rel = (turn @ (target - mean[:, :2]).unsqueeze(-1)).squeeze(-1)
    frame = turn @ cov[:, :2, :2] @ turn.mT
    scale, distance = MODEL.target_distance[1], rel.norm(dim=-1)
    sd = frame.diagonal(dim1=-2, dim2=-1).sqrt()
    expected = torch.stack(
        [
            rel[:, 0] / scale,
            rel[:, 1] / scale,
            distance / scale,
            rel[:, 1] / distance,
            rel[:, 0] / distance,
            sd[:, 0] / scale,
            sd[:, 1] / scale,
            frame[:, 0, 1] / (sd[:, 0] * sd[:, 1]),
        ],
        -1,
    )
    torch.testing.assert_close(f[:, [0, 1, 2, 3, 4, 7, 8, 9]], expected, rtol=1e-9, atol=1e-12)
    assert f[:, 9].abs().max() <= 1


def test_targets_are_uniform_in_distance_and_in_angle_on_both_sides_of_the_heading():
    """20 000 targets (seed 0): distance uniform on ``target_distance`` and bearing uniform on
    ``±target_angle`` (Kolmogorov–Smirnov distance under 0.015; its 1% critical value is 0.012),
    so the task turns left as often as right."""
    theta = SPACE.default().double().expand(20_000, -1)
    state, target = MODEL.initial_state(theta, torch.Generator().manual_seed(0))
    assert torch.equal(state, torch.zeros_like(state))
    distance, angle = target.norm(dim=-1), torch.atan2(target[:, 1], target[:, 0])
    lo, hi = MODEL.target_distance
    for values, a, b in ((distance, lo, hi), (angle, -MODEL.target_angle, MODEL.target_angle)):
        assert a <= values.min() and values.max() <= b
        ordered = ((values.sort().values - a) / (b - a)).numpy()
        uniform = (torch.arange(1, len(ordered) + 1, dtype=torch.float64) / len(ordered)).numpy()
        assert abs(ordered - uniform).max() < 0.015


def test_the_world_scores_a_stop_at_the_state_it_was_taken_in_by_the_task_theta():
    """The world's reward of a stop at ``min_steps`` reads the true state before the step and
    the task's radius 0.5 and effort cost 0.05: leaving the goal at full speed still pays, and
    a stop 0.3 from the target pays though the agent's radius 0.2 would not."""
    agent = SPACE.from_dict({"goal_radius": 0.2, "effort_cost": 0.0})
    task = SPACE.from_dict({"goal_radius": 0.5, "effort_cost": 0.05})
    env = Firefly2DEnv(batch_size=(2,), theta=agent, task_theta=task, seed=0)
    td = env.reset()
    td["target"] = torch.tensor([[1.0, 0.0]] * 2)
    # 0.45 from the target, moving away at 1.6 (0.61 after the step); 0.3 from it, at rest
    td["state"] = torch.tensor([[1.45, 0.0, 0.0, 1.6, 0.0], [1.3, 0.0, 0.0, 0.0, 0.0]])
    td["step"] = torch.full((2, 1), MODEL.min_steps)
    td["action"] = torch.tensor([[0.0, 0.5]] * 2)
    out = env.step(td)["next"]
    torch.testing.assert_close(out["reward"], torch.full((2, 1), 10 - 0.05 * 0.25))
    assert (out["state"][0, :2] - td["target"][0]).norm() > 0.5
    assert out["terminated"].all() and not out["truncated"].any()


def test_the_first_observation_is_noisy_with_the_task_variance():
    """The observation at a reset carries the task's observation noise as every later one does
    (5000 draws of the velocity observation at rest, 4% tolerance on the std)."""
    task = SPACE.from_dict({"obs_sigma_v": 0.8, "obs_sigma_w": 0.3})
    env = Firefly2DEnv(batch_size=(5000,), theta=SPACE.default(), task_theta=task, seed=0)
    td = env.reset()
    noise = td["observation"] - MODEL.observe(td["state"], td["task_theta"])
    torch.testing.assert_close(noise.std(0), torch.tensor([0.8, 0.3]), rtol=0.04, atol=0)


def test_an_action_outside_the_bounds_is_refused():
    """A finite action outside ``[-1, 1]²`` is refused with the range it had, not clipped."""
    env = Firefly2DEnv(batch_size=(2,))
    td = env.reset().set("action", torch.tensor([[1.5, 0.0], [0.5, 0.0]]))
    with pytest.raises(ValueError, match=r"within the bounds .* got values in \[0.0, 1.5\]"):
        env.step(td)
