"""Checks that a saved model fits the env it is about to be used with (``train.py -i`` / ``--resume``, ``enjoy.py``,
``python -m sb3_pearl.diagnose``).

The run folder's ``args.yml`` names the env a model was trained on; without one, the model's own record tells its task
family (:func:`check_model_family`, or :func:`check_saved_model_family` before the model is loaded), and the message
names the env id to pass. Spaces are checked too (:func:`check_model_spaces`).

All raise :class:`~sb3_pearl.zoo.usage.UsageError` (one line, exit status 2) instead of a shape error deep in torch.
"""

from __future__ import annotations

import glob
import os
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.persistence import loaded_model_data, read_model_data
from sb3_pearl.common.tasks import env_task_family, family_fix, task_family_problem, vec_env_task_error
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.zoo.safe_config import load_run_yaml
from sb3_pearl.zoo.usage import UsageError


def check_model_env(model_path: str, env_id: str) -> None:
    """
    Raise a clear error (:class:`~sb3_pearl.zoo.usage.UsageError`) if the run folder of ``model_path`` says the model
    was trained on another env.

    :param model_path: path of the model zip (its folder holds ``<EnvId>/args.yml`` in the zoo layout)
    :param env_id: the env id it is about to be used with
    """
    for args_path in glob.glob(os.path.join(os.path.dirname(os.path.abspath(model_path)), "*", "args.yml")):
        saved = load_run_yaml(args_path) or {}
        trained_env = saved.get("env")
        if trained_env is not None and trained_env != env_id:
            raise UsageError(f"{model_path} was trained on {trained_env}, not on {env_id} (see {args_path})")


def check_model_spaces(model: BaseAlgorithm, env: Any, model_path: str, env_id: str) -> None:
    """
    Raise a clear error (:class:`~sb3_pearl.zoo.usage.UsageError`) if the model's observation / action spaces are not
    the env's.

    :param model: the loaded model
    :param env: the env (gymnasium env or VecEnv)
    :param model_path: for the message
    :param env_id: for the message
    """
    prepare_env = getattr(model, "prepare_env", None)
    if callable(prepare_env):  # the env as the model acts in it (the oracle: the task in the observation)
        env = prepare_env(env)
    for kind in ("observation_space", "action_space"):
        model_space, env_space = getattr(model, kind), getattr(env, kind)
        same = type(model_space) is type(env_space) and getattr(model_space, "shape", None) == getattr(
            env_space, "shape", None
        )
        if same and hasattr(model_space, "n"):
            same = int(model_space.n) == int(env_space.n)  # type: ignore[attr-defined]
        if not same:
            raise UsageError(f"{model_path} was saved for another env: its {kind} is {model_space}, {env_id} has {env_space}")


def check_model_family(model: BaseAlgorithm, env: Any, model_path: str, env_id: str, flag: str = "--env") -> None:
    """
    Raise a clear error (:class:`~sb3_pearl.zoo.usage.UsageError`) if the model was trained on another task family than
    the env's: the family the model recorded (``task_family``), else its training tasks checked with the env's
    ``task_error`` (a zip saved before the family was recorded). Two families can share their spaces (PointGoal and
    SafePointGoal, Walker2d and HalfCheetah), and a run folder without ``args.yml`` does not name its env.

    :param model: the loaded model
    :param env: the env (a gymnasium env, possibly wrapped, or a VecEnv)
    :param model_path: for the message
    :param env_id: for the message
    :param flag: the flag that chose the env, named by the fix (``--env``, ``--env-id``)
    """
    message = model_family_error(
        getattr(model, "task_family", None), list(getattr(model, "train_tasks", None) or []), env, model_path, env_id, flag
    )
    if message is not None:
        raise UsageError(message)


def check_saved_model_family(
    model_path: str, env: Any, env_id: str, flag: str = "--env", model_label: str | None = None
) -> None:
    """
    :func:`check_model_family` before the model is loaded: the family and training tasks are read from the zip's record
    (loading a model with an env of another family fails inside the constructor, with a fix for library users).

    :param model_path: the model zip (a truncated or corrupt one raises the ValueError of
        :func:`~sb3_pearl.common.persistence.read_model_data`)
    :param env: the env it is about to be used with (a gymnasium env or a VecEnv)
    :param env_id: for the message
    :param flag: the flag that chose the env, named by the fix
    :param model_label: how the message names the model (default: its path), e.g. ``-i <path>``
    """
    data = read_model_data(model_path)
    record = loaded_model_data({key: data[key] for key in ("task_family", "train_tasks") if key in data}, None)
    tasks = list(record.get("train_tasks") or [])
    message = model_family_error(record.get("task_family"), tasks, env, model_label or model_path, env_id, flag)
    if message is not None:
        raise UsageError(message)


def model_family_error(
    task_family: str | None, train_tasks: list[Task], env: Any, model_path: str, env_id: str, flag: str
) -> str | None:
    """
    The one-line message for a model of another task family than the env's, naming the env id(s) to pass, or None.

    :param task_family: the family the model recorded (None: a zip saved before the family was recorded)
    :param train_tasks: the model's training tasks (checked with the env's ``task_error``)
    :param env: a gymnasium env (possibly wrapped) or a VecEnv
    :param model_path: for the message
    :param env_id: for the message
    :param flag: the flag that chose the env
    :return: the message, or None when nothing says the families differ
    """
    if isinstance(env, VecEnv):
        family, task_error = env_task_family(env), vec_env_task_error(env)
    else:
        base = getattr(env, "unwrapped", env)
        family = base.task_family() if callable(getattr(base, "task_family", None)) else None
        task_error = getattr(base, "task_error", None)
        task_error = task_error if callable(task_error) else None
    problem = task_family_problem(task_family, train_tasks, family, task_error)
    if problem is None:
        return None
    fix = family_fix(task_family, f"pass {flag}", f"pass the {flag} it was trained on")
    return f"{model_path} was not trained on {env_id}: {problem}; {fix}"


__all__ = ["check_model_env", "check_model_family", "check_model_spaces", "check_saved_model_family", "model_family_error"]
