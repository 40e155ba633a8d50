"""The algorithm side of the task protocol, shared by PEARL, PEARL+, Fine-Tune and MAML.

Checking that an env is a task family the algorithm can use, and drawing a model's training and
held-out test tasks. The env side (``sample_tasks`` / ``set_task`` / ``get_task``) lives in
:mod:`sb3_pearl.envs.task_protocol`.
"""

from __future__ import annotations

from typing import Any

from gymnasium import spaces

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
    tasks = env.env_method("sample_tasks", n_train + n_test, seed, indices=[0])[0]
    return list(tasks[:n_train]), list(tasks[n_train:])


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
    :return: training tasks, test tasks
    """
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
