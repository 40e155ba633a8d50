"""Learning curves on the held-out test tasks (``curve.csv`` in the run folder), when the budget asks for one.

Every ``every`` env steps of training (at the next iteration start, where the reference evaluates: after an
iteration's gradient steps) and once at the end, :class:`LearningCurve` runs the PEARL reference's evaluation
(katerakelly/oyster, ``rlkit/core/rl_algorithm.py`` ``_do_eval`` / ``collect_paths``; docs/reproduce.md, "Learning
curves") on the first ``n_tasks`` test tasks of the run's meta-test: per task, the context is cleared and
``n_adapt + 1`` trajectories are rolled out with deterministic actions, the first ``n_prior_trajectories`` with z
from the prior, each later one with the posterior of every transition so far; the curve's ``reference_return`` is
the mean over tasks of the *last* trajectory's return (the reference's ``AverageReturn_all_test_tasks``). The same
rollouts give the k = 0 return and violation rate (the prior policy's); the harness's competence check on training
tasks (the family's criteria, e.g. Walker2D-vel's velocity error and falls) is run at every point too, so the curve
says at which env step the model becomes competent (``competent``, ``criterion_<i>``). Common random numbers (the
eval seed) make consecutive points differ by the training only.

The evaluation restores the global RNG streams (``meta_test(crn_seed=...)``) and runs on its own env, so a run with a
curve trains the same weights, bit for bit, as one without (tests/test_reproduce_resume.py). Rows are written
atomically after each point; a resumed run keeps the rows up to its checkpoint and recomputes the rest identically.
"""

from __future__ import annotations

import csv
import io
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from pearl_paper.experiments.spec import Criterion
from pearl_paper.reproduce.competence import evaluate_competence
from sb3_pearl.common.atomic import atomic_write
from sb3_pearl.common.callbacks import StopOnSignalCallback
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.evaluation.held_out import run_meta_test

CURVE_FILE = "curve.csv"
COLUMNS = (
    "env_steps",
    "reference_return",
    "reference_return_std",
    "k0_return",
    "k0_violation",
    "last_violation",
    "n_tasks",
    "competent",
    "criterion_0",
    "criterion_1",
    "wall_s",
)
MAX_CRITERIA = 2  # criterion_<i>: the value of the family's i-th competence criterion (nan: none)


def read_curve(path: str | Path) -> list[dict[str, float]]:
    """The rows of a ``curve.csv`` (numbers), [] when there is none."""
    path = Path(path)
    if not path.is_file():
        return []
    with open(path, newline="") as file:
        return [{key: float(value) if value != "" else math.nan for key, value in row.items()} for row in csv.DictReader(file)]


def write_curve(path: str | Path, rows: list[dict[str, float]]) -> None:
    """Write the rows atomically."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS)
    writer.writeheader()
    writer.writerows({key: row.get(key, math.nan) for key in COLUMNS} for row in rows)
    with atomic_write(path, "w") as file:
        file.write(buffer.getvalue())


def evaluate_point(
    model: Any,
    env: gym.Env,
    tasks: list[Task],
    settings: dict[str, Any],
    eval_seed: int,
    competence: tuple[Sequence[Criterion], dict[str, Any], tuple[str, ...]] | None = None,
) -> dict[str, float]:
    """
    One point of the curve (module docstring).

    :param model: the model being trained
    :param env: an evaluation env of the family
    :param tasks: the test tasks
    :param settings: the budget's ``curve`` entry
    :param eval_seed: the experiment's eval seed (common random numbers)
    :param competence: the family's criteria, the competence meta-test's settings and trace keys: the competence
        check on the model's first training tasks (the harness's, docs/reproduce.md) joins the row; None: nan
    :return: the row without ``env_steps``
    """
    start = time.time()
    training = model.policy.training if hasattr(model, "policy") else False
    protocol = {"n_adapt": settings["n_adapt"], "n_repeats": 1, "deterministic": True}
    result = run_meta_test(model, env, tasks, protocol, eval_seed, n_prior_trajectories=settings["n_prior_trajectories"])
    last = settings["n_adapt"]
    finals = np.array([row["return"] for row in result.rows if row["k"] == last])
    k0 = result.summary[0]
    check: dict[str, float] = {"competent": math.nan, **{f"criterion_{i}": math.nan for i in range(MAX_CRITERIA)}}
    if competence is not None and getattr(model, "train_tasks", None):
        criteria, comp_settings, trace_keys = competence
        train_tasks = list(model.train_tasks)[: comp_settings["n_tasks"]]
        on_train = run_meta_test(model, env, train_tasks, comp_settings, eval_seed, trace_keys=trace_keys)
        verdict = evaluate_competence(on_train, criteria)
        check["competent"] = float(verdict["passed"])
        for i, entry in enumerate(verdict["criteria"][:MAX_CRITERIA]):
            check[f"criterion_{i}"] = float(entry["value"])
    if hasattr(model, "policy"):
        model.policy.set_training_mode(training)
    return {
        "reference_return": float(finals.mean()),
        "reference_return_std": float(finals.std()),
        "k0_return": float(k0["return_mean"]),
        "k0_violation": float(k0["violation_rate"]),
        "last_violation": float(result.summary[-1]["violation_rate"]),
        "n_tasks": float(len(tasks)),
        **check,
        "wall_s": time.time() - start,
    }


class LearningCurve(BaseCallback):
    """
    Append a point to ``curve.csv`` every ``settings["every"]`` env steps (at the next iteration start) and at the end.

    :param path: the run's ``curve.csv``
    :param env: an evaluation env of the family
    :param tasks: the held-out test tasks (the first ``settings["n_tasks"]`` are used)
    :param settings: the budget's ``curve`` entry
    :param eval_seed: the experiment's eval seed
    :param resume_at: the env steps of the checkpoint a resumed run starts from (its later rows are dropped)
    :param competence: the family's competence check, evaluated at every point too (:func:`evaluate_point`)
    :param stop: the run's stop callback: training stopped by it ends without the end point (the resumed run's grid
        goes on from the checkpoint; a point there would be off the grid, or on it for a partly trained iteration)
    """

    def __init__(
        self,
        path: Path,
        env: gym.Env,
        tasks: list[Task],
        settings: dict[str, Any],
        eval_seed: int,
        resume_at: int = 0,
        competence: tuple[Sequence[Criterion], dict[str, Any], tuple[str, ...]] | None = None,
        stop: StopOnSignalCallback | None = None,
    ) -> None:
        super().__init__()
        self.path = path
        self.stop = stop
        self.env = env
        self.tasks = list(tasks)[: settings["n_tasks"]]
        self.settings = settings
        self.eval_seed = eval_seed
        self.competence = competence
        self.rows = [row for row in read_curve(path) if row["env_steps"] <= resume_at]
        last = int(self.rows[-1]["env_steps"]) if self.rows else 0
        self.next_at = (last // settings["every"] + 1) * settings["every"]  # the uninterrupted run's grid

    def _point(self) -> None:
        steps = int(self.model.num_timesteps)
        if self.rows and int(self.rows[-1]["env_steps"]) >= steps:
            return
        point = evaluate_point(self.model, self.env, self.tasks, self.settings, self.eval_seed, self.competence)
        self.rows.append({"env_steps": float(steps), **point})
        write_curve(self.path, self.rows)

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        steps = int(self.model.num_timesteps)
        if steps >= self.next_at:
            self._point()
            self.next_at = (steps // self.settings["every"] + 1) * self.settings["every"]

    def _on_training_end(self) -> None:
        if self.stop is None or not self.stop.stopped:
            self._point()


def curve_value(row: dict[str, Any], key: str) -> float:
    """A curve row's value as a float: nan where the row has none (result.json stores nan as null)."""
    value = row.get(key)
    return math.nan if value is None else float(value)


def curve_table(experiment: Any, group: Any) -> list[str]:
    """
    Each run's learning curve (result.json ``curve``) in one row, for ``reproduce report``: its last point, and where
    it checks competence, the first env step at which the model was competent (every criterion passed) and the best
    value of each criterion. The k = 0 violation rate is n/a on a family that cannot violate (HalfCheetah-Vel).

    :param experiment: the experiment (variant order and labels)
    :param group: variant -> seed -> result
    :return: markdown table lines, then one line per published point of the family's curve
    """
    lines = [
        "| variant | seed | env steps | return (reference protocol) | k = 0 return | k = 0 violation % | first competent at "
        "| criteria at the end (best) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for variant in [v for v in experiment.variants if v.name in group]:
        for seed, result in sorted(group[variant.name].items()):
            rows = result.get("curve")
            if not rows:
                continue
            last = rows[-1]
            family = experiment.family(result["family"])
            violation = f"{100 * curve_value(last, 'k0_violation'):.1f}" if family.has_violations else "n/a"
            checked = [row for row in rows if math.isfinite(curve_value(row, "competent"))]
            first = next((int(row["env_steps"]) for row in checked if curve_value(row, "competent") == 1.0), None)
            competent = "not checked" if not checked else (f"{first}" if first is not None else "not competent")
            criteria = []
            for index, criterion in enumerate(family.competence):
                values = [curve_value(row, f"criterion_{index}") for row in checked]
                values = [value for value in values if math.isfinite(value)]
                if values:
                    best = min(values) if criterion.better == "lower" else max(values)
                    bar = "<=" if criterion.better == "lower" else ">="
                    criteria.append(f"{values[-1]:.3g} ({best:.3g}; bar {bar} {criterion.threshold:g})")
            lines.append(
                f"| {variant.label} | {seed} | {int(last['env_steps'])} | {curve_value(last, 'reference_return'):.1f} | "
                f"{curve_value(last, 'k0_return'):.1f} | {violation} | {competent} | "
                f"{'; '.join(criteria) or 'n/a'} |"
            )
    families = {result["family"] for runs in group.values() for result in runs.values()}
    published = [point for family in sorted(families) for point in experiment.family(family).published_curve]
    if published:
        lines.append("")
    lines += [f"Published: {p.value:g} at {p.env_steps:,} env steps, {p.source}; the star in the figure." for p in published]
    return lines
