"""The env side of the task protocol every task family implements (``docs/design.md``).

A task family is a Gymnasium env whose *task* (goal, target velocity, traffic) is a
JSON-serialisable ``dict``:

- ``sample_tasks(n, seed=None) -> list[dict]``: reproducible for a seed, drawn from the ranges
  given as constructor kwargs (a shifted test distribution is one kwarg);
- ``set_task(task)``: sticky until the next call, takes effect at the next ``reset()``;
- ``get_task() -> dict``;
- ``info["cost"]``: 1.0 on a step that violates safety, else 0.0.

:class:`MetaTaskEnv` is the mixin that holds the task bookkeeping; families implement
``_sample_task(rng)`` and read ``self._task`` (the task in force since the last reset).
"""

from __future__ import annotations

import copy
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

Task = dict[str, Any]

TASK_METHODS = ("sample_tasks", "set_task", "get_task")


@runtime_checkable
class TaskFamily(Protocol):
    """Structural type of a task family env (``env.unwrapped``)."""

    def sample_tasks(self, n: int, seed: int | None = None) -> list[Task]: ...

    def set_task(self, task: Task) -> None: ...

    def get_task(self) -> Task: ...


class MetaTaskEnv:
    """
    Mixin for the task bookkeeping of a task family.

    Subclasses call :meth:`_init_task` in ``__init__`` (after their ranges are known) and
    :meth:`_apply_pending_task` at the start of ``reset()``; they implement
    :meth:`_sample_task`.
    """

    # Scalar info entries the meta-test records per trajectory (last value seen), e.g. the merge
    # family's ``b_min``; and per-step info entries kept as traces (e.g. ``ego_speed``).
    trajectory_info_keys: ClassVar[tuple[str, ...]] = ()
    step_trace_keys: ClassVar[tuple[str, ...]] = ()

    _task: Task
    _pending_task: Task | None

    def _init_task(self) -> None:
        self._task = self._sample_task(np.random.default_rng(0))
        self._pending_task = None

    def _sample_task(self, rng: np.random.Generator) -> Task:
        raise NotImplementedError

    def sample_tasks(self, n: int, seed: int | None = None) -> list[Task]:
        """
        Draw ``n`` tasks from this env's task distribution.

        :param n: number of tasks
        :param seed: seed of the draw; the same seed gives the same list
        :return: JSON-serialisable task dicts
        """
        if n < 0:
            raise ValueError(f"sample_tasks: n must be >= 0, got {n}")
        rng = np.random.default_rng(seed)
        return [self._sample_task(rng) for _ in range(n)]

    def set_task(self, task: Task) -> None:
        """Set the task used from the next ``reset()`` on (sticky until the next call)."""
        if not isinstance(task, dict):
            raise TypeError(f"set_task expects a task dict as returned by sample_tasks(), got {type(task).__name__}")
        self._validate_task(task)
        self._pending_task = copy.deepcopy(task)

    def get_task(self) -> Task:
        """The task that the next ``reset()`` will use (the pending one if ``set_task`` was called)."""
        return copy.deepcopy(self._pending_task if self._pending_task is not None else self._task)

    def _validate_task(self, task: Task) -> None:
        expected = set(self._task)
        if set(task) != expected:
            raise ValueError(f"{type(self).__name__}.set_task: task keys {sorted(task)} != expected {sorted(expected)}")

    def _apply_pending_task(self) -> None:
        if self._pending_task is not None:
            self._task = self._pending_task
            self._pending_task = None
