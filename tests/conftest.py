"""Shared fixtures: tiny PEARL / PEARL+ configurations that train in a second on the CPU."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback

import sb3_pearl  # noqa: F401  (registers the envs)
from sb3_pearl.envs.point_goal import PointGoalMetaEnv

th.set_num_threads(1)

# The zoo's fast SafePointGoal entry shrunk to seconds of training, as `-params` for train.py (tests/test_cli.py,
# tests/test_newcomer.py).
TINY_ZOO_PARAMS = [
    "num_initial_steps:30",
    "num_train_steps_per_itr:5",
    "num_steps_prior:30",
    "num_extra_rl_steps_posterior:30",
    "n_train_tasks:4",
    "n_test_tasks:3",
    "meta_batch:2",
    "batch_size:16",
    "embedding_batch_size:8",
    "meta_test:dict(n_adapt=2)",
]

TINY: dict[str, Any] = dict(
    n_train_tasks=4,
    n_test_tasks=2,
    num_initial_steps=60,
    num_tasks_sample=2,
    num_steps_prior=30,
    num_steps_posterior=10,
    num_extra_rl_steps_posterior=30,
    num_train_steps_per_itr=5,
    meta_batch=3,
    batch_size=16,
    embedding_batch_size=8,
    latent_dim=3,
    encoder_arch=[16],
    prior_critic_arch=[16],
    policy_kwargs=dict(net_arch=[32, 32]),
)


class DiscretePointGoalEnv(PointGoalMetaEnv):
    """The point robot with 5 discrete moves (stay, +x, -x, +y, -y): a Discrete task family for tests."""

    MOVES = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.float64) * 0.1

    def __init__(self) -> None:
        super().__init__()
        self.action_space = spaces.Discrete(5)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        return super().step(self.MOVES[int(action)])


def make_point_env() -> gym.Env:
    """Picklable factory: a SubprocVecEnv worker imports this module, hence sb3_pearl and its env ids."""
    return gym.make("PointGoalMeta-v0")


def make_discrete_env() -> gym.Env:
    return gym.wrappers.TimeLimit(DiscretePointGoalEnv(), max_episode_steps=20)


@pytest.fixture
def tiny_kwargs() -> dict[str, Any]:
    return {key: (dict(value) if isinstance(value, dict) else value) for key, value in TINY.items()}


class CountSteps(BaseCallback):
    """Counts ``on_step`` calls (one per VecEnv step)."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def _on_step(self) -> bool:
        self.calls += 1
        return True
