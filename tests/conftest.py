"""Shared fixtures: tiny PEARL / PEARL+ configurations that train in a second on the CPU."""

from __future__ import annotations

import contextlib
import io
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
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


def family_class(env_id: str) -> Callable[..., gym.Env]:
    """The class of a registered task family, to build it with any kwarg (``gym.make`` takes ``max_episode_steps``)."""
    from gymnasium.envs.registration import load_env_creator

    entry_point = gym.spec(env_id).entry_point
    return load_env_creator(entry_point) if isinstance(entry_point, str) else entry_point  # type: ignore[return-value]


def make_point_env() -> gym.Env:
    """Picklable factory: a SubprocVecEnv worker imports this module, hence sb3_pearl and its env ids."""
    return gym.make("PointGoalMeta-v0")


def make_discrete_env() -> gym.Env:
    return gym.wrappers.TimeLimit(DiscretePointGoalEnv(), max_episode_steps=20)


@pytest.fixture
def tiny_kwargs() -> dict[str, Any]:
    return {key: (dict(value) if isinstance(value, dict) else value) for key, value in TINY.items()}


@dataclass
class Completed:
    """What an entry point called in-process gave: the fields of ``subprocess.CompletedProcess`` the tests read."""

    returncode: int
    stdout: str
    stderr: str


def run_in_process(main: Callable[[list[str]], Any], *args: str, check: bool = True) -> Completed:
    """
    Call a command-line entry point (``sb3_pearl.zoo.train``, ``enjoy``, ``pearl_paper.reproduce.cli.main``, ...) in this
    process with ``args`` as its command line, and return its exit status and output.

    A new interpreter costs ~6 s before the first line of work (torch, rl_zoo3 and highway-env imports, and torch's
    lazy ``torch._dynamo`` import at the first optimizer): the tests call the entry points in-process wherever the
    separate process is not what they test (signals, a fresh install, concurrent workers and the harness's own child
    processes keep theirs). The exit status is that of ``SystemExit`` (0 when the entry point returns, or its return
    value when it returns an int; a message given to ``SystemExit`` goes to stderr with status 1, as Python does).
    Unlike a separate process, other exceptions propagate to the caller (``pytest.raises`` them), and only what is
    written to ``sys.stdout`` / ``sys.stderr`` is captured: logging handlers made before the call (Optuna's) are not.

    :param main: the entry point, taking the command line as a list
    :param args: the command line
    :param check: raise if the exit status is not 0
    :return: exit status, stdout and stderr
    """
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            value = main(list(args))
            code = value if isinstance(value, int) and not isinstance(value, bool) else 0
        except SystemExit as exit_info:
            code = exit_info.code if isinstance(exit_info.code, int) else (0 if exit_info.code is None else 1)
            if exit_info.code is not None and not isinstance(exit_info.code, int):
                print(exit_info.code, file=err)
    completed = Completed(code, out.getvalue(), err.getvalue())
    if check and code != 0:
        raise AssertionError(f"{' '.join(args)} exited {code}:\n{completed.stdout[-3000:]}\n{completed.stderr[-3000:]}")
    return completed


def write_model_zip(path: Path, size: int | None = None) -> None:
    """
    A minimal readable model zip (a ``data`` entry holding a JSON dict): a stand-in for a checkpoint's model where a test
    is about something else than the model (``reproduce status`` calls a zip it cannot read damaged).

    :param path: the zip to write
    :param size: pad the zip to exactly this many bytes (a checkpoint of a given size on disk)
    """

    def write(padding: int) -> None:
        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("data", "{}")
            if padding:
                archive.writestr("policy.pth", b"m" * padding)

    write(0)
    if size is not None:
        write(1)
        overhead = path.stat().st_size - 1
        write(size - overhead)
        assert path.stat().st_size == size


class CountSteps(BaseCallback):
    """Counts ``on_step`` calls (one per VecEnv step)."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def _on_step(self) -> bool:
        self.calls += 1
        return True


# The modules that take longest (Ray, harness runs, train.py processes) first: `make test` runs the suite on 2 workers,
# one module at a time each (`--dist loadfile`), and a long module dealt last leaves one worker idle meanwhile.
LONGEST_MODULES = (
    "test_reproduce_ray.py",
    "test_reliability.py",
    "test_cli.py",
    "test_reproduce.py",
    "test_reproduce_resume.py",
    "test_finetune.py",
    "test_newcomer.py",
    "test_tuning_storage.py",
    "test_reproduce_ownership.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Deal the longest modules first (stable: the order inside a module, and of the other modules, is kept)."""
    rank = {name: index for index, name in enumerate(LONGEST_MODULES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
