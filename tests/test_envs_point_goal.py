"""The point task families: env contract, task protocol, rewards and the hazard."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

import sb3_pearl  # noqa: F401
from tests.conftest import ENV_ID


@pytest.mark.parametrize("env_id", ["PointGoalMeta-v0", "SafePointGoalMeta-v0"])
def test_check_env_and_task_protocol(env_id: str) -> None:
    env = gym.make(env_id)
    check_env(env.unwrapped, warn=False)
    base = env.unwrapped
    tasks = base.sample_tasks(5, seed=3)
    assert tasks == base.sample_tasks(5, seed=3) and tasks != base.sample_tasks(5, seed=4)
    base.set_task(tasks[1])
    assert base.get_task() == tasks[1]
    for _ in range(2):  # sticky across resets
        env.reset()
        assert base.get_task() == tasks[1]
    _, _, _, _, info = env.step(np.zeros(2, dtype=np.float32))
    assert info["cost"] == 0.0


def test_point_goal_reward_and_ranges() -> None:
    env = gym.make("PointGoalMeta-v0")
    base = env.unwrapped
    goals = np.array([t["goal"] for t in base.sample_tasks(200, seed=0)])
    assert goals.min() >= -1.0 and goals.max() <= 1.0
    base.set_task({"goal": [0.3, -0.4]})
    env.reset()
    obs, reward, *_ = env.step(np.array([0.1, 0.5], dtype=np.float32))  # clipped to (0.1, 0.1)
    np.testing.assert_allclose(obs, [0.1, 0.1])
    assert reward == pytest.approx(-np.hypot(0.2, 0.5))
    shifted = gym.make("PointGoalMeta-v0", goal_low=2.0, goal_high=3.0).unwrapped.sample_tasks(10, seed=0)
    assert all(2.0 <= g <= 3.0 for t in shifted for g in t["goal"])
    with pytest.raises(ValueError, match="goal_low"):
        gym.make("PointGoalMeta-v0", goal_low=1.0, goal_high=1.0)


def test_set_task_takes_effect_at_reset_and_validates() -> None:
    env = gym.make("PointGoalMeta-v0")
    base = env.unwrapped
    base.set_task({"goal": [1.0, 0.0]})
    env.reset()
    base.set_task({"goal": [-1.0, 0.0]})
    _, reward, *_ = env.step(np.zeros(2, dtype=np.float32))
    assert reward == pytest.approx(-1.0)  # still the old goal until reset
    env.reset()
    _, reward, *_ = env.step(np.array([0.1, 0.0], dtype=np.float32))
    assert reward == pytest.approx(-1.1)
    with pytest.raises(ValueError, match="task keys"):
        base.set_task({"velocity": 1.0})


def test_safe_point_tasks_goal_on_arc_hazard_rotated_towards_the_middle() -> None:
    base = gym.make("SafePointGoalMeta-v0").unwrapped
    tasks = base.sample_tasks(200, seed=0)
    goals = np.array([t["goal"] for t in tasks])
    hazards = np.array([t["hazard"] for t in tasks])
    np.testing.assert_allclose(np.linalg.norm(goals, axis=1), 1.0)
    np.testing.assert_allclose(np.linalg.norm(hazards, axis=1), 0.6)
    goal_angles = np.arctan2(goals[:, 1], goals[:, 0])
    hazard_angles = np.arctan2(hazards[:, 1], hazards[:, 0])
    assert goal_angles.min() >= np.pi / 6 - 1e-9 and goal_angles.max() <= 5 * np.pi / 6 + 1e-9
    expected = np.where(goal_angles < np.pi / 2, goal_angles + np.pi / 3, goal_angles - np.pi / 3)
    np.testing.assert_allclose(hazard_angles, expected, atol=1e-9)
    # the straight path to a task's own goal never touches its hazard (closest approach > radius)
    for goal, hazard in zip(goals, hazards):
        closest = goal * np.clip(goal @ hazard, 0.0, 1.0)  # projection of the hazard centre on the path
        assert np.linalg.norm(hazard - closest) > 0.25


def test_safe_point_hazard_ends_episode_with_cost_and_penalty() -> None:
    env = gym.make("SafePointGoalMeta-v0")
    base = env.unwrapped
    # goal at 30 degrees -> hazard at 90 degrees, centre (0, 0.6)
    base.set_task({"goal": [np.cos(np.pi / 6), 0.5], "hazard": [0.0, 0.6]})
    env.reset()
    rewards, costs = [], []
    for t in range(1, 6):  # straight up, 0.08 per step: 0.08 .. 0.32 outside (distance > 0.25), 0.40 inside
        _, reward, terminated, truncated, info = env.step(np.array([0.0, 0.08], dtype=np.float32))
        rewards.append(reward)
        costs.append(info["cost"])
        assert terminated == (t == 5) and not truncated
    assert costs == [0.0, 0.0, 0.0, 0.0, 1.0]
    distance = np.hypot(np.cos(np.pi / 6), 0.5 - 0.40)
    assert rewards[4] == pytest.approx(-distance - 2.0 * (30 - 5))  # 2.0 per skipped step
    # heading for the task's own goal is safe for the whole episode
    env.reset()
    direction = np.array([np.cos(np.pi / 6), 0.5])
    for _ in range(30):
        _, _, terminated, truncated, info = env.step((0.1 * direction).astype(np.float32))
        assert not terminated and info["cost"] == 0.0
    assert truncated


def test_rendering_rgb_array() -> None:
    env = gym.make("SafePointGoalMeta-v0", render_mode="rgb_array")
    env.reset()
    frame = env.render()
    assert frame.shape == (128, 128, 3) and frame.dtype == np.uint8
    assert (frame == np.array([220, 60, 60], dtype=np.uint8)).all(axis=-1).sum() > 50  # the hazard is drawn


def test_safe_point_refuses_a_hazard_over_the_start() -> None:
    env = gym.make(ENV_ID).unwrapped
    with pytest.raises(ValueError, match=r"the hazard \[0.1, 0.0\] covers the start \(0, 0\)"):
        env.set_task({"goal": [0.0, 1.0], "hazard": [0.1, 0.0]})


def test_a_nan_action_is_not_counted_as_a_safe_step() -> None:
    env = gym.make(ENV_ID)  # guards against: stepped, position nan, cost 0.0
    env.reset(seed=0)
    with pytest.raises(ValueError, match="SafePointGoalMetaEnv.step: the action"):
        env.step(np.array([np.nan, 0.0], dtype=np.float32))
