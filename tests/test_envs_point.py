"""The sparse point robot and the PointMaze family: env contract, task protocol, rewards, reachability."""

from __future__ import annotations

import json
import math
import pickle
from collections import deque

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

import sb3_pearl  # noqa: F401  (registers the envs)
from sb3_pearl.envs.point_maze_goal import free_cells
from tests.conftest import family_class

POINT_IDS = ["SparsePointGoalMeta-v0", "PointMazeGoalMeta-v0"]


@pytest.mark.parametrize("env_id", POINT_IDS)
def test_check_env_and_task_protocol(env_id: str) -> None:
    env = gym.make(env_id)
    check_env(env.unwrapped, warn=False)
    assert isinstance(env.observation_space, gym.spaces.Box)
    base = env.unwrapped
    tasks = base.sample_tasks(5, seed=3)
    assert tasks == base.sample_tasks(5, seed=3) and tasks != base.sample_tasks(5, seed=4)
    assert json.loads(json.dumps(tasks)) == tasks  # JSON-serialisable task dicts
    base.set_task(tasks[1])
    assert base.get_task() == tasks[1]
    for seed in (0, 1):  # sticky across resets
        _, info = env.reset(seed=seed)
        assert base.get_task() == tasks[1] and info["cost"] == 0.0
        _, _, terminated, _, info = env.step(np.zeros(2, dtype=np.float32))
        assert info["cost"] == 0.0 and not terminated
    assert env.spec is not None and env.spec.max_episode_steps == {"SparsePointGoalMeta-v0": 20}.get(env_id, 300)


def test_sparse_point_goals_on_half_circle() -> None:
    base = gym.make("SparsePointGoalMeta-v0").unwrapped
    goals = np.array([t["goal"] for t in base.sample_tasks(200, seed=0)])
    np.testing.assert_allclose(np.linalg.norm(goals, axis=1), 1.0)
    assert goals[:, 1].min() >= 0.0 and goals[:, 0].min() < -0.95 and goals[:, 0].max() > 0.95
    shifted = gym.make("SparsePointGoalMeta-v0", goal_angle_low=math.pi, goal_angle_high=2 * math.pi).unwrapped
    assert all(t["goal"][1] <= 1e-12 for t in shifted.sample_tasks(20, seed=0))
    with pytest.raises(ValueError, match="goal_angle_low"):
        gym.make("SparsePointGoalMeta-v0", goal_angle_low=1.0, goal_angle_high=0.5)
    with pytest.raises(ValueError, match="reward_radius"):
        gym.make("SparsePointGoalMeta-v0", reward_radius=0.0)


def test_sparse_reward_zero_outside_radius() -> None:
    env = gym.make("SparsePointGoalMeta-v0")
    env.unwrapped.set_task({"goal": [0.0, 1.0]})
    env.reset()
    rewards, dense = [], []
    for _ in range(14):  # straight up: distances 0.93, 0.86, ..., 0.23 (outside), 0.16, 0.09, 0.02 (inside)
        _, reward, _, _, info = env.step(np.array([0.0, 0.07], dtype=np.float32))
        rewards.append(reward)
        dense.append(info["dense_reward"])
    distances = 1.0 - np.float32(0.07) * np.arange(1, 15)
    np.testing.assert_allclose(dense, -distances, atol=1e-9)
    inside = distances <= 0.2
    assert inside.sum() == 3
    assert all(r == 0.0 for r in np.array(rewards)[~inside])  # exactly zero outside the radius
    np.testing.assert_allclose(np.array(rewards)[inside], 1.0 - distances[inside], atol=1e-9)
    # another goal on the half circle: the same path earns nothing
    env.unwrapped.set_task({"goal": [1.0, 0.0]})
    env.reset()
    assert all(env.step(np.array([0.0, 0.1], dtype=np.float32))[1] == 0.0 for _ in range(20))


def test_point_maze_observation_hides_goal_and_reward_is_dense() -> None:
    env = gym.make("PointMazeGoalMeta-v0")
    base = env.unwrapped
    assert env.observation_space.shape == (4,)  # x, y, vx, vy: no desired_goal
    obs_by_task, rewards_by_task = [], []
    for task in base.sample_tasks(2, seed=0):
        base.set_task(task)
        obs, _ = env.reset(seed=7)
        observations, rewards = [obs], []
        for _ in range(5):
            obs, reward, _, _, info = env.step(np.array([1.0, 0.0], dtype=np.float32))
            goal = np.asarray(task["goal"])
            assert reward == pytest.approx(math.exp(-np.linalg.norm(obs[:2] - goal)))  # PointMaze's dense reward
            assert info["success"] == (np.linalg.norm(obs[:2] - goal) <= 0.45)
            observations.append(obs)
            rewards.append(reward)
        np.testing.assert_allclose(base.maze_env.goal, task["goal"])  # the goal in force is the task's
        obs_by_task.append(np.array(observations))
        rewards_by_task.append(rewards)
    np.testing.assert_allclose(obs_by_task[0], obs_by_task[1])  # same seed: the observations cannot tell the tasks
    assert rewards_by_task[0] != pytest.approx(rewards_by_task[1])  # the rewards can
    start = base.maze.cell_rowcol_to_xy(np.array(base.start_cell))
    assert np.abs(obs_by_task[0][0][:2] - start).max() <= 0.25  # start cell plus PointMaze's reset noise


def test_point_maze_tasks_in_goal_cells_and_validated() -> None:
    base = gym.make("PointMazeGoalMeta-v0").unwrapped
    free = free_cells(base.maze.maze_map)
    assert len(free) == 26 and len(base.goal_cells) == 25 and base.start_cell not in base.goal_cells
    tasks = base.sample_tasks(300, seed=0)
    assert {tuple(t["goal_cell"]) for t in tasks} == set(base.goal_cells)
    for task in tasks:
        centre = base.maze.cell_rowcol_to_xy(np.array(task["goal_cell"]))
        assert np.abs(np.asarray(task["goal"]) - centre).max() <= 0.25
    # disjoint train / test cells: one kwarg
    test_cells = [(6, 5), (6, 6), (5, 6)]
    held_out = gym.make("PointMazeGoalMeta-v0", goal_cells=test_cells).unwrapped.sample_tasks(20, seed=0)
    assert {tuple(t["goal_cell"]) for t in held_out} == set(test_cells)
    with pytest.raises(ValueError, match="wall or the start"):
        base.set_task({"goal_cell": [0, 0], "goal": [-3.5, 3.5]})
    with pytest.raises(ValueError, match="not inside"):
        base.set_task({"goal_cell": [6, 5], "goal": [0.0, 0.0]})
    for kwargs, match in [
        ({"maze": "huge"}, "maze must be"),
        ({"start_cell": (0, 0)}, "start_cell"),
        ({"goal_cells": [(0, 0)]}, "goal_cells"),
        ({"goal_cells": []}, "empty"),
        ({"goal_noise": 0.5}, "goal_noise"),
        ({"reward_type": "shaped"}, "reward_type"),
    ]:
        with pytest.raises(ValueError, match=match):
            gym.make("PointMazeGoalMeta-v0", **kwargs)
    umaze = gym.make("PointMazeGoalMeta-v0", maze="umaze").unwrapped
    assert len(umaze.goal_cells) == 6
    clone = pickle.loads(pickle.dumps(base))
    assert clone.sample_tasks(3, seed=1) == base.sample_tasks(3, seed=1)


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize(
    "env_id, kwargs, match",
    [
        ("PointGoalMeta-v0", {"goal_low": NAN}, r"goal_low and goal_high must be finite"),
        ("PointGoalMeta-v0", {"goal_high": INF}, r"goal_low and goal_high must be finite"),
        ("PointGoalMeta-v0", {"max_step": 0.0}, r"max_step must be a finite number > 0 .*got 0.0"),
        ("PointGoalMeta-v0", {"max_step": NAN}, r"max_step must be a finite number > 0"),
        ("SafePointGoalMeta-v0", {"hazard_radius": -0.3}, r"hazard_radius must be a finite number > 0 .*got -0.3"),
        ("SafePointGoalMeta-v0", {"hazard_radius": NAN}, r"hazard_radius must be a finite number > 0 .*got nan"),
        ("SafePointGoalMeta-v0", {"goal_radius": NAN}, r"goal_radius must be a finite number in \(0, 2\) .*got nan"),
        ("SafePointGoalMeta-v0", {"goal_radius": -1.0}, r"goal_radius must be a finite number in \(0, 2\)"),
        ("SafePointGoalMeta-v0", {"goal_angle_low": NAN}, r"goal_angle_low and goal_angle_high must be finite"),
        ("SafePointGoalMeta-v0", {"hazard_offset": INF}, r"hazard_offset must be a finite number"),
        ("SafePointGoalMeta-v0", {"hazard_distance": NAN}, r"hazard_distance must be a finite number > 0"),
        ("SafePointGoalMeta-v0", {"crash_penalty": -1.0}, r"crash_penalty must be a finite number >= 0"),
        ("SafePointGoalMeta-v0", {"crash_penalty": NAN}, r"crash_penalty must be a finite number >= 0"),
        ("SafePointGoalMeta-v0", {"max_episode_steps": 0}, r"max_episode_steps must be an integer >= 1"),
        ("SparsePointGoalMeta-v0", {"reward_radius": INF}, r"reward_radius must be a finite number > 0"),
        ("SparsePointGoalMeta-v0", {"max_step": NAN}, r"max_step must be a finite number > 0"),
        ("PointMazeGoalMeta-v0", {"start_cell": (1.5, 1)}, r"start_cell must be \[row, column\], two integers"),
        ("PointMazeGoalMeta-v0", {"goal_cells": [(6.5, 2)]}, r"goal_cells\[0\] must be \[row, column\], two integers"),
        ("PointMazeGoalMeta-v0", {"goal_cells": [(6, True)]}, r"goal_cells\[0\] must be \[row, column\], two integers"),
    ],
)
def test_point_families_refuse_kwargs_that_hide_violations(env_id: str, kwargs: dict[str, object], match: str) -> None:
    """A non-finite or out-of-range kwarg is refused naming it: a negative or nan hazard radius would build an env on
    which nothing is ever a violation."""
    with pytest.raises(ValueError, match=match):
        family_class(env_id)(**kwargs)  # the class itself: gym.make takes max_episode_steps for its TimeLimit


def test_point_maze_converts_integer_valued_float_cells() -> None:
    """Cells given as integer-valued floats (YAML, JSON) are taken as the integers they are: in the kwargs and in a
    task's goal_cell, which reaches gymnasium-robotics as integers (a float cell crashed its reset)."""
    env = gym.make("PointMazeGoalMeta-v0", start_cell=(1.0, 1.0), goal_cells=[[6.0, 2.0]])
    base = env.unwrapped
    assert base.start_cell == (1, 1) and base.goal_cells == [(6, 2)]
    task = base.sample_tasks(1, seed=0)[0]
    assert task["goal_cell"] == [6, 2] and all(type(c) is int for c in task["goal_cell"])
    base.set_task({"goal_cell": [6.0, 2.0], "goal": task["goal"]})
    assert base.get_task()["goal_cell"] == [6, 2] and all(type(c) is int for c in base.get_task()["goal_cell"])
    env.reset(seed=0)
    env.step(np.zeros(2, dtype=np.float32))
    with pytest.raises(ValueError, match="goal_cell must be .*an integer"):
        base.set_task({"goal_cell": [6.5, 2.0], "goal": task["goal"]})


def _bfs_path(free: set[tuple[int, int]], start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]]:
    previous: dict[tuple[int, int], tuple[int, int] | None] = {start: None}
    queue = deque([start])
    while queue:
        cell = queue.popleft()
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nxt = (cell[0] + di, cell[1] + dj)
            if nxt in free and nxt not in previous:
                previous[nxt] = cell
                queue.append(nxt)
    path = [goal]
    while (prev := previous[path[-1]]) is not None:
        path.append(prev)
    return path[::-1]


def test_point_maze_every_goal_reachable_within_horizon() -> None:
    """A scripted waypoint controller reaches every goal (worst case of the goal noise) within the 300-step limit."""
    env = gym.make("PointMazeGoalMeta-v0")
    base = env.unwrapped
    free = set(free_cells(base.maze.maze_map))
    for cell in base.goal_cells:
        centre = base.maze.cell_rowcol_to_xy(np.array(cell))
        base.set_task({"goal_cell": list(cell), "goal": (centre + 0.249).tolist()})
        obs, _ = env.reset(seed=1)
        waypoints = [base.maze.cell_rowcol_to_xy(np.array(c)) for c in _bfs_path(free, base.start_cell, cell)[1:-1]]
        waypoints.append(base.goal)
        k, reached, truncated = 0, False, False
        while not (reached or truncated):
            action = np.clip(10.0 * (waypoints[k] - obs[:2]) - obs[2:], -1.0, 1.0).astype(np.float32)
            obs, _, _, truncated, info = env.step(action)
            if k < len(waypoints) - 1 and np.linalg.norm(waypoints[k] - obs[:2]) < 0.4:
                k += 1
            reached = info["success"]
        assert reached, f"goal cell {cell} not reached within the horizon"


def test_point_maze_renders_headless() -> None:
    pytest.importorskip("mujoco")
    import os

    if os.environ.get("MUJOCO_GL") not in ("egl", "osmesa"):
        pytest.skip("headless MuJoCo rendering needs MUJOCO_GL=egl or osmesa")
    env = gym.make("PointMazeGoalMeta-v0", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    env.close()
    assert frame is not None and frame.ndim == 3 and frame.std() > 0
