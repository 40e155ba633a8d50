"""The MuJoCo task families: env contract, task protocol, hand-computed rewards, health termination and cost."""

from __future__ import annotations

import json
import math
import pickle
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

import sb3_pearl  # noqa: F401  (registers the envs)
from tests.conftest import family_class

MUJOCO_IDS = ["HalfCheetahVelMeta-v0", "Walker2dVelMeta-v0", "AntVelMeta-v0", "AntDirMeta-v0", "AntGoalMeta-v0"]
HEALTH_IDS = ["Walker2dVelMeta-v0", "AntVelMeta-v0", "AntDirMeta-v0", "AntGoalMeta-v0"]
# a task per family, and a second one with a different reward
TASKS: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "HalfCheetahVelMeta-v0": ({"velocity": 0.5}, {"velocity": 2.5}),
    "Walker2dVelMeta-v0": ({"velocity": 0.3}, {"velocity": 1.7}),
    "AntVelMeta-v0": ({"direction": 0.0, "speed": 1.0}, {"direction": math.pi / 2, "speed": 2.0}),
    "AntDirMeta-v0": ({"direction": 0.0}, {"direction": math.pi}),
    "AntGoalMeta-v0": ({"goal": [2.0, 1.0]}, {"goal": [-1.0, -2.5]}),
}


def _controlled_step(env: gym.Env, action: np.ndarray, seed: int = 0) -> tuple[float, dict[str, Any], np.ndarray, np.ndarray]:
    """
    Reset to a fixed state, step once; return the reward, info and the planar position before/after.

    The position is the root joint's ``qpos[:2]`` for the 2-D robots and the torso's ``xpos[:2]`` for
    the ant (Gymnasium measures the ant's velocity on ``data.body(1).xpos``).
    """
    env.reset(seed=seed)
    base = env.unwrapped
    base.set_state(base.init_qpos + 0.01, base.init_qvel + 0.3)  # the same state whatever the task
    position = (lambda: base.data.body(1).xpos[:2].copy()) if env_id_is_ant(env) else (lambda: base.data.qpos[:2].copy())
    before = position()
    _, reward, terminated, _, info = env.step(action)
    assert not terminated
    return float(reward), info, before, position()


def env_id_is_ant(env: gym.Env) -> bool:
    return env.spec is not None and env.spec.id.startswith("Ant")


@pytest.mark.parametrize("env_id", MUJOCO_IDS)
def test_check_env_and_task_protocol(env_id: str) -> None:
    env = gym.make(env_id)
    check_env(env.unwrapped, warn=False)
    assert env.spec is not None and env.spec.max_episode_steps == 200
    base = env.unwrapped
    tasks = base.sample_tasks(6, seed=3)
    assert tasks == base.sample_tasks(6, seed=3) and tasks != base.sample_tasks(6, seed=4)
    assert json.loads(json.dumps(tasks)) == tasks  # JSON-serialisable task dicts
    assert base.sample_tasks(0, seed=1) == []
    first, second = TASKS[env_id]
    base.set_task(first)
    env.reset(seed=0)
    base.set_task(second)
    assert base.get_task() == second
    for seed in (1, 2):  # sticky across resets
        _, info = env.reset(seed=seed)
        assert base.get_task() == second and info["cost"] == 0.0
        _, _, _, _, info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        assert info["cost"] == 0.0
    with pytest.raises(ValueError, match="task keys"):
        base.set_task({"not_a_key": 1.0})
    clone = pickle.loads(pickle.dumps(base))  # EzPickle rebuilds the meta env, not the Gymnasium base
    assert type(clone) is type(base) and clone.sample_tasks(3, seed=0) == base.sample_tasks(3, seed=0)


@pytest.mark.parametrize("env_id", MUJOCO_IDS)
def test_set_task_changes_reward_as_specified(env_id: str) -> None:
    env = gym.make(env_id)
    base = env.unwrapped
    action = np.linspace(-0.8, 0.8, env.action_space.shape[0]).astype(np.float32)
    rewards = []
    for task in TASKS[env_id]:
        base.set_task(task)
        reward, info, before, after = _controlled_step(env, action)
        rewards.append(reward)
        velocity = (after - before) / base.dt  # x (and y for the ant)
        ctrl = float(np.sum(np.square(action)))
        if env_id == "HalfCheetahVelMeta-v0":
            expected = -abs(velocity[0] - task["velocity"]) - 0.05 * ctrl
        elif env_id == "Walker2dVelMeta-v0":
            expected = -abs(velocity[0] - task["velocity"]) + 1.0 - 1e-3 * ctrl
        else:  # the ants: the task term + healthy 1 - 0.5 |a|^2 - 5e-4 |clip(cfrc_ext)|^2
            rest = 1.0 - 0.5 * ctrl - 5e-4 * float(np.sum(np.square(np.clip(base.data.cfrc_ext, -1.0, 1.0))))
            if env_id == "AntVelMeta-v0":
                target = task["speed"] * np.array([math.cos(task["direction"]), math.sin(task["direction"])])
                expected = -float(np.linalg.norm(velocity - target)) + rest
            elif env_id == "AntDirMeta-v0":
                expected = float(velocity @ [math.cos(task["direction"]), math.sin(task["direction"])]) + rest
            else:
                position = np.array([info["x_position"], info["y_position"]])  # the torso's qpos
                np.testing.assert_allclose(position, base.data.qpos[:2])
                expected = -float(np.abs(position - task["goal"]).sum()) + rest
        assert reward == pytest.approx(expected, rel=1e-6, abs=1e-6), task
        assert info["cost"] == 0.0
    assert rewards[0] != pytest.approx(rewards[1])


def test_ant_dir_forward_is_gymnasium_ant_reward() -> None:
    """Direction 0 is Ant-v5's own reward; direction pi flips the forward term only."""
    meta, raw = gym.make("AntDirMeta-v0"), gym.make("Ant-v5")
    action = np.full(8, 0.3, dtype=np.float32)
    results = []
    for env, task in ((meta, {"direction": 0.0}), (raw, None), (meta, {"direction": math.pi})):
        if task is not None:
            env.unwrapped.set_task(task)
        env.reset(seed=5)
        env.unwrapped.set_state(env.unwrapped.init_qpos, env.unwrapped.init_qvel + 0.5)
        _, reward, _, _, info = env.step(action)
        results.append((reward, info["x_velocity"]))
    assert results[0][0] == pytest.approx(results[1][0])
    assert results[2][0] == pytest.approx(results[1][0] - 2 * results[1][1])


def _unhealthy_qpos(env_id: str, qpos: np.ndarray) -> np.ndarray:
    qpos = qpos.copy()
    if env_id == "Walker2dVelMeta-v0":
        qpos[1] = 0.5  # torso height below Gymnasium's (0.8, 2.0)
    else:
        qpos[2] = 1.5  # ant torso above Gymnasium's [0.2, 1.0]
    return qpos


@pytest.mark.parametrize("env_id", HEALTH_IDS)
def test_unhealthy_step_terminates_with_cost_one(env_id: str) -> None:
    env = gym.make(env_id)
    base = env.unwrapped
    env.reset(seed=0)
    zero = np.zeros(env.action_space.shape, dtype=np.float32)
    costs = []
    for _ in range(3):
        _, _, terminated, _, info = env.step(zero)
        costs.append(info["cost"])
        assert not terminated
    base.set_state(_unhealthy_qpos(env_id, base.data.qpos), base.data.qvel)
    _, reward, terminated, truncated, info = env.step(zero)
    costs.append(info["cost"])
    assert terminated and not truncated
    assert costs == [0.0, 0.0, 0.0, 1.0]
    assert info["reward_survive"] == 0.0  # Gymnasium pays no healthy reward on the unhealthy step
    # the fall on step 4 skips 196 steps of the 200-step horizon
    assert info["unhealthy_penalty"] == pytest.approx(base.unhealthy_penalty * 196)
    task_terms = info["reward_forward"] + info["reward_ctrl"] + info.get("reward_contact", 0.0)
    assert reward == pytest.approx(task_terms - info["unhealthy_penalty"])


def test_walker_falls_naturally_cost_only_on_terminal_step() -> None:
    """Without control the walker collapses: cost is 0 on every step but the terminal one."""
    env = gym.make("Walker2dVelMeta-v0")
    env.reset(seed=0)
    costs, terminated, truncated = [], False, False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(np.full(6, -1.0, dtype=np.float32))
        costs.append(info["cost"])
    assert terminated and len(costs) < 200
    assert costs[-1] == 1.0 and sum(costs) == 1.0


def test_unhealthy_penalty_defaults_and_zero() -> None:
    """Defaults: the largest task error of a robot standing still; 0 gives the bare reward."""
    assert gym.make("Walker2dVelMeta-v0").unwrapped.unhealthy_penalty == 2.0
    assert gym.make("Walker2dVelMeta-v0", velocity_low=-3.0, velocity_high=1.0).unwrapped.unhealthy_penalty == 3.0
    assert gym.make("AntVelMeta-v0").unwrapped.unhealthy_penalty == 3.0
    assert gym.make("AntGoalMeta-v0").unwrapped.unhealthy_penalty == pytest.approx(3 * math.sqrt(2))
    assert gym.make("AntDirMeta-v0").unwrapped.unhealthy_penalty == 0.0
    env = gym.make("Walker2dVelMeta-v0", unhealthy_penalty=0.0)
    env.reset(seed=0)
    env.unwrapped.set_state(_unhealthy_qpos("Walker2dVelMeta-v0", env.unwrapped.data.qpos), env.unwrapped.data.qvel)
    _, reward, terminated, _, info = env.step(np.zeros(6, dtype=np.float32))
    assert terminated and info["cost"] == 1.0
    assert reward == pytest.approx(info["reward_forward"] + info["reward_ctrl"])


def test_cheetah_never_terminates_and_time_limit_truncates() -> None:
    env = gym.make("HalfCheetahVelMeta-v0")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    steps, truncated = 0, False
    while not truncated:
        _, _, terminated, truncated, info = env.step(rng.uniform(-1, 1, 6).astype(np.float32))
        steps += 1
        assert not terminated and info["cost"] == 0.0
    assert steps == 200


def test_task_ranges() -> None:
    make = lambda env_id, **kw: gym.make(env_id, **kw).unwrapped  # noqa: E731
    vel = np.array([t["velocity"] for t in make("Walker2dVelMeta-v0").sample_tasks(200, seed=0)])
    assert vel.min() >= 0.0 and vel.max() <= 2.0 and vel.max() > 1.9
    vel = np.array([t["velocity"] for t in make("HalfCheetahVelMeta-v0").sample_tasks(200, seed=0)])
    assert vel.min() >= 0.0 and vel.max() <= 3.0 and vel.max() > 2.9
    shifted = make("HalfCheetahVelMeta-v0", velocity_low=3.0, velocity_high=4.0)
    assert all(3.0 <= t["velocity"] <= 4.0 for t in shifted.sample_tasks(20, seed=0))
    assert 3.0 <= shifted.get_task()["velocity"] <= 4.0  # the initial task already follows the kwargs
    ant = make("AntVelMeta-v0").sample_tasks(300, seed=0)
    directions, speeds = np.array([t["direction"] for t in ant]), np.array([t["speed"] for t in ant])
    assert directions.min() >= 0.0 and directions.max() < 2 * math.pi and np.ptp(directions) > 6.0
    assert speeds.min() >= 0.0 and speeds.max() <= 3.0
    goals = np.array([t["goal"] for t in make("AntGoalMeta-v0").sample_tasks(2000, seed=0)])
    radii = np.linalg.norm(goals, axis=1)
    assert radii.max() <= 3.0 and np.mean(radii <= 1.5) == pytest.approx(0.25, abs=0.04)  # uniform in area
    annulus = np.array([t["goal"] for t in make("AntGoalMeta-v0", goal_radius_low=3.0, goal_radius_high=4.0).sample_tasks(50)])
    assert np.all((np.linalg.norm(annulus, axis=1) >= 3.0 - 1e-9) & (np.linalg.norm(annulus, axis=1) <= 4.0 + 1e-9))


def test_ant_dir_tasks_are_balanced_and_held_out() -> None:
    base = gym.make("AntDirMeta-v0").unwrapped
    train, test = base.sample_tasks(10, seed=0), base.sample_tasks(10, seed=1)
    for tasks in (train, test):
        theta = np.array([t["direction"] for t in tasks])
        assert np.all((theta >= 0.0) & (theta < 2 * math.pi))
        forward = np.minimum(theta, 2 * math.pi - theta) <= math.pi / 12 + 1e-9
        backward = np.abs(theta - math.pi) <= math.pi / 12 + 1e-9
        assert np.all(forward ^ backward) and forward.sum() == 5  # balanced
    assert not {t["direction"] for t in train} & {t["direction"] for t in test}  # held-out directions
    pearl = gym.make("AntDirMeta-v0", direction_spread=0.0).unwrapped.sample_tasks(4, seed=0)
    assert sorted(t["direction"] for t in pearl) == [0.0, 0.0, math.pi, math.pi]  # PEARL's two exact tasks


def test_ant_vel_single_direction_tracks_forward_speed() -> None:
    """direction_low == direction_high: every task moves along that direction (MAML's forward Ant-Vel with 0)."""
    env = gym.make("AntVelMeta-v0", direction_low=0.0, direction_high=0.0)
    tasks = env.unwrapped.sample_tasks(20, seed=0)
    assert {t["direction"] for t in tasks} == {0.0}
    assert len({t["speed"] for t in tasks}) == 20 and all(0.0 <= t["speed"] <= 3.0 for t in tasks)
    env.unwrapped.set_task({"direction": 0.0, "speed": 2.0})
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(env.action_space.shape))
    velocity = np.array([info["x_velocity"], info["y_velocity"]])
    assert info["reward_forward"] == pytest.approx(-np.linalg.norm(velocity - np.array([2.0, 0.0])))


@pytest.mark.parametrize(
    "env_id, kwargs, match",
    [
        ("Walker2dVelMeta-v0", {"velocity_low": 1.0, "velocity_high": 1.0}, "velocity_low"),
        ("Walker2dVelMeta-v0", {"velocity_low": 0.0, "velocity_high": math.inf}, "finite"),
        ("Walker2dVelMeta-v0", {"terminate_when_unhealthy": False}, "terminate_when_unhealthy"),
        ("Walker2dVelMeta-v0", {"unhealthy_penalty": -1.0}, "unhealthy_penalty"),
        ("HalfCheetahVelMeta-v0", {"velocity_low": 2.0, "velocity_high": 1.0}, "velocity_low"),
        ("AntVelMeta-v0", {"speed_low": -1.0}, "speed_low"),
        ("AntVelMeta-v0", {"direction_low": 1.0, "direction_high": 0.5}, "direction_low"),
        ("AntDirMeta-v0", {"base_directions": ()}, "base_directions"),
        ("AntDirMeta-v0", {"direction_spread": -0.1}, "direction_spread"),
        ("AntGoalMeta-v0", {"goal_radius_low": 2.0, "goal_radius_high": 1.0}, "goal_radius_low"),
        ("AntGoalMeta-v0", {"max_episode_steps": 0}, "max_episode_steps"),
    ],
)
def test_bad_kwargs_raise(env_id: str, kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        gym.make(env_id, **kwargs)


@pytest.mark.parametrize(
    "env_id, kwargs, match",
    [
        ("HalfCheetahVelMeta-v0", {"ctrl_cost_weight": -1.0}, r"ctrl_cost_weight must be a finite number >= 0"),
        ("HalfCheetahVelMeta-v0", {"ctrl_cost_weight": math.nan}, r"ctrl_cost_weight must be a finite number >= 0"),
        ("Walker2dVelMeta-v0", {"max_episode_steps": math.nan}, r"max_episode_steps must be an integer >= 1 .*got nan"),
        ("AntDirMeta-v0", {"max_episode_steps": 2.5}, r"max_episode_steps must be an integer >= 1 .*got 2.5"),
        ("AntDirMeta-v0", {"base_directions": ["up"]}, r"base_directions must be a non-empty sequence of finite angles"),
        ("AntVelMeta-v0", {"unhealthy_penalty": "high"}, r"unhealthy_penalty must be a finite number >= 0"),
    ],
)
def test_kwargs_that_hide_violations_are_refused(env_id: str, kwargs: dict[str, Any], match: str) -> None:
    """Every kwarg of a MuJoCo family is checked (finite, in range), the error naming it."""
    with pytest.raises(ValueError, match=match):
        family_class(env_id)(**kwargs)  # the class itself: gym.make takes max_episode_steps for its TimeLimit


def test_ant_goal_rejects_malformed_goal() -> None:
    with pytest.raises(ValueError, match="goal must be"):
        gym.make("AntGoalMeta-v0").unwrapped.set_task({"goal": [1.0]})
