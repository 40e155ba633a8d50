"""The one definition of a trained model's meta-test: which tasks it uses, how it is seeded, and what it writes.

``train.py`` (the zoo's final meta-test and its ``--eval-freq`` callback), ``enjoy.py`` and the reproduction harness
(held-out, shifted and learning-curve meta-tests) all go through this module, so a zoo run's ``meta_test.csv`` /
``meta_test.json`` and a harness run's ``result.json`` of the same model hold the same numbers:

- **tasks**: ``n_tasks`` tasks of ``env.sample_tasks(n_tasks, eval_seed)``, drawn from the evaluation env (a shifted
  distribution is an env built with other ranges), refused if one is a training task of the model. The eval seed is
  recorded in the result; an experiment fixes one for all its variants and model seeds.
- **common random numbers**: the protocol runs with ``seed=eval_seed`` and ``crn_seed=eval_seed``, so every model
  meets the same env resets and draws its prior z from the same numbers (:func:`~sb3_pearl.evaluation.meta_test.meta_test`).
- **output**: :func:`meta_test_record` (the result's JSON dict with its settings), written by
  :func:`write_meta_test` as ``meta_test.json`` with the per-trajectory rows as ``meta_test.csv``; the harness stores
  the same record as ``result.json``'s ``meta_test`` section.

Before this module the zoo meta-tested on the model's saved ``test_tasks`` with the run's seed; since then every
pipeline uses the tasks above (CHANGELOG).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium as gym
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.evaluation.meta_test import MetaTestResult, json_value, meta_test

# The eval seed of train.py / enjoy.py when none is given (the harness's experiments fix their own, 10001-10004).
DEFAULT_EVAL_SEED = 10_000
# The settings of one meta-test and their defaults: K, repeats per task, deterministic actions, tasks (None: as many as
# the model holds test tasks, else 10).
META_TEST_DEFAULTS: dict[str, Any] = {"n_adapt": 5, "n_repeats": 1, "n_tasks": None, "deterministic": True}
DEFAULT_N_TASKS = 10


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_meta_test_settings(settings: Mapping[str, Any]) -> None:
    """
    Raise a ValueError naming the first meta-test setting out of its range; only the keys present are checked (a
    partial ``meta_test`` entry is checked before the defaults fill it in). A value is never replaced by a default:
    ``n_tasks=0`` is refused, not taken as "the model's test tasks", and ``deterministic='False'`` is refused, not
    taken as true.

    :param settings: some of ``n_adapt``, ``n_repeats``, ``n_tasks``, ``deterministic`` (:data:`META_TEST_DEFAULTS`)
        and the zoo's ``eval_seed``
    """
    rules = {
        "n_adapt": (lambda v: _is_int(v) and v >= 0, "an integer >= 0 (the last adapted trajectory k; 0: the prior only)"),
        "n_repeats": (lambda v: _is_int(v) and v >= 1, "an integer >= 1 (prior draws per task)"),
        "n_tasks": (lambda v: v is None or (_is_int(v) and v >= 1), "None (the model's test tasks) or an integer >= 1"),
        "deterministic": (lambda v: isinstance(v, bool), "True or False"),
        "eval_seed": (lambda v: _is_int(v) and v >= 0, "an integer >= 0 (the seed of the test tasks)"),
    }
    for key, (valid, expected) in rules.items():
        if key in settings and not valid(settings[key]):
            raise ValueError(f"meta_test {key} must be {expected}, got {settings[key]!r}")


def default_n_tasks(model: Any) -> int:
    """The number of test tasks when the settings leave it open: the model's own ``n_test_tasks`` (else 10)."""
    return len(getattr(model, "test_tasks", None) or []) or DEFAULT_N_TASKS


def held_out_tasks(
    env: gym.Env | VecEnv, n_tasks: int, eval_seed: int, train_tasks: Sequence[Task] = (), what: str = ""
) -> list[Task]:
    """
    The test tasks of a meta-test: ``env.sample_tasks(n_tasks, eval_seed)``.

    :param env: the evaluation env (a gymnasium env, possibly wrapped, or a VecEnv of one env)
    :param n_tasks: number of tasks
    :param eval_seed: seed of the draw
    :param train_tasks: the model's training tasks: a test task among them is an error
    :param what: the run, for the message
    :return: task dicts
    """
    if isinstance(env, VecEnv):
        tasks = list(env.env_method("sample_tasks", n_tasks, eval_seed, indices=[0])[0])
    else:
        base = env.unwrapped
        if not callable(getattr(base, "sample_tasks", None)):
            raise ValueError(f"{type(base).__name__} has no sample_tasks(): a meta-test needs a task-family env")
        tasks = list(base.sample_tasks(n_tasks, eval_seed))  # type: ignore[attr-defined]
    train = list(train_tasks)
    overlap = [task for task in tasks if task in train]
    if overlap:
        raise ValueError(
            f"{what + ': ' if what else ''}{len(overlap)} test task(s) drawn with eval_seed {eval_seed} are training tasks "
            "of the model: choose another eval seed"
        )
    return tasks


def model_test_tasks(model: Any, env: gym.Env | VecEnv, n_tasks: int | None, eval_seed: int, what: str = "") -> list[Task]:
    """
    :func:`held_out_tasks` for a trained model: ``n_tasks`` of them (None: :func:`default_n_tasks`), none of them one
    of the model's training tasks.

    :param model: the trained model (its ``train_tasks`` and ``test_tasks`` are read)
    :param env: the evaluation env
    :param n_tasks: number of tasks, or None
    :param eval_seed: seed of the draw
    :param what: the run, for the message
    :return: task dicts
    """
    train_tasks = list(getattr(model, "train_tasks", None) or [])
    return held_out_tasks(env, int(n_tasks or default_n_tasks(model)), eval_seed, train_tasks, what)


def run_meta_test(
    model: Any,
    env: gym.Env | VecEnv,
    tasks: Sequence[Task],
    settings: Mapping[str, Any],
    eval_seed: int,
    trace_keys: Sequence[str] | None = None,
    on_trajectory_start: Callable[[int, int, int], None] | None = None,
    progress_bar: bool = False,
    description: str = "Meta-test",
    n_prior_trajectories: int = 1,
) -> MetaTestResult:
    """
    The meta-test protocol on ``tasks`` with ``settings`` (``n_adapt``, ``n_repeats``, ``deterministic``), seeded by
    ``eval_seed`` with common random numbers; the eval seed is recorded in the result's config.

    :param model: a model with the adaptation API
    :param env: the evaluation env
    :param tasks: the tasks (:func:`held_out_tasks`, or training tasks for a competence check)
    :param settings: the meta-test settings
    :param eval_seed: seed of the resets and of the common random numbers
    :param trace_keys: per-step info entries kept as traces (None: the family's)
    :param on_trajectory_start: called with (task index, repeat, k) before each trajectory
    :param progress_bar: show a progress bar
    :param description: the bar's text
    :param n_prior_trajectories: trajectories with the prior before the first ``adapt()`` (the learning curve's protocol)
    :return: the result
    """
    result = meta_test(
        model,
        env,
        tasks,
        n_adapt=int(settings["n_adapt"]),
        n_repeats=int(settings["n_repeats"]),
        deterministic=bool(settings["deterministic"]),
        seed=eval_seed,
        trace_keys=trace_keys,
        crn_seed=eval_seed,
        on_trajectory_start=on_trajectory_start,
        progress_bar=progress_bar,
        description=description,
        n_prior_trajectories=n_prior_trajectories,
    )
    result.config["eval_seed"] = eval_seed
    return result


def held_out_meta_test(
    model: Any, env: gym.Env | VecEnv, settings: Mapping[str, Any], eval_seed: int, what: str = "", **kwargs: Any
) -> MetaTestResult:
    """
    :func:`run_meta_test` on :func:`model_test_tasks` (``settings["n_tasks"]`` of them, None: :func:`default_n_tasks`).

    :param model: a trained model with the adaptation API
    :param env: the evaluation env (the training ranges, or shifted ones)
    :param settings: some of ``n_adapt``, ``n_repeats``, ``n_tasks``, ``deterministic`` (the others from
        :data:`META_TEST_DEFAULTS`; the zoo's ``eval_seed`` may be among them); another key, or a value out of its
        range, is a ValueError that names it
    :param eval_seed: seed of the task draw, the resets and the common random numbers
    :param what: the run, for error messages
    :param kwargs: the other arguments of :func:`run_meta_test`
    :return: the result
    """
    known = {*META_TEST_DEFAULTS, "eval_seed"}
    unknown = sorted(set(settings) - known)
    if unknown:
        raise ValueError(f"meta-test settings: unknown key(s) {unknown}; the settings are some of {sorted(known)}")
    check_meta_test_settings(settings)
    settings = {**META_TEST_DEFAULTS, **settings}
    tasks = model_test_tasks(model, env, settings["n_tasks"], eval_seed, what)
    return run_meta_test(model, env, tasks, settings, eval_seed, **kwargs)


def meta_test_record(result: MetaTestResult, **extra: Any) -> dict[str, Any]:
    """The result as one JSON dict (config with the eval seed, summary, paper table, tasks, rows, traces) plus ``extra``."""
    return json_value({**result.to_dict(), **extra})


def held_out_record(
    model: Any,
    env: gym.Env | VecEnv,
    settings: Mapping[str, Any],
    eval_seed: int,
    env_kwargs: dict[str, Any],
    what: str = "",
    on_trajectory_start: Callable[[int, int, int], None] | None = None,
) -> dict[str, Any]:
    """
    A run's held-out meta-test as the harness's result.json stores it (``meta_test`` / ``shift``): the meta-test of
    every trained model (:func:`held_out_meta_test`, train.py's too) with its wall time and env kwargs, without per-step
    traces.

    :param model: the trained model
    :param env: the evaluation env (built with ``env_kwargs``)
    :param settings: the budget's meta-test settings
    :param eval_seed: the experiment's eval seed
    :param env_kwargs: the env's kwargs, recorded
    :param what: the run, for messages
    :param on_trajectory_start: called before every trajectory (the resume tests' interruption hook)
    :return: the record
    """
    start = time.time()
    # no per-step traces in result.json (the merge family's would add megabytes per run): trace_keys=()
    result = held_out_meta_test(model, env, settings, eval_seed, what, trace_keys=(), on_trajectory_start=on_trajectory_start)
    return meta_test_record(result, wall_time_s=time.time() - start, env_kwargs=env_kwargs)


def write_meta_test(result: MetaTestResult, folder: str | os.PathLike[str], title: str = "") -> dict[str, str]:
    """
    Write ``meta_test.csv`` (one row per trajectory), ``meta_test.json`` (:func:`meta_test_record`) and
    ``adaptation.png`` into ``folder``.

    :param result: the meta-test result
    :param folder: the run folder
    :param title: figure title
    :return: the written paths by kind
    """
    from sb3_pearl.evaluation.figures import plot_adaptation  # matplotlib only when needed

    os.makedirs(folder, exist_ok=True)
    paths = {
        "csv": os.path.join(folder, "meta_test.csv"),
        "json": os.path.join(folder, "meta_test.json"),
        "png": os.path.join(folder, "adaptation.png"),
    }
    result.to_csv(paths["csv"])
    result.to_json(paths["json"])
    plot_adaptation({title or result.config.get("algorithm", "model"): result}, paths["png"], title=title)
    return paths
