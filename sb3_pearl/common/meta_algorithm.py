"""The base class of every meta-RL algorithm of the project: task sets, checks, training plan, save and load.

PEARL / PEARL+ (on SB3's ``OffPolicyAlgorithm``), Fine-Tune (SAC) and MAML (``BaseAlgorithm``) train and adapt each
in their own way; :class:`MetaAlgorithm` holds what they have in common, written once:

- the task sets: ``n_train_tasks`` training and ``n_test_tasks`` held-out test tasks, drawn in one
  ``env.sample_tasks(n_train_tasks + n_test_tasks, seed)`` call with the model seed (so a seed gives every algorithm the
  same tasks), or explicit ``train_tasks`` / ``test_tasks`` (:func:`~sb3_pearl.common.tasks.resolve_train_test_tasks`);
- the checks: the task arguments (:func:`check_task_arguments`, before anything is built), the env as a task family the
  algorithm can use (:func:`~sb3_pearl.common.tasks.check_meta_env`), at construction, ``load(env=...)`` and
  ``set_env`` alike, an env of the task family the model was trained on (:attr:`MetaAlgorithm.task_family`, saved with
  the model), a training task to learn on, and the transitions handed to the adaptation API's ``observe()``
  (:func:`check_observed_transition`);
- :attr:`MetaAlgorithm.stochastic_adaptation`: how the meta-test protocol rolls the model out;
- :meth:`MetaAlgorithm.training_plan`: what ``learn(total_timesteps)`` will still collect and train;
- saving and loading (:mod:`sb3_pearl.common.persistence`): an atomic ``save``, a ``load`` that checks the file and
  the hyperparameters before SB3 builds anything, the RNG streams and the envs' open episodes saved with the model
  (exact resume). The off-policy algorithms save their replay buffers with
  :func:`~sb3_pearl.common.persistence.save_replay_buffer_file` (atomic, tagged with the training tasks).

An algorithm puts :class:`MetaAlgorithm` first among its bases, before its SB3 algorithm class (``PEARL(MetaAlgorithm,
OffPolicyAlgorithm)``, ``FineTune(MetaAlgorithm, DiscreteSAC)``, ``MAML(MetaAlgorithm)``), and calls, in this order:
:func:`check_task_arguments` with its other argument checks, ``super().__init__(...)``,
:meth:`~MetaAlgorithm._init_meta_algorithm`, and :meth:`~MetaAlgorithm._setup_tasks` in its ``_setup_model``.

Trust model, as in SB3: a model zip holds pickled objects and a replay buffer is a pickle. Loading
one runs whatever code its author put in it: load only files you trust.
"""

from __future__ import annotations

import inspect
import io
import json
import os
import pathlib
import warnings
import zipfile
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import unwrap_vec_normalize

from sb3_pearl.common.adaptation import check_finite_observation, check_finite_transition
from sb3_pearl.common.checks import check_task_counts
from sb3_pearl.common.env_state import EnvStateError, capture_env_state, restore_env_state
from sb3_pearl.common.persistence import loaded_model_data, read_model_data, saved_policy_name, write_sb3_file
from sb3_pearl.common.seeding import capture_training_rng_state, restore_training_rng_state
from sb3_pearl.common.tasks import (
    check_meta_env,
    env_task_family,
    family_fix,
    resolve_train_test_tasks,
    task_family_problem,
    vec_env_task_error,
)
from sb3_pearl.common.threads import apply_default_num_threads
from sb3_pearl.common.type_aliases import TrainingPlan
from sb3_pearl.envs.task_protocol import Task

SelfMetaAlgorithm = TypeVar("SelfMetaAlgorithm", bound="MetaAlgorithm")
AlgorithmClass = TypeVar("AlgorithmClass", bound=type)

# The classes that declare the data keys every zip of theirs holds (filled by MetaAlgorithm.__init_subclass__).
_SIGNATURES: dict[str, type[MetaAlgorithm]] = {}


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


def forwards_arguments_to(parent: type, refused: tuple[str, ...] = ()) -> Callable[[AlgorithmClass], AlgorithmClass]:
    """
    Class decorator for an algorithm whose ``__init__`` states its own parameters and forwards the others to
    ``parent``'s by ``**kwargs`` (SB3's set-up idiom): ``inspect.signature`` of the class then lists both, its own first,
    ``parent``'s after them as keyword-only, with their defaults (each parameter is written once, in its own class).

    :param parent: the class whose constructor takes the forwarded ``**kwargs``
    :param refused: parameters of ``parent`` that the class refuses (left out of its signature)
    :return: the decorator
    """

    def decorate(cls: AlgorithmClass) -> AlgorithmClass:
        own = [p for p in inspect.signature(vars(cls)["__init__"]).parameters.values() if p.name != "self"]
        forwarded = [p for p in own if p.kind == p.VAR_KEYWORD]
        if not forwarded:
            raise TypeError(f"{cls.__name__}.__init__ forwards no **kwargs to {parent.__name__}")
        named = [p for p in own if p.kind != p.VAR_KEYWORD]
        taken = {p.name for p in named}
        inherited = [
            p.replace(kind=inspect.Parameter.KEYWORD_ONLY)
            for p in inspect.signature(parent).parameters.values()
            if p.name not in taken and p.name not in refused and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)
        ]
        last_own = [p for p in named if p.name == "_init_setup_model"]  # SB3 keeps it last
        parameters = [p for p in named if p.name != "_init_setup_model"] + inherited + last_own
        setattr(cls, "__signature__", inspect.Signature(parameters))  # noqa: B010 (not a declared attribute of type)
        return cls

    return decorate


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


class MetaAlgorithm(BaseAlgorithm):
    """
    The base of a meta-RL algorithm (module docstring): its task sets, checks, training plan, save and load.

    Put it first among the bases, before the SB3 algorithm class. Its attributes (:attr:`n_train_tasks`,
    :attr:`n_test_tasks`, :attr:`train_tasks`, :attr:`test_tasks`, :attr:`task_family`) are saved with the model. A
    class lists in :attr:`saved_data_keys` the parameters every zip of it holds; ``load`` refuses a zip without them and
    names the class that wrote it when it is one of the project's.
    """

    # Read by the meta-test protocol (sb3_pearl.evaluation.meta_test): True makes it roll the model out with its
    # stochastic policy even when deterministic trajectories are asked for (MAML: an inner policy-gradient step
    # learns nothing from deterministic ones).
    stochastic_adaptation: ClassVar[bool] = False
    # The algorithm's networks take flat observations only (a Box of shape (obs_dim,)): checked with the env.
    requires_flat_observations: ClassVar[bool] = False
    # Parameters every zip of the class holds (load() refuses a zip without them, e.g. a SAC one).
    saved_data_keys: ClassVar[tuple[str, ...]] = ()

    n_train_tasks: int
    n_test_tasks: int
    train_tasks: list[Task]
    test_tasks: list[Task]
    # The task family the model was built on (MetaTaskEnv.task_family; None: its env does not tell, or a model saved
    # before it was recorded): load(env=...) and set_env refuse an env of another family.
    task_family: str | None
    # VecEnv steps taken in training (one ``on_step`` call of the callbacks each, whatever the number of envs stepping):
    # a resumed run's call-counting callbacks continue from it. A model saved before it was recorded loads with
    # ``num_timesteps // n_envs``.
    num_vec_env_steps: int

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "__init__" in vars(cls):  # a signature shown for a parent's constructor (forwards_arguments_to) is not its own
            setattr(cls, "__signature__", None)  # noqa: B010 (None: inspect reads __init__)
        if cls.__dict__.get("saved_data_keys"):
            _SIGNATURES[cls.__name__] = cls

    # ------------------------------------------------------------------------------------------
    # Task sets and env checks
    # ------------------------------------------------------------------------------------------
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
        self.num_vec_env_steps = 0
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
        """
        SB3's ``_setup_learn`` after the checks of the budget and the training tasks; around SB3's reset of the envs
        (a new run, or a model whose envs' saved state was not restored) the algorithm's
        :meth:`_before_env_reset` and :meth:`_after_env_reset`; the first ``learn()`` after ``load()`` then continues
        the saved RNG streams.

        :param total_timesteps: the ``learn`` budget
        :param callback: SB3 callback(s)
        :param reset_num_timesteps: restart the step counter
        :param tb_log_name: TensorBoard run name
        :param progress_bar: show a progress bar
        :return: the budget and the callback, as SB3's
        """
        if total_timesteps < 0:
            raise ValueError(
                f"{type(self).__name__}.learn(): total_timesteps must be >= 0 (env steps to train on), got {total_timesteps}"
            )
        if self.env is None:  # before anything reads it (SB3 checks later, after the algorithm's own set-up)
            raise ValueError(
                f"{type(self).__name__}.learn(): the model has no env (loaded without one): "
                f"{type(self).__name__}.load(path, env=env) or model.set_env(env) first"
            )
        self._check_train_tasks()
        apply_default_num_threads(self.policy)  # the fastest count for these networks, unless the user chose one
        env_reset = reset_num_timesteps or self._last_obs is None  # SB3's condition for resetting the envs
        if env_reset:
            self._before_env_reset()
        if reset_num_timesteps:  # SB3 restarts num_timesteps in _setup_learn, before the callbacks read the counters
            self.num_vec_env_steps = 0
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        # First learn() after load(): continue the saved RNG streams (after SB3's env reset, when the envs' saved state
        # was not restored, reseeded them).
        state = self.__dict__.pop("_rng_to_restore", None)
        if state is not None:
            restore_training_rng_state(state, self.env, self.action_space)
        if env_reset:
            self._after_env_reset()
        return result

    def _before_env_reset(self) -> None:
        """Called by ``learn()`` before SB3 resets the envs (see :meth:`_setup_learn`); nothing here."""

    def _after_env_reset(self) -> None:
        """Called by ``learn()`` after SB3 reset the envs (and the saved RNG streams were restored); nothing here."""

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

    # ------------------------------------------------------------------------------------------
    # Save / load
    # ------------------------------------------------------------------------------------------
    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Any = None,
        include: Any = None,
    ) -> None:
        """
        SB3's ``save``, written to a temporary file and renamed into place (a kill mid-save keeps the old file).

        :param path: the zip (``.zip`` is appended when the path has no suffix, as in SB3) or an open binary file
        :param exclude: parameters to exclude in addition to the default ones
        :param include: parameters to include although excluded by default
        """
        self._rng_state = capture_training_rng_state(self.env, self.action_space)  # saved with the data
        self._env_state = capture_env_state(self.env)  # the open episodes (DummyVecEnv only), for an exact resume
        sb3_save = super().save
        try:
            write_sb3_file(path, "zip", lambda file: sb3_save(file, exclude=exclude, include=include))
        finally:
            del self._env_state

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_rng_to_restore"]

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfMetaAlgorithm],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        restore_env: bool = True,
        strict_env: bool = False,
        **kwargs: Any,
    ) -> SelfMetaAlgorithm:
        """
        SB3's ``load``, after checking that the file is a complete zip of this class (clear errors otherwise).

        A zip saved from a DummyVecEnv holds its envs' mid-episode state (:mod:`sb3_pearl.common.env_state`) and
        every RNG state of the run: with ``restore_env`` and an ``env`` of the same structure, the envs continue
        the saved episodes instead of being reset, and ``learn(..., reset_num_timesteps=False)`` continues the
        run bit for bit (exact resume).

        :param path: the model zip
        :param env: the env to run the model on
        :param device: torch device
        :param custom_objects: objects replacing saved ones (SB3)
        :param print_system_info: print the system info of the save
        :param force_reset: reset the env before the next ``learn`` (unless its saved state is restored)
        :param restore_env: restore the envs' saved state into ``env`` when the zip holds one and ``env`` has the same
            structure (same number of envs, same wrappers); otherwise (or False) the env is reset, as in SB3
        :param strict_env: raise :class:`~sb3_pearl.common.env_state.EnvStateError` when the saved env state cannot be
            read here (another MuJoCo release wrote it); False: warn and reset the env (the model, its RNG streams and
            everything else load whole: what evaluation needs). The harness resumes strictly (exact resume)
        :param kwargs: attributes to set on the loaded model
        :return: the model
        :raises ValueError: the file is not a complete zip of this class, or a hyperparameter (saved, in
            ``custom_objects`` or in ``kwargs``) fails the constructor's checks
        """
        source = str(path) if isinstance(path, (str, os.PathLike)) else str(getattr(path, "name", "the model file"))
        cls._refuse_foreign_overrides({**(custom_objects or {}), **kwargs}, source)
        held: dict[str, Any] | None = None
        if isinstance(path, (str, os.PathLike)):
            held = data = read_model_data(path)
            cls._check_saved_data(data, str(path))
            # Before SB3 builds anything from them: a bad value fails here with the constructor's message.
            cls._check_loaded_arguments({**loaded_model_data(data, custom_objects), **kwargs}, str(path))
        elif path.seekable():  # a stream: its data entry read here too, the stream handed back to SB3 where it was
            start = path.tell()
            with zipfile.ZipFile(path) as archive:
                held = json.loads(archive.read("data")) if "data" in archive.namelist() else None
            path.seek(start)
        model = super().load(  # type: ignore[misc]
            path,
            env=env,
            device=device,
            custom_objects=custom_objects,
            print_system_info=print_system_info,
            force_reset=force_reset and not (restore_env and env is not None),
            **kwargs,
        )
        if not isinstance(path, (str, os.PathLike)):  # a stream is read once, by SB3: its model is checked instead
            cls._check_saved_data(vars(model), source)
            cls._check_loaded_arguments(vars(model), source)
        model._settle_added_data(held, kwargs)
        env_state = model.__dict__.pop("_env_state", None)
        if restore_env and env is not None:
            resumable = env_state is not None and model._last_obs is not None
            try:
                restored = resumable and restore_env_state(model.env, env_state)
            except EnvStateError as error:
                if strict_env:
                    raise EnvStateError(f"{path}: {error}") from error
                warnings.warn(f"{path}: {error}. The envs start new episodes instead.", stacklevel=2)
                restored = False
            if not restored:
                model._last_obs = None  # nothing to continue: SB3's reset before the next learn()
        state = getattr(model, "_rng_state", None)
        if state is not None:  # the saved streams, not SB3's reseed; the envs' at the first learn()
            restore_training_rng_state(state, None, model.action_space)
            model.__dict__["_rng_to_restore"] = state
        return model

    @classmethod
    def _check_saved_arguments(cls, saved: Mapping[str, Any]) -> None:
        """
        Run the constructor's argument checks on a model's attributes (each class checks its own arguments, reusing
        the checks its constructor runs; :func:`saved_arguments` maps attributes to arguments). Nothing here.

        :param saved: the attributes by name: a zip's data with ``load``'s replacements, or ``vars(model)``
        """

    @classmethod
    def _check_loaded_arguments(cls, saved: Mapping[str, Any], source: str) -> None:
        """
        :meth:`_check_saved_arguments` with the file named in the error.

        :param saved: the attributes by name
        :param source: the model file, for the message
        """
        try:
            cls._check_saved_arguments(saved)
        except ValueError as error:
            raise ValueError(
                f"{source}: {error} ({cls.__name__}.load checks the hyperparameters as the constructor does: the "
                "value is the zip's, or the one given in custom_objects or as a load() keyword)"
            ) from None

    @classmethod
    def _added_data(cls) -> dict[str, Any]:
        """
        The saved entries this class adds to its parent's, each with the value that stands for none of what it adds,
        where models of its parent were saved with them (before the two classes were split). Asked only of the classes
        that define it: the parent's ``load`` drops these entries (and refuses them as ``load`` overrides), this class's
        ``load`` gives a parent's zip without them these values.

        :return: name -> neutral value
        """
        return {}

    @classmethod
    def _data_of_classes(cls, classes: list[type[MetaAlgorithm]]) -> dict[str, tuple[type[MetaAlgorithm], Any]]:
        """The :meth:`_added_data` of ``classes`` (those that define it): name -> (the class, the neutral value)."""
        return {
            name: (algorithm, value)
            for algorithm in classes
            if "_added_data" in vars(algorithm)
            for name, value in algorithm._added_data().items()
        }

    @classmethod
    def _foreign_data(cls) -> dict[str, tuple[type[MetaAlgorithm], Any]]:
        """The entries that subclasses add (:meth:`_added_data`) and this class does not own: its ``load`` drops them."""
        subclasses: list[type[MetaAlgorithm]] = []
        pending = cls.__subclasses__()
        while pending:
            subclasses.append(pending.pop())
            pending.extend(subclasses[-1].__subclasses__())
        own = cls._data_of_classes([c for c in cls.__mro__ if issubclass(c, MetaAlgorithm)])
        return {name: entry for name, entry in cls._data_of_classes(subclasses).items() if name not in own}

    @classmethod
    def _refuse_foreign_overrides(cls, overrides: Mapping[str, Any], source: str) -> None:
        """
        A ``load`` keyword or ``custom_objects`` entry that only a subclass has (e.g. ``prior_coef`` given to
        ``PEARL.load``) is refused: this class has no such setting.

        :param overrides: the ``custom_objects`` and ``load`` keywords by name
        :param source: the model file, for the message
        """
        for name, (owner, _) in cls._foreign_data().items():
            if name in overrides:
                raise ValueError(
                    f"{source}: {name}={overrides[name]!r} is a setting of {owner.__name__}, which {cls.__name__} does not "
                    f"have: a {owner.__name__} model loads with {owner.__name__}.load"
                )

    def _settle_added_data(self, held: Mapping[str, Any] | None, overrides: Mapping[str, Any]) -> None:
        """
        After SB3's load: drop the entries of subclasses that a zip of this class may hold with their neutral values
        (:meth:`_foreign_data`), and give this class's own added entries (:meth:`_added_data`) their neutral values
        where the zip (a parent's) does not hold them.

        :param held: the zip's data (None: unknown)
        :param overrides: the ``load`` keywords (they win)
        """
        for name in type(self)._foreign_data():
            self.__dict__.pop(name, None)
        if held is None:
            return
        if "num_vec_env_steps" not in held:  # saved before it was recorded: every env stepped at each VecEnv step
            self.num_vec_env_steps = int(self.num_timesteps) // max(int(self.n_envs), 1)
        own = type(self)._data_of_classes([c for c in type(self).__mro__ if issubclass(c, MetaAlgorithm)])
        for name, (_, value) in own.items():
            if name not in held and name not in overrides:
                setattr(self, name, value)

    @classmethod
    def _variant_of(cls, data: dict[str, Any]) -> str | None:
        """
        What a zip holds when it is this class's and its parent cannot load it (a subclass that adds what its parent
        would drop says so here: PEARLPlus, for a zip with a prior term); None: its parent loads the zip too. Asked
        only of the classes that define it.

        :param data: a zip's ``data`` entry
        :return: the model the zip holds, for the message (e.g. ``"a PEARL+ model (prior_coef=0.1, ...)"``), or None
        """
        return None

    @staticmethod
    def _variant_writer(data: dict[str, Any]) -> tuple[type[MetaAlgorithm], str] | None:
        """The most derived algorithm class whose :meth:`_variant_of` claims a zip's data, with its claim (None: none)."""
        found: tuple[type[MetaAlgorithm], str] | None = None
        pending: list[type[MetaAlgorithm]] = MetaAlgorithm.__subclasses__()
        while pending:
            algorithm = pending.pop()
            claim = algorithm._variant_of(data) if "_variant_of" in vars(algorithm) else None
            if claim is not None and (found is None or issubclass(algorithm, found[0])):
                found = (algorithm, claim)
            pending.extend(algorithm.__subclasses__())
        return found

    @classmethod
    def _check_saved_data(cls, data: dict[str, Any], path: str) -> None:
        """
        Raise a clear error unless a zip's data fits this class: it holds :attr:`saved_data_keys` (else the message
        names the class that wrote it), and no subclass that this class is not claims it (:meth:`_variant_of`).

        :param data: the zip's ``data`` entry (:func:`read_model_data`)
        :param path: the zip, for the message
        """
        missing = [key for key in cls.saved_data_keys if key not in data]
        variant = cls._variant_writer(data)
        if not missing:
            if variant is not None and not issubclass(cls, variant[0]):
                writer, held = variant[0].__name__, variant[1]
                raise ValueError(
                    f"{path} holds {held}: load it with {writer}.load; {cls.__name__}.load would drop what {writer} adds"
                )
            return
        writers = [writer for writer in _SIGNATURES.values() if all(key in data for key in writer.saved_data_keys)]
        if writers:
            name = variant[0].__name__ if variant is not None and issubclass(variant[0], writers[-1]) else writers[-1].__name__
            raise ValueError(f"{path} holds a {name} model, not a {cls.__name__} one: load it with {name}.load")
        raise ValueError(
            f"{path} is not a {cls.__name__} model: it lacks {missing} and its policy is {saved_policy_name(data)}. "
            "Load it with the algorithm that saved it (e.g. stable_baselines3.SAC.load for a SAC zip)"
        )


__all__ = [
    "MetaAlgorithm",
    "SelfMetaAlgorithm",
    "check_observed_transition",
    "check_task_arguments",
    "forwards_arguments_to",
]
