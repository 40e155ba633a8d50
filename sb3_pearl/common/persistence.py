"""Saving and loading the project's algorithms: the file checks and buffer tags behind their ``save`` / ``load``.

:class:`~sb3_pearl.common.meta_algorithm.MetaAlgorithm` wraps SB3's ``save`` / ``load`` / ``save_replay_buffer`` /
``load_replay_buffer`` with these pieces:

- ``save`` and ``save_replay_buffer`` write through :func:`sb3_pearl.common.atomic.atomic_write`, so
  a process killed mid-save leaves the previous file intact (this covers rl_zoo3's final model,
  checkpoints and ``best_model.zip``, which all call ``model.save``). SB3's rule of appending
  ``.zip`` / ``.pkl`` to a path without a suffix is kept.
- ``load`` first reads the zip's ``data`` entry and checks every entry's CRC (:func:`read_model_data`): a truncated or
  corrupt zip, a zip of another algorithm (SB3's SAC, or MAML into PEARL) and a zip of a sibling class (PEARL+ into
  ``PEARL.load``) get an error naming the file and the class to use. The hyperparameters the model will have (the saved
  ones, with ``custom_objects`` and ``load()``'s keywords in their place, :func:`loaded_model_data`) then go through the
  constructor's own argument checks (:func:`saved_arguments`): a value the constructor refuses is refused at load too,
  with the constructor's message.
- a saved replay buffer carries the training tasks it was collected on (:func:`tag_buffer_tasks`);
  ``load_replay_buffer`` refuses a buffer of other tasks (:func:`check_buffer_tasks`: another family or another seed
  with the same dimensions would silently train on the wrong data).

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
from typing import Any, cast

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.save_util import json_to_data, load_from_pkl, save_to_pkl

from sb3_pearl.common.atomic import atomic_write, sb3_file_path
from sb3_pearl.envs.task_protocol import Task

# Attribute of a saved replay buffer holding the training tasks it was collected on.
BUFFER_TASKS_ATTR = "sb3_pearl_train_tasks"


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


def save_replay_buffer_file(
    buffer: Any, tasks: list[Task], path: str | pathlib.Path | io.BufferedIOBase, verbose: int = 0
) -> None:
    """
    SB3's ``save_replay_buffer`` for an off-policy algorithm of the project: the buffer tagged with the training tasks
    it was collected on (:func:`tag_buffer_tasks`), only its filled rows (:func:`compact_buffer`), written atomically.

    :param buffer: the model's replay buffer
    :param tasks: the model's training tasks
    :param path: the pickle (``.pkl`` is appended when the path has no suffix, as in SB3) or an open binary file
    :param verbose: SB3 verbosity
    """
    assert buffer is not None, "The replay buffer is not defined"
    tag_buffer_tasks(buffer, tasks)
    compact = compact_buffer(buffer)  # only the filled rows are pickled
    write_sb3_file(path, "pkl", lambda file: save_to_pkl(file, compact, verbose))


def write_sb3_file(
    path: str | pathlib.Path | io.BufferedIOBase, suffix: str, write: Callable[[io.BufferedIOBase], None]
) -> None:
    """
    Write an SB3 file atomically: to a temporary file renamed into place (a kill or a full disk mid-save keeps the
    previous file), with SB3's rule of appending ``.<suffix>`` to a path without one; an open file is written as it is.

    :param path: the file, or an open binary file
    :param suffix: ``"zip"`` (a model) or ``"pkl"`` (a replay buffer)
    :param write: writes the content into the open file it is given (SB3's ``save`` or ``save_to_pkl``)
    """
    if isinstance(path, (str, os.PathLike)):
        with atomic_write(sb3_file_path(path, suffix)) as file:
            write(cast(io.BufferedIOBase, file))
    else:
        write(path)


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
    "save_replay_buffer_file",
    "write_sb3_file",
    "saved_policy_name",
    "tag_buffer_tasks",
]
