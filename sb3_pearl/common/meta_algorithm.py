"""The frame every meta-RL algorithm of the project shares: task sets, meta-env and adaptation checks, training plan.

PEARL / PEARL+ (SB3's ``OffPolicyAlgorithm``), Fine-Tune (SAC) and MAML (``BaseAlgorithm``) train and adapt each in
their own way; :class:`MetaAlgorithm` holds what they have in common, written once:

- the task sets: ``n_train_tasks`` training and ``n_test_tasks`` held-out test tasks, drawn in one
  ``env.sample_tasks(n_train_tasks + n_test_tasks, seed)`` call with the model seed (so a seed gives every algorithm the
  same tasks), or explicit ``train_tasks`` / ``test_tasks`` (:func:`~sb3_pearl.common.tasks.resolve_train_test_tasks`);
- the checks: the task arguments (:func:`check_task_arguments`, before anything is built), the env as a task family the
  algorithm can use (:func:`~sb3_pearl.common.tasks.check_meta_env`), at construction, ``load(env=...)`` and
  ``set_env`` alike, an env of the task family the model was trained on (:attr:`MetaAlgorithm.task_family`, saved with
  the model), a training task to learn on, and the transitions handed to the adaptation API's ``observe()``
  (:func:`check_observed_transition`);
- :attr:`MetaAlgorithm.stochastic_adaptation`: how the meta-test protocol rolls the model out;
- :meth:`MetaAlgorithm.training_plan`: what ``learn(total_timesteps)`` will still collect and train.

An algorithm mixes :class:`MetaAlgorithm` in before its SB3 base class and calls, in this order:
:func:`check_task_arguments` with its other argument checks, ``super().__init__(...)``,
:meth:`~MetaAlgorithm._init_meta_algorithm`, and :meth:`~MetaAlgorithm._setup_tasks` in its ``_setup_model``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import unwrap_vec_normalize

from sb3_pearl.common.adaptation import check_finite_observation, check_finite_transition
from sb3_pearl.common.checks import check_task_counts
from sb3_pearl.common.tasks import (
    check_meta_env,
    env_task_family,
    family_fix,
    resolve_train_test_tasks,
    task_family_problem,
    vec_env_task_error,
)
from sb3_pearl.common.threads import apply_default_num_threads
from sb3_pearl.envs.task_protocol import Task

if TYPE_CHECKING:
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.policies import BasePolicy

    from sb3_pearl.common.type_aliases import TrainingPlan

    _AlgorithmBase = BaseAlgorithm
else:
    _AlgorithmBase = object


def check_task_arguments(
    n_train_tasks: Any,
    n_test_tasks: Any,
    train_tasks: list[Task] | None,
    test_tasks: list[Task] | None,
) -> None:
    """
    Raise a ValueError for task arguments out of range (called before anything is built).

    Explicit tasks are checked against the env's task family later, when the env is known
    (:func:`~sb3_pearl.common.tasks.check_tasks`).

    :param n_train_tasks: training tasks to draw (>= 1)
    :param n_test_tasks: held-out test tasks to draw with them (>= 0)
    :param train_tasks: explicit training tasks (None: draw them); an empty list is refused
    :param test_tasks: explicit test tasks (None: draw them)
    """
    check_task_counts(n_train_tasks, n_test_tasks)
    if train_tasks is not None and len(train_tasks) == 0:
        raise ValueError("train_tasks must hold at least one task (or be None to draw them)")


def check_observed_transition(
    observation_space: spaces.Space, obs: Any, reward: Any, next_obs: Any
) -> tuple[np.ndarray, np.ndarray]:
    """
    The checks of one transition handed to ``observe()`` (the adaptation API): finite values, one observation each and
    one (scalar) reward.

    :param observation_space: the model's observation space (a Box)
    :param obs: observation the action was taken in
    :param reward: reward of the step
    :param next_obs: observation after the step
    :return: ``obs`` and ``next_obs`` as float32 arrays of the observation space's shape
    """
    if np.size(reward) != 1:
        raise ValueError(
            f"observe(): reward must be a scalar (one transition), got shape {np.shape(reward)}: "
            "call observe() once per step with that step's reward"
        )
    check_finite_transition(obs, reward, next_obs)
    shape = observation_space.shape
    assert shape is not None
    obs_arr = np.asarray(obs, dtype=np.float32)
    next_obs_arr = np.asarray(next_obs, dtype=np.float32)
    size = int(np.prod(shape))
    if obs_arr.size != size or next_obs_arr.size != size:
        raise ValueError(
            f"observe() takes one transition: obs and next_obs of shape {tuple(shape)}, "
            f"got {np.shape(obs)} and {np.shape(next_obs)}"
        )
    return obs_arr.reshape(shape), next_obs_arr.reshape(shape)


class MetaAlgorithm(_AlgorithmBase):
    """
    The frame of a meta-RL algorithm (module docstring): its task sets, checks and training plan.

    A mixin: put it before the SB3 base class (and after the adaptation mixins). Its attributes
    (:attr:`n_train_tasks`, :attr:`n_test_tasks`, :attr:`train_tasks`, :attr:`test_tasks`, :attr:`task_family`) are
    saved with the model.
    """

    # Read by the meta-test protocol (sb3_pearl.evaluation.meta_test): True makes it roll the model out with its
    # stochastic policy even when deterministic trajectories are asked for (MAML: an inner policy-gradient step
    # learns nothing from deterministic ones).
    stochastic_adaptation: ClassVar[bool] = False
    # The algorithm's networks take flat observations only (a Box of shape (obs_dim,)): checked with the env.
    requires_flat_observations: ClassVar[bool] = False

    n_train_tasks: int
    n_test_tasks: int
    train_tasks: list[Task]
    test_tasks: list[Task]
    # The task family the model was built on (MetaTaskEnv.task_family; None: its env does not tell, or a model saved
    # before it was recorded): load(env=...) and set_env refuse an env of another family.
    task_family: str | None

    def _init_meta_algorithm(
        self,
        n_train_tasks: int,
        n_test_tasks: int,
        train_tasks: list[Task] | None,
        test_tasks: list[Task] | None,
    ) -> None:
        """
        Set the task arguments and check the env (if any) is a task family the algorithm can use; called in
        ``__init__`` after ``super().__init__`` (SB3's, which wraps the env), before ``_setup_model``.

        :param n_train_tasks: training tasks to draw
        :param n_test_tasks: held-out test tasks to draw with them
        :param train_tasks: explicit training tasks (None: draw them)
        :param test_tasks: explicit test tasks (None: draw them)
        """
        self.n_train_tasks = n_train_tasks
        self.n_test_tasks = n_test_tasks
        self.train_tasks = list(train_tasks) if train_tasks is not None else []
        self.test_tasks = list(test_tasks) if test_tasks is not None else []
        self.task_family = None
        if self.env is not None:
            check_meta_env(
                type(self).__name__,
                self.env,
                self.observation_space,
                self.action_space,
                self._vec_normalize_env,
                flat_observations=self.requires_flat_observations,
            )

    def _setup_tasks(self) -> None:
        """
        The task sets, in ``_setup_model``: explicit ones checked against the env, else drawn with the model seed.

        Without an env (``load`` without one) the saved task sets stay as they are. With one, a loaded model's
        family must be the env's (:attr:`task_family`, recorded here).
        """
        if self.env is not None:
            family = env_task_family(self.env)
            problem = task_family_problem(self.task_family, [], family, None)  # the tasks: resolve_train_test_tasks
            if problem is not None:
                fix = family_fix(self.task_family, "give it an env of that family:", "give it an env of that family")
                raise ValueError(f"{type(self).__name__}: the env is not of the task family of the model: {problem}; {fix}")
            self.task_family = family if family is not None else self.task_family
            self.train_tasks, self.test_tasks = resolve_train_test_tasks(
                self.env, self.train_tasks, self.test_tasks, self.n_train_tasks, self.n_test_tasks, self.seed
            )

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """
        SB3's ``set_env`` (same number of envs, same spaces), after the constructor's checks of the env (a task family,
        no VecNormalize) and a check that it is of the task family the model was trained on (:attr:`task_family`, and
        its training tasks through the env's ``task_error``): a refused env raises a one-line ValueError and the model
        keeps its env.

        :param env: the env (wrapped into a VecEnv as SB3 does)
        :param force_reset: reset the env before the next ``learn``
        """
        vec_env = self._wrap_env(env, self.verbose)
        name = type(self).__name__
        check_meta_env(
            name,
            vec_env,
            vec_env.observation_space,
            vec_env.action_space,
            unwrap_vec_normalize(vec_env),
            flat_observations=self.requires_flat_observations,
        )
        family = env_task_family(vec_env)
        problem = task_family_problem(self.task_family, self.train_tasks, family, vec_env_task_error(vec_env))
        if problem is not None:
            fix = family_fix(self.task_family, "give it an env of that family:", "give it an env of that family")
            raise ValueError(f"{name}.set_env: the env is not of the task family the model was trained on: {problem}; {fix}")
        super().set_env(vec_env, force_reset)
        self.task_family = family if family is not None else self.task_family

    def _check_train_tasks(self) -> None:
        """Raise a clear error when there is no training task to learn on."""
        if not self.train_tasks:
            raise ValueError(
                f"{type(self).__name__} has no training tasks: construct it with a task-family env "
                "(e.g. gym.make('SafePointGoalMeta-v0')) or pass train_tasks"
            )

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        if total_timesteps < 0:
            raise ValueError(
                f"{type(self).__name__}.learn(): total_timesteps must be >= 0 (env steps to train on), got {total_timesteps}"
            )
        self._check_train_tasks()
        apply_default_num_threads(self.policy)  # the fastest count for these networks, unless the user chose one
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        SB3's ``predict``; an observation holding a nan or an inf is refused (its action would be non-finite too).

        :param observation: the input observation
        :param state: the recurrent state (None for feed-forward policies)
        :param episode_start: episode-start flags of recurrent policies
        :param deterministic: return deterministic actions
        :return: the actions and the next state
        """
        check_finite_observation(self, observation)
        return self.adapted_policy.predict(observation, state, episode_start, deterministic)

    @property
    def adapted_policy(self) -> BasePolicy:
        """The policy :meth:`predict` acts with (SB3's ``self.policy``; Fine-Tune's fine-tuned copy once adapted)."""
        return self.policy

    def training_plan(self, total_timesteps: int) -> TrainingPlan | None:
        """
        What ``learn(total_timesteps)`` will still collect and train, for the progress callback's announcement and
        ETA (:class:`~sb3_pearl.evaluation.progress.TrainingProgressCallback`); None when it is not known ahead.

        The frame does not know it (MAML's: a meta-iteration lasts until its episodes end); PEARL / PEARL+ and
        Fine-Tune override this with their own schedules.

        :param total_timesteps: the ``learn`` budget, counted from 0 (a resumed run plans what is left)
        :return: the plan, or None
        """
        return None


__all__ = ["MetaAlgorithm", "check_observed_transition", "check_task_arguments"]
