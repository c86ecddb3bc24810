"""The 1D firefly task as a TorchRL environment, its belief filter and belief reward.

The paper's 1D belief: with no observations, ``μ_{t+1} = μ_t + g_a·a`` and
``σ²_{t+1} = σ²_t + σ₀²`` under the AGENT's θ, while the world moves with the TASK's θ.
"""

from __future__ import annotations

import math

import pytest
import torch
from scipy import stats
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from irc_torchrl.envs import BeliefReward, EKFBelief, Firefly1DEnv, Firefly1DModel
from irc_torchrl.envs.firefly1d import LEFT, RIGHT, STOP

MODEL = Firefly1DModel()
SPACE = MODEL.theta_space


def theta_of(g_a: float, sigma0: float) -> torch.Tensor:
    return SPACE.from_dict({"g_a": g_a, "log_sigma0": math.log(sigma0)})


def belief_env(batch=(), **kwargs) -> TransformedEnv:
    return TransformedEnv(
        Firefly1DEnv(batch_size=batch, **kwargs), Compose(EKFBelief(MODEL), BeliefReward(MODEL))
    )


def run(env, actions: torch.Tensor) -> list[TensorDict]:
    """Step ``env`` through ``actions [T, *B]`` from a reset; the list of root tensordicts."""
    td = env.reset()
    out = [td.clone()]
    for a in actions:
        td.set("action", a)
        td = env.step(td)
        out.append(td.clone())
        td = step_mdp(td)
    return out


@pytest.mark.parametrize("batch", [(), (8,)])
@pytest.mark.parametrize("with_belief", [False, True])
def test_check_env_specs(batch, with_belief):
    env = belief_env(batch, seed=1) if with_belief else Firefly1DEnv(batch_size=batch, seed=1)
    check_env_specs(env, seed=0)
    td = env.reset()
    assert td["theta"].shape == (*batch, SPACE.dim)
    assert td["state"].shape == (*batch, 1) and td["target"].shape == (*batch, 1)
    if with_belief:
        assert td["belief", "mean"].shape == (*batch, 1)
        assert td["belief", "cov"].shape == (*batch, 1, 1)


def test_belief_follows_agent_theta_and_world_follows_task_theta():
    """Belief: μ_t = μ₀ + g_a(agent)·Σ moves and σ²_t = 1e-4 + t·σ₀(agent)² exactly.

    World: state increments for 'right' are task g_a + N(0, task σ₀²). With 4000 envs and a
    fixed seed, the mean increment must be within 4 standard errors of 0.6 and the sample
    standard deviation within 5% of the task σ₀ = 0.5 (its relative SE is ~1.1%).
    """
    agent, task = theta_of(1.4, 0.1), theta_of(0.6, 0.5)
    n, steps = 4000, 6
    env = belief_env((n,), theta=agent, task_theta=task, seed=7)
    g = torch.Generator().manual_seed(0)
    moves = torch.where(torch.rand(steps, n, generator=g) < 0.5, LEFT, RIGHT)
    moves[:, :5] = RIGHT  # a few envs only ever go right
    tds = run(env, moves)
    mean0 = tds[0]["belief", "mean"]
    assert torch.equal(mean0, tds[0]["state"])  # the agent knows where it starts
    torch.testing.assert_close(tds[0]["belief", "cov"], torch.full((n, 1, 1), 1e-4))
    cum = torch.zeros(n, 1)
    for t in range(1, steps + 1):
        cum += (moves[t - 1] - STOP).unsqueeze(-1).float()
        nxt = tds[t]["next"]
        torch.testing.assert_close(nxt["belief", "mean"], mean0 + 1.4 * cum, atol=1e-5, rtol=0)
        torch.testing.assert_close(
            nxt["belief", "cov"], torch.full((n, 1, 1), 1e-4 + t * 0.1**2), atol=1e-6, rtol=1e-5
        )
        assert torch.equal(nxt["theta"], agent.expand(n, -1))
        assert torch.equal(nxt["task_theta"], task.expand(n, -1))
    # the world: increments of the state over one move, divided by the move's sign
    states = torch.stack([tds[0]["state"]] + [td["next", "state"] for td in tds[1:]])
    sign = (moves - STOP).unsqueeze(-1).float()
    increments = ((states[1:] - states[:-1]) * sign).flatten()
    se = 0.5 / math.sqrt(increments.numel())
    assert abs(increments.mean().item() - 0.6) < 4 * se
    assert abs(increments.std().item() / 0.5 - 1) < 0.05
    # the belief drifted far from the world: the agent's gain is wrong
    assert (tds[-1]["next", "belief", "mean"] - tds[-1]["next", "state"]).abs().mean() > 1.0


def test_belief_reward_stop_and_move():
    """On stop the reward is 10·P(|x − target| < r) under N(μ, σ²); a move pays −move_cost."""
    env = belief_env((64,), theta=theta_of(1.0, 0.6), seed=3)
    actions = torch.full((6, 64), RIGHT)
    actions[5] = STOP
    tds = run(env, actions)
    for td in tds[1:6]:
        torch.testing.assert_close(td["next", "reward"], torch.full((64, 1), -0.3))
    last = tds[6]
    mean, var = last["belief", "mean"].squeeze(-1), last["belief", "cov"].reshape(-1)
    target, radius = last["target"].squeeze(-1), 1.0
    sd = var.sqrt().double().numpy()
    d = (mean - target).double().numpy()
    expected = 10 * (stats.norm.cdf((radius - d) / sd) - stats.norm.cdf((-radius - d) / sd))
    torch.testing.assert_close(
        last["next", "reward"].squeeze(-1).double(),
        torch.from_numpy(expected),
        atol=1e-5,
        rtol=1e-4,
    )
    assert last["next", "done"].all() and last["next", "terminated"].all()
    assert not last["next", "truncated"].any()
    # the world's own reward (no BeliefReward) is 10 · 1{|x − target| < r}
    world = Firefly1DEnv(batch_size=(64,), theta=theta_of(1.0, 0.6), seed=3)
    wtds = run(world, actions)
    inside = ((wtds[6]["state"] - wtds[6]["target"]).abs() < 1.0).float() * 10
    torch.testing.assert_close(wtds[6]["next", "reward"], inside)


def test_timeout_truncates():
    model = Firefly1DModel(max_steps=3)
    env = Firefly1DEnv(batch_size=(2,), model=model, theta=SPACE.default())
    tds = run(env, torch.full((3, 2), RIGHT))
    assert not tds[2]["next", "done"].any()
    assert tds[3]["next", "done"].all() and tds[3]["next", "truncated"].all()


def test_seeding():
    def rollout(seed):
        env = belief_env((16,), seed=seed)
        torch.manual_seed(0)  # the random policy uses the global generator
        return env.rollout(40, break_when_any_done=False)

    a, b, c = rollout(5), rollout(5), rollout(6)
    assert (a == b).all()
    assert not torch.equal(a["target"], c["target"])
    assert not torch.equal(a["theta"], c["theta"])
    env = belief_env((16,))
    env.set_seed(5)
    torch.manual_seed(0)
    assert (env.rollout(40, break_when_any_done=False) == a).all()


def test_theta_held_across_auto_resets_or_resampled():
    held = theta_of(0.7, 0.2)
    env = belief_env((32,), theta=held, seed=0)
    torch.manual_seed(0)
    r = env.rollout(60, break_when_any_done=False)
    assert r["next", "done"].sum() > 32  # many trials ended and were auto-reset
    assert torch.equal(r["theta"], held.expand(32, 60, -1))
    assert torch.equal(r["task_theta"], held.expand(32, 60, -1))

    free = belief_env((32,), seed=0)
    torch.manual_seed(0)
    r = free.rollout(60, break_when_any_done=False)
    theta = r["theta"]
    assert (theta >= SPACE.low()).all() and (theta <= SPACE.high()).all()
    assert torch.equal(r["task_theta"], theta)  # task θ defaults to the agent's
    assert (theta[..., 2] == 1.0).all() and (theta[..., 3] == 0.3).all()  # fixed parameters
    # θ is constant within a trial and changes after a reset
    done = r["next", "done"][..., 0]
    same_next = (theta[:, 1:] == theta[:, :-1]).all(-1)
    assert same_next[~done[:, :-1]].all()
    assert not same_next[done[:, :-1]].any()
    distinct = torch.unique(theta[..., 0]).numel()
    assert distinct > 32 + 10


def test_reset_kwargs_through_transformed_env():
    env = belief_env((4,), seed=0)
    agent, task = theta_of(1.3, 0.05), theta_of(0.8, 0.9)
    td = env.reset(theta=agent, task_theta=task)
    assert torch.equal(td["theta"], agent.expand(4, -1))
    assert torch.equal(td["task_theta"], task.expand(4, -1))
    td.set("action", torch.full((4,), RIGHT))
    nxt = env.step(td)["next"]
    torch.testing.assert_close(nxt["belief", "mean"], td["belief", "mean"] + 1.3)
    torch.testing.assert_close(nxt["belief", "cov"], torch.full((4, 1, 1), 1e-4 + 0.05**2))
    # one reset only: the next reset draws again
    assert not torch.equal(env.reset()["theta"], agent.expand(4, -1))


@pytest.mark.parametrize(
    "argument, message",
    [
        ({"max_steps": 0}, "max_steps: expected an integer ≥ 1, got 0"),
        ({"max_steps": 2.5}, "max_steps: expected an integer ≥ 1, got 2.5"),
        ({"target_range": float("nan")}, "target_range: expected a positive finite number"),
        ({"target_range": -5.0}, "target_range: expected a positive finite number, got -5.0"),
        ({"reward_value": float("inf")}, "reward_value: expected a positive finite number"),
    ],
)
def test_a_task_that_cannot_run_is_refused(argument, message):
    with pytest.raises(ValueError, match=message):
        Firefly1DModel(**argument)


def test_bad_inputs():
    bad = SPACE.default().clone()
    bad[0] = 3.0
    with pytest.raises(ValueError, match=r"theta: g_a=3"):
        Firefly1DEnv(theta=bad)
    with pytest.raises(ValueError, match=r"task_theta: g_a=3"):
        Firefly1DEnv(task_theta=bad)
    with pytest.raises(ValueError, match="theta"):
        Firefly1DEnv(theta=torch.ones(3))
    with pytest.raises(ValueError, match="task_theta"):
        Firefly1DEnv(batch_size=(4,), task_theta=SPACE.default().expand(3, -1))
    env = belief_env((2,))
    with pytest.raises(ValueError, match="theta: g_a=3"):
        env.reset(theta=bad)
    with pytest.raises(ValueError, match="task_theta"):
        env.reset(task_theta=torch.ones(5))
    td = env.reset()
    td.set("action", torch.tensor([5, 1]))
    with pytest.raises(ValueError, match="action"):
        env.step(td)


def test_targets_are_uniform_over_the_whole_range_on_both_sides():
    """4000 first targets of ``target_range`` 12: uniform on [−12, 12] (a half on each side
    within 0.03, sd 0.008; quartiles ±6 within 0.6, sd 0.2; both ends reached within 0.3)."""
    target = Firefly1DEnv(batch_size=(4000,), seed=0).reset()["target"][:, 0]
    assert target.abs().max() <= 12
    assert abs((target < 0).double().mean().item() - 0.5) < 0.03
    quartiles = torch.quantile(target, torch.tensor([0.25, 0.5, 0.75]))
    torch.testing.assert_close(quartiles, torch.tensor([-6.0, 0.0, 6.0]), atol=0.6, rtol=0)
    assert target.min() < -11.7 and target.max() > 11.7


def test_belief_features_are_the_documented_scaled_quantities():
    """For beliefs N(±0.5 from the target, 0.3²) at step 6 of 30: position over the target
    range and its size, the std, the time fraction, P(|x − target| < 1) from scipy and θ in
    [−1, 1] (g_a 1.4 → 0.8, σ₀ 0.1 → 2 log 2 / log 20 − 1, radius 1 → −1/3, cost 0.3 → −9/19)."""
    theta = theta_of(1.4, 0.1)
    mean = torch.tensor([[2.5], [1.5]])
    features = MODEL.belief_features(
        mean, torch.full((2, 1, 1), 0.09), torch.tensor([[2.0]]), torch.tensor([[6]]), theta
    )
    p_goal = stats.norm.cdf(0.5 / 0.3) - stats.norm.cdf(-1.5 / 0.3)
    unit = [0.8, 2 * math.log(2) / math.log(20) - 1, -1 / 3, -9 / 19]
    expected = torch.tensor(
        [[sign * 0.5 / 12, 0.5 / 12, 0.3, 0.2, p_goal, *unit] for sign in (1, -1)],
        dtype=torch.float32,
    )
    torch.testing.assert_close(features, expected, atol=1e-6, rtol=1e-5)


def test_the_world_pays_inside_the_goal_radius_of_theta_and_charges_its_move_cost():
    """With the radius and cost free at 0.5 and 0.6, a stop 0.4 from the target pays 10, one
    0.7 from it nothing (it would pay 10 within the default radius 1), and a move costs 0.6."""
    space = SPACE.free()
    theta = space.from_dict({"goal_radius": 0.5, "move_cost": 0.6})
    model = Firefly1DModel(theta_space=space)
    state, target = torch.tensor([[0.4], [-0.7], [3.0]]), torch.zeros(3, 1)
    action = torch.tensor([STOP, STOP, RIGHT])
    reward = model.reward(state, target, action, model.stops(action, torch.zeros(3, 1)), theta)
    torch.testing.assert_close(reward, torch.tensor([[10.0], [0.0], [-0.6]]))


def test_another_tasks_theta_space_is_refused_and_a_parameter_read_by_name():
    """A θ space of other parameters (the 2D task's) once built a model that failed on its
    first step; each parameter is read by its name, an unknown name listing the valid ones."""
    from irc_torchrl.envs.firefly2d import firefly2d_theta_space

    with pytest.raises(ValueError, match=r"theta_space: expected parameters \['g_a', 'log_sigma0'"):
        Firefly1DModel(theta_space=firefly2d_theta_space())
    theta = SPACE.from_dict({"g_a": 1.25})
    assert MODEL.parameter(theta, "g_a").tolist() == [1.25]
    assert MODEL.parameter(theta.expand(4, 3, -1), "log_sigma0").shape == (4, 3, 1)
    with pytest.raises(KeyError, match="g_v"):
        MODEL.parameter(theta, "g_v")


def test_reset_redraws_theta_even_from_a_tensordict_that_holds_one():
    """A ``theta`` in the TensorDict given to ``reset`` is the ending trial's: it is not read,
    so a manual ``env.reset(td)`` draws a new θ from the prior (reading it would hold θ)."""
    env = Firefly1DEnv(batch_size=(8,), seed=0)
    first = env.reset()
    again = env.reset(first.clone())
    assert (again["theta"][:, 0] != first["theta"][:, 0]).all()


def test_the_world_pays_by_the_task_theta_not_the_agents():
    """The world's reward reads ``task_theta``: a stop at the start pays 10 exactly where the
    target is within the task's radius 2.0 (not the agent's 0.5) and a move costs the task's
    0.8 (not the agent's 0.05); 256 trials, seed 0."""
    space = SPACE.free()
    agent = space.from_dict({"goal_radius": 0.5, "move_cost": 0.05})
    task = space.from_dict({"goal_radius": 2.0, "move_cost": 0.8})
    model = Firefly1DModel(theta_space=space)
    env = Firefly1DEnv(model=model, batch_size=(256,), theta=agent, task_theta=task, seed=0)
    td = env.reset()
    action = torch.where(torch.arange(256) % 2 == 0, STOP, RIGHT)
    out = env.step(td.set("action", action))["next"]
    inside = (td["target"].abs() < 2.0).float() * 10
    expected = torch.where((action == STOP).unsqueeze(-1), inside, torch.tensor(-0.8))
    torch.testing.assert_close(out["reward"], expected)
    assert 0 < inside[::2].count_nonzero() < 128  # the radii disagree on some stops


def test_a_stop_on_the_last_step_terminates_without_truncating():
    """At the time limit a trial terminates (nothing follows to bootstrap from) and is also
    truncated, unless the agent stopped there: then it ended by its own stop only."""
    model = Firefly1DModel(max_steps=3)
    env = Firefly1DEnv(batch_size=(2,), model=model, theta=SPACE.default())
    actions = torch.tensor([[RIGHT, RIGHT], [RIGHT, RIGHT], [STOP, RIGHT]])
    last = run(env, actions)[3]["next"]
    assert last["done"].squeeze(-1).tolist() == [True, True]
    assert last["terminated"].squeeze(-1).tolist() == [True, True]
    assert last["truncated"].squeeze(-1).tolist() == [False, True]
    assert last["step"].squeeze(-1).tolist() == [3, 3]
