"""Saving and loading the project's algorithms: atomic writes, and clear errors for files that do not fit.

:class:`SaveLoadMixin` (every algorithm) and :class:`ReplayBufferSaveLoadMixin` (the off-policy ones)
wrap SB3's ``save`` / ``load`` / ``save_replay_buffer`` / ``load_replay_buffer``:

- ``save`` and ``save_replay_buffer`` write through :func:`sb3_pearl.common.atomic.atomic_write`, so
  a process killed mid-save leaves the previous file intact (this covers rl_zoo3's final model,
  checkpoints and ``best_model.zip``, which all call ``model.save``). SB3's rule of appending
  ``.zip`` / ``.pkl`` to a path without a suffix is kept.
- ``load`` first reads the zip's ``data`` entry and checks every entry's CRC: a truncated or corrupt
  zip, a zip of another algorithm (SB3's SAC, or MAML into PEARL) and, through
  :meth:`SaveLoadMixin._check_saved_data`, a zip of a sibling class (PEARL+ into ``PEARL.load``) get
  an error naming the file and the class to use. The hyperparameters the model will have (the saved
  ones, with ``custom_objects`` and ``load()``'s keywords in their place) then go through the
  constructor's own argument checks (:meth:`SaveLoadMixin._check_saved_arguments`): a value the
  constructor refuses is refused at load too, with the constructor's message.
- a saved replay buffer carries the training tasks it was collected on; ``load_replay_buffer``
  refuses a buffer of other tasks (another family or another seed with the same dimensions would
  silently train on the wrong data).

Trust model, as in SB3: a model zip holds pickled objects and a replay buffer is a pickle. Loading
one runs whatever code its author put in it: load only files you trust.
"""

from __future__ import annotations

import copy
import inspect
import io
import json
import os
import pathlib
import pickle
import re
import warnings
import zipfile
import zlib
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar, cast

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.save_util import json_to_data, load_from_pkl
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback

from sb3_pearl.common.atomic import atomic_write, sb3_file_path
from sb3_pearl.common.env_state import EnvStateError, capture_env_state, restore_env_state
from sb3_pearl.common.seeding import capture_training_rng_state, restore_training_rng_state
from sb3_pearl.envs.task_protocol import Task

if TYPE_CHECKING:
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    _AlgorithmBase = BaseAlgorithm
    _OffPolicyBase = OffPolicyAlgorithm
else:
    _AlgorithmBase = object
    _OffPolicyBase = object

SelfSaveLoad = TypeVar("SelfSaveLoad", bound="SaveLoadMixin")

# Attribute of a saved replay buffer holding the training tasks it was collected on.
BUFFER_TASKS_ATTR = "sb3_pearl_train_tasks"

# The classes that declare the data keys every zip of theirs holds (filled by SaveLoadMixin.__init_subclass__).
_SIGNATURES: dict[str, type[SaveLoadMixin]] = {}


def resolve_model_path(path: str | os.PathLike[str]) -> pathlib.Path:
    """
    The zip SB3's ``load`` opens for ``path``: ``path``, else ``path.zip``.

    :param path: the path given to ``load``
    :return: the existing file
    """
    candidate = pathlib.Path(path)
    if candidate.is_file():
        return candidate
    with_zip = pathlib.Path(f"{path}.zip")
    if with_zip.is_file():
        return with_zip
    raise FileNotFoundError(f"no model zip at {path} (nor {with_zip}): check the path")


class DamagedModelError(ValueError):
    """
    A model zip that cannot be read: truncated, corrupt or not a Stable-Baselines3 zip.

    :param problem: what is wrong, naming the file (:attr:`problem`, for callers that give their own fix)
    :param fix: what to do about it
    """

    def __init__(self, problem: str, fix: str) -> None:
        super().__init__(f"{problem}: {fix}")
        self.problem = problem


def read_model_data(path: str | os.PathLike[str]) -> dict[str, Any]:
    """
    The ``data`` entry of an SB3 model zip as a JSON dict (serialised objects stay strings), after a CRC check of every entry.

    :param path: the model zip (or its path without ``.zip``)
    :return: the saved class parameters
    :raises DamagedModelError: the zip is truncated, corrupt or not a model zip
    """
    file = resolve_model_path(path)
    fix = (
        "the file is truncated or corrupt (e.g. a copy or a save that was cut short): load an earlier checkpoint "
        "or best_model.zip of the run, or save the model again"
    )
    try:
        with zipfile.ZipFile(file) as archive:
            if "data" not in archive.namelist():
                raise DamagedModelError(f"{file} holds no 'data' entry, so it is not a Stable-Baselines3 model zip", fix)
            bad_entry = archive.testzip()
            if bad_entry is not None:
                raise DamagedModelError(f"{file}: the entry {bad_entry!r} fails its CRC check", fix)
            raw = archive.read("data")
    except (zipfile.BadZipFile, EOFError, zlib.error) as error:
        raise DamagedModelError(f"{file} is not a readable zip ({error})", fix) from None
    try:
        data = json.loads(raw)
    except ValueError as error:
        raise DamagedModelError(f"{file}: its 'data' entry is not valid JSON ({error})", fix) from None
    if not isinstance(data, dict):
        raise DamagedModelError(f"{file}: its 'data' entry is not a dict of class parameters", fix)
    return data


def loaded_model_data(data: dict[str, Any], custom_objects: dict[str, Any] | None) -> dict[str, Any]:
    """
    A zip's data as SB3's ``load`` will set it on the model: serialised objects unpickled, and the entries that
    ``custom_objects`` names replaced by its values (SB3's rule: a key the zip does not hold is ignored).

    :param data: the zip's ``data`` entry (:func:`read_model_data`)
    :param custom_objects: the objects given to ``load``
    :return: the attributes by name
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # SB3's load itself warns about an object it cannot unpickle: once is enough
        return json_to_data(json.dumps(data), custom_objects=custom_objects)


def saved_arguments(constructor: Callable[..., Any], saved: Mapping[str, Any], **derived: Any) -> dict[str, Any]:
    """
    The arguments of ``constructor`` that a model's attributes stand for, for the constructor's argument checks at load.

    Every parameter with a default takes, in this order of precedence: ``derived`` (an argument kept under another
    name, e.g. ``latent_dim`` in ``policy_kwargs``), the attribute of the same name, the default. An empty
    ``train_tasks`` / ``test_tasks`` list (a model built without an env) stands for None, as the constructor takes it.

    :param constructor: the class's ``__init__``
    :param saved: the model's attributes by name (a zip's data, or ``vars(model)``)
    :param derived: arguments read from attributes of other names
    :return: the arguments by name
    """
    parameters = inspect.signature(constructor).parameters
    arguments = {name: p.default for name, p in parameters.items() if p.default is not inspect.Parameter.empty}
    arguments.update({name: saved[name] for name in arguments if name in saved})
    arguments.update(derived)
    for name in ("train_tasks", "test_tasks"):
        if name in arguments and not arguments[name]:
            arguments[name] = None
    return arguments


def saved_policy_name(data: dict[str, Any]) -> str:
    """The policy class recorded in a zip's data, e.g. ``stable_baselines3.sac.policies.SACPolicy`` (for messages)."""
    policy = data.get("policy_class")
    if not isinstance(policy, dict):
        return "an unknown policy"
    match = re.search(r"<function (\w+)\.__init__", str(policy.get("__init__", "")))
    name = match.group(1) if match else "?"
    return f"{policy.get('__module__', '?')}.{name}"


def _normalised_tasks(tasks: Any) -> Any:
    """Tasks as plain JSON values (tuples -> lists, numpy scalars -> numbers), for comparisons."""
    return json.loads(json.dumps(tasks, sort_keys=True, default=lambda value: getattr(value, "tolist", lambda: str(value))()))


def tag_buffer_tasks(buffer: Any, tasks: list[Task]) -> None:
    """Record on a replay buffer the training tasks it is collected on (saved with it)."""
    setattr(buffer, BUFFER_TASKS_ATTR, _normalised_tasks(list(tasks)))


def check_buffer_tasks(buffer: Any, tasks: list[Task], path: Any) -> None:
    """
    Raise a clear error unless ``buffer`` was collected on ``tasks`` (a buffer saved before the tag existed only warns).

    :param buffer: the loaded replay buffer
    :param tasks: the model's training tasks
    :param path: the buffer file, for the message
    """
    saved = getattr(buffer, BUFFER_TASKS_ATTR, None)
    if saved is None:
        warnings.warn(
            f"{path} does not record the training tasks it was collected on (saved by an older version): "
            "make sure it belongs to this model",
            stacklevel=3,
        )
        return
    current = _normalised_tasks(list(tasks))
    if saved != current:
        first_saved = saved[0] if saved else None
        first_current = current[0] if current else None
        raise ValueError(
            f"{path} was collected on other training tasks than this model's ({len(saved)} tasks, the first {first_saved}; "
            f"the model has {len(current)}, the first {first_current}): another env family, seed or task list. "
            "Load the replay buffer saved with this model, or construct the model with train_tasks=<the buffer's tasks> "
            f"(they are in the buffer's {BUFFER_TASKS_ATTR!r} attribute)"
        )


def refuse_model_zip(path: str | pathlib.Path | io.BufferedIOBase, algo_name: str) -> None:
    """
    Raise a clear error if ``path`` is a zip (a saved model) given to ``load_replay_buffer`` instead of its pickle.

    :param path: what was given to ``load_replay_buffer``
    :param algo_name: the model's class, for the message
    """
    if isinstance(path, (str, os.PathLike)) and os.path.isfile(path) and zipfile.is_zipfile(path):
        raise ValueError(
            f"{path} is a model zip, not a replay buffer pickle: load it with {algo_name}.load, and give "
            "load_replay_buffer the .pkl saved by save_replay_buffer"
        )


def read_replay_buffer(
    path: str | pathlib.Path | io.BufferedIOBase, verbose: int = 0, algo_name: str = "the model class"
) -> Any:
    """
    ``load_from_pkl`` with a clear error for a model zip given instead, or for a truncated or corrupt pickle.

    :param path: the pickle (``.pkl`` is appended if missing, as in SB3)
    :param verbose: SB3 verbosity
    :param algo_name: the model's class, for the message on a model zip
    :return: the unpickled buffer
    """
    refuse_model_zip(path, algo_name)
    try:
        return load_from_pkl(path, verbose)
    except (EOFError, pickle.UnpicklingError) as error:
        raise IncompleteReplayBufferError(path, error) from None


class IncompleteReplayBufferError(ValueError):
    """
    A replay buffer pickle that is empty, truncated or corrupt (e.g. a copy or a save cut short, a full disk).

    :param path: the pickle
    :param error: what unpickling it raised
    """

    def __init__(self, path: Any, error: BaseException) -> None:
        self.path = path
        empty = isinstance(path, (str, os.PathLike)) and os.path.isfile(path) and os.path.getsize(path) == 0
        self.reason = "0 bytes: the file is empty" if empty else f"{type(error).__name__}: {error}"
        super().__init__(
            f"{path} is not a complete replay buffer pickle ({self.reason}): the file is truncated or corrupt; save the "
            "replay buffer again, or train without it"
        )


class SaveLoadMixin(_AlgorithmBase):
    """
    Atomic ``save`` and a checked ``load`` for an SB3 algorithm (module docstring); put it first among the bases.

    A class lists in :attr:`saved_data_keys` the parameters every zip of it holds; ``load`` refuses a zip
    without them and names the class that wrote it when it is one of the project's.
    """

    saved_data_keys: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("saved_data_keys"):
            _SIGNATURES[cls.__name__] = cls

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
        try:
            if isinstance(path, (str, os.PathLike)):
                with atomic_write(sb3_file_path(path, "zip")) as file:
                    super().save(cast(io.BufferedIOBase, file), exclude=exclude, include=include)
            else:
                super().save(path, exclude=exclude, include=include)
        finally:
            del self._env_state

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_rng_to_restore"]

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        # First learn() after load(): continue the saved RNG streams (after SB3's env reset, when the envs' saved state
        # was not restored, reseeded them).
        state = self.__dict__.pop("_rng_to_restore", None)
        if state is not None:
            restore_training_rng_state(state, self.env, self.action_space)
        return result

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfSaveLoad],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        restore_env: bool = True,
        strict_env: bool = False,
        **kwargs: Any,
    ) -> SelfSaveLoad:
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
        if isinstance(path, (str, os.PathLike)):
            data = read_model_data(path)
            cls._check_saved_data(data, str(path))
            # Before SB3 builds anything from them: a bad value fails here with the constructor's message.
            cls._check_loaded_arguments({**loaded_model_data(data, custom_objects), **kwargs}, str(path))
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
            cls._check_loaded_arguments(vars(model), str(getattr(path, "name", "the model file")))
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
    def _saved_class_name(cls, data: dict[str, Any]) -> str:
        """The class that wrote a zip whose data holds :attr:`saved_data_keys` (subclasses tell their variants apart)."""
        return cls.__name__

    @classmethod
    def _check_saved_data(cls, data: dict[str, Any], path: str) -> None:
        """
        Raise a clear error unless a zip's data fits this class (subclasses add their own checks).

        :param data: the zip's ``data`` entry (:func:`read_model_data`)
        :param path: the zip, for the message
        """
        missing = [key for key in cls.saved_data_keys if key not in data]
        if not missing:
            return
        writers = [writer for writer in _SIGNATURES.values() if all(key in data for key in writer.saved_data_keys)]
        if writers:
            name = writers[-1]._saved_class_name(data)
            raise ValueError(f"{path} holds a {name} model, not a {cls.__name__} one: load it with {name}.load")
        raise ValueError(
            f"{path} is not a {cls.__name__} model: it lacks {missing} and its policy is {saved_policy_name(data)}. "
            "Load it with the algorithm that saved it (e.g. stable_baselines3.SAC.load for a SAC zip)"
        )


class ReplayBufferSaveLoadMixin(SaveLoadMixin, _OffPolicyBase):
    """
    :class:`SaveLoadMixin` for off-policy algorithms: atomic ``save_replay_buffer``; the buffer carries the
    training tasks it was collected on and ``load_replay_buffer`` refuses a buffer of other tasks.
    """

    train_tasks: list[Task]

    def save_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase) -> None:
        """
        SB3's ``save_replay_buffer``, atomic, with the training tasks recorded in the buffer.

        :param path: the pickle (``.pkl`` is appended when the path has no suffix, as in SB3) or an open binary file
        """
        assert self.replay_buffer is not None, "The replay buffer is not defined"
        tag_buffer_tasks(self.replay_buffer, self.train_tasks)
        full_buffer = self.replay_buffer
        self.replay_buffer = compact_buffer(full_buffer)  # only the filled rows are pickled
        try:
            if isinstance(path, (str, os.PathLike)):
                with atomic_write(sb3_file_path(path, "pkl")) as file:
                    super().save_replay_buffer(cast(io.BufferedIOBase, file))
            else:
                super().save_replay_buffer(path)
        finally:
            self.replay_buffer = full_buffer

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """
        SB3's ``load_replay_buffer``, refusing a model zip, a truncated pickle or a buffer collected on other training tasks.

        :param path: the pickle
        :param truncate_last_traj: SB3's option for ``HerReplayBuffer``
        """
        refuse_model_zip(path, type(self).__name__)
        previous = self.replay_buffer
        try:
            super().load_replay_buffer(path, truncate_last_traj)
        except (EOFError, pickle.UnpicklingError) as error:
            raise IncompleteReplayBufferError(path, error) from None
        expand_buffer(self.replay_buffer)
        try:
            check_buffer_tasks(self.replay_buffer, self.train_tasks, path)
        except ValueError:
            self.replay_buffer = previous
            raise


COMPACT_CAPACITY_ATTR = "_sb3_pearl_capacity"  # set on a pickled SB3 ReplayBuffer holding only its filled rows
_ROW_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def compact_buffer(buffer: Any) -> Any:
    """
    A shallow copy of an SB3 ``ReplayBuffer`` that is not full, holding only its filled rows (``[:pos]``) and its
    capacity in :data:`COMPACT_CAPACITY_ATTR`: SB3 allocates and pickles all ``buffer_size`` rows (a 1M-row Ant buffer
    is ~1.8 GB however little is filled), so a part-way run's checkpoint would be too large to keep. Anything else
    (a full buffer, PEARL's per-task buffer, dict observations) is returned as it is.

    :param buffer: the replay buffer
    :return: what to pickle
    """
    if (
        type(buffer) is not ReplayBuffer
        or buffer.full
        or buffer.pos >= buffer.buffer_size
        or buffer.optimize_memory_usage  # its next observations live in observations[pos]: keep the layout as it is
        or hasattr(buffer, COMPACT_CAPACITY_ATTR)
        or buffer.observations.shape[0] != buffer.buffer_size  # compact already
    ):
        return buffer
    compact = copy.copy(buffer)
    for name in _ROW_ARRAYS:
        array = getattr(buffer, name, None)
        if isinstance(array, np.ndarray) and array.shape[:1] == (buffer.buffer_size,):
            setattr(compact, name, array[: buffer.pos].copy())
    setattr(compact, COMPACT_CAPACITY_ATTR, buffer.buffer_size)
    return compact


def expand_buffer(buffer: Any) -> None:
    """
    Undo :func:`compact_buffer` in place on a loaded buffer: every row array back to ``buffer_size`` rows, the rows
    past ``pos`` zero as SB3 allocates them (so sampling, and a resumed run, are those of the buffer that was saved).

    :param buffer: the loaded replay buffer
    """
    capacity = getattr(buffer, COMPACT_CAPACITY_ATTR, None)
    if capacity is None:
        return
    for name in _ROW_ARRAYS:
        array = getattr(buffer, name, None)
        if isinstance(array, np.ndarray) and array.shape[:1] == (buffer.pos,):
            full = np.zeros((capacity, *array.shape[1:]), dtype=array.dtype)
            full[: buffer.pos] = array
            setattr(buffer, name, full)
    delattr(buffer, COMPACT_CAPACITY_ATTR)


__all__ = [
    "BUFFER_TASKS_ATTR",
    "COMPACT_CAPACITY_ATTR",
    "ReplayBufferSaveLoadMixin",
    "SaveLoadMixin",
    "check_buffer_tasks",
    "compact_buffer",
    "expand_buffer",
    "loaded_model_data",
    "read_model_data",
    "DamagedModelError",
    "IncompleteReplayBufferError",
    "read_replay_buffer",
    "refuse_model_zip",
    "resolve_model_path",
    "saved_arguments",
    "saved_policy_name",
    "tag_buffer_tasks",
]
