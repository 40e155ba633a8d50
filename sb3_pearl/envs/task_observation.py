"""The task in the observation: what a task-aware agent (the oracle) is told, for any family with the task protocol.

:class:`TaskObservation` appends the task in force to every observation, as a fixed-length vector: the family's
:meth:`~sb3_pearl.envs.task_protocol.MetaTaskEnv.task_features` (every number of the task dict in sorted-key order,
an angle as its cosine and sine), standardised with the mean and standard deviation of those features over
:data:`REFERENCE_TASKS` tasks of the *training* distribution (``sample_tasks(REFERENCE_TASKS, seed=0)`` of the env the
agent trains in: fixed by its ranges, never by the held-out tasks), so that a density of 30-50 veh/km and a target speed
of 0-3 m/s enter the networks at the same scale.

The standardisation is part of the agent, not of the env it acts in: an env of a shifted distribution (target speeds
beyond the training range) must be wrapped with the training one (``standardisation=``; the oracle passes its own, which
it saves), or a 2.5 m/s target would be standardised against the shifted range and read as an average training task.

The task is read once per episode, right after the wrapped env's ``reset()`` applied it (``set_task`` takes effect at
the next reset, so a task set during an episode, as Fine-Tune and the oracle do for the next one, never leaks into the
current episode's observations).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_pearl.envs.task_protocol import Task, _flat_numbers

REFERENCE_TASKS = 1000

Standardisation = Mapping[str, Sequence[float]]
"""The task vector's standardisation: ``{"mean": [...], "std": [...]}``, one number per task feature."""


def task_features(base: Any, task: Task) -> np.ndarray:
    """
    The raw feature vector of ``task`` for the family env ``base`` (its ``task_features`` if it has one, else every
    number of the task in sorted-key order).

    :param base: the family env (``env.unwrapped``)
    :param task: a task of the family
    :return: float64 features
    """
    features = base.task_features(task) if callable(getattr(base, "task_features", None)) else _flat_numbers(task)
    return np.asarray(features, dtype=np.float64)


def training_standardisation(env_id: str, env_kwargs: Mapping[str, Any] | None = None) -> dict[str, list[float]]:
    """
    The standardisation of the task vector over a training distribution: what an oracle trained in
    ``gym.make(env_id, **env_kwargs)`` was told with. For a model saved before it recorded its own:
    ``Oracle.load(path, task_standardisation=training_standardisation(env_id, training_kwargs))``.

    :param env_id: the family's env id
    :param env_kwargs: the training env's kwargs (the run's, not a shifted distribution's)
    :return: ``{"mean": [...], "std": [...]}``
    """
    env = gym.make(env_id, **dict(env_kwargs or {}))
    try:
        return TaskObservation(env).standardisation
    finally:
        env.close()


class TaskObservation(gym.ObservationWrapper):
    """
    Append the standardised task vector of the episode's task to each (flat ``Box``) observation.

    :param env: a task-family env (``env.unwrapped`` has ``sample_tasks`` and ``get_task``) with a 1-D ``Box``
        observation space
    :param standardisation: the mean and standard deviation of the task features (``{"mean": [...], "std": [...]}``,
        :attr:`standardisation` of the wrapper around the training env); ``None``: computed from ``env``'s own
        distribution, which is right only when ``env`` is the training distribution
    """

    def __init__(self, env: gym.Env, standardisation: Standardisation | None = None) -> None:
        super().__init__(env)
        base: Any = env.unwrapped
        if not all(callable(getattr(base, name, None)) for name in ("sample_tasks", "get_task")):
            raise ValueError(
                f"TaskObservation needs a task-family env (sample_tasks, set_task, get_task): {type(base).__name__} has "
                "no get_task(); use one of the families registered by sb3_pearl (e.g. Walker2dVelMeta-v0)"
            )
        space = env.observation_space
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise ValueError(
                f"TaskObservation appends the task to a flat Box observation; {type(base).__name__}'s observation space "
                f"is {space} (flatten it first, e.g. gymnasium.wrappers.FlattenObservation)"
            )
        if standardisation is None:  # the training distribution's own statistics, over REFERENCE_TASKS of its tasks
            reference = np.stack([task_features(base, task) for task in base.sample_tasks(REFERENCE_TASKS, seed=0)])
            std = reference.std(axis=0)
            std = np.where(std > 1e-8, std, 1.0)  # a constant feature is only centred
            standardisation = {"mean": reference.mean(axis=0).tolist(), "std": std.tolist()}
        self.task_dim = int(task_features(base, base.get_task()).shape[0])
        if self.task_dim == 0:
            raise ValueError(f"TaskObservation: {type(base).__name__}'s tasks hold no number to tell the agent")
        self.standardise_with(standardisation)
        self._features = self.task_vector(base.get_task())
        # float32, as the networks read it (MuJoCo's float64 observations would double the replay buffer: a 500k Ant
        # buffer is 0.9 GB in float64)
        self.observation_space = spaces.Box(
            low=np.concatenate([space.low, np.full(self.task_dim, -np.inf)]).astype(np.float32),
            high=np.concatenate([space.high, np.full(self.task_dim, np.inf)]).astype(np.float32),
            dtype=np.float32,
        )

    @property
    def standardisation(self) -> dict[str, list[float]]:
        """The mean and standard deviation the task features are standardised with (JSON-serialisable)."""
        return {"mean": [float(x) for x in self.task_mean], "std": [float(x) for x in self.task_std]}

    def standardise_with(self, standardisation: Standardisation) -> None:
        """
        Standardise the task features with ``standardisation`` from now on (the current episode's vector included).

        :param standardisation: ``{"mean": [...], "std": [...]}``, :attr:`task_dim` positive-std numbers each
        """
        mean = np.asarray(standardisation["mean"], dtype=np.float64)
        std = np.asarray(standardisation["std"], dtype=np.float64)
        if mean.shape != (self.task_dim,) or std.shape != (self.task_dim,) or not np.all(std > 0):
            raise ValueError(
                f"TaskObservation: the standardisation needs {self.task_dim} means and {self.task_dim} positive stds "
                f"for {type(self.env.unwrapped).__name__}'s task features; got mean {mean.tolist()}, std {std.tolist()} "
                "(was the model trained on another task family?)"
            )
        self.task_mean, self.task_std = mean, std
        if hasattr(self, "_features"):
            self._features = self.task_vector(self.env.unwrapped.get_task())  # type: ignore[attr-defined]

    def task_vector(self, task: Task) -> np.ndarray:
        """
        The standardised features of ``task`` (what is appended to the observation).

        :param task: a task of the family
        :return: a vector of length :attr:`task_dim`
        """
        features = task_features(self.env.unwrapped, task)
        if features.shape != (self.task_dim,):
            raise ValueError(f"TaskObservation: task {task!r} gives {features.shape[0]} features, expected {self.task_dim}")
        return ((features - self.task_mean) / self.task_std).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        self._features = self.task_vector(self.env.unwrapped.get_task())  # type: ignore[attr-defined]
        return self.observation(obs), info

    def observation(self, observation: Any) -> np.ndarray:
        return np.concatenate([np.asarray(observation, dtype=np.float32), self._features])
