"""Every task family (``sb3_pearl.envs.FAMILIES``): a bad task or a non-finite action is refused with a message
naming it. Each family's own behaviour is in tests/test_envs_point_goal.py, test_envs_point.py, test_envs_mujoco.py and
test_envs_highway.py."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from sb3_pearl.envs import FAMILIES


@pytest.mark.parametrize("env_id", sorted(FAMILIES))
def test_set_task_checks_types_and_values_on_every_family(env_id: str) -> None:
    env = gym.make(env_id).unwrapped
    good = env.get_task()
    env.set_task(good)  # a sampled task is accepted
    for key, value in good.items():
        if isinstance(value, list):
            wrong_type, wrong_shape = "abc", [*value, 1.0]
            nan_value = [float("nan")] * len(value)
        else:
            wrong_type, wrong_shape = str(value), [value, value]  # Walker {"velocity": [1, 2]}
            nan_value = float("nan")
        for bad in (nan_value, wrong_type, wrong_shape):
            with pytest.raises(ValueError, match=rf"set_task: {key} must be .*as from sample_tasks\(\)"):
                env.set_task({**good, key: bad})
            assert env.task_error({**good, key: bad}) is not None
    assert env.get_task() == good  # refused tasks change nothing
    env.close()


@pytest.mark.parametrize("env_id", sorted(FAMILIES))
def test_every_family_refuses_a_non_finite_action(env_id: str) -> None:
    env = gym.make(env_id)
    env.reset(seed=0)
    good = env.action_space.sample()
    for bad in (float("nan"), float("inf")):
        action = np.full(env.action_space.shape, bad) if env.action_space.shape else bad
        with pytest.raises(ValueError, match=r"\.step: the action \[?(nan|inf).* is not finite: refused rather than stepped"):
            env.step(action)
    env.step(good)  # the env is still usable
    env.close()
