"""The meta-test protocol behind every number of the paper, for any algorithm with the adaptation API.

For each test task and each repeat: the task is set, the model forgets everything task-specific
(``reset_adaptation()``), then trajectories ``k = 0..n_adapt`` are rolled out in sequence.
Trajectory ``k = 0`` acts with the prior (no ``adapt()`` call before it); trajectory ``k`` acts
after ``adapt()`` on every transition of trajectories ``0..k-1`` (each one passed to
``observe()`` as it happens). Actions are deterministic by default.

One row per (task, repeat, k): ``return``, ``cost`` (sum of ``info["cost"]``), ``length``,
``violated`` (any cost) and the family extras found in ``info`` (:data:`EXTRA_INFO_KEYS`, e.g.
``b_min`` and ``merged`` for the merge family; the last value seen in the trajectory). Per-step
traces of :data:`TRACE_INFO_KEYS` (the merge family's ``ego_speed``) are kept for the plots.

The summary per k (:func:`summarize`): mean and std of the return, the violation rate with its
95% Wilson interval, the CVaR_10% of the return over tasks and the cumulative violations up to k.
The paper's "0/1/3/5 traj." columns are :data:`PAPER_KS`.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from sb3_pearl.envs.task_protocol import Task

PAPER_KS = (0, 1, 3, 5)
ROW_COLUMNS = ("task", "repeat", "k", "return", "cost", "length", "violated")
# Family extras: scalar info entries recorded per trajectory when the env reports them (last value seen).
EXTRA_INFO_KEYS = ("merged", "crashed", "b_min", "rear_deceleration")
# Per-step info entries kept as traces (speed profiles of the merge family).
TRACE_INFO_KEYS = ("ego_speed",)
SUMMARY_COLUMNS = (
    "k",
    "n",
    "return_mean",
    "return_std",
    "violation_rate",
    "violation_ci_low",
    "violation_ci_high",
    "return_cvar10",
    "cum_violations",
)
WILSON_Z95 = 1.959963984540054


@runtime_checkable
class AdaptiveModel(Protocol):
    """The adaptation API every algorithm of the project implements (``DESIGN.md``)."""

    def reset_adaptation(self) -> None: ...

    def observe(self, obs: np.ndarray, action: Any, reward: float, next_obs: np.ndarray, done: bool) -> None: ...

    def adapt(self) -> None: ...

    def predict(
        self,
        observation: Any,
        state: Any = None,
        episode_start: Any = None,
        deterministic: bool = False,
    ) -> tuple[Any, Any]: ...


def check_adaptive(model: Any) -> None:
    """
    Raise a clear error unless ``model`` implements the adaptation API.

    :param model: the model to evaluate
    """
    missing = [
        name for name in ("reset_adaptation", "observe", "adapt", "predict") if not callable(getattr(model, name, None))
    ]
    if missing:
        raise TypeError(
            f"{type(model).__name__} does not implement the adaptation API (missing {missing}): the meta-test "
            "protocol needs reset_adaptation(), observe(obs, action, reward, next_obs, done), adapt() and predict()"
        )


# ----------------------------------------------------------------------------------------------
# Statistics
# ----------------------------------------------------------------------------------------------
def wilson_interval(successes: int, n: int, z: float = WILSON_Z95) -> tuple[float, float]:
    """
    Wilson score interval of a binomial proportion (95% by default).

    :param successes: number of positive outcomes
    :param n: number of trials
    :param z: normal quantile of the interval
    :return: (low, high); (nan, nan) when ``n == 0``
    """
    if n <= 0:
        return math.nan, math.nan
    p = successes / n
    denom = 1.0 + z**2 / n
    centre = (p + z**2 / (2 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z**2 / (4 * n**2)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def cvar(values: Sequence[float] | np.ndarray, alpha: float = 0.1) -> float:
    """
    Conditional value at risk of returns: the mean of the worst ``ceil(alpha * n)`` values (at least one).

    :param values: returns (higher is better)
    :param alpha: tail share
    :return: the lower-tail mean; nan for no values
    """
    array = np.sort(np.asarray(values, dtype=np.float64))
    if array.size == 0:
        return math.nan
    n_tail = max(1, math.ceil(alpha * array.size - 1e-9))
    return float(array[:n_tail].mean())


def summarize(rows: Sequence[dict[str, Any]], alpha: float = 0.1) -> list[dict[str, Any]]:
    """
    The summary per k of meta-test rows.

    - ``return_mean``, ``return_std`` (population std) over all (task, repeat) trajectories at k;
    - ``violation_rate``: share of those trajectories with any cost, ``violation_ci_low/high`` its
      95% Wilson interval;
    - ``return_cvar10``: CVaR_alpha over tasks of the per-task return (mean over repeats);
    - ``cum_violations``: violating trajectories among 0..k, averaged over (task, repeat);
    - ``<extra>_mean`` for every numeric family extra present (nan values ignored).

    :param rows: rows as produced by :func:`meta_test`
    :param alpha: tail share of the CVaR
    :return: one dict per k, in increasing k
    """
    if not rows:
        return []
    extra_keys = [key for key in EXTRA_INFO_KEYS if any(key in row for row in rows)]
    ks = sorted({int(row["k"]) for row in rows})
    episodes = sorted({(row["task"], row["repeat"]) for row in rows})
    violated = {(row["task"], row["repeat"], int(row["k"])): bool(row["violated"]) for row in rows}
    summary = []
    for k in ks:
        at_k = [row for row in rows if int(row["k"]) == k]
        returns = np.array([row["return"] for row in at_k], dtype=np.float64)
        n_violated = int(sum(bool(row["violated"]) for row in at_k))
        low, high = wilson_interval(n_violated, len(at_k))
        per_task: dict[Any, list[float]] = {}
        for row in at_k:
            per_task.setdefault(row["task"], []).append(float(row["return"]))
        cum = [sum(violated.get((task, repeat, j), False) for j in ks if j <= k) for task, repeat in episodes]
        entry: dict[str, Any] = {
            "k": k,
            "n": len(at_k),
            "return_mean": float(returns.mean()),
            "return_std": float(returns.std()),
            "violation_rate": n_violated / len(at_k),
            "violation_ci_low": low,
            "violation_ci_high": high,
            "return_cvar10": cvar([float(np.mean(v)) for v in per_task.values()], alpha),
            "cum_violations": float(np.mean(cum)),
        }
        for key in extra_keys:
            values = np.array([float(row.get(key, math.nan)) for row in at_k], dtype=np.float64)
            finite = values[~np.isnan(values)]
            entry[f"{key}_mean"] = float(finite.mean()) if finite.size else math.nan
        summary.append(entry)
    return summary


# ----------------------------------------------------------------------------------------------
# Result container and writers
# ----------------------------------------------------------------------------------------------
def _json_value(value: Any) -> Any:
    """Plain JSON value: nan/inf become None, numpy scalars Python numbers."""
    if isinstance(value, (np.floating, float)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, dict):
        return {str(k): _json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_value(v) for v in value]
    return value


@dataclass
class MetaTestResult:
    """
    Result of :func:`meta_test`.

    :param rows: one dict per (task, repeat, k) with :data:`ROW_COLUMNS` and the extras found
    :param summary: one dict per k (:func:`summarize`)
    :param tasks: the test tasks, in row order of ``task``
    :param traces: per-step info traces (``{"task", "repeat", "k", <key>: [...]}``)
    :param config: the protocol settings (n_adapt, n_repeats, deterministic, ...)
    """

    rows: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    tasks: list[Task] = field(default_factory=list)
    traces: list[dict[str, Any]] = field(default_factory=list)
    config: dict[str, Any] = field(default_factory=dict)

    @property
    def columns(self) -> list[str]:
        """CSV columns: :data:`ROW_COLUMNS` then the family extras present, in :data:`EXTRA_INFO_KEYS` order."""
        return [*ROW_COLUMNS, *(key for key in EXTRA_INFO_KEYS if any(key in row for row in self.rows))]

    def summary_at(self, k: int) -> dict[str, Any]:
        """The summary entry of trajectory ``k`` (KeyError if it was not rolled out)."""
        for entry in self.summary:
            if entry["k"] == k:
                return entry
        raise KeyError(f"no trajectory k={k} in this meta-test (k = 0..{self.config.get('n_adapt')})")

    def paper_table(self, ks: Sequence[int] = PAPER_KS) -> list[dict[str, Any]]:
        """The summary entries of the paper's columns (k = 0, 1, 3, 5) that were rolled out."""
        return [entry for entry in self.summary if entry["k"] in ks]

    def to_csv(self, path: str | os.PathLike[str]) -> None:
        """Write the rows as CSV (columns :attr:`columns`; missing extras are empty)."""
        columns = self.columns
        with open(path, "w", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=columns, extrasaction="ignore", restval="")
            writer.writeheader()
            for row in self.rows:
                writer.writerow({key: _csv_value(row.get(key, "")) for key in columns})

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: config, summary, paper table, tasks, rows and traces."""
        return _json_value(
            {
                "config": self.config,
                "summary": self.summary,
                "paper": {str(entry["k"]): entry for entry in self.paper_table()},
                "tasks": self.tasks,
                "rows": self.rows,
                "traces": self.traces,
            }
        )

    def to_json(self, path: str | os.PathLike[str]) -> None:
        """Write :meth:`to_dict` as JSON."""
        with open(path, "w") as file:
            json.dump(self.to_dict(), file, indent=1)

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> MetaTestResult:
        """Read a result written by :meth:`to_json` (None back to nan in numbers)."""
        with open(path) as file:
            data = json.load(file)

        def fix(entry: dict[str, Any]) -> dict[str, Any]:
            return {key: (math.nan if value is None else value) for key, value in entry.items()}

        return cls(
            rows=[fix(row) for row in data.get("rows", [])],
            summary=[fix(entry) for entry in data.get("summary", [])],
            tasks=data.get("tasks", []),
            traces=data.get("traces", []),
            config=data.get("config", {}),
        )

    def format_summary(self, ks: Sequence[int] | None = None) -> str:
        """A plain-text table of the summary (all k, or ``ks``)."""
        entries = self.summary if ks is None else [e for e in self.summary if e["k"] in ks]
        return format_summary_table(entries)


def _csv_value(value: Any) -> Any:
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (float, np.floating)) and math.isnan(value):
        return ""
    return value


def format_summary_table(entries: Sequence[dict[str, Any]]) -> str:
    """
    Plain-text table of summary entries: k, return mean +- std, CVaR_10%, violation rate [95% CI], cumulative violations.

    :param entries: summary dicts
    :return: the table
    """
    lines = [f"{'k':>3} {'return':>20} {'CVaR10%':>10} {'viol. rate':>10} {'95% CI':>15} {'cum. viol.':>10}"]
    for e in entries:
        ret = f"{e['return_mean']:.2f} +- {e['return_std']:.2f}"
        ci = f"[{e['violation_ci_low']:.2f}, {e['violation_ci_high']:.2f}]"
        rates = f"{e['violation_rate']:>10.2f} {ci:>15} {e['cum_violations']:>10.2f}"
        lines.append(f"{e['k']:>3} {ret:>20} {e['return_cvar10']:>10.2f} {rates}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# Rollouts
# ----------------------------------------------------------------------------------------------
class _SingleEnv:
    """One env, gymnasium or a one-env VecEnv, behind set_task / reset / step (with terminated and truncated)."""

    def __init__(self, env: gym.Env | VecEnv) -> None:
        self.vec_env: VecEnv | None = None
        self.env: gym.Env | None = None
        if isinstance(env, DummyVecEnv) and env.num_envs == 1:
            self.env = env.envs[0]
        elif isinstance(env, VecEnv):
            if env.num_envs != 1:
                raise ValueError(f"the meta-test runs one env at a time: got a VecEnv of {env.num_envs} envs")
            self.vec_env = env
        else:
            self.env = env
        self._seed: int | None = None

    def seed(self, seed: int | None) -> None:
        self._seed = seed
        if self.vec_env is not None and seed is not None:
            self.vec_env.seed(seed)

    def set_task(self, task: Task) -> None:
        if self.vec_env is not None:
            self.vec_env.env_method("set_task", task)
        else:
            assert self.env is not None
            base = self.env.unwrapped
            if not callable(getattr(base, "set_task", None)):
                raise ValueError(f"{type(base).__name__} has no set_task(): the meta-test needs a task-family env")
            base.set_task(task)  # type: ignore[attr-defined]

    def reset(self) -> np.ndarray:
        if self.vec_env is not None:
            return np.asarray(self.vec_env.reset())[0]
        assert self.env is not None
        seed, self._seed = self._seed, None  # seed the first reset only
        obs, _ = self.env.reset(seed=seed)
        return obs

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.vec_env is not None:
            obs, rewards, dones, infos = self.vec_env.step(np.asarray(action)[None])
            info = dict(infos[0])
            done = bool(dones[0])
            truncated = done and bool(info.get("TimeLimit.truncated", False))
            next_obs = info.pop("terminal_observation") if done else np.asarray(obs)[0]
            return next_obs, float(rewards[0]), done and not truncated, truncated, info
        assert self.env is not None
        next_obs, reward, terminated, truncated, info = self.env.step(action)
        return next_obs, float(reward), bool(terminated), bool(truncated), info


def rollout(
    model: AdaptiveModel,
    env: _SingleEnv,
    deterministic: bool = True,
    max_steps: int | None = None,
    trace_keys: Sequence[str] = TRACE_INFO_KEYS,
) -> tuple[dict[str, Any], dict[str, list[float]]]:
    """
    One trajectory with the model's current adaptation state; every transition goes to ``model.observe``.

    :param model: the adaptive model
    :param env: the env, already set to the task
    :param deterministic: deterministic actions
    :param max_steps: stop after this many steps (None: until the episode ends)
    :param trace_keys: per-step info entries to keep
    :return: the row values (return, cost, length, violated, extras) and the traces
    """
    obs = env.reset()
    ret, cost, length = 0.0, 0.0, 0
    extras: dict[str, Any] = {}
    traces: dict[str, list[float]] = {}
    done = False
    while not done:
        action, _ = model.predict(obs, deterministic=deterministic)
        next_obs, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated or (max_steps is not None and length + 1 >= max_steps)
        model.observe(obs, action, reward, next_obs, done)
        ret += reward
        cost += float(info.get("cost", 0.0))
        length += 1
        for key in EXTRA_INFO_KEYS:
            if key in info and info[key] is not None:
                extras[key] = float(info[key])
        for key in trace_keys:
            if key in info:
                traces.setdefault(key, []).append(float(info[key]))
        obs = next_obs
    return {"return": ret, "cost": cost, "length": length, "violated": cost > 0.0, **extras}, traces


def meta_test(
    model: Any,
    env: gym.Env | VecEnv,
    tasks: Sequence[Task],
    n_adapt: int = 5,
    n_repeats: int = 1,
    deterministic: bool = True,
    seed: int | None = None,
    max_steps: int | None = None,
    trace_keys: Sequence[str] = TRACE_INFO_KEYS,
    on_trajectory_start: Callable[[int, int, int], None] | None = None,
) -> MetaTestResult:
    """
    The meta-test protocol (module docstring) on ``tasks``.

    :param model: any object with ``reset_adaptation``, ``observe``, ``adapt`` and ``predict``
    :param env: a task-family env (gymnasium env, possibly wrapped, or a VecEnv of one env)
    :param tasks: the test tasks (e.g. ``model.test_tasks``, see :func:`get_test_tasks`)
    :param n_adapt: last trajectory index K: trajectories k = 0..K are rolled out per task
    :param n_repeats: repeats of the whole sequence per task (the context is cleared for each)
    :param deterministic: deterministic actions (ignored for models with ``stochastic_adaptation = True``,
        e.g. MAML, whose inner gradient step needs trajectories of the stochastic policy; the
        setting actually used is recorded in the result's config)
    :param seed: seed of the env's first reset (None: not seeded)
    :param max_steps: cap on trajectory length (None: the env's own horizon)
    :param trace_keys: per-step info entries kept as traces
    :param on_trajectory_start: called with (task index, repeat, k) before each trajectory's reset
        (e.g. to name a video file)
    :return: rows, summary, traces and the settings
    """
    check_adaptive(model)
    if n_adapt < 0 or n_repeats < 1:
        raise ValueError(f"meta_test: n_adapt must be >= 0 and n_repeats >= 1, got {n_adapt}, {n_repeats}")
    if len(tasks) == 0:
        raise ValueError("meta_test: no test tasks (the model has none saved; pass tasks or n_tasks)")
    # An inner policy-gradient step (MAML) learns nothing from deterministic rollouts: algorithms that
    # adapt on their own stochastic data say so with `stochastic_adaptation = True` and act stochastically.
    deterministic = deterministic and not getattr(model, "stochastic_adaptation", False)
    runner = _SingleEnv(env)
    runner.seed(seed)
    rows: list[dict[str, Any]] = []
    traces: list[dict[str, Any]] = []
    for task_index, task in enumerate(tasks):
        runner.set_task(task)
        for repeat in range(n_repeats):
            model.reset_adaptation()
            for k in range(n_adapt + 1):
                if k > 0:
                    model.adapt()  # posterior from trajectories 0..k-1
                if on_trajectory_start is not None:
                    on_trajectory_start(task_index, repeat, k)
                values, trace = rollout(model, runner, deterministic, max_steps, trace_keys)
                rows.append({"task": task_index, "repeat": repeat, "k": k, **values})
                if trace:
                    traces.append({"task": task_index, "repeat": repeat, "k": k, **trace})
    config = {
        "n_tasks": len(tasks),
        "n_adapt": n_adapt,
        "n_repeats": n_repeats,
        "deterministic": deterministic,
        "seed": seed,
        "max_steps": max_steps,
        "algorithm": type(model).__name__,
    }
    return MetaTestResult(rows=rows, summary=summarize(rows), tasks=list(tasks), traces=traces, config=config)


def get_test_tasks(
    model: Any,
    env: gym.Env | VecEnv | None = None,
    n_tasks: int | None = None,
    seed: int | None = None,
    sample: bool = False,
) -> list[Task]:
    """
    The held-out tasks of a meta-test.

    By default the model's saved ``test_tasks`` (the first ``n_tasks`` of them). With ``sample=True``
    (or a model without test tasks) ``n_tasks`` tasks are drawn from ``env.sample_tasks(n, seed)``,
    e.g. from an env built with other ranges for a shifted test distribution.

    :param model: the trained model
    :param env: the env to sample from
    :param n_tasks: number of tasks (None: all saved ones; required when sampling)
    :param seed: seed of the draw
    :param sample: draw from the env instead of using the saved list
    :return: task dicts
    """
    saved = list(getattr(model, "test_tasks", None) or [])
    if not sample and saved:
        return saved if n_tasks is None else saved[:n_tasks]
    if env is None:
        raise ValueError("get_test_tasks: the model has no saved test tasks: pass an env to sample them from")
    n = n_tasks if n_tasks is not None else (len(saved) or 10)
    if isinstance(env, VecEnv):
        return list(env.env_method("sample_tasks", n, seed, indices=[0])[0])
    base = env.unwrapped
    if not callable(getattr(base, "sample_tasks", None)):
        raise ValueError(f"{type(base).__name__} has no sample_tasks(): the meta-test needs a task-family env")
    return list(base.sample_tasks(n, seed))  # type: ignore[attr-defined]


__all__ = [
    "EXTRA_INFO_KEYS",
    "PAPER_KS",
    "ROW_COLUMNS",
    "SUMMARY_COLUMNS",
    "TRACE_INFO_KEYS",
    "AdaptiveModel",
    "MetaTestResult",
    "check_adaptive",
    "cvar",
    "format_summary_table",
    "get_test_tasks",
    "meta_test",
    "rollout",
    "summarize",
    "wilson_interval",
]
