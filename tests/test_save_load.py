"""Save, load and resume, for every algorithm: a loaded model acts as the saved one; writes are atomic (a killed
save, a failed write or a full disk keeps the previous file); loads check what they read; a resume from a save or a
checkpoint continues bit for bit.

docs/reliability.md lists the faults these tests try and what each gets.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import multiprocessing
import os
import random
import signal
import tempfile
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from stable_baselines3 import SAC
from stable_baselines3.common.env_util import make_vec_env

import tests.faulty_envs  # noqa: F401  (registers the failing families)
from sb3_pearl import MAML, PEARL, FineTune, Oracle, PEARLPlus
from sb3_pearl.common import atomic, persistence
from sb3_pearl.common.atomic import atomic_write, sb3_file_path
from sb3_pearl.evaluation.meta_test import MetaTestResult
from sb3_pearl.zoo import train
from sb3_pearl.zoo.usage import program_name
from tests.conftest import (
    ENV_ID,
    TINY_ZOO,
    TINY_ZOO_PARAMS,
    Completed,
    CountSteps,
    make_discrete_env,
    run_in_process,
    tiny_finetune,
    tiny_maml,
    tiny_pearl,
)
from tests.test_finetune import probe_actions, rollout, tiny_model  # Fine-Tune's own save / load test
from tests.test_maml import make_model  # MAML's own save / load test
from tests.test_oracle import TINY  # the oracle's own save / load test

# ----------------------------------------------------------------------------------------------
# Every algorithm, as SB3's test_save_load.py: saved, loaded, the same parameters, actions and replay buffer
# ----------------------------------------------------------------------------------------------
ALGOS = ("pearl", "pearlplus", "finetune", "maml", "oracle")


def smoke_model(algo: str, tiny_kwargs: dict[str, Any]) -> Any:
    """An untrained smoke-size model of ``algo`` on :data:`ENV_ID` (seed 0) and the budget that trains it a little."""
    if algo in ("pearl", "pearlplus"):
        return tiny_pearl(tiny_kwargs, PEARL if algo == "pearl" else PEARLPlus, seed=0), 300  # 240 initial + training
    if algo == "oracle":
        return Oracle("MlpPolicy", ENV_ID, n_train_tasks=4, n_test_tasks=2, learning_starts=10, batch_size=8, seed=0), 100
    return (tiny_finetune(), 100) if algo == "finetune" else (tiny_maml(), 1)  # MAML: one meta-iteration at least


def assert_same(saved: Any, loaded: Any, where: str) -> None:
    """Tensors, arrays, numbers and the containers of them (state dicts, optimizer states) are equal, bit for bit."""
    if isinstance(saved, th.Tensor):
        assert isinstance(loaded, th.Tensor) and th.equal(saved.cpu(), loaded.cpu()), where
    elif isinstance(saved, np.ndarray):
        np.testing.assert_array_equal(saved, loaded, err_msg=where)
    elif isinstance(saved, dict):
        assert saved.keys() == loaded.keys(), where
        for key in saved:
            assert_same(saved[key], loaded[key], f"{where}[{key!r}]")
    elif isinstance(saved, (list, tuple)):
        assert len(saved) == len(loaded), where
        for index, (a, b) in enumerate(zip(saved, loaded)):
            assert_same(a, b, f"{where}[{index}]")
    else:
        assert saved == loaded, where


def buffer_rows(buffer: Any, where: str = "replay_buffer") -> dict[str, np.ndarray]:
    """The rows in use of every array of a replay buffer, by attribute path: what a saved buffer holds (rows past a
    buffer's size are free space, zeros or stale). PEARL's buffer holds per-task RL and context buffers, whose arrays
    are (task, row, ...) with a size per task; SB3's holds (row, env, ...) with one size."""
    if hasattr(buffer, "rl") and hasattr(buffer, "context"):
        return {**buffer_rows(buffer.rl, f"{where}.rl"), **buffer_rows(buffer.context, f"{where}.context")}
    per_task = isinstance(buffer.size, np.ndarray)
    rows = {}
    for name, value in vars(buffer).items():
        if not isinstance(value, np.ndarray):
            continue
        if per_task and name not in ("pos", "size"):
            for task, size in enumerate(buffer.size):
                rows[f"{where}.{name}[{task}]"] = value[task, :size]
        else:
            rows[f"{where}.{name}"] = value if per_task else value[: buffer.size()]
    return rows


def assert_same_buffers(saved: Any, loaded: Any) -> None:
    """The rows in use of two replay buffers are equal, array by array (and every buffer holds some)."""
    saved_rows, loaded_rows = buffer_rows(saved), buffer_rows(loaded)
    assert saved_rows and saved_rows.keys() == loaded_rows.keys()
    assert all(len(rows) for rows in saved_rows.values())  # learn() filled every buffer
    for name, rows in saved_rows.items():
        np.testing.assert_array_equal(rows, loaded_rows[name], err_msg=name)


def act_after_adaptation(model: Any, observations: np.ndarray, transitions: list[tuple[Any, ...]]) -> list[np.ndarray]:
    """The adaptation API as the meta-test calls it: deterministic actions on ``observations`` with the prior (k = 0),
    then after ``observe`` of ``transitions`` and ``adapt`` (k = 1)."""
    model.set_random_seed(3)  # PEARL draws z from the prior and the posterior; Fine-Tune's adaptation samples batches
    model.reset_adaptation()
    actions = [model.predict(observations, deterministic=True)[0]]
    for transition in transitions:
        model.observe(*transition)
    model.adapt()
    actions.append(model.predict(observations, deterministic=True)[0])
    return actions


@pytest.mark.parametrize("algo", ALGOS)
def test_save_load(algo: str, tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    """Every algorithm, learnt a little at smoke size, saved and loaded (no env): the same parameters and optimizer
    states, the same deterministic actions before and after adapting to the same observed transitions, and (off-policy
    algorithms) the same replay buffer."""
    model, budget = smoke_model(algo, tiny_kwargs)
    model.learn(budget)
    model.save(tmp_path / "model.zip")
    loaded = type(model).load(tmp_path / "model.zip")
    assert type(loaded) is type(model)
    assert loaded.train_tasks == model.train_tasks and loaded.test_tasks == model.test_tasks
    assert_same(model.get_parameters(), loaded.get_parameters(), "get_parameters()")

    rng = np.random.default_rng(0)
    shape = model.observation_space.shape
    observations = rng.uniform(-1, 1, size=(16, *shape)).astype(np.float32)
    transitions = []
    for step in range(10):
        obs, next_obs = rng.uniform(-1, 1, size=(2, *shape)).astype(np.float32)
        action = rng.uniform(model.action_space.low, model.action_space.high).astype(np.float32)
        transitions.append((obs, action, -1.0 + 0.1 * step, next_obs, step == 9))
    expected = act_after_adaptation(model, observations, transitions)
    got = act_after_adaptation(loaded, observations, transitions)
    for k, (a, b) in enumerate(zip(expected, got)):
        np.testing.assert_array_equal(a, b, err_msg=f"deterministic actions after {k} adaptation(s)")

    if algo == "maml":  # on-policy: no replay buffer
        assert not hasattr(model, "save_replay_buffer")
        return
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    assert_same_buffers(model.replay_buffer, loaded.replay_buffer)


def test_learn_after_a_load_without_env_says_what_to_do(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    """Guards against: FineTune.load(path).learn() ended in an AssertionError without a message (MAML too)."""
    for model in (tiny_pearl(tiny_kwargs), tiny_finetune(), tiny_maml()):
        name = type(model).__name__
        model.save(tmp_path / name)
        loaded = type(model).load(tmp_path / f"{name}.zip")
        with pytest.raises(ValueError, match=rf"{name}.learn\(\): the model has no env .*set_env\(env\) first"):
            loaded.learn(10)


@pytest.mark.parametrize("algo", ALGOS)
def test_save_load_to_file_objects(algo: str, tiny_kwargs: dict[str, Any]) -> None:
    """SB3's ``save`` / ``load`` and ``save_replay_buffer`` / ``load_replay_buffer`` also take open files (an
    ``io.BytesIO`` here), not only paths, for every algorithm."""
    model, budget = smoke_model(algo, tiny_kwargs)
    model.learn(budget)
    file = io.BytesIO()
    model.save(file)
    file.seek(0)
    loaded = type(model).load(file)
    assert_same(model.get_parameters(), loaded.get_parameters(), "get_parameters()")
    if algo == "maml":
        return
    file = io.BytesIO()
    model.save_replay_buffer(file)
    file.seek(0)
    loaded.load_replay_buffer(file)
    assert_same_buffers(model.replay_buffer, loaded.replay_buffer)


def no_temporary_files(folder: Path) -> bool:
    return not [name for name in os.listdir(folder) if ".tmp" in name]


# ----------------------------------------------------------------------------------------------
# Atomic writes
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
# Checked loads: a file that does not fit is refused with its reason
# ----------------------------------------------------------------------------------------------
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
        ("pearl", {"prior_coef": float("nan")}, r"prior_coef=nan is a setting of PEARLPlus, which PEARL does not have"),
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


def _with_data(path: Path, out: Path, **entries: Any) -> Path:
    """A copy of the zip ``path`` at ``out`` whose ``data`` entry also holds ``entries`` (a zip of an older version)."""
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(out, "w") as target:
        for item in source.infolist():
            raw = source.read(item.filename)
            if item.filename == "data":
                raw = json.dumps({**json.loads(raw), **entries}).encode()
            target.writestr(item, raw)
    return out


def test_pearl_zips_with_and_without_pearlpluss_settings(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    """PEARL saves no PEARL+ setting; a PEARL zip written before the split (PEARL+'s settings at their neutral values)
    loads with PEARL, which drops them, and acts the same; PEARLPlus.load takes either with no prior term."""
    model = tiny_pearl(tiny_kwargs, PEARL, seed=0)
    model.learn(4 * tiny_kwargs["num_initial_steps"])
    model.save(tmp_path / "new.zip")
    new_data = persistence.read_model_data(tmp_path / "new.zip")
    assert not [key for key in new_data if key.startswith("prior_")]
    old = _with_data(tmp_path / "new.zip", tmp_path / "old.zip", prior_coef=0.0, prior_critic_mode="none", prior_data="all")
    obs = np.random.default_rng(0).uniform(-1, 1, (5, model.observation_space.shape[0])).astype(np.float32)
    actions = []
    for path in (tmp_path / "new.zip", old):
        loaded = PEARL.load(path)
        assert not [name for name in vars(loaded) if name.startswith("prior_")]
        loaded.reset_adaptation()
        th.manual_seed(1)
        actions.append(loaded.predict(obs, deterministic=True)[0])
        with open(path, "rb") as file:  # a stream as well
            assert not [name for name in vars(PEARL.load(file)) if name.startswith("prior_")]
    np.testing.assert_array_equal(actions[0], actions[1])
    for path in (tmp_path / "new.zip", old):
        plus = PEARLPlus.load(path)
        settings = (plus.prior_coef, plus.prior_critic_mode, plus.prior_data, plus.prior_critic, plus.uses_prior_term)
        assert settings == (0.0, "none", "all", None, False), path
        with open(path, "rb") as file:
            assert PEARLPlus.load(file).prior_coef == 0.0
    # A zip with a prior term is PEARL+'s, whichever way it is handed over.
    plus_zip = _with_data(tmp_path / "new.zip", tmp_path / "plus.zip", prior_coef=0.1, prior_critic_mode="shared")
    with pytest.raises(ValueError, match=r"holds a PEARL\+ model .*load it with PEARLPlus.load"):
        PEARL.load(plus_zip)
    with open(plus_zip, "rb") as file, pytest.raises(ValueError, match=r"holds a PEARL\+ model"):
        PEARL.load(file)


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
# Exact resume
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


# ----------------------------------------------------------------------------------------------
# Failed saves and resumes: one line naming the file or the flag
# ----------------------------------------------------------------------------------------------
def test_a_resume_without_its_replay_buffer_is_refused_in_one_line(tmp_path: Path) -> None:
    model = tmp_path / f"{ENV_ID}.zip"  # the run's model: its buffer is the folder's replay_buffer.pkl
    model.write_bytes(b"")  # the check comes before anything reads it
    refused = run_in_process(train, "--algo", "pearlplus", "--env", ENV_ID, f"--resume={model}", check=False)
    assert refused.returncode == 2
    assert refused.stderr.strip().count("\n") == 0
    assert f"--resume {model}: no replay buffer beside it ({tmp_path / 'replay_buffer.pkl'})" in refused.stderr
    assert "add --resume-without-buffer to go on anyway" in refused.stderr


def test_a_resume_of_a_model_the_folders_buffer_does_not_belong_to_is_refused(tmp_path: Path) -> None:
    """Guards against: --resume best_model.zip loaded the folder's replay_buffer.pkl, the buffer of the run's last
    step, into an earlier model."""
    model = tmp_path / "best_model.zip"
    model.write_bytes(b"")
    (tmp_path / "replay_buffer.pkl").write_bytes(b"x")
    refused = run_in_process(train, "--algo", "pearlplus", "--env", ENV_ID, "--resume", str(model), check=False)
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0
    assert f"--resume {model}: no replay buffer belongs to this model" in refused.stderr
    assert "the folder's replay_buffer.pkl is of another step" in refused.stderr


def test_save_to_a_path_it_cannot_write_names_the_destination(
    tmp_path: Path, tiny_kwargs: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0)
    (tmp_path / "file").write_text("")
    with pytest.raises(OSError, match=rf"cannot write {tmp_path / 'file' / 'model.zip'}: {tmp_path / 'file'} is a file"):
        model.save(tmp_path / "file" / "model.zip")

    def refused(*args: Any, **kwargs: Any) -> Any:  # what a folder without write permission gives (tests run as root)
        raise PermissionError(13, "Permission denied", str(tmp_path / ".model.x1y2.tmp.zip"))

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    with pytest.raises(PermissionError, match=rf"cannot write {tmp_path / 'model.zip'}: Permission denied in {tmp_path}$"):
        model.save(tmp_path / "model.zip")


# ----------------------------------------------------------------------------------------------
# An empty checkpoint replay buffer: the advice works, --resume-without-buffer goes on
# ----------------------------------------------------------------------------------------------
def test_resume_with_an_empty_checkpoint_buffer_names_it_and_the_flag_works(tmp_path: Path) -> None:
    """Guards against: '... not a complete replay buffer pickle ...; train without it', also with --resume-without-buffer."""
    logs = tmp_path / "logs"
    base = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(logs), "--seed", "1", "--eval-freq", "1000"]
    run_in_process(train, *base, "-n", "300", "--save-freq", "100", "-params", *TINY_ZOO_PARAMS)
    run = logs / "pearlplus" / f"{ENV_ID}_1"
    checkpoint, buffer = run / "rl_model_120_steps.zip", run / "rl_model_replay_buffer_120_steps.pkl"
    buffer.write_bytes(b"")
    resume = [*base, "-n", "300", "--resume", str(checkpoint)]
    refused = run_in_process(train, *resume, "-params", *TINY_ZOO_PARAMS, check=False)
    problem = f"{buffer} is not a complete replay buffer pickle (0 bytes: the file is empty)"
    assert refused.returncode == 2 and refused.stderr.strip().splitlines()[-1].endswith(
        f"{problem}: add --resume-without-buffer to resume from an empty buffer (the run then differs from the "
        "uninterrupted one)"
    )
    resumed = run_in_process(train, *resume, "--resume-without-buffer", "-params", *TINY_ZOO_PARAMS)
    assert f"Warning: {problem}: going on from an empty replay buffer (--resume-without-buffer)" in resumed.stdout
    assert "Resuming at 120 timesteps: 180 to go" in resumed.stdout
    assert (logs / "pearlplus" / f"{ENV_ID}_2" / f"{ENV_ID}.zip").is_file()
    # rl_zoo3's own <folder>/replay_buffer.pkl, loaded with -i, is checked the same way
    pickle_path = run / "replay_buffer.pkl"
    pickle_path.write_bytes(b"\x80\x05")
    model = str(run / f"{ENV_ID}.zip")
    refused = run_in_process(train, *base, "-n", "100", "-i", model, "-params", *TINY_ZOO_PARAMS, check=False)
    assert refused.returncode == 2 and refused.stderr.strip().splitlines()[-1].endswith(
        f"{pickle_path} is not a complete replay buffer pickle (EOFError: Ran out of input): move it away to continue "
        "training from an empty buffer"
    )


# ----------------------------------------------------------------------------------------------
# Disk full at train.py's final save: one line naming the file; nothing older overwritten
# ----------------------------------------------------------------------------------------------
def test_a_full_disk_at_the_final_save_is_one_line_naming_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Guards against: three to five chained tracebacks (zipfile, atomic_write, rl_zoo3) naming no file."""
    real_atomic_write = atomic.atomic_write
    model_file = tmp_path / "logs" / "pearlplus" / f"{ENV_ID}_1" / f"{ENV_ID}.zip"

    @contextlib.contextmanager
    def full_disk(path: str | os.PathLike[str], mode: str = "wb", **kwargs: Any) -> Iterator[IO[Any]]:
        with real_atomic_write(path, mode, **kwargs) as file:
            if Path(path) == model_file:
                file.write(b"PK\x03\x04 half a zip")
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as a write to the full device raises it
            yield file

    monkeypatch.setattr(persistence, "atomic_write", full_disk)
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "logs"), "-n", "200", "--eval-freq", "1000"]
    proc = run_in_process(train, *argv, "-params", *TINY_ZOO_PARAMS, check=False)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines() == [
        f"{program_name()}: error: saving the trained model failed: cannot write {model_file}: No space left on device "
        "(ENOSPC); "
        "nothing older was overwritten (every save writes a temporary file and renames it into place, and the "
        "temporary file was removed): free space (or choose another -f) and train again"
    ]
    assert not model_file.exists() and not [path for path in model_file.parent.iterdir() if ".tmp" in path.name]


def test_a_write_error_keeps_the_previous_file_and_names_it(tmp_path: Path) -> None:
    """What the message promises: the previous file is kept, the temporary one removed, the error names the file."""
    destination = tmp_path / "model.zip"
    destination.write_bytes(b"the previous model")
    with (
        pytest.raises(OSError, match=rf"cannot write {destination}: No space left on device$") as raised,
        atomic.atomic_write(destination) as file,
    ):
        file.write(b"half a zip")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert raised.value.errno == errno.ENOSPC
    assert destination.read_bytes() == b"the previous model" and os.listdir(tmp_path) == ["model.zip"]


# ----------------------------------------------------------------------------------------------
# Each algorithm's own save / load: what its zip holds beyond the parameters
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("discrete", [False, True])
def test_pearlplus_save_load_equivalence(tmp_path: Path, discrete: bool, tiny_kwargs: dict[str, Any]) -> None:
    env = make_discrete_env() if discrete else gym.make("SafePointGoalMeta-v0")
    # the learned entropy coefficient (saved as a tensor with its optimizer) and the fixed default
    model = PEARLPlus("MlpPolicy", env, seed=0, ent_coef=1.0 if discrete else "auto", **tiny_kwargs)
    model.learn(400)
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded = PEARLPlus.load(tmp_path / "model.zip")  # no env needed
    assert loaded.train_tasks == model.train_tasks and loaded.test_tasks == model.test_tasks
    obs = th.rand(32, 2) * 2 - 1
    z = th.randn(32, model.latent_dim)
    assert th.equal(model.policy.act(obs, z, deterministic=True), loaded.policy.act(obs, z, deterministic=True))
    x = th.cat([obs, z], dim=-1)
    if not discrete:
        x = th.cat([x, th.rand(32, 2) * 2 - 1], dim=-1)
    assert model.prior_critic is not None and loaded.prior_critic is not None
    assert th.equal(model.prior_critic(x), loaded.prior_critic(x))
    assert th.equal(model.critic_target(x), loaded.critic_target(x))
    for name in ("encoder", "actor", "critic", "prior_critic"):
        saved = getattr(model, name).optimizer.state_dict()["state"]
        restored = getattr(loaded, name).optimizer.state_dict()["state"]
        assert th.equal(saved[0]["exp_avg"], restored[0]["exp_avg"]), name
    if discrete:
        assert loaded.log_ent_coef is None and th.equal(loaded.ent_coef_tensor, model.ent_coef_tensor)
    else:
        assert loaded.log_ent_coef is not None and th.equal(loaded.log_ent_coef, model.log_ent_coef)
    # Adaptation gives the same posterior from the same context.
    for m in (model, loaded):
        m.reset_adaptation()
        for t in range(5):
            m.observe(
                np.array([0.1 * t, 0.0]), 1 if discrete else np.array([0.05, -0.05]), -1.0 + t, np.array([0.1, 0.2]), False
            )
    assert all(th.allclose(a, b) for a, b in zip(model.infer_posterior(), loaded.infer_posterior()))
    # Buffers round trip, and training goes on with the env set again.
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    np.testing.assert_array_equal(loaded.replay_buffer.rl.observations, model.replay_buffer.rl.observations)
    np.testing.assert_array_equal(loaded.replay_buffer.context.size, model.replay_buffer.context.size)
    loaded.set_env(env)
    loaded.learn(100, reset_num_timesteps=False)
    assert loaded.num_timesteps == 500


def test_load_rejects_another_env(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "SafePointGoalMeta-v0", seed=0, **tiny_kwargs)
    model.save(tmp_path / "model.zip")
    with pytest.raises(ValueError, match="Action spaces do not match|Observation spaces do not match"):
        PEARLPlus.load(tmp_path / "model.zip", env=make_vec_env(make_discrete_env))


def test_saved_replay_buffer_holds_only_used_rows(tmp_path: Path, tiny_kwargs: dict[str, Any]) -> None:
    model = PEARLPlus("MlpPolicy", "PointGoalMeta-v0", seed=0, buffer_size=1_000_000, **tiny_kwargs)
    model.learn(300)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    assert (tmp_path / "buffer.pkl").stat().st_size < 1_000_000  # 4 tasks x 1e6 rows would be > 100 MB
    model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert model.replay_buffer.rl.observations.shape == (4, 1_000_000, 2)
    model.learn(100, reset_num_timesteps=False)


@pytest.mark.parametrize("discrete", [False, True])
def test_finetune_save_load_equivalence(tmp_path: Path, discrete: bool) -> None:
    model = tiny_model(make_discrete_env() if discrete else "PointGoalMeta-v0", learn=200)
    if not discrete:  # save while adapted: the zip holds the pretrained model only
        rollout(model, model.test_tasks[0], deterministic=False)
        model.adapt()
    model.save(tmp_path / "model.zip")
    loaded = FineTune.load(tmp_path / "model.zip")
    assert loaded.train_tasks == model.train_tasks and loaded.test_tasks == model.test_tasks
    assert loaded.max_episode_steps == model.max_episode_steps == 20
    assert loaded.adapt_gradient_steps == model.adapt_gradient_steps
    assert type(loaded.policy) is type(model.policy)
    # Saving forgot the adaptation: the loaded model acts like the pretrained policy.
    model.reset_adaptation()
    np.testing.assert_array_equal(probe_actions(loaded), probe_actions(model))
    if discrete:
        return
    # Optimizer states and the entropy coefficient were saved too: the same fine-tuning gives the same policy.
    results = []
    for m in (model, loaded):
        m.reset_adaptation()
        m.set_random_seed(3)
        rollout(m, model.test_tasks[0], deterministic=False)
        m.adapt()
        results.append(probe_actions(m))
    np.testing.assert_allclose(results[0], results[1], atol=1e-6)


def test_learn_save_load_identical_actions(tmp_path: Any) -> None:
    model = make_model(n_envs=2)
    callback = CountSteps()
    model.learn(1, callback=callback)  # one meta-iteration: 2 phases x 4 tasks x 4 episodes x 20 steps
    assert model.num_timesteps == 2 * 4 * 4 * 20
    assert callback.calls == 2 * 4 * 4 * 20 // 2
    model.save(tmp_path / "maml.zip")
    loaded = MAML.load(tmp_path / "maml.zip")
    assert loaded.train_tasks == model.train_tasks and loaded.test_tasks == model.test_tasks
    assert loaded.max_episode_steps == 20
    obs = np.random.default_rng(0).uniform(-1, 1, size=(16, 2)).astype(np.float32)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    # with an env (another n_envs): training continues, on the saved task lists
    resumed = MAML.load(tmp_path / "maml.zip", env=make_vec_env("PointGoalMeta-v0", n_envs=1, seed=1))
    assert resumed.train_tasks == model.train_tasks
    resumed.learn(1, reset_num_timesteps=False)
    assert resumed.num_timesteps == 2 * model.num_timesteps


def test_oracle_learns_saves_loads_and_acts_identically(tmp_path) -> None:
    model = Oracle("MlpPolicy", "PointGoalMeta-v0", seed=0, **TINY)
    assert model.observation_space.shape == (4,)  # position (2) + goal (2)
    model.learn(300)
    path = tmp_path / "oracle.zip"
    model.save(path)
    loaded = Oracle.load(path)
    assert loaded.train_tasks == model.train_tasks and loaded.test_tasks == model.test_tasks
    obs = np.stack([model.observation_space.sample() for _ in range(8)])
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    # a Fine-Tune zip is not an oracle's (its policy sees no task)
    finetune = FineTune("MlpPolicy", "PointGoalMeta-v0", seed=0, **TINY)
    finetune.save(tmp_path / "finetune.zip")
    with pytest.raises(ValueError, match="holds a FineTune model, not a Oracle one"):
        Oracle.load(tmp_path / "finetune.zip")


# ----------------------------------------------------------------------------------------------
# Replay buffers saved compact: the filled rows only
# ----------------------------------------------------------------------------------------------


def test_a_part_filled_sac_buffer_is_saved_compact_and_loads_to_the_same_rows(tmp_path: Path) -> None:
    """SB3 pickles all buffer_size rows of a replay buffer; the project's save keeps the filled ones (a checkpoint of a
    part-way 500k Ant run was 1.8 GB), and the load restores the full allocation, rows past pos zero as SB3 makes them."""
    from sb3_pearl import FineTune

    kwargs: dict[str, Any] = dict(n_train_tasks=4, n_test_tasks=2, learning_starts=10, batch_size=8, seed=0)
    model = FineTune("MlpPolicy", NOISY_ENV, buffer_size=100_000, **kwargs)  # far more rows than are filled
    model.learn(150)
    model.save_replay_buffer(tmp_path / "buffer")
    full = model.replay_buffer
    assert (tmp_path / "buffer.pkl").stat().st_size < 0.05 * full.observations.nbytes
    other = FineTune("MlpPolicy", NOISY_ENV, buffer_size=100_000, **kwargs)
    other.load_replay_buffer(tmp_path / "buffer.pkl")
    buffer = other.replay_buffer
    assert (buffer.pos, buffer.full, buffer.buffer_size) == (full.pos, full.full, full.buffer_size)
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        np.testing.assert_array_equal(getattr(buffer, name), getattr(full, name))
    assert full.observations.shape[0] == 100_000  # the model's own buffer was left whole by the save


def test_an_older_checkpoint_is_compacted_in_place_and_loads_the_same_buffer(tmp_path: Path) -> None:
    """`reproduce compact`: a checkpoint written with the whole allocation (before compact buffers) is rewritten with
    the filled rows only; the state names the new parts, the old ones are gone, and loading it gives the same buffer."""
    import pickle

    from pearl_paper.reproduce.checkpoint import PART_BYTES, RunCheckpoint
    from sb3_pearl import FineTune

    kwargs: dict[str, Any] = dict(n_train_tasks=4, n_test_tasks=2, learning_starts=10, batch_size=8, seed=0)
    model = FineTune("MlpPolicy", NOISY_ENV, buffer_size=200_000, **kwargs).learn(150)
    checkpoint = RunCheckpoint(tmp_path)
    files = checkpoint.save_model(model, None)
    whole = pickle.dumps(model.replay_buffer)  # as an older save wrote it: every allocated row
    assert len(whole) > PART_BYTES / 10
    files = {key: name for key, name in files.items() if not key.startswith("replay")}
    files.update(checkpoint._write_parts("replay_150.pkl", whole, "replay"))
    checkpoint.write_state({"phase": "train", "files": files, "num_timesteps": 150})
    before, after = checkpoint.compact_replay()
    assert before == len(whole) and after < before / 20
    state = checkpoint.read_state()
    assert state is not None and "replay_150.pkl" not in state["files"].values()
    assert not (checkpoint.folder / "replay_150.pkl").exists() and any(checkpoint.folder.glob("replay_150_compact*"))
    resumed = checkpoint.load_model(state, FineTune, gym.make(NOISY_ENV))
    for name in ("observations", "actions", "rewards", "dones"):
        np.testing.assert_array_equal(getattr(resumed.replay_buffer, name), getattr(model.replay_buffer, name))
    files_before = dict(checkpoint.read_state()["files"])  # type: ignore[index]
    mtimes = {name: (checkpoint.folder / name).stat().st_mtime_ns for name in files_before.values()}
    again, again_after = checkpoint.compact_replay()  # compact already: nothing is rewritten
    assert again == again_after and checkpoint.read_state()["files"] == files_before  # type: ignore[index]
    assert all((checkpoint.folder / name).stat().st_mtime_ns == mtime for name, mtime in mtimes.items())


def test_a_buffer_that_keeps_next_observations_in_place_is_not_compacted() -> None:
    """With optimize_memory_usage SB3 keeps the last next observation in observations[pos]: cutting at pos would lose
    it, so such a buffer is pickled whole."""
    from stable_baselines3.common.buffers import ReplayBuffer

    from sb3_pearl.common.persistence import compact_buffer

    env = gym.make(NOISY_ENV)
    buffer = ReplayBuffer(
        100, env.observation_space, env.action_space, optimize_memory_usage=True, handle_timeout_termination=False
    )
    for _ in range(3):
        obs = env.observation_space.sample()[None]
        buffer.add(obs, obs + 1, env.action_space.sample()[None], np.zeros(1), np.zeros(1), [{}])
    assert compact_buffer(buffer) is buffer
    plain = ReplayBuffer(100, env.observation_space, env.action_space)
    compact = compact_buffer(plain)
    assert compact is not plain and compact_buffer(compact) is compact  # compacting twice changes nothing
