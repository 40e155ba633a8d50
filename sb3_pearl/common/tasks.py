"""The algorithm side of the task protocol, shared by PEARL, PEARL+, Fine-Tune and MAML.

Checking that an env is a task family the algorithm can use, and drawing a model's training and
held-out test tasks. The env side (``sample_tasks`` / ``set_task`` / ``get_task``) lives in
:mod:`sb3_pearl.envs.task_protocol`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from gymnasium import spaces
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from sb3_pearl.envs.task_protocol import TASK_METHODS, Task


def check_meta_env(
    algorithm: str,
    env: Any,
    observation_space: spaces.Space,
    action_space: spaces.Space | None,
    vec_normalize_env: Any = None,
    flat_observations: bool = False,
) -> None:
    """
    Raise a clear error unless ``env`` is a VecEnv of task families the algorithm can use.

    :param algorithm: name of the algorithm, for the messages
    :param env: the VecEnv
    :param observation_space: its observation space (a Box)
    :param action_space: its action space (Box or Discrete); None skips the check (the algorithm checks it)
    :param vec_normalize_env: the model's VecNormalize wrapper, if any (not supported)
    :param flat_observations: also require a 1-D observation space
    """
    if action_space is not None and not isinstance(action_space, (spaces.Box, spaces.Discrete)):
        raise ValueError(
            f"{algorithm} supports Box and Discrete action spaces, got {type(action_space).__name__}: {action_space}"
        )
    if not isinstance(observation_space, spaces.Box) or (flat_observations and len(observation_space.shape) != 1):
        shape = "a flat Box observation space of shape (obs_dim,)" if flat_observations else "a Box observation space"
        raise ValueError(f"{algorithm} needs {shape}, got {observation_space}")
    if vec_normalize_env is not None:
        raise ValueError(
            "VecNormalize is not supported: the adaptation API passes raw observations and rewards, and per-env "
            "task switches reset envs below the VecEnv wrappers"
        )
    check_task_vec_env(env, algorithm)


def check_task_vec_env(env: Any, algorithm: str) -> None:
    """
    Raise a clear error unless every env of a VecEnv follows the task protocol.

    :param env: the VecEnv
    :param algorithm: name of the algorithm, for the message
    """
    missing = [name for name in TASK_METHODS if not env.has_attr(name)]
    if missing:
        raise ValueError(
            f"{algorithm} needs a task-family env with sample_tasks(n, seed), set_task(task) and get_task(); "
            f"missing {missing}. See sb3_pearl.envs.task_protocol.MetaTaskEnv, e.g. gym.make('SafePointGoalMeta-v0')."
        )


def env_task_family(env: Any) -> str | None:
    """
    The task family of a VecEnv's first env (:meth:`~sb3_pearl.envs.task_protocol.MetaTaskEnv.task_family`).

    :param env: a VecEnv
    :return: the family's name, or None for an env that does not tell it (a task family of another package)
    """
    if not env.has_attr("task_family"):
        return None
    return str(env.env_method("task_family", indices=[0])[0])


def vec_env_task_error(env: Any) -> Callable[[Task], str | None] | None:
    """
    The ``task_error`` of a VecEnv's first env as a function (None when the env has none).

    :param env: a VecEnv
    :return: task -> why it is not a task of the env, or None
    """
    if not env.has_attr("task_error"):
        return None
    return lambda task: env.env_method("task_error", task, indices=[0])[0]


def family_env_ids(family: str | None) -> list[str]:
    """
    The registered env ids of a task family: those whose entry point is the family's class (a family's name is its
    class name, :meth:`~sb3_pearl.envs.task_protocol.MetaTaskEnv.task_family`), for the fix a message suggests.

    :param family: the family's name (None: not recorded)
    :return: e.g. ``["PointGoalMeta-v0"]``; empty for None or a family no registered id builds
    """
    import gymnasium as gym

    if family is None:
        return []
    return sorted(
        env_id
        for env_id, spec in gym.registry.items()
        if isinstance(spec.entry_point, str) and spec.entry_point.rpartition(":")[2] == family
    )


def family_fix(family: str | None, how: str, otherwise: str) -> str:
    """
    The fix of a family mismatch: ``how`` followed by the family's env id(s), or ``otherwise`` when none is known.

    :param family: the family the model was trained on (None: not recorded)
    :param how: e.g. ``"pass --env"``
    :param otherwise: e.g. ``"pass the --env it was trained on"``
    :return: e.g. ``"pass --env PointGoalMeta-v0"``
    """
    ids = family_env_ids(family)
    return f"{how} {' or '.join(ids)}" if ids else otherwise


def task_family_problem(
    task_family: str | None,
    train_tasks: Sequence[Task],
    env_family: str | None,
    task_error: Callable[[Task], str | None] | None,
) -> str | None:
    """
    Why an env is not of the task family a model was trained on, or None when nothing says so.

    The family the model recorded is compared with the env's; then each training task must be a task of the env
    (its ``task_error``), which also covers a model saved before the family was recorded.

    :param task_family: the family the model was trained on (None: not recorded)
    :param train_tasks: the model's training tasks
    :param env_family: the env's family (None: the env does not tell it)
    :param task_error: the env's ``task_error`` (None: the env has none)
    :return: the problem, for a one-line message, or None
    """
    if task_family is not None and env_family is not None and task_family != env_family:
        return f"the model was trained on {task_family} tasks, the env is a {env_family}"
    if task_error is not None:
        for index, task in enumerate(train_tasks):
            error = task_error(task)
            if error is not None:
                return f"its train_tasks[{index}] = {task!r} is not a task of the env ({error})"
    return None


def set_vec_env_task(env: Any, task: Task, indices: Sequence[int] | None = None) -> None:
    """
    ``env.env_method("set_task", task, indices=indices)``, with a bad task refused in this process where a raising
    ``set_task`` would kill a worker: outside a ``DummyVecEnv`` (a ``SubprocVecEnv``'s worker dies on an exception,
    leaving an empty ``EOFError`` and a dead VecEnv) the task is first checked with the family's ``task_error``, which
    does not raise; a worker that dies anyway is reported in one line naming the task.

    :param env: a VecEnv of a task family (possibly wrapped)
    :param task: the task
    :param indices: the envs to set (None: all)
    :raises ValueError: the env's ``task_error`` refuses the task (no env was changed)
    :raises RuntimeError: a worker died on the task (the VecEnv is unusable)
    """
    innermost = _innermost_vec_env(env)
    if isinstance(innermost, DummyVecEnv):
        env.env_method("set_task", task, indices=indices)  # a bad task raises here, the env stays usable
        return
    if env.has_attr("task_error"):
        first = None if indices is None else list(indices)[:1]
        error = env.env_method("task_error", task, indices=first if first else [0])[0]
        if error is not None:
            raise ValueError(
                f"set_task({task!r}): {error} (refused before it reached the {type(innermost).__name__}'s worker processes, "
                "which die on an exception; the env is unchanged)"
            )
    try:
        env.env_method("set_task", task, indices=indices)
    except (EOFError, BrokenPipeError, ConnectionResetError) as error:
        raise RuntimeError(
            f"set_task({task!r}) ended a worker process of the {type(innermost).__name__} ({type(error).__name__}): the env "
            "does not take that task (the worker's traceback is on stderr), and the VecEnv is unusable: make a new one"
        ) from None


def _innermost_vec_env(env: Any) -> Any:
    """The VecEnv below every ``VecEnvWrapper`` (``venv`` attributes)."""
    while isinstance(getattr(env, "venv", None), VecEnv):
        env = env.venv
    return env


def draw_train_test_tasks(env: Any, n_train: int, n_test: int, seed: int | None) -> tuple[list[Task], list[Task]]:
    """
    Draw the training and held-out test tasks of a model in one ``sample_tasks`` call.

    One call split in two keeps the lists of every algorithm identical for the same seed.

    :param env: a VecEnv of a task family
    :param n_train: number of training tasks
    :param n_test: number of test tasks
    :param seed: the model seed
    :return: training tasks, test tasks
    """
    if n_train < 1 or n_test < 0:
        raise ValueError(f"n_train_tasks must be >= 1 and n_test_tasks >= 0, got {n_train} and {n_test}")
    tasks = env.env_method("sample_tasks", n_train + n_test, seed, indices=[0])[0]
    return list(tasks[:n_train]), list(tasks[n_train:])


def check_tasks(env: Any, tasks: list[Task], name: str) -> None:
    """
    Raise a clear error unless every task of ``tasks`` is a valid task of the env (checked on its first env).

    Uses the family's ``task_error`` (:class:`~sb3_pearl.envs.task_protocol.MetaTaskEnv`), which leaves the env
    as it is; an env without it is probed with ``set_task`` and given its task back (a ``DummyVecEnv`` only:
    a raising ``SubprocVecEnv`` worker would die).

    :param env: a VecEnv of a task family
    :param tasks: explicit tasks given to the algorithm
    :param name: their argument name (``train_tasks`` / ``test_tasks``), for the message
    """
    if not isinstance(tasks, (list, tuple)):
        raise TypeError(
            f"{name} must be a list of task dicts (as from env.unwrapped.sample_tasks(n)), got {type(tasks).__name__}"
        )
    fix = "pass tasks as returned by env.unwrapped.sample_tasks(n) (or let the algorithm draw them)"
    if env.has_attr("task_error"):
        for index, task in enumerate(tasks):
            error = env.env_method("task_error", task, indices=[0])[0]
            if error is not None:
                raise ValueError(f"{name}[{index}] = {task!r} is not a task of this env: {error}; {fix}")
        return
    if not isinstance(env, DummyVecEnv):
        return
    original = env.env_method("get_task", indices=[0])[0]
    try:
        for index, task in enumerate(tasks):
            try:
                env.env_method("set_task", task, indices=[0])
            except (ValueError, TypeError, KeyError, IndexError) as error:
                raise ValueError(f"{name}[{index}] = {task!r} is not a task of this env: {error}; {fix}") from None
    finally:
        env.env_method("set_task", original, indices=[0])


def resolve_train_test_tasks(
    env: Any,
    train_tasks: list[Task],
    test_tasks: list[Task],
    n_train: int,
    n_test: int,
    seed: int | None,
) -> tuple[list[Task], list[Task]]:
    """
    A model's task lists: explicit lists win; without training tasks both are drawn by :func:`draw_train_test_tasks`.

    :param env: a VecEnv of a task family
    :param train_tasks: explicit training tasks (empty: draw)
    :param test_tasks: explicit test tasks (empty: the drawn ones, if training tasks are drawn)
    :param n_train: number of training tasks to draw
    :param n_test: number of test tasks to draw
    :param seed: the model seed
    :return: training tasks, test tasks (explicit ones checked with :func:`check_tasks`)
    """
    check_tasks(env, train_tasks, "train_tasks")
    check_tasks(env, test_tasks, "test_tasks")
    if train_tasks:
        return list(train_tasks), list(test_tasks)
    train, test = draw_train_test_tasks(env, n_train, n_test, seed)
    return train, list(test_tasks) if test_tasks else test


def env_time_limit(env: Any) -> int | None:
    """
    The time limit of the first env of a VecEnv: its registered ``max_episode_steps``, else that of a
    ``TimeLimit`` wrapper, else None.
    """
    limit = getattr(env.get_attr("spec", indices=[0])[0], "max_episode_steps", None)
    if limit is None:
        try:
            limit = env.get_attr("_max_episode_steps", indices=[0])[0]
        except AttributeError:
            return None
    return int(limit) if limit is not None else None
