"""Environments, the agent's belief filter and belief features (mirrors ``torchrl.envs``)."""

from irc_torchrl.envs.belief import (
    BeliefFeatures,
    BeliefReward,
    EKFBelief,
    ekf_predict,
    ekf_step,
    ekf_update,
)
from irc_torchrl.envs.firefly1d import Firefly1DEnv, Firefly1DModel, firefly1d_theta_space
from irc_torchrl.envs.firefly2d import (
    Firefly2DEnv,
    Firefly2DModel,
    firefly2d_theta_space,
    seed_paper_theta_space,
)
from irc_torchrl.envs.gym_adapter import GYM_ID, Firefly2DGymEnv, register_gym
from irc_torchrl.envs.model import TaskModel
from irc_torchrl.envs.probe import check_model
from irc_torchrl.envs.task_env import TaskEnv

__all__ = [
    "BeliefFeatures",
    "BeliefReward",
    "EKFBelief",
    "Firefly1DEnv",
    "Firefly1DModel",
    "Firefly2DEnv",
    "Firefly2DGymEnv",
    "Firefly2DModel",
    "GYM_ID",
    "TaskEnv",
    "TaskModel",
    "check_model",
    "ekf_predict",
    "ekf_step",
    "ekf_update",
    "firefly1d_theta_space",
    "firefly2d_theta_space",
    "register_gym",
    "seed_paper_theta_space",
]

register_gym()
