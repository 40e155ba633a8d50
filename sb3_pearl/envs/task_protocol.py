"""The env side of the task protocol every task family implements (``docs/design.md``).

A task family is a Gymnasium env whose *task* (goal, target velocity, traffic) is a
JSON-serialisable ``dict``:

- ``sample_tasks(n, seed=None) -> list[dict]``: reproducible for a seed, drawn from the ranges
  given as constructor kwargs (a shifted test distribution is one kwarg);
- ``set_task(task)``: sticky until the next call, takes effect at the next ``reset()``;
- ``get_task() -> dict``;
- ``info["cost"]``: 1.0 on a step that violates safety, else 0.0;
- ``step(action)`` refuses an action holding nan or inf (:func:`refuse_non_finite_action`): stepped, it would
  leave the state non-finite and be counted as a safe step (cost 0).

:class:`MetaTaskEnv` is the mixin that holds the task bookkeeping; families implement
``_sample_task(rng)`` and read ``self._task`` (the task in force since the last reset).
"""

from __future__ import annotations

import copy
import math
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

Task = dict[str, Any]

TASK_METHODS = ("sample_tasks", "set_task", "get_task")


def refuse_non_finite_action(env: object, action: Any) -> None:
    """
    Raise a ``ValueError`` naming the env if ``action`` holds a nan or an inf (every family's ``step`` calls it first).

    A diverged policy (or a non-finite observation fed to it) gives such actions; stepped, they leave the state
    non-finite while ``info["cost"]`` says 0, so a diverged rollout would be counted as safe.

    :param env: the env (for the message)
    :param action: the action given to ``step``
    """
    values = np.asarray(action).ravel().tolist()
    if not all(map(math.isfinite, values)):
        raise non_finite_action_error(env, values)


def non_finite_action_error(env: object, values: Any) -> ValueError:
    """The error of :func:`refuse_non_finite_action` (families with a faster check of their own raise it too)."""
    return ValueError(
        f"{type(env).__name__}.step: the action {np.asarray(values).tolist()} is not finite: refused rather than stepped "
        "(it would be counted as a safe step); the policy diverged or was given a non-finite observation"
    )


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
        """
        Set the task used from the next ``reset()`` on (sticky until the next call).

        :param task: a task dict as returned by :meth:`sample_tasks`; a value of another type or shape than the
            family's, a non-finite number or (family-specific) a value out of range raises a ``ValueError``. Where the
            family's tasks hold an integer, an integer-valued float (``6.0``, as JSON or YAML may give it) is stored as
            that integer; any other float is refused
        """
        if not isinstance(task, dict):
            raise TypeError(f"set_task expects a task dict as returned by sample_tasks(), got {type(task).__name__}")
        self._validate_task(task)
        self._pending_task = _conformed(self._task, _plain(task))

    def task_error(self, task: Any) -> str | None:
        """
        Why ``task`` is not a valid task of this env, or None if it is (``set_task`` without side effects).

        Works through ``VecEnv.env_method`` (a raising worker would bring a ``SubprocVecEnv`` down).

        :param task: the candidate task
        :return: the message ``set_task`` would raise, or None
        """
        if not isinstance(task, dict):
            return f"a task must be a dict as returned by sample_tasks(), got {type(task).__name__}"
        try:
            self._validate_task(task)
        except (ValueError, TypeError, KeyError, IndexError) as error:
            return str(error)
        return None

    def task_family(self) -> str:
        """
        The name of this env's task family, which a model records to refuse an env of another family later (two
        families may share spaces and task keys, e.g. Walker2d's and HalfCheetah's velocity tasks): the class name of
        the family, i.e. the first class of this env's MRO defined in :mod:`sb3_pearl.envs`, so that a variant
        subclassing a family elsewhere (a test's failure-injecting env) stays that family; outside the package, the
        env's own class name.

        :return: e.g. ``"SafePointGoalMetaEnv"``
        """
        for klass in type(self).__mro__:
            if klass.__module__.startswith("sb3_pearl.envs."):
                return klass.__name__
        return type(self).__name__

    def get_task(self) -> Task:
        """The task that the next ``reset()`` will use (the pending one if ``set_task`` was called)."""
        return copy.deepcopy(self._pending_task if self._pending_task is not None else self._task)

    def _validate_task(self, task: Task) -> None:
        """
        Raise unless ``task`` has the keys of this family's tasks and every value the type and shape of theirs
        (numbers finite). Families add range checks (calling this first).
        """
        expected = set(self._task)
        if set(task) != expected:
            raise ValueError(f"{type(self).__name__}.set_task: task keys {sorted(task)} != expected {sorted(expected)}")
        for key in sorted(expected):
            problem = _value_problem(self._task[key], task[key])
            if problem is not None:
                raise ValueError(
                    f"{type(self).__name__}.set_task: {key} must be {problem}, as from sample_tasks() "
                    f"(e.g. {self._task[key]!r}), got {task[key]!r}"
                )

    def task_features(self, task: Task) -> list[float]:
        """
        The task as a fixed-length list of numbers, the same order for every task of the family: what a task-aware
        agent (the oracle, :mod:`sb3_pearl.envs.task_observation`) is told. Default: every number of the task, keys
        in sorted order, lists flattened in order (bools as 0 / 1, strings skipped). Families whose task holds an
        angle override it with a continuous encoding (the angle's cosine and sine).

        :param task: a task of this family
        :return: the features
        """
        return _flat_numbers(task)

    def _apply_pending_task(self) -> None:
        if self._pending_task is not None:
            self._task = self._pending_task
            self._pending_task = None


def _flat_numbers(value: Any) -> list[float]:
    """Every number of a task value in a fixed order: dict keys sorted, lists in order, bools as 0 / 1."""
    if isinstance(value, dict):
        return [number for key in sorted(value) for number in _flat_numbers(value[key])]
    if isinstance(value, (list, tuple, np.ndarray)):
        return [number for item in value for number in _flat_numbers(item)]
    if isinstance(value, (bool, np.bool_)) or _is_number(value):
        return [float(value)]
    return []


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _value_problem(template: Any, value: Any) -> str | None:
    """What ``value`` must be to match ``template`` (a value of a sampled task), or None when it does."""
    if isinstance(template, (bool, np.bool_)):
        return None if isinstance(value, (bool, np.bool_)) else "a bool"
    if _is_number(template):
        if isinstance(value, np.ndarray) and value.shape == ():
            value = value.item()
        if not _is_number(value) or not math.isfinite(float(value)):
            return "a finite number"
        if isinstance(template, (int, np.integer)) and float(value) != int(value):
            return "an integer"
        return None
    if isinstance(template, str):
        return None if isinstance(value, str) else "a string"
    if isinstance(template, (list, tuple, np.ndarray)):
        if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != len(template):
            return f"a list of {len(template)} values"
        for item_template, item in zip(template, value):
            problem = _value_problem(item_template, item)
            if problem is not None:
                return f"a list of {len(template)} values, each {problem}"
        return None
    if isinstance(template, dict):
        if not isinstance(value, dict) or set(value) != set(template):
            return f"a dict with keys {sorted(template)}"
        for key in template:
            problem = _value_problem(template[key], value[key])
            if problem is not None:
                return f"a dict whose {key!r} is {problem}"
    return None


def _conformed(template: Any, value: Any) -> Any:
    """
    A validated task value (:func:`_plain`) with the integer-valued floats at the places where ``template`` (a task of
    the family) holds integers turned into ints: ``[6.0, 2.0]`` for a maze cell is stored as ``[6, 2]``.
    """
    if isinstance(template, dict) and isinstance(value, dict):
        return {key: _conformed(template.get(key), item) for key, item in value.items()}
    if isinstance(template, (list, tuple)) and isinstance(value, list):
        return [_conformed(item_template, item) for item_template, item in zip(template, value)]
    if isinstance(template, (int, np.integer)) and not isinstance(template, (bool, np.bool_)) and _is_number(value):
        return int(value)
    return value


def _plain(value: Any) -> Any:
    """A deep copy with numpy values as Python ones (tasks stay JSON-serialisable)."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return copy.deepcopy(value)
