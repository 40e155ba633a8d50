"""The meta-test protocol behind every number of the paper, for any model with the adaptation API.

For each test task and each repeat: the task is set, the model forgets everything task-specific
(``reset_adaptation()``), then trajectories ``k = 0..n_adapt`` are rolled out in sequence.
Trajectory ``k = 0`` acts with the prior (no ``adapt()`` call before it); trajectory ``k`` acts
after ``adapt()`` on every transition of trajectories ``0..k-1`` (each one passed to
``observe()`` as it happens). Actions are deterministic by default. The adaptation API is
:class:`sb3_pearl.common.adaptation.AdaptiveModel`.

One row per (task, repeat, k): ``return``, ``cost`` (sum of ``info["cost"]``), ``length``,
``violated`` (any cost) and the family extras: the ``info`` entries the env's family declares in
``trajectory_info_keys`` (e.g. ``b_min`` and ``merged`` for the merge family; the last value seen
in the trajectory). Per-step traces of the family's ``step_trace_keys`` (the merge family's
``ego_speed``) are kept for the plots. Both are class attributes of
:class:`sb3_pearl.envs.task_protocol.MetaTaskEnv`; the keys used are recorded in the result's config.

The summary per k is :func:`sb3_pearl.evaluation.statistics.summarize`; the paper's "0/1/3/5 traj."
columns are :data:`PAPER_KS`.
"""

from __future__ import annotations

import csv
import inspect
import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from sb3_pearl.common.adaptation import AdaptiveModel, check_adaptive
from sb3_pearl.common.atomic import atomic_write
from sb3_pearl.common.seeding import derived_seed, get_global_rng_state, seed_global_rngs, set_global_rng_state
from sb3_pearl.common.tasks import set_vec_env_task
from sb3_pearl.envs.task_observation import TaskObservation
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.evaluation.progress import ProgressBar
from sb3_pearl.evaluation.statistics import format_summary_table, summarize

PAPER_KS = (0, 1, 3, 5)
ROW_COLUMNS = ("task", "repeat", "k", "return", "cost", "length", "violated")
# Class attributes of a task family (MetaTaskEnv) naming its per-trajectory extras and per-step traces.
TRAJECTORY_INFO_KEYS_ATTR = "trajectory_info_keys"
STEP_TRACE_KEYS_ATTR = "step_trace_keys"


# ----------------------------------------------------------------------------------------------
# Result container and writers
# ----------------------------------------------------------------------------------------------
def json_value(value: Any) -> Any:
    """A plain JSON value (for result files): nan / inf become None, numpy scalars Python numbers, tuples lists."""
    if isinstance(value, (np.floating, float)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, dict):
        return {str(k): json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_value(v) for v in value]
    return value


def _csv_value(value: Any) -> Any:
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (float, np.floating)) and math.isnan(value):
        return ""
    return value


def read_json(path: str | os.PathLike[str]) -> Any:
    """
    A JSON file of the project (``meta_test.json``, ``result.json``); a truncated or edited one is an error that names it.

    :param path: the file
    :return: its content
    """
    with open(path) as file:
        try:
            return json.load(file)
        except json.JSONDecodeError as error:
            raise ValueError(
                f"{path} is not valid JSON ({error}): truncated or edited; rerun what writes it (train.py's or the "
                "harness's meta-test)"
            ) from None


@dataclass
class MetaTestResult:
    """
    Result of :func:`meta_test`.

    :param rows: one dict per (task, repeat, k) with :data:`ROW_COLUMNS` and the family extras found
    :param summary: one dict per k (:func:`sb3_pearl.evaluation.statistics.summarize`)
    :param tasks: the test tasks, in row order of ``task``
    :param traces: per-step info traces (``{"task", "repeat", "k", <key>: [...]}``)
    :param config: the protocol settings (n_adapt, n_repeats, deterministic, the family's info keys, ...)
    """

    rows: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    tasks: list[Task] = field(default_factory=list)
    traces: list[dict[str, Any]] = field(default_factory=list)
    config: dict[str, Any] = field(default_factory=dict)

    @property
    def info_keys(self) -> list[str]:
        """
        The family's per-trajectory extras: ``config["trajectory_info_keys"]`` (as recorded by :func:`meta_test`),
        else the row entries beyond :data:`ROW_COLUMNS` in order of appearance (results written before it was recorded).
        """
        recorded = self.config.get(TRAJECTORY_INFO_KEYS_ATTR)
        if recorded is not None:
            return list(recorded)
        found: dict[str, None] = {}
        for row in self.rows:
            found.update((key, None) for key in row if key not in ROW_COLUMNS)
        return list(found)

    @property
    def trace_keys(self) -> list[str]:
        """The per-step traces held: ``config["step_trace_keys"]``, else the keys found in :attr:`traces`."""
        recorded = self.config.get(STEP_TRACE_KEYS_ATTR)
        if recorded is not None:
            return list(recorded)
        found: dict[str, None] = {}
        for trace in self.traces:
            found.update((key, None) for key in trace if key not in ("task", "repeat", "k"))
        return list(found)

    @property
    def columns(self) -> list[str]:
        """CSV columns: :data:`ROW_COLUMNS` then the family extras present in the rows, in :attr:`info_keys` order."""
        return [*ROW_COLUMNS, *(key for key in self.info_keys if any(key in row for row in self.rows))]

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
        """Write the rows as CSV (columns :attr:`columns`; missing extras are empty), atomically."""
        columns = self.columns
        with atomic_write(path, "w", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=columns, extrasaction="ignore", restval="")
            writer.writeheader()
            for row in self.rows:
                writer.writerow({key: _csv_value(row.get(key, "")) for key in columns})

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: config, summary, paper table, tasks, rows and traces."""
        return json_value(
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
        """Write :meth:`to_dict` as JSON, atomically."""
        with atomic_write(path, "w") as file:
            json.dump(self.to_dict(), file, indent=1)

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> MetaTestResult:
        """Read a result written by :meth:`to_json` (None back to nan in numbers)."""
        return cls.from_dict(read_json(path))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MetaTestResult:
        """A result from :meth:`to_dict`'s form (``meta_test.json``, or a harness ``result.json``'s ``meta_test``)."""

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


# ----------------------------------------------------------------------------------------------
# Rollouts
# ----------------------------------------------------------------------------------------------
class SingleEnvRunner:
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

    def family_keys(self, name: str) -> tuple[str, ...]:
        """
        A tuple class attribute of the task family, e.g. ``trajectory_info_keys``; () when the env has none.

        :param name: the attribute
        :return: its value
        """
        if self.vec_env is not None:
            if not self.vec_env.has_attr(name):
                return ()
            return tuple(self.vec_env.get_attr(name, indices=[0])[0])
        assert self.env is not None
        return tuple(getattr(self.env.unwrapped, name, ()))

    def seed(self, seed: int | None) -> None:
        self._seed = seed
        if self.vec_env is not None and seed is not None:
            self.vec_env.seed(seed)

    def set_task(self, task: Task) -> None:
        if self.vec_env is not None:
            set_vec_env_task(self.vec_env, task)  # a bad task: one line, the workers of a SubprocVecEnv alive
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


def observes_truncation(model: Any) -> bool:
    """
    Whether ``model.observe`` takes the optional ``truncated`` keyword (Fine-Tune's and the oracle's do): the meta-test
    then tells it whether an ending step was a cut (time limit, step cap) or a terminal state. The adaptation API's
    five arguments stay the contract; a model without the keyword is called with them.

    :param model: the adaptive model
    :return: whether to pass ``truncated=``
    """
    try:
        parameters = inspect.signature(model.observe).parameters
    except (TypeError, ValueError):  # a builtin or C callable: the contract's five arguments
        return False
    return "truncated" in parameters


def rollout(
    model: AdaptiveModel,
    env: SingleEnvRunner,
    deterministic: bool = True,
    max_steps: int | None = None,
    trace_keys: Sequence[str] | None = None,
    info_keys: Sequence[str] | None = None,
) -> tuple[dict[str, Any], dict[str, list[float]]]:
    """
    One trajectory with the model's current adaptation state; every transition goes to ``model.observe``.

    :param model: the adaptive model
    :param env: the env, already set to the task
    :param deterministic: deterministic actions
    :param max_steps: stop after this many steps (None: until the episode ends)
    :param trace_keys: per-step info entries to keep (None: the family's ``step_trace_keys``)
    :param info_keys: info entries recorded per trajectory, last value seen (None: the family's ``trajectory_info_keys``)
    :return: the row values (return, cost, length, violated, extras) and the traces
    """
    if trace_keys is None:
        trace_keys = env.family_keys(STEP_TRACE_KEYS_ATTR)
    if info_keys is None:
        info_keys = env.family_keys(TRAJECTORY_INFO_KEYS_ATTR)
    tells_truncation = observes_truncation(model)
    obs = env.reset()
    ret, cost, length = 0.0, 0.0, 0
    extras: dict[str, Any] = {}
    traces: dict[str, list[float]] = {}
    done = False
    while not done:
        action, _ = model.predict(obs, deterministic=deterministic)
        next_obs, reward, terminated, truncated, info = env.step(action)
        capped = max_steps is not None and length + 1 >= max_steps
        done = terminated or truncated or capped
        if tells_truncation:  # a cut (time limit, step cap) is not a terminal state, even at the time limit's step
            observe: Any = model.observe  # the optional keyword, beyond the protocol's five arguments
            observe(obs, action, reward, next_obs, done, truncated=(truncated or capped) and not terminated)
        else:
            model.observe(obs, action, reward, next_obs, done)
        ret += reward
        cost += float(info.get("cost", 0.0))
        length += 1
        for key in info_keys:
            if key in info and info[key] is not None:
                extras[key] = float(info[key])
        for key in trace_keys:
            if key in info:
                traces.setdefault(key, []).append(float(info[key]))
        obs = next_obs
    return {"return": ret, "cost": cost, "length": length, "violated": cost > 0.0, **extras}, traces


def _told_task_standardisation(env: gym.Env | VecEnv) -> dict[str, Any]:
    """The standardisation of the task vector a task-aware model was told in ``env`` (the oracle's), to record."""
    if isinstance(env, VecEnv):  # asked first: a missing attribute would end a SubprocVecEnv's worker
        told = env.get_attr("standardisation", indices=[0])[0] if env.env_is_wrapped(TaskObservation, indices=[0])[0] else None
    else:
        told = env.get_wrapper_attr("standardisation") if is_wrapped(env, TaskObservation) else None
    return {} if told is None else {"task_standardisation": told}


def meta_test(
    model: Any,
    env: gym.Env | VecEnv,
    tasks: Sequence[Task],
    n_adapt: int = 5,
    n_repeats: int = 1,
    deterministic: bool = True,
    seed: int | None = None,
    max_steps: int | None = None,
    trace_keys: Sequence[str] | None = None,
    on_trajectory_start: Callable[[int, int, int], None] | None = None,
    crn_seed: int | None = None,
    progress_bar: bool = False,
    description: str = "Meta-test",
    n_prior_trajectories: int = 1,
) -> MetaTestResult:
    """
    The meta-test protocol (module docstring) on ``tasks``.

    :param model: any object with ``reset_adaptation``, ``observe``, ``adapt`` and ``predict``
        (:class:`~sb3_pearl.common.adaptation.AdaptiveModel`)
    :param env: a task-family env (gymnasium env, possibly wrapped, or a VecEnv of one env); a model with a
        ``prepare_env(env)`` method (the oracle) acts in the env that method returns
    :param tasks: the test tasks (a trained model's: :func:`sb3_pearl.evaluation.held_out.model_test_tasks`)
    :param n_adapt: last trajectory index K: trajectories k = 0..K are rolled out per task
    :param n_repeats: repeats of the whole sequence per task (the context is cleared for each)
    :param deterministic: deterministic actions (ignored for models with ``stochastic_adaptation = True``,
        e.g. MAML, whose inner gradient step needs trajectories of the stochastic policy; the
        setting actually used is recorded in the result's config)
    :param seed: seed of the env's first reset (None: not seeded)
    :param max_steps: cap on trajectory length (None: the env's own horizon)
    :param trace_keys: per-step info entries kept as traces (None: the family's ``step_trace_keys``)
    :param on_trajectory_start: called with (task index, repeat, k) before each trajectory's reset
        (e.g. to name a video file)
    :param crn_seed: common random numbers across models: before each (task, repeat) sequence numpy's
        and torch's global RNGs are seeded from (crn_seed, task index, repeat), so the prior z of
        ``reset_adaptation()`` and the posterior samples are drawn from the same numbers for every
        model of the same latent size; every trajectory's reset is seeded from (crn_seed, task index,
        repeat, k) (instead of ``seed``). The global RNG states are restored afterwards. None: off
    :param progress_bar: show a progress bar over the trajectories, with the ETA
        (:class:`~sb3_pearl.evaluation.progress.ProgressBar`)
    :param description: the bar's text (e.g. what Ctrl-C does)
    :param n_prior_trajectories: trajectories rolled out before the first ``adapt()`` (1, the default: only k = 0
        acts with the prior; the PEARL reference's ``num_exp_traj_eval``: its first trajectories each act with a fresh
        z from the prior (``resample_prior()`` where the model has it), the posterior is inferred from all of them
        before the next one)
    :return: rows, summary, traces and the settings
    """
    check_adaptive(model)
    if n_prior_trajectories < 1:
        raise ValueError(f"meta_test: n_prior_trajectories must be >= 1, got {n_prior_trajectories}")
    if n_adapt < 0 or n_repeats < 1:
        raise ValueError(f"meta_test: n_adapt must be >= 0 and n_repeats >= 1, got {n_adapt}, {n_repeats}")
    if len(tasks) == 0:
        raise ValueError("meta_test: no test tasks (the model has none saved; pass tasks or n_tasks)")
    # An inner policy-gradient step (MAML) learns nothing from deterministic rollouts: algorithms that
    # adapt on their own stochastic data say so with `stochastic_adaptation = True` and act stochastically.
    deterministic = deterministic and not getattr(model, "stochastic_adaptation", False)
    prepare_env = getattr(model, "prepare_env", None)
    if callable(prepare_env):  # the env as the model acts in it (the oracle: the task in the observation)
        env = prepare_env(env)
    runner = SingleEnvRunner(env)
    info_keys = runner.family_keys(TRAJECTORY_INFO_KEYS_ATTR)
    trace_keys = runner.family_keys(STEP_TRACE_KEYS_ATTR) if trace_keys is None else tuple(trace_keys)
    runner.seed(seed)
    rows: list[dict[str, Any]] = []
    traces: list[dict[str, Any]] = []
    saved_rng = get_global_rng_state() if crn_seed is not None else None
    bar = ProgressBar(description, len(tasks) * n_repeats * (n_adapt + 1), "trajectories") if progress_bar else None
    try:
        for task_index, task in enumerate(tasks):
            runner.set_task(task)
            for repeat in range(n_repeats):
                if crn_seed is not None:
                    seed_global_rngs(crn_seed, task_index, repeat)
                model.reset_adaptation()
                for k in range(n_adapt + 1):
                    if k >= n_prior_trajectories:
                        model.adapt()  # posterior from trajectories 0..k-1
                    elif k > 0 and hasattr(model, "resample_prior"):
                        model.resample_prior()  # another exploration trajectory, with a fresh prior z (PEARL)
                    if on_trajectory_start is not None:
                        on_trajectory_start(task_index, repeat, k)
                    if crn_seed is not None:
                        runner.seed(derived_seed(crn_seed, task_index, repeat, k))
                    values, trace = rollout(model, runner, deterministic, max_steps, trace_keys, info_keys)
                    rows.append({"task": task_index, "repeat": repeat, "k": k, **values})
                    if trace:
                        traces.append({"task": task_index, "repeat": repeat, "k": k, **trace})
                    if bar is not None:
                        bar.advance()
    finally:
        if bar is not None:
            bar.close()
        if saved_rng is not None:
            set_global_rng_state(saved_rng)
    config = {
        "n_tasks": len(tasks),
        "n_adapt": n_adapt,
        "n_repeats": n_repeats,
        "deterministic": deterministic,
        "seed": seed,
        "max_steps": max_steps,
        "algorithm": type(model).__name__,
        TRAJECTORY_INFO_KEYS_ATTR: list(info_keys),
        STEP_TRACE_KEYS_ATTR: list(trace_keys),
        "crn_seed": crn_seed,
        **({"n_prior_trajectories": n_prior_trajectories} if n_prior_trajectories != 1 else {}),
        **_told_task_standardisation(env),
    }
    summary = summarize(rows, extra_keys=info_keys)
    return MetaTestResult(rows=rows, summary=summary, tasks=list(tasks), traces=traces, config=config)


__all__ = [
    "PAPER_KS",
    "ROW_COLUMNS",
    "STEP_TRACE_KEYS_ATTR",
    "TRAJECTORY_INFO_KEYS_ATTR",
    "MetaTestResult",
    "SingleEnvRunner",
    "meta_test",
    "read_json",
    "rollout",
]
