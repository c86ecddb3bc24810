"""The gymnasium adapter of the 2D task: registration, the checker, seeding, θ, episodes."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import irc_torchrl.envs  # noqa: F401  (registers the id)
from irc_torchrl.envs import GYM_ID, Firefly2DGymEnv, Firefly2DModel

torch.set_num_threads(1)


def test_registered_and_passes_gymnasium_checker():
    env = gym.make(GYM_ID)
    assert isinstance(env.unwrapped, Firefly2DGymEnv)
    check_env(env.unwrapped, skip_render_check=True)


def test_observation_is_the_feature_vector():
    env = Firefly2DGymEnv(theta={"g_v": 1.0})
    obs, info = env.reset(seed=0)
    model = Firefly2DModel()
    assert obs.shape == (model.belief_feature_dim + model.theta_space.dim,)
    assert obs.dtype == np.float32 and env.observation_space.contains(obs)
    assert info["theta"][0] == pytest.approx(1.0)
    np.testing.assert_allclose(
        obs[model.belief_feature_dim :],
        model.theta_space.normalise(torch.as_tensor(info["theta"])).numpy(),
        atol=1e-6,
    )


def test_seeded_episodes_are_reproducible_and_end():
    def episode(seed):
        env = Firefly2DGymEnv()
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(0)
        observations, rewards = [obs], []
        for _ in range(200):
            action = np.array([rng.uniform(0.2, 1.0), rng.uniform(-1, 1)], dtype=np.float32)
            obs, reward, terminated, truncated, _ = env.step(action)
            observations.append(obs)
            rewards.append(reward)
            if terminated or truncated:
                return np.array(observations), rewards, terminated, truncated
        raise AssertionError("the episode did not end")

    a, b, c = episode(3), episode(3), episode(4)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1] and not np.array_equal(a[0][0], c[0][0])
    # never stopped: the time limit ends the trial, and nothing follows it to bootstrap from
    assert a[2] and a[3] and len(a[1]) == Firefly2DModel().max_steps


def test_stopping_terminates_with_task_theta_from_options():
    env = Firefly2DGymEnv()
    task = {"g_v": 0.8, "goal_radius": 0.5}
    _, info = env.reset(seed=1, options={"theta": {"g_v": 1.5}, "task_theta": task})
    assert info["theta"][0] == pytest.approx(1.5) and info["task_theta"][0] == pytest.approx(0.8)
    for step in range(10):  # noqa: B007  (read after the loop)
        _, reward, terminated, truncated, _ = env.step(np.array([-1.0, 0.0], dtype=np.float32))
        if terminated:
            break
    assert terminated and not truncated and step == Firefly2DModel().min_steps


def test_bad_input_errors():
    with pytest.raises(ValueError, match="theta: g_v=9 is outside its space"):
        Firefly2DGymEnv(theta={"g_v": 9.0})
    with pytest.raises(KeyError, match="unknown θ parameter 'gain'"):
        Firefly2DGymEnv(task_theta={"gain": 1.0})
    env = Firefly2DGymEnv()
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(np.zeros(2, dtype=np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action: expected finite values"):
        env.step(np.array([np.nan, 0.0], dtype=np.float32))
    with pytest.raises(ValueError, match=r"action: expected shape \[2\]"):
        env.step(np.zeros(3, dtype=np.float32))


def test_sync_vector_env_over_the_adapter():
    envs = gym.vector.SyncVectorEnv([lambda: gym.make(GYM_ID) for _ in range(3)])
    obs, _ = envs.reset(seed=0)
    assert obs.shape == (3, envs.single_observation_space.shape[0])
    obs, reward, *_ = envs.step(np.full((3, 2), 0.5, dtype=np.float32))
    assert np.isfinite(obs).all() and reward.shape == (3,)
    assert not np.array_equal(obs[0], obs[1])  # sub-environments are seeded differently
    envs.close()


def test_unseeded_adapters_draw_different_trials():
    first, _ = Firefly2DGymEnv().reset()
    second, _ = Firefly2DGymEnv().reset()
    assert not np.array_equal(first, second)


def test_step_reports_the_worlds_state_and_reward_under_the_task_theta():
    """``info["state"]`` is the true state (noise-free task: v = 0.8 a_v, the task's gain, not
    the agent's 1.5 its belief predicts) and the reward is the world's, −0.05‖a‖² per move."""
    task = {"g_v": 0.8, "sigma_v": 0.0, "sigma_w": 0.0, "effort_cost": 0.05}
    env = Firefly2DGymEnv(theta={"g_v": 1.5, "effort_cost": 0.0}, task_theta=task)
    env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step(np.array([1.0, 0.5], dtype=np.float32))
    assert info["state"][3] == pytest.approx(0.8, abs=1e-2)
    assert reward == pytest.approx(-0.05 * 1.25, rel=1e-6)
    assert not terminated and not truncated
