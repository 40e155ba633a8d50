"""Slow learning checks (``make test-slow``): PEARL learns to use adaptation on the point robot."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_pearl import PEARL
from sb3_pearl.evaluation.meta_test import meta_test

# Reference point-robot settings (oyster configs/point-robot.json: fixed entropy 1, reward_scale 100,
# kl 0.1), scaled down: 40/10 tasks, 64x64 networks, 16k env steps (about a minute on one core).
POINT_ROBOT = dict(
    n_train_tasks=40,
    n_test_tasks=10,
    num_initial_steps=100,
    num_tasks_sample=5,
    num_steps_prior=40,
    num_steps_posterior=0,
    num_extra_rl_steps_posterior=40,
    num_train_steps_per_itr=200,
    meta_batch=8,
    batch_size=128,
    embedding_batch_size=40,
    encoder_arch=[64, 64],
    policy_kwargs=dict(net_arch=[64, 64]),
    ent_coef=1.0,
    reward_scale=100.0,
)


def adapted_returns(model: PEARL, env: gym.Env, n_adapt: int = 2) -> np.ndarray:
    """Mean return over the model's test tasks of trajectories k = 0..n_adapt (k = 0: prior z), by the meta-test protocol."""
    result = meta_test(model, env, model.test_tasks, n_adapt=n_adapt)
    return np.array([row["return_mean"] for row in result.summary])


def random_return(env: gym.Env, tasks: list[dict], seed: int = 0) -> float:
    env.action_space.seed(seed)
    total = 0.0
    for task in tasks:
        env.unwrapped.set_task(task)
        env.reset(seed=seed)
        done = False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total += float(reward)
            done = terminated or truncated
    return total / len(tasks)


@pytest.mark.slow
def test_pearl_beats_random_after_adaptation_on_point_robot() -> None:
    th.set_num_threads(1)
    model = PEARL("MlpPolicy", "PointGoalMeta-v0", seed=0, **POINT_ROBOT)  # type: ignore[arg-type]
    model.learn(16_000)
    env = gym.make("PointGoalMeta-v0")
    returns = adapted_returns(model, env)
    baseline = random_return(env, model.test_tasks)
    print(f"held-out mean return per k: {np.round(returns, 2).tolist()}, random policy: {baseline:.2f}")
    assert returns[1:].mean() > baseline + 1.0


# The settings of the earlier SafePoint comparison (docs/results.md, "earlier measurements"): the reference
# point-robot setting (oyster configs/point-robot.json: fixed entropy 1, kl 0.1) scaled down to minutes on one core.
SAFE_POINT_SETTINGS: dict = {
    **POINT_ROBOT,
    **dict(n_test_tasks=20, num_initial_steps=150, num_steps_prior=60, num_extra_rl_steps_posterior=60),
    **dict(num_train_steps_per_itr=300, embedding_batch_size=60),
}


@pytest.mark.slow
def test_pearl_adapts_on_safe_point_goal() -> None:
    """With the reference entropy setting (fixed 1, reward_scale 5) PEARL's posterior beats its prior."""
    th.set_num_threads(1)
    model = PEARL("MlpPolicy", "SafePointGoalMeta-v0", seed=0, **{**SAFE_POINT_SETTINGS, "reward_scale": 5.0})
    model.learn(30_000)
    returns = adapted_returns(model, gym.make("SafePointGoalMeta-v0"))
    print(f"held-out mean return per k: {np.round(returns, 2).tolist()}")
    assert returns[1:].min() > returns[0] + 3.0  # measured: -36.4 -> -16.6, -15.6 (seed 0)
