"""The oracle: a task-aware soft actor-critic, the usual upper bound of meta-RL evaluations.

SB3's SAC (Box actions) or the project's soft discrete SAC (Discrete actions), trained on the mixture of the
training tasks exactly as :class:`~sb3_pearl.finetune.FineTune` is (a uniformly drawn training task per episode), but
its observation carries the true task: every env it acts in is wrapped in
:class:`~sb3_pearl.envs.task_observation.TaskObservation`, which appends the episode's task as a standardised vector.
It is what perfect task inference could reach with the same learner, networks and env-step budget: where the oracle
does not do the job at a budget, no meta-learner can be expected to, and where it does, a meta-learner's gap to it is
the cost of inferring the task.

It has the adaptation API of every algorithm of the project, so the meta-test serves it unchanged: its k = 0
trajectory is already informed (the task is in the observation from the first step), :meth:`adapt` does nothing,
and every k acts with the same policy. The meta-test wraps the env it is given with :meth:`prepare_env`.

The task vector's standardisation is the training distribution's (:attr:`Oracle.task_standardisation`, saved with the
model): an env of a shifted distribution is wrapped with it, so a target beyond the training range reads as one.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any, ClassVar

import gymnasium as gym
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv
from stable_baselines3.sac.policies import SACPolicy

from sb3_pearl.common.meta_algorithm import forwards_arguments_to
from sb3_pearl.envs.task_observation import Standardisation, TaskObservation
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.finetune.discrete_sac import DiscreteSACPolicy
from sb3_pearl.finetune.finetune import FineTune

_FINE_TUNING_KWARGS = ("adapt_gradient_steps", "adapt_batch_size", "adapt_learning_rate", "adapt_buffer_size")


def with_task_observation(env: gym.Env | VecEnv, standardisation: Standardisation | None = None) -> gym.Env | VecEnv:
    """
    ``env`` with the task in its observations (:class:`TaskObservation`); an env that already has it is kept, its
    task vector standardised with ``standardisation`` when one is given.

    :param env: a task-family env, or a ``DummyVecEnv`` of them (rebuilt around the wrapped envs)
    :param standardisation: the task vector's standardisation (the training distribution's); ``None``: ``env``'s own
    :return: the env the oracle acts in
    """
    if isinstance(env, VecEnv):
        if all(env.env_is_wrapped(TaskObservation)):
            if standardisation is not None:
                env.env_method("standardise_with", standardisation)
            return env
        if type(env) is DummyVecEnv:
            return DummyVecEnv([functools.partial(TaskObservation, inner, standardisation) for inner in env.envs])
        raise ValueError(
            f"Oracle: the {type(env).__name__} given does not put the task in its observations; build its envs with "
            "wrapper_class=sb3_pearl.envs.task_observation.TaskObservation (make_vec_env) or pass a single env"
        )
    if is_wrapped(env, TaskObservation):
        if standardisation is not None:
            env.get_wrapper_attr("standardise_with")(standardisation)
        return env
    return TaskObservation(env, standardisation)


@forwards_arguments_to(FineTune, refused=_FINE_TUNING_KWARGS)
class Oracle(FineTune):
    """
    Task-aware SAC: Fine-Tune's meta-training with the true task appended to the observation, no adaptation.

    :param policy: ``"MlpPolicy"`` (SAC's MlpPolicy for Box, :class:`DiscreteSACPolicy` for Discrete) or a class
    :param env: an env id or env following the task protocol (wrapped in :class:`TaskObservation` here), or a VecEnv
        whose envs already are
    :param n_train_tasks: training tasks: the first ``n_train_tasks`` of ``env.sample_tasks(n_train_tasks +
        n_test_tasks, seed)`` (the same draw as PEARL / PEARL+ / Fine-Tune / MAML: a seed gives every algorithm the
        same tasks)
    :param n_test_tasks: held-out test tasks: the rest of that draw
    :param train_tasks: explicit training tasks (overrides the draw)
    :param test_tasks: explicit test tasks (overrides the draw)
    :param max_episode_steps: the task family's episode length (``None``: the env's registered time limit)
    :param _init_setup_model: build the networks at construction
    :param kwargs: SAC's arguments, as :class:`~sb3_pearl.finetune.discrete_sac.DiscreteSAC` takes them
        (``learning_rate``, ``buffer_size``, ``batch_size``, ``gamma``, ``ent_coef``, ``policy_kwargs``, ``seed``, ...)

    :attr:`task_standardisation` is the task vector's standardisation, taken from the training env (``env``) and saved
    with the model; every env the oracle acts in (``set_env``, ``load(env=...)``, :meth:`prepare_env`) is standardised
    with it. A model saved before it was recorded takes it from the env given to ``load`` (the training distribution),
    or from ``load(path, task_standardisation=training_standardisation(env_id, training_kwargs))``
    (:func:`~sb3_pearl.envs.task_observation.training_standardisation`; a zip saved with a float64 observation space
    refuses ``load(env=...)``); loaded with neither, from each env :meth:`prepare_env` wraps, with a warning.
    """

    # Every Oracle zip holds these (load() refuses one without them, e.g. a Fine-Tune zip: its policy sees no task).
    saved_data_keys: ClassVar[tuple[str, ...]] = ("train_tasks", "task_aware")

    def __init__(
        self,
        policy: str | type[SACPolicy] | type[DiscreteSACPolicy],
        env: GymEnv | str,
        *,
        n_train_tasks: int = 100,
        n_test_tasks: int = 30,
        train_tasks: list[Task] | None = None,
        test_tasks: list[Task] | None = None,
        max_episode_steps: int | None = None,
        _init_setup_model: bool = True,
        **kwargs: Any,
    ):
        given = sorted(set(kwargs) & set(_FINE_TUNING_KWARGS))
        if given:
            raise ValueError(f"Oracle does not fine-tune (it is told the task): remove {given}")
        self.task_aware = True
        self.task_standardisation: dict[str, list[float]] | None = None
        super().__init__(
            policy,
            env,
            n_train_tasks=n_train_tasks,
            n_test_tasks=n_test_tasks,
            train_tasks=train_tasks,
            test_tasks=test_tasks,
            max_episode_steps=max_episode_steps,
            adapt_gradient_steps=0,
            _init_setup_model=_init_setup_model,
            **kwargs,
        )

    @staticmethod
    def _wrap_env(env: GymEnv, verbose: int = 0, monitor_wrapper: bool = True) -> VecEnv:
        """SB3's wrapping (Monitor, DummyVecEnv) around the env with the task in its observation."""
        return BaseAlgorithm._wrap_env(with_task_observation(env), verbose, monitor_wrapper)  # type: ignore[arg-type]

    def _setup_model(self) -> None:
        super()._setup_model()
        self._standardise_own_env()

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        super().set_env(env, force_reset)
        self._standardise_own_env()

    def _standardise_own_env(self) -> None:
        """The training env sets :attr:`task_standardisation` if it is unset; otherwise the env takes the model's."""
        if self.env is None:
            return
        if self.task_standardisation is None:
            self.task_standardisation = self.env.get_attr("standardisation", indices=[0])[0]
        else:
            self.env.env_method("standardise_with", self.task_standardisation)

    def prepare_env(self, env: gym.Env | VecEnv) -> gym.Env | VecEnv:
        """
        The env as the oracle acts in it: ``env`` with the task in its observation, standardised as in training (the
        meta-test calls this).

        :param env: a task-family env or a VecEnv of one
        :return: the wrapped env
        """
        if self.task_standardisation is None:
            warnings.warn(
                "Oracle: this model was saved without its task standardisation; the task vector is standardised over "
                "the distribution of the env it acts in, which is right only for the training distribution (for a "
                "shifted one, load it with task_standardisation=sb3_pearl.envs.task_observation.training_standardisation"
                "(env_id, training_env_kwargs))",
                stacklevel=2,
            )
        return with_task_observation(env, self.task_standardisation)

    def adapt(self) -> None:
        """Nothing to adapt: the oracle is told the task."""
