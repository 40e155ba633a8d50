"""Reliability (issue 10): atomic writes, checked loads, safe configs, validated inputs, SIGTERM, divergence guard.

docs/reliability.md lists the bad inputs and faults these tests try and what each gets.
"""

from __future__ import annotations

import multiprocessing
import os
import random
import signal
import subprocess
import sys
import time
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from stable_baselines3 import SAC
from stable_baselines3.common.env_util import make_vec_env

import tests.faulty_envs  # noqa: F401  (registers the failing families)
from sb3_pearl import MAML, PEARL, FineTune, PEARLPlus
from sb3_pearl.common.atomic import atomic_write, sb3_file_path
from sb3_pearl.common.divergence import DivergenceError, NonFiniteEnvError
from sb3_pearl.envs import FAMILIES
from sb3_pearl.evaluation.meta_test import MetaTestResult
from sb3_pearl.zoo import enjoy, train
from sb3_pearl.zoo.safe_config import UnsafeConfigError, load_run_yaml, parse_dict_string
from tests.conftest import Completed, run_in_process

ENV_ID = "SafePointGoalMeta-v0"


def tiny_pearl(tiny_kwargs: dict[str, Any], cls: type[PEARL] = PEARLPlus, env: str = ENV_ID, **overrides: Any) -> PEARL:
    kwargs = {**tiny_kwargs, **overrides}
    if cls is PEARL:
        kwargs.pop("prior_critic_arch", None)
    return cls("MlpPolicy", env, **kwargs)


def tiny_finetune(env: str = ENV_ID, **overrides: Any) -> FineTune:
    kwargs: dict[str, Any] = dict(n_train_tasks=4, n_test_tasks=2, learning_starts=10, batch_size=8, seed=0)
    kwargs.update(overrides)
    return FineTune("MlpPolicy", env, **kwargs)


def tiny_maml(env: str = ENV_ID, **overrides: Any) -> MAML:
    kwargs: dict[str, Any] = dict(n_train_tasks=4, n_test_tasks=2, meta_batch_size=2, episodes_per_task=1, seed=0)
    kwargs.update(overrides)
    return MAML("MlpPolicy", env, **kwargs)


def no_temporary_files(folder: Path) -> bool:
    return not [name for name in os.listdir(folder) if ".tmp" in name]


# ----------------------------------------------------------------------------------------------
# 1. Atomic writes
# ----------------------------------------------------------------------------------------------
def _save_forever(model: PEARL, path: str) -> None:  # runs in a forked child until killed
    while True:
        model.save(path)


def test_sigkill_mid_save_keeps_the_previous_model(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    # A model whose zip takes tens of milliseconds to write, so that the kills land inside save().
    model = tiny_pearl(tiny_kwargs, seed=0, policy_kwargs=dict(net_arch=[400, 400]), encoder_arch=[200, 200])
    path = tmp_path / "model.zip"
    model.save(path)
    reference = {k: v.clone() for k, v in model.policy.state_dict().items()}
    context = multiprocessing.get_context("fork")
    rng = random.Random(0)
    for _ in range(4):
        child = context.Process(target=_save_forever, args=(model, str(path)))
        child.start()
        time.sleep(0.15 + rng.random() * 0.3)
        assert child.pid is not None
        os.kill(child.pid, signal.SIGKILL)
        child.join()
        loaded = PEARLPlus.load(path, device="cpu")
        for key, value in loaded.policy.state_dict().items():
            assert th.equal(value, reference[key]), key
    # a stale temporary file may stay behind after a kill, never a broken model.zip
    assert zipfile.ZipFile(path).testzip() is None


def test_save_keeps_sb3_suffix_rule_and_leaves_no_temporary_file(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0)
    model.learn(80)
    model.save(tmp_path / "model")  # no suffix: SB3 writes model.zip
    model.save_replay_buffer(tmp_path / "buffer")  # no suffix: SB3 writes buffer.pkl
    model.save(str(tmp_path / "sub" / "other.zip"))  # a missing folder is created
    assert sorted(os.listdir(tmp_path)) == ["buffer.pkl", "model.zip", "sub"]
    assert sb3_file_path("a/model", "zip") == Path("a/model.zip")
    assert sb3_file_path("a/model.zip", "zip") == Path("a/model.zip")
    assert PEARLPlus.load(tmp_path / "model").num_timesteps == model.num_timesteps
    assert no_temporary_files(tmp_path)


def test_failed_write_keeps_the_previous_file(tmp_path: Path) -> None:
    path = tmp_path / "result.json"
    path.write_text("old")
    with pytest.raises(RuntimeError), atomic_write(path, "w") as file:
        file.write("half of the new")
        raise RuntimeError("killed")
    assert path.read_text() == "old"
    assert no_temporary_files(tmp_path)


def test_meta_test_files_are_written_atomically(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    result = MetaTestResult(
        rows=[{"task": 0, "repeat": 0, "k": 0, "return": 1.0, "cost": 0.0, "length": 3, "violated": 0}], summary=[]
    )
    result.to_csv(tmp_path / "meta_test.csv")
    result.to_json(tmp_path / "meta_test.json")
    before = {name: (tmp_path / name).read_text() for name in ("meta_test.csv", "meta_test.json")}

    def fail(*args: Any, **kwargs: Any) -> None:
        raise OSError("disk full")

    monkeypatch.setattr("json.dump", fail)
    monkeypatch.setattr("csv.DictWriter.writeheader", fail)
    with pytest.raises(OSError):
        result.to_json(tmp_path / "meta_test.json")
    with pytest.raises(OSError):
        result.to_csv(tmp_path / "meta_test.csv")
    assert {name: (tmp_path / name).read_text() for name in before} == before
    assert no_temporary_files(tmp_path)


# ----------------------------------------------------------------------------------------------
# 2. Configs and run folders never run code
# ----------------------------------------------------------------------------------------------
def _zoo_run_folder(root: Path, tiny_kwargs: dict[str, Any]) -> Path:
    """A run folder in rl_zoo3's layout, its YAML written the way rl_zoo3 writes it (yaml.dump of OrderedDicts)."""
    run_dir = root / "pearlplus" / f"{ENV_ID}_1"
    tiny_pearl(tiny_kwargs, seed=0).save(run_dir / f"{ENV_ID}.zip")
    (run_dir / ENV_ID).mkdir()
    args = OrderedDict(sorted({"algo": "pearlplus", "env": ENV_ID, "env_kwargs": None, "seed": 1, "gym_packages": []}.items()))
    config = OrderedDict([("n_envs", 1), ("policy", "MlpPolicy"), ("policy_kwargs", "dict(net_arch=[32, 32])")])
    (run_dir / ENV_ID / "args.yml").write_text(yaml.dump(args))
    (run_dir / ENV_ID / "config.yml").write_text(yaml.dump(config))
    return run_dir


def test_run_folder_yaml_is_read_safely(tmp_path: Path) -> None:
    written = OrderedDict([("env", ENV_ID), ("train_freq", (1, "episode")), ("env_kwargs", {"a": [1.5, None]})])
    path = tmp_path / "args.yml"
    path.write_text(yaml.dump(written))
    assert "!!python/object/apply:collections.OrderedDict" in path.read_text()  # what rl_zoo3 writes
    assert load_run_yaml(path) == written
    path.write_text('!!python/object/apply:os.system ["echo pwned"]\n')
    with pytest.raises(UnsafeConfigError, match="refusing the YAML tag '!!python/object/apply:os.system'"):
        load_run_yaml(path)
    path.write_text("env: !!python/name:os.system\n")
    with pytest.raises(UnsafeConfigError, match="python/name:os.system"):
        load_run_yaml(path)


@pytest.mark.parametrize("poisoned", ["args.yml", "config.yml"])
def test_enjoy_refuses_a_run_folder_that_would_run_code(tmp_path: Path, tiny_kwargs: dict[str, Any], poisoned: str) -> None:
    run_dir = _zoo_run_folder(tmp_path / "logs", tiny_kwargs)
    marker = tmp_path / "pwned"
    (run_dir / ENV_ID / poisoned).write_text(f'!!python/object/apply:os.system ["touch {marker}"]\n')
    with pytest.raises(SystemExit, match="refusing the YAML tag '!!python/object/apply:os.system'"):
        enjoy(["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "logs"), "--no-render", "--n-tasks", "1"])
    assert not marker.exists()


def test_meta_test_strings_are_parsed_without_eval(tmp_path: Path) -> None:
    assert parse_dict_string("dict(n_adapt=3, deterministic=False)", "meta_test") == {"n_adapt": 3, "deterministic": False}
    assert parse_dict_string("{'n_tasks': None}", "meta_test") == {"n_tasks": None}
    marker = tmp_path / "pwned"
    for text in (f"__import__('os').system('touch {marker}')", f"dict(n_adapt=__import__('os').system('touch {marker}'))"):
        with pytest.raises(ValueError, match="meta_test: .* is not a dict of literals"):
            parse_dict_string(text, "meta_test")
    assert not marker.exists()
    with pytest.raises(ValueError, match=r"meta_test: cannot parse 'dict\(n_adapt=' \(.*\); write a dict of literals"):
        parse_dict_string("dict(n_adapt=", "meta_test")
    with pytest.raises(ValueError, match="meta_test must be a dict"):
        parse_dict_string("[1, 2]", "meta_test")


# ----------------------------------------------------------------------------------------------
# 3. Validated inputs: each an error naming the argument, before anything is built
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


def test_safe_point_refuses_a_hazard_over_the_start() -> None:
    env = gym.make(ENV_ID).unwrapped
    with pytest.raises(ValueError, match=r"the hazard \[0.1, 0.0\] covers the start \(0, 0\)"):
        env.set_task({"goal": [0.0, 1.0], "hazard": [0.1, 0.0]})


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


def test_load_refuses_files_that_do_not_fit(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    plus = tiny_pearl(tiny_kwargs, seed=0)
    plus.save(tmp_path / "plus.zip")
    with pytest.raises(
        ValueError, match=r"holds a PEARL\+ model \(prior_coef=0.1, prior_critic='separate'\): load it with PEARLPlus"
    ):
        PEARL.load(tmp_path / "plus.zip")
    data = (tmp_path / "plus.zip").read_bytes()
    (tmp_path / "truncated.zip").write_bytes(data[: len(data) // 3])
    with pytest.raises(ValueError, match=r"truncated.zip .*the file is truncated or corrupt.*load an earlier checkpoint"):
        PEARLPlus.load(tmp_path / "truncated.zip")
    SAC("MlpPolicy", "Pendulum-v1", learning_starts=0).save(tmp_path / "sac")
    with pytest.raises(
        ValueError, match=r"sac is not a PEARLPlus model: .*stable_baselines3.sac.policies.SACPolicy.*SAC.load"
    ):
        PEARLPlus.load(tmp_path / "sac")
    with pytest.raises(ValueError, match=r"holds a PEARLPlus model, not a MAML one: load it with PEARLPlus.load"):
        MAML.load(tmp_path / "plus.zip")
    assert PEARLPlus.load(tmp_path / "plus").prior_coef == 0.1


def _saved_model(algo: str, folder: Path, tiny_kwargs: dict[str, Any]) -> tuple[Any, Path]:
    """An untrained tiny model of ``algo`` saved to ``folder/model.zip``: its class and the zip."""
    from sb3_pearl import Oracle

    if algo in ("pearl", "pearlplus"):
        model: Any = tiny_pearl(tiny_kwargs, PEARL if algo == "pearl" else PEARLPlus, seed=0)
    elif algo == "oracle":
        model = Oracle("MlpPolicy", ENV_ID, n_train_tasks=4, n_test_tasks=2, learning_starts=10, batch_size=8, seed=0)
    else:
        model = tiny_finetune() if algo == "finetune" else tiny_maml()
    model.save(folder / "model.zip")
    return type(model), folder / "model.zip"


@pytest.mark.parametrize(
    "algo, override, match",
    [
        ("pearl", {"prior_coef": float("nan")}, r"prior_coef must be 0 for PEARL .*got nan"),
        ("pearl", {"meta_batch": 0}, r"meta_batch must be an integer >= 1 .*got 0"),
        ("pearlplus", {"prior_coef": float("nan")}, r"prior_coef must be a finite number >= 0 .*got nan"),
        ("pearlplus", {"gamma": 1.5}, r"gamma must be a finite number in \(0, 1\] .*got 1.5"),
        ("pearlplus", {"kl_weight": -1.0}, r"kl_weight must be a finite number >= 0 .*got -1.0"),
        ("pearlplus", {"prior_target": "nope"}, r"unknown prior_target 'nope'"),
        ("finetune", {"gamma": 1.5}, r"gamma must be a finite number in \(0, 1\]"),
        ("finetune", {"adapt_gradient_steps": -1}, r"adapt_gradient_steps must be an integer >= 0 .*got -1"),
        ("oracle", {"tau": 2.0}, r"tau must be a finite number in \[0, 1\] .*got 2.0"),
        ("maml", {"inner_lr": float("nan")}, r"inner_lr must be a finite number >= 0 .*got nan"),
        ("maml", {"gae_lambda": 1.5}, r"gae_lambda must be a finite number in \[0, 1\]"),
    ],
)
def test_load_runs_the_constructors_checks(
    algo: str, override: dict[str, Any], match: str, tmp_path: Path, tiny_kwargs: dict[str, Any]
) -> None:
    """A hyperparameter replaced at load (custom_objects, or a load() keyword) is checked as the constructor checks it,
    with the constructor's message: the argument, its range and the value."""
    cls, path = _saved_model(algo, tmp_path, tiny_kwargs)
    with pytest.raises(ValueError, match=rf"model.zip: {match}"):
        cls.load(path, custom_objects=override)
    with pytest.raises(ValueError, match=match):
        cls.load(path, **override)
    with open(path, "rb") as file, pytest.raises(ValueError, match=match):  # a stream is checked too
        cls.load(file, custom_objects=override)
    cls.load(path)  # the saved values pass


def test_set_env_refuses_vec_normalize_and_another_task_family(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    """set_env checks the env as the constructor does (no VecNormalize) and refuses an env of another task family in
    one line, whether the spaces match (PointGoal / SafePointGoal, Walker2d / HalfCheetah) or not; load(env=) too."""
    from stable_baselines3.common.vec_env import VecNormalize

    model = tiny_pearl(tiny_kwargs, seed=0)
    env = model.env
    with pytest.raises(ValueError, match=r"VecNormalize is not supported: the adaptation API passes raw observations"):
        model.set_env(VecNormalize(make_vec_env(ENV_ID)))
    with pytest.raises(ValueError, match=r"set_env: .*trained on SafePointGoalMetaEnv tasks.* a PointGoalMetaEnv"):
        model.set_env(make_vec_env("PointGoalMeta-v0"))
    model.task_family = None  # a model saved before the family was recorded: its training tasks tell
    with pytest.raises(ValueError, match=r"set_env: .*train_tasks\[0\] = \{'goal'.*is not a task of the env"):
        model.set_env(make_vec_env("PointGoalMeta-v0"))
    assert model.env is env  # a refused env is not set
    model.set_env(make_vec_env(ENV_ID))
    assert model.task_family == "SafePointGoalMetaEnv"

    walker = tiny_finetune(env="Walker2dVelMeta-v0", buffer_size=1000)
    cheetah = make_vec_env("HalfCheetahVelMeta-v0")  # the same spaces, the same task keys: only the family tells
    with pytest.raises(ValueError, match=r"set_env: .*Walker2dVelMetaEnv tasks.* a HalfCheetahVelMetaEnv"):
        walker.set_env(cheetah)
    walker.save(tmp_path / "walker.zip")
    with pytest.raises(ValueError, match=r"Walker2dVelMetaEnv tasks.* a HalfCheetahVelMetaEnv"):
        FineTune.load(tmp_path / "walker.zip", env=cheetah)
    assert FineTune.load(tmp_path / "walker.zip", env=make_vec_env("Walker2dVelMeta-v0")).task_family == "Walker2dVelMetaEnv"


def test_replay_buffer_of_other_tasks_is_refused(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0)
    model.learn(80)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    other_family = tiny_pearl(tiny_kwargs, seed=0, env="PointGoalMeta-v0")  # same dims (2-d obs and actions)
    fresh = other_family.replay_buffer
    with pytest.raises(ValueError, match=r"buffer.pkl was collected on other training tasks than this model's"):
        other_family.load_replay_buffer(tmp_path / "buffer.pkl")
    assert other_family.replay_buffer is fresh
    with pytest.raises(ValueError, match="other training tasks"):
        tiny_pearl(tiny_kwargs, seed=1).load_replay_buffer(tmp_path / "buffer.pkl")  # same family, other seed
    model.load_replay_buffer(tmp_path / "buffer.pkl")
    finetune = tiny_finetune()
    finetune.learn(30)
    finetune.save_replay_buffer(tmp_path / "finetune_buffer")
    with pytest.raises(ValueError, match="other training tasks"):
        tiny_finetune(env="PointGoalMeta-v0").load_replay_buffer(tmp_path / "finetune_buffer")
    (tmp_path / "cut.pkl").write_bytes((tmp_path / "buffer.pkl").read_bytes()[:100])
    with pytest.raises(ValueError, match="cut.pkl is not a complete replay buffer pickle"):
        model.load_replay_buffer(tmp_path / "cut.pkl")


# ----------------------------------------------------------------------------------------------
# 4. SIGTERM and exceptions during train.py save the model and say where
# ----------------------------------------------------------------------------------------------
ROOT = Path(__file__).resolve().parent.parent
TINY_ZOO: dict[str, Any] = {
    "n_timesteps": 1_000_000,
    "policy": "MlpPolicy",
    "n_envs": 1,
    "num_initial_steps": 30,
    "num_train_steps_per_itr": 5,
    "num_steps_prior": 30,
    "num_extra_rl_steps_posterior": 30,
    "n_train_tasks": 4,
    "n_test_tasks": 2,
    "meta_batch": 2,
    "batch_size": 16,
    "embedding_batch_size": 8,
    "latent_dim": 3,
    "encoder_arch": [16],
    "prior_critic_arch": [16],
    "policy_kwargs": "dict(net_arch=[32, 32])",
}


def start_train(folder: Path, env_id: str, *extra: str) -> subprocess.Popen[str]:
    conf = folder / "conf.yml"
    conf.write_text(yaml.safe_dump({env_id: TINY_ZOO}))
    command = [sys.executable, str(ROOT / "train.py"), "--algo", "pearlplus", "--env", env_id, "-f", str(folder / "logs")]
    command += ["-conf", str(conf), "--seed", "1", "--num-threads", "1", "--gym-packages", "tests.faulty_envs", *extra]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "MPLBACKEND": "Agg"}
    return subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_sigterm_saves_the_model_and_says_where(tmp_path: Path) -> None:
    proc = start_train(tmp_path, ENV_ID)
    assert proc.stdout is not None
    output = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # training has started once the logger printed its first iteration
        line = proc.stdout.readline()
        output.append(line)
        if "n_updates" in line or not line:
            break
    assert any("n_updates" in line for line in output), "".join(output)
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=60)
    text = "".join(output) + rest
    model_path = tmp_path / "logs" / "pearlplus" / f"{ENV_ID}_1" / f"{ENV_ID}.zip"
    assert proc.returncode == 128 + signal.SIGTERM, text[-3000:]
    assert "Received SIGTERM: stopping training where it resumes exactly" in text
    assert f"the model is saved to {model_path} with its replay buffer" in text
    assert PEARLPlus.load(model_path).num_timesteps > 0


def test_exception_during_training_saves_the_model_and_reraises(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    env_id = "FailingSafePointGoalMeta-v0"
    conf = tmp_path / "conf.yml"
    conf.write_text(yaml.safe_dump({env_id: TINY_ZOO}))
    argv = ["--algo", "pearlplus", "--env", env_id, "-f", str(tmp_path / "logs"), "-conf", str(conf), "--seed", "1"]
    with pytest.raises(RuntimeError, match=r"the simulator crashed \(on purpose\)"):  # re-raised, so the exit status is 1
        train([*argv, "--num-threads", "1", "--gym-packages", "tests.faulty_envs"])  # train.py's entry point, in-process
    model_path = tmp_path / "logs" / "pearlplus" / f"{env_id}_1" / f"{env_id}.zip"
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert f"Training stopped by RuntimeError at 200 timesteps: the model reached so far is saved to {model_path}" in text
    assert PEARLPlus.load(model_path).num_timesteps == 200


# ----------------------------------------------------------------------------------------------
# 5. Divergence guard
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("what, shown", [("reward", r"reward \(nan\)"), ("obs", r"observation \(\[inf, inf\]\)")])
@pytest.mark.parametrize("algo", ["pearlplus", "finetune", "maml"])
def test_non_finite_env_output_names_env_task_and_step(algo: str, what: str, shown: str, tiny_kwargs: dict[str, Any]) -> None:
    value = float("nan") if what == "reward" else float("inf")
    env = make_vec_env("NonFiniteSafePointGoalMeta-v0", n_envs=2, env_kwargs=dict(what=what, value=value, fail_after=40))
    model = {
        "pearlplus": lambda: PEARLPlus("MlpPolicy", env, seed=0, **tiny_kwargs),
        "finetune": lambda: tiny_finetune(env),  # type: ignore[arg-type]
        "maml": lambda: tiny_maml(env),  # type: ignore[arg-type]
    }[algo]()
    with pytest.raises(
        NonFiniteEnvError,
        match=rf"NonFiniteSafePointGoalMeta-v0 returned a non-finite {shown} at timestep \d+ \(env index \d, task \{{'goal'",
    ):
        model.learn(400)


def all_finite(model: PEARL) -> bool:
    tensors = list(model.policy.parameters())
    for optimizer in model.policy.optimizers():
        tensors += [v for state in optimizer.state.values() for v in state.values() if th.is_tensor(v)]
    return all(bool(th.isfinite(t).all()) for t in tensors)


def test_non_finite_losses_are_skipped_and_repeated_ones_stop_training(tiny_kwargs: dict[str, Any]) -> None:
    # One reward of 1e30 (finite, so no env error): its critic targets overflow; those steps are skipped and the
    # Adam state stays finite; the poisoned context keeps coming back, so training stops with the cause named.
    env = gym.make("NonFiniteSafePointGoalMeta-v0", value=1e30, fail_after=100)
    model = PEARLPlus("MlpPolicy", env, seed=0, **tiny_kwargs)
    with (
        pytest.warns(UserWarning, match="skipped a gradient step with non-finite critic_loss=inf"),
        pytest.raises(
            DivergenceError, match=r"10 gradient steps in a row had a non-finite loss .*critic_loss=inf.*reward_scale"
        ),
    ):
        model.learn(2000)
    assert model._update_guard.skipped >= 10 and all_finite(model)


def test_huge_learning_rate_stops_with_a_message_instead_of_a_torch_error(tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0, learning_rate=1e6)
    with (
        pytest.warns(UserWarning, match="skipped a gradient step"),
        pytest.raises(DivergenceError, match=r"Likely fixes: a lower learning_rate.*learning_rate=1000000.0"),
    ):
        model.learn(3000)
    assert all(bool(th.isfinite(p).all()) for p in model.policy.parameters())


def test_guard_skips_a_step_with_a_non_finite_gradient_only(tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0)
    model.learn(100)
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    hook = model.actor.mu.weight.register_hook(lambda grad: grad * float("inf"))
    with pytest.warns(UserWarning, match="finite losses but a non-finite gradient"):
        model.train(gradient_steps=3, batch_size=8)
    hook.remove()
    assert model._update_guard.skipped == 3 and model._update_guard.consecutive == 3
    assert all(th.equal(v, before[k]) for k, v in model.policy.state_dict().items())  # nothing stepped
    model.train(gradient_steps=1, batch_size=8)
    assert model._update_guard.consecutive == 0 and all_finite(model)


# ----------------------------------------------------------------------------------------------
# 6. bfloat16 only where it is native
# ----------------------------------------------------------------------------------------------
def test_bf16_falls_back_to_float32_without_native_support(
    monkeypatch: pytest.MonkeyPatch, tiny_kwargs: dict[str, Any]
) -> None:
    from sb3_pearl.common import precision

    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset({"avx2", "fma"}))  # an AVX2-only CPU
    with pytest.warns(UserWarning, match=r"no native bfloat16 .*1.5-18x slower.*trains in float32.*use_bf16='force'"):
        model = tiny_pearl(tiny_kwargs, seed=0, use_bf16=True, device="cpu")
    assert model.use_bf16 is True and not model._bf16_enabled
    assert tiny_pearl(tiny_kwargs, seed=0, use_bf16="force", device="cpu")._bf16_enabled
    monkeypatch.setattr(precision, "cpu_flags", lambda: frozenset({"avx2", "avx512_bf16"}))
    assert tiny_pearl(tiny_kwargs, seed=0, use_bf16=True, device="cpu")._bf16_enabled
    assert precision.native_bf16(th.device("cpu"))[0]


# ----------------------------------------------------------------------------------------------
# 7. Exact resume
# ----------------------------------------------------------------------------------------------
NOISY_ENV = "NoisyResetSafePointGoalMeta-v0"  # its resets draw from the env's np_random: the env RNG must resume too


def _make_for_resume(algo: str, tiny_kwargs: dict[str, Any]) -> Any:
    env = gym.make(NOISY_ENV)
    if algo == "maml":
        return tiny_maml(env)  # type: ignore[arg-type]
    if algo == "finetune":
        return tiny_finetune(env, policy_kwargs=dict(net_arch=[32, 32]))  # type: ignore[arg-type]
    return tiny_pearl(tiny_kwargs, PEARL if algo == "pearl" else PEARLPlus, env=env, seed=0)  # type: ignore[arg-type]


def _weights(model: Any) -> dict[str, th.Tensor]:
    return {key: value.clone() for key, value in model.policy.state_dict().items()}


# PEARL (tiny): iteration 0 = 4 tasks x 60 = 240 steps, then 2 x (30 + 10 + 30) = 140: 380 ends an iteration.
# MAML learns whole meta-iterations: its first learn() ends at the iteration boundary past the budget.
# Fine-Tune (SAC) collects across episodes: 130 splits an episode, which the saved env state continues.
@pytest.mark.parametrize(
    "algo, first, total", [("pearl", 380, 660), ("pearlplus", 380, 660), ("maml", 240, 600), ("finetune", 130, 200)]
)
def test_resume_after_save_load_is_bit_identical(
    tmp_path: Path, tiny_kwargs: dict[str, Any], algo: str, first: int, total: int
) -> None:
    unsplit = _make_for_resume(algo, tiny_kwargs)
    unsplit.learn(total)
    split = _make_for_resume(algo, tiny_kwargs)
    split.learn(first)
    done = split.num_timesteps
    split.save(tmp_path / "model")
    if hasattr(split, "save_replay_buffer"):
        split.save_replay_buffer(tmp_path / "buffer")
    th.manual_seed(123), np.random.seed(123)  # whatever happens in between: the saved RNG streams continue
    resumed = type(split).load(tmp_path / "model", env=gym.make(NOISY_ENV))
    if hasattr(resumed, "load_replay_buffer"):
        resumed.load_replay_buffer(tmp_path / "buffer.pkl")
    resumed.learn(total - done, reset_num_timesteps=False)
    assert resumed.num_timesteps == unsplit.num_timesteps and resumed._n_updates == unsplit._n_updates
    expected = _weights(unsplit)
    assert all(th.equal(value, expected[key]) for key, value in _weights(resumed).items())


# partial_iteration="carry": a budget ending inside an iteration keeps it open (with the envs' episodes), so a split
# anywhere is exact. 100 falls inside iteration 0 (4 x 60 initial steps), 300 inside iteration 1 (240 + 140).
# With prior_target="mc" the open iteration also holds the trajectory pieces awaiting their Monte-Carlo returns.
@pytest.mark.parametrize("first", [100, 300])
@pytest.mark.parametrize("reload", [False, True], ids=["same-process", "save-load"])
@pytest.mark.parametrize("prior_target", ["prior", "mc"])
def test_carry_splits_inside_an_iteration_bit_identically(
    tmp_path: Path, tiny_kwargs: dict[str, Any], first: int, reload: bool, prior_target: str
) -> None:
    def make() -> PEARL:
        env = gym.make(NOISY_ENV)
        return tiny_pearl(tiny_kwargs, env=env, seed=0, partial_iteration="carry", prior_target=prior_target)  # type: ignore[arg-type]

    unsplit = make().learn(660)
    split = make().learn(first)
    assert split.num_timesteps == first and split._open_iteration is not None
    assert split._n_updates == (5 if first > 240 else 0)  # only finished iterations are trained
    if reload:
        split.save(tmp_path / "model")
        split.save_replay_buffer(tmp_path / "buffer")
        th.manual_seed(123), np.random.seed(123)
        split = PEARLPlus.load(tmp_path / "model", env=gym.make(NOISY_ENV))
        split.load_replay_buffer(tmp_path / "buffer.pkl")
        assert split._open_iteration is not None and split._open_iteration.collected > 0
    split.learn(660 - first, reset_num_timesteps=False)
    assert split.num_timesteps == unsplit.num_timesteps == 660 and split._n_updates == unsplit._n_updates
    expected = _weights(unsplit)
    assert all(th.equal(value, expected[key]) for key, value in _weights(split).items())
    if prior_target == "mc":
        assert np.array_equal(split.replay_buffer.rl.return_reward, unsplit.replay_buffer.rl.return_reward)


def test_default_trains_the_collected_share_and_a_reset_requeues_an_open_iteration(tiny_kwargs: dict[str, Any]) -> None:
    share = tiny_pearl(tiny_kwargs, seed=0).learn(300)  # "train": iteration 1 is 60 of 140 steps in: ceil(5 * 60 / 140)
    assert share._open_iteration is None and share._n_updates == 5 + 3
    assert share.training_plan(440).gradient_steps == 5  # the next learn() starts a new, full iteration
    carry = tiny_pearl(tiny_kwargs, seed=0, partial_iteration="carry").learn(300)
    state = carry._open_iteration
    assert state is not None and (state.collected, state.planned) == (60, 140)
    assert carry.training_plan(380).gradient_steps == 5  # finishing the open iteration trains it in full
    open_steps = int(state.remaining.sum()) + sum(seg.n_steps for visit in state.running for seg in visit)
    carry.learn(80)  # reset_num_timesteps=True: the envs are reset, the open segments start again on fresh episodes
    assert carry._open_iteration is None and carry._n_updates == 10 and open_steps > 0
    assert carry.replay_buffer.rl.size.sum() == 380  # the iteration still collected exactly what it planned


@pytest.mark.parametrize("algo", ["pearlplus", "finetune", "maml"])
def test_resume_in_the_same_process_is_bit_identical(tiny_kwargs: dict[str, Any], algo: str) -> None:
    first, total = (380, 660) if algo == "pearlplus" else (240, 600) if algo == "maml" else (130, 200)
    unsplit = _make_for_resume(algo, tiny_kwargs)
    unsplit.learn(total)
    split = _make_for_resume(algo, tiny_kwargs)
    split.learn(first)
    split.learn(total - split.num_timesteps, reset_num_timesteps=False)
    expected = _weights(unsplit)
    assert all(th.equal(value, expected[key]) for key, value in _weights(split).items())


def test_train_py_resume_of_a_checkpoint_is_bit_identical(tmp_path: Path) -> None:
    # Tiny zoo entry: iteration 0 = 4 x 30 = 120 steps, then 5 x (30 + 30) = 300: --save-freq 100 saves at 120.
    def run(folder: Path, *extra: str) -> Completed:
        conf = tmp_path / "conf.yml"
        conf.write_text(yaml.safe_dump({ENV_ID: {**TINY_ZOO, "n_timesteps": 420, "meta_test": "dict(n_adapt=0)"}}))
        command = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(folder)]
        command += ["-conf", str(conf), "--seed", "1", "--num-threads", "1", "--eval-episodes", "1", *extra]
        return run_in_process(train, *command)  # train.py's entry point, in this process

    full = run(tmp_path / "full", "--save-freq", "100")
    run_dir = tmp_path / "full" / "pearlplus" / f"{ENV_ID}_1"
    assert f"Saving resumable checkpoint to {run_dir / 'rl_model_120_steps.zip'}" in full.stdout
    resumed = run(tmp_path / "resumed", "--resume", str(run_dir / "rl_model_120_steps.zip"))
    assert "Resuming at 120 timesteps: 300 to go" in resumed.stdout
    a = PEARLPlus.load(run_dir / f"{ENV_ID}.zip")
    b = PEARLPlus.load(tmp_path / "resumed" / "pearlplus" / f"{ENV_ID}_1" / f"{ENV_ID}.zip")
    assert a.num_timesteps == b.num_timesteps == 420
    assert all(th.equal(x, y) for x, y in zip(a.policy.state_dict().values(), b.policy.state_dict().values()))


def test_train_py_resume_of_a_fine_tune_checkpoint_is_bit_identical(tmp_path: Path) -> None:
    # SAC collects across episodes: the checkpoint at step 100 falls inside an episode (the envs' state is in the zip).
    conf = tmp_path / "conf.yml"
    entry = {
        "n_timesteps": 260,
        "policy": "MlpPolicy",
        "n_envs": 1,
        "learning_starts": 50,
        "batch_size": 16,
        "n_train_tasks": 4,
        "n_test_tasks": 2,
        "adapt_gradient_steps": 2,
        "policy_kwargs": "dict(net_arch=[32, 32])",
        "meta_test": "dict(n_adapt=0)",
    }
    conf.write_text(yaml.safe_dump({NOISY_ENV: entry}))

    def run(folder: Path, *extra: str) -> str:
        command = ["--algo", "finetune", "--env", NOISY_ENV, "-f", str(folder)]
        command += ["-conf", str(conf), "--seed", "1", "--num-threads", "1", "--eval-episodes", "1", *extra]
        command += ["--gym-packages", "tests.faulty_envs"]
        return run_in_process(train, *command).stdout  # train.py's entry point, in this process

    run(tmp_path / "full", "--save-freq", "100")
    run_dir = tmp_path / "full" / "finetune" / f"{NOISY_ENV}_1"
    assert (run_dir / "rl_model_100_steps.zip").is_file() and (run_dir / "rl_model_replay_buffer_100_steps.pkl").is_file()
    resumed = run(tmp_path / "resumed", "--resume", str(run_dir / "rl_model_100_steps.zip"))
    assert "Resuming at 100 timesteps: 160 to go" in resumed
    a = FineTune.load(run_dir / f"{NOISY_ENV}.zip")
    b = FineTune.load(tmp_path / "resumed" / "finetune" / f"{NOISY_ENV}_1" / f"{NOISY_ENV}.zip")
    assert a.num_timesteps == b.num_timesteps == 260 and a._n_updates == b._n_updates
    assert all(th.equal(x, y) for x, y in zip(a.policy.state_dict().values(), b.policy.state_dict().values()))


# ----------------------------------------------------------------------------------------------
# 8. Weak cases: one line each
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cls", [PEARL, PEARLPlus])
def test_observe_refuses_a_reward_that_is_not_a_scalar(cls: type[PEARL], tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, cls=cls, seed=0)
    obs = np.zeros(2, dtype=np.float32)
    with pytest.raises(ValueError, match=r"observe\(\): reward must be a scalar \(one transition\), got shape \(2,\)"):
        model.observe(obs, np.zeros(2), np.array([1.0, 2.0]), obs, False)
    assert model._adapt_context == []
    model.observe(obs, np.zeros(2), np.array([1.0]), obs, False)  # one reward in an array of one is one transition


def test_load_replay_buffer_of_a_model_zip_says_what_to_load(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0)
    model.save(tmp_path / "model.zip")
    fresh = model.replay_buffer
    with pytest.raises(ValueError, match=r"model.zip is a model zip, not a replay buffer pickle: load it with PEARLPlus.load"):
        model.load_replay_buffer(tmp_path / "model.zip")
    assert model.replay_buffer is fresh
    finetune = tiny_finetune()  # SB3's load_replay_buffer under the project's mixin
    finetune.save(tmp_path / "finetune.zip")
    with pytest.raises(
        ValueError, match=r"finetune.zip is a model zip, not a replay buffer pickle: load it with FineTune.load"
    ):
        finetune.load_replay_buffer(tmp_path / "finetune.zip")


def test_reproduce_seeds_beyond_numpys_bound_are_refused(tmp_path: Path) -> None:
    from pearl_paper.reproduce.cli import main
    from pearl_paper.reproduce.layout import parse_seeds

    assert parse_seeds("4294967295") == [4294967295]
    for text in ("4294967296", "0,4294967290-4294967296"):
        with pytest.raises(ValueError, match=r"--seeds: seeds must be integers in \[0, 4294967295\], got 4294967296"):
            parse_seeds(text)
    argv = ["status", "safe-point", "--seeds", "4294967296", "--results-dir", str(tmp_path)]
    proc = run_in_process(main, *argv, check=False)
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        "error: --seeds: seeds must be integers in [0, 4294967295], got 4294967296 (in '4294967296')"
    ]
