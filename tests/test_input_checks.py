"""Bad arguments and inputs to the library's API, each refused with an error that names it: constructor arguments
before anything is built, held-out tasks, ``observe`` transitions, budgets, the task family of a model, tasks sent to
SubprocVecEnv workers. docs/reliability.md lists each case."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_pearl import MAML, PEARL, FineTune, PEARLPlus
from tests.conftest import (
    ENV_ID,
    tiny_finetune,
    tiny_maml,
    tiny_pearl,
)

# ----------------------------------------------------------------------------------------------
# Validated inputs: each an error naming the argument, before anything is built
# ----------------------------------------------------------------------------------------------
NO_ENV = "NoSuchEnvIsBuiltBeforeTheArgumentCheck-v0"  # gym.make would fail: the argument check must come first


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"prior_coef": float("nan")}, r"prior_coef must be a finite number >= 0 .*got nan"),
        ({"prior_coef": float("inf")}, r"prior_coef must be a finite number >= 0"),
        ({"kl_weight": -1}, r"kl_weight must be a finite number >= 0 .*got -1"),
        ({"n_test_tasks": -1}, r"n_test_tasks must be an integer >= 0 .*got -1"),
        ({"num_train_steps_per_itr": -5}, r"num_train_steps_per_itr must be an integer >= 0 .*got -5"),
        ({"encoder_arch": [0]}, r"encoder_arch must be a list of hidden-layer sizes, each an integer >= 1 .*got \[0\]"),
        ({"prior_critic_arch": [16, -1]}, r"prior_critic_arch must be a list of hidden-layer sizes"),
        ({"policy_kwargs": {"net_arch": [0]}}, r"policy_kwargs\['net_arch'\] must be a list"),
        ({"gamma": 1.5}, r"gamma must be a finite number in \(0, 1\] .*got 1.5"),
        ({"gamma": 0.0}, r"gamma must be a finite number in \(0, 1\]"),
        ({"tau": -0.1}, r"tau must be a finite number in \[0, 1\]"),
        ({"ent_coef": -1.0}, r"ent_coef must be a finite number >= 0"),
        ({"ent_coef": "auto_-1"}, r"ent_coef must be a number >= 0, 'auto' or 'auto_<init>'"),
        ({"reward_scale": 0.0}, r"reward_scale must be a finite number > 0"),
        ({"learning_rate": float("nan")}, r"learning_rate must be a finite number >= 0"),
        ({"batch_size": 0}, r"batch_size must be an integer >= 1"),
        ({"num_tasks_sample": 0}, r"num_tasks_sample must be an integer >= 1"),
        ({"meta_batch": 2.5}, r"meta_batch must be an integer >= 1 .*got 2.5"),
        ({"use_bf16": "yes"}, r"use_bf16 must be True, False or 'force'"),
    ],
)
def test_pearl_arguments_are_checked_first(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        PEARLPlus("MlpPolicy", NO_ENV, **kwargs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"batch_size": 0}, r"batch_size must be an integer >= 1 .*got 0"),
        ({"gamma": 2.0}, r"gamma must be a finite number in \(0, 1\]"),
        ({"tau": -1.0}, r"tau must be a finite number in \[0, 1\]"),
        ({"ent_coef": -0.5}, r"ent_coef must be a finite number >= 0"),
        ({"n_test_tasks": -1}, r"n_test_tasks must be an integer >= 0"),
        ({"gradient_steps": -2}, r"gradient_steps must be an integer >= 0, or -1"),
        ({"policy_kwargs": {"net_arch": {"pi": [64], "qf": [0]}}}, r"policy_kwargs\['net_arch'\]\['qf'\] must be a list"),
    ],
)
def test_finetune_arguments_are_checked_first(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        FineTune("MlpPolicy", NO_ENV, **kwargs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"gamma": 1.01}, r"gamma must be a finite number in \(0, 1\]"),
        ({"inner_lr": float("nan")}, r"inner_lr must be a finite number >= 0"),
        ({"n_test_tasks": -1}, r"n_test_tasks must be an integer >= 0"),
        ({"gae_lambda": 1.5}, r"gae_lambda must be a finite number in \[0, 1\]"),
    ],
)
def test_maml_arguments_are_checked_first(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        MAML("MlpPolicy", NO_ENV, **kwargs)


def test_test_tasks_are_checked_at_construction(tiny_kwargs: dict[str, Any]) -> None:
    good = gym.make(ENV_ID).unwrapped.sample_tasks(2, seed=0)
    with pytest.raises(ValueError, match=r"test_tasks\[1\] = \{'goal': \[1.0, 0.5, 0.2\].*is not a task of this env"):
        tiny_pearl(tiny_kwargs, test_tasks=[good[0], {"goal": [1.0, 0.5, 0.2], "hazard": [0.6, 0.0]}])
    with pytest.raises(ValueError, match=r"train_tasks\[0\] = \{'velocity': 1.0\} is not a task of this env"):
        tiny_finetune(train_tasks=[{"velocity": 1.0}])
    with pytest.raises(ValueError, match=r"test_tasks\[0\] .*goal must be a list of 2 values"):
        tiny_maml(test_tasks=[{"goal": [0.0], "hazard": [0.6, 0.0]}])


def test_observe_clips_box_actions_and_refuses_bad_ones(tiny_kwargs: dict[str, Any]) -> None:
    obs = np.zeros(2, dtype=np.float32)
    far = np.array([5.0, -5.0], dtype=np.float32)  # 50x the box [-0.1, 0.1]^2
    pearl = tiny_pearl(tiny_kwargs, seed=0)
    pearl.observe(obs, far, -1.0, obs, False)
    assert np.array_equal(pearl._adapt_context[-1][1], [1.0, -1.0])  # stored as the clipped action the env executed
    finetune = tiny_finetune()
    finetune.observe(obs, far, -1.0, obs, False)
    assert finetune._adapt_buffer is not None and np.array_equal(finetune._adapt_buffer.actions[0, 0], [1.0, -1.0])
    maml = tiny_maml()
    maml.observe(obs, far, -1.0, obs, False)
    assert np.array_equal(maml._current_episode[1][-1], [1.0, -1.0])
    for model in (pearl, finetune, maml):
        with pytest.raises(ValueError, match=r"observe\(\): reward holds a non-finite value"):
            model.observe(obs, far, float("nan"), obs, False)
        with pytest.raises(ValueError, match=r"observe\(\): the action \[nan, 0.0\] is not finite"):
            model.observe(obs, np.array([np.nan, 0.0]), -1.0, obs, False)


def test_observe_refuses_a_discrete_action_out_of_range(tiny_kwargs: dict[str, Any]) -> None:
    from tests.conftest import make_discrete_env

    model = PEARLPlus("MlpPolicy", make_vec_env(make_discrete_env), **tiny_kwargs)
    obs = np.zeros(2, dtype=np.float32)
    model.observe(obs, 4, -1.0, obs, False)
    for action in (5, -1):
        with pytest.raises(ValueError, match=rf"observe\(\): Discrete action {action} is out of range \[0, 5\)"):
            model.observe(obs, action, -1.0, obs, False)


@pytest.mark.parametrize("cls", [PEARL, PEARLPlus])
def test_observe_refuses_a_reward_that_is_not_a_scalar(cls: type[PEARL], tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, cls=cls, seed=0)
    obs = np.zeros(2, dtype=np.float32)
    with pytest.raises(ValueError, match=r"observe\(\): reward must be a scalar \(one transition\), got shape \(2,\)"):
        model.observe(obs, np.zeros(2), np.array([1.0, 2.0]), obs, False)
    assert model._adapt_context == []
    model.observe(obs, np.zeros(2), np.array([1.0]), obs, False)  # one reward in an array of one is one transition


@pytest.mark.parametrize("algo", ["pearlplus", "finetune", "maml"])
def test_learn_refuses_a_negative_budget(algo: str, tiny_kwargs: dict[str, Any]) -> None:
    model = {"pearlplus": lambda: tiny_pearl(tiny_kwargs, seed=0), "finetune": tiny_finetune, "maml": tiny_maml}[algo]()
    with pytest.raises(ValueError, match=r"learn\(\): total_timesteps must be >= 0 \(env steps to train on\), got -1"):
        model.learn(-1)
    assert model.num_timesteps == 0


def test_the_libraries_family_error_names_the_families_env_id(point_goal_model: Path) -> None:
    with pytest.raises(ValueError, match=r"give it an env of that family: PointGoalMeta-v0$"):
        PEARLPlus.load(point_goal_model, env=gym.make(ENV_ID))


# ----------------------------------------------------------------------------------------------
# A bad task for a SubprocVecEnv: refused in this process, the workers alive
# ----------------------------------------------------------------------------------------------
def test_a_bad_task_for_a_subprocess_vec_env_is_one_line_and_the_env_lives() -> None:
    """Guards against: the worker died on set_task's ValueError; the parent got an empty EOFError and a dead VecEnv."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv, VecCheckNan

    from sb3_pearl.common.tasks import set_vec_env_task
    from sb3_pearl.evaluation.meta_test import SingleEnvRunner

    fork = {"start_method": "fork"}
    env = VecCheckNan(make_vec_env(ENV_ID, n_envs=2, vec_env_cls=SubprocVecEnv, vec_env_kwargs=fork))  # wrapped
    try:
        good = env.env_method("get_task", indices=[0])[0]
        bad = {"goal": np.array([np.nan, 1.0])}
        with pytest.raises(
            ValueError, match=r"^set_task\(\{'goal': .*\}\): SafePointGoalMetaEnv.set_task: task keys \['goal'\] != "
        ):
            set_vec_env_task(env, bad, [1])
        with pytest.raises(ValueError, match=r"refused before it reached the SubprocVecEnv's worker processes, which die"):
            set_vec_env_task(env, {**good, "goal": np.array([np.nan, 1.0])})
        set_vec_env_task(env, good, [1])  # the workers are alive and take a good task
        assert env.env_method("get_task") == [good, good]
    finally:
        env.close()
    single = make_vec_env(ENV_ID, n_envs=1, vec_env_cls=SubprocVecEnv, vec_env_kwargs=fork)
    try:  # the meta-test's runner on a one-env SubprocVecEnv
        with pytest.raises(ValueError, match=r"set_task\(.*\): SafePointGoalMetaEnv"):
            SingleEnvRunner(single).set_task(bad)
        assert single.env_method("get_task")[0].keys() == good.keys()
    finally:
        single.close()
