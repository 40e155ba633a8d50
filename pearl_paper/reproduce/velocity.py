"""``reproduce velocity``: the velocity error of committed models on held-out tasks, judged against the oracle.

The measure and the rules are :mod:`pearl_paper.experiments.oracle`'s: each finished run of a velocity family is
meta-tested again, without retraining, on the 20 held-out tasks of its own meta-test (the experiment's eval seed),
2 repeats per task, k = 0..5, with the per-step velocity error (``-info["reward_forward"]``) kept per trajectory. The
record, ``velocity_held_out.json`` beside the run's ``result.json``, holds one row per trajectory: task index, the
task's target velocity (the family's task features: Walker and the cheetah a speed, Ant a planar vector), k, repeat,
the mean error over its steps, its length and whether it violated.

:func:`family_verdicts` reads the records of the oracle and of the meta-learners on each family and applies
:data:`~pearl_paper.experiments.oracle.COMPETENCE_RULES`; :func:`constant_references` gives the two task-independent
references (standing still and the best constant velocity) from the held-out targets alone.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from pearl_paper.experiments.oracle import (
    CALIBRATIONS,
    COMPETENCE_RULES,
    JUDGED_RUNS,
    ORACLE,
    ORACLE_VARIANT,
    SPEED_BINS,
    CompetenceRules,
)
from pearl_paper.experiments.spec import Family
from pearl_paper.reproduce.layout import RESULT_FILE, read_run_result, write_json_atomic
from pearl_paper.reproduce.merge_competence import merge_competence_section
from sb3_pearl.envs.task_observation import task_features
from sb3_pearl.evaluation.held_out import model_test_tasks, run_meta_test
from sb3_pearl.evaluation.meta_test import json_value, read_json

VELOCITY_FILE = "velocity_held_out.json"
ERROR_KEY = "velocity_error"  # the velocity families' per-trajectory mean of |v - v*| (their trajectory_info_keys)
N_HELD_OUT = 20  # the tasks of a run's own meta-test where its result.json does not say (the cpu preset's)


def geometric_median(points: np.ndarray, iterations: int = 500, tolerance: float = 1e-10) -> np.ndarray:
    """
    The point minimising the mean Euclidean distance to ``points`` (Weiszfeld's iteration; 1-D: the median).

    :param points: shape (n, d)
    :param iterations: iteration cap
    :param tolerance: stop when the step is below this
    :return: shape (d,)
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or len(points) == 0:
        raise ValueError(f"geometric_median: expected points of shape (n, d) with n >= 1, got {points.shape}")
    if points.shape[1] == 1:
        return np.median(points, axis=0)
    estimate = points.mean(axis=0)
    for _ in range(iterations):
        distances = np.linalg.norm(points - estimate, axis=1)
        on_point = distances < 1e-12
        if np.any(on_point):  # Weiszfeld's weights are undefined on a data point: is that point the minimum?
            pull = ((points[~on_point] - estimate) / distances[~on_point, None]).sum(axis=0)
            if np.linalg.norm(pull) <= np.count_nonzero(on_point):
                return estimate  # the pull of the other points does not exceed the point's own weight: optimal
            estimate = estimate + 1e-6 * pull / np.linalg.norm(pull)  # not optimal: step off it, downhill
            continue
        weights = 1.0 / distances
        new = (points * weights[:, None]).sum(axis=0) / weights.sum()
        if np.linalg.norm(new - estimate) < tolerance:
            return new
        estimate = new
    return estimate


def constant_references(targets: np.ndarray) -> dict[str, Any]:
    """
    The two task-independent references of the rules on held-out targets.

    :param targets: target velocities, shape (n_tasks, d) (d = 1: a forward speed; 2: a planar vector)
    :return: ``standing`` (mean |v*|), ``best_constant`` (min over c of the mean |c - v*|) and the constant itself
    """
    targets = np.asarray(targets, dtype=np.float64).reshape(len(targets), -1)
    constant = geometric_median(targets)
    return {
        "standing": float(np.linalg.norm(targets, axis=1).mean()),
        "best_constant": float(np.linalg.norm(targets - constant, axis=1).mean()),
        "constant": [float(value) for value in constant],
    }


def measure_model(
    model: Any, env: gym.Env, eval_seed: int, rules: CompetenceRules = COMPETENCE_RULES, n_tasks: int = N_HELD_OUT
) -> dict[str, Any]:
    """
    The held-out velocity measure of one model (module docstring).

    :param model: a trained model with the adaptation API
    :param env: the family's evaluation env
    :param eval_seed: the experiment's eval seed
    :param rules: the measure's repeats and last k
    :param n_tasks: the held-out tasks of the run's own meta-test
    :return: the record (``rows``, ``targets``, ``settings``, ``wall_time_s``)
    """
    start = time.time()
    tasks = model_test_tasks(model, env, n_tasks, eval_seed)
    settings = {"n_adapt": rules.n_adapt, "n_repeats": rules.repeats, "deterministic": True}
    result = run_meta_test(model, env, tasks, settings, eval_seed, trace_keys=())
    base = env.unwrapped
    targets = [task_features(base, task).tolist() for task in tasks]
    rows = [
        {
            "task": int(row["task"]),
            "repeat": int(row["repeat"]),
            "k": int(row["k"]),
            "error": float(row.get(ERROR_KEY, math.nan)),  # the family's per-trajectory mean of |v - v*|
            "length": int(row["length"]),
            "violated": bool(row["violated"]),
            "return": float(row["return"]),
        }
        for row in result.rows
    ]
    return json_value(
        {
            "settings": {**settings, "n_tasks": len(tasks)},
            "eval_seed": eval_seed,
            "tasks": tasks,
            "targets": targets,
            "rows": rows,
            "wall_time_s": time.time() - start,
        }
    )


def measure_run(folder: Path, force: bool = False) -> Path | None:
    """
    Write ``velocity_held_out.json`` for the finished run in ``folder`` unless it exists (``force``: again).

    :param folder: the run folder
    :param force: measure again when the record exists
    :return: the record written, or None
    """
    from pearl_paper.reproduce.remeasure import measure_committed_model

    out = folder / VELOCITY_FILE
    if not (folder / RESULT_FILE).is_file() or (out.is_file() and out.stat().st_size > 0 and not force):
        return None
    result = read_run_result(folder / RESULT_FILE)
    n_tasks = int(((result.get("meta_test") or {}).get("config") or {}).get("n_tasks") or N_HELD_OUT)
    record = measure_committed_model(
        folder, result, lambda model, env: measure_model(model, env, int(result["eval_seed"]), n_tasks=n_tasks)
    )
    write_json_atomic(out, record)
    return out


@dataclass
class RunVelocity:
    """One run's held-out velocity error: adapted (k >= 1), prior (k = 0), per target-speed bin (k >= 1)."""

    seed: int
    adapted: float
    prior: float
    by_bin: dict[str, float]
    adapted_violation: float


def summarize_record(record: Mapping[str, Any], bins: Sequence[float]) -> RunVelocity:
    """The numbers of one record (:class:`RunVelocity`)."""
    speeds = [float(np.linalg.norm(target)) for target in record["targets"]]
    adapted = [row for row in record["rows"] if row["k"] >= 1 and math.isfinite(row["error"])]
    prior = [row for row in record["rows"] if row["k"] == 0 and math.isfinite(row["error"])]
    by_bin: dict[str, float] = {}
    for low, high in zip(bins[:-1], bins[1:]):
        errors = [row["error"] for row in adapted if low <= speeds[row["task"]] < high]
        label = f"[{low:g}, {high:g})" if math.isfinite(high) else f">= {low:g}"
        by_bin[label] = float(np.mean(errors)) if errors else math.nan
    return RunVelocity(
        seed=int(record["seed"]),
        adapted=float(np.mean([row["error"] for row in adapted])) if adapted else math.nan,
        prior=float(np.mean([row["error"] for row in prior])) if prior else math.nan,
        by_bin=by_bin,
        adapted_violation=float(np.mean([row["violated"] for row in record["rows"] if row["k"] >= 1])),
    )


@dataclass
class FamilyCompetence:
    """The competence verdicts of one family: the oracle's, and each meta-learner's against it."""

    family: str
    references: dict[str, Any]
    runs: dict[str, list[RunVelocity]] = field(default_factory=dict)
    learnable: str = "pending"
    competent: dict[str, str] = field(default_factory=dict)

    def mean(self, label: str, attribute: str = "adapted") -> float:
        values = [getattr(run, attribute) for run in self.runs.get(label, [])]
        return float(np.mean(values)) if values else math.nan


def family_verdicts(
    family: str, records: Mapping[str, Sequence[Mapping[str, Any]]], rules: CompetenceRules = COMPETENCE_RULES
) -> FamilyCompetence:
    """
    Apply the competence rules to one family.

    :param family: the family name (its speed bins: :data:`~pearl_paper.experiments.oracle.SPEED_BINS`)
    :param records: label -> the velocity records of its seeds; the label ``"oracle"`` is the oracle
    :param rules: the rules
    :return: the verdicts with every number they rest on
    """
    bins = SPEED_BINS.get(family, (0.0, math.inf))
    first = next((r for rs in records.values() for r in rs), None)
    references = constant_references(np.asarray(first["targets"])) if first is not None else {}
    decision = FamilyCompetence(family, references)
    for label, label_records in records.items():
        targets = [record["targets"] for record in label_records]
        if any(t != targets[0] for t in targets) or (first is not None and targets and targets[0] != first["targets"]):
            raise ValueError(f"{family}: the velocity records of {label} were measured on other held-out tasks")
        decision.runs[label] = [summarize_record(record, bins) for record in label_records]
    constant = references.get("best_constant", math.nan)
    oracle = decision.mean("oracle")
    if "oracle" in decision.runs and decision.runs["oracle"]:
        decision.learnable = "learnable" if oracle <= rules.oracle_fraction_of_constant * constant else "not learnable"
    for label in decision.runs:
        if label == "oracle":
            continue
        error = decision.mean(label)
        if math.isnan(oracle):
            decision.competent[label] = "pending (no oracle run)"
        else:
            ok = error <= rules.oracle_ratio * oracle and error <= rules.constant_fraction * constant
            decision.competent[label] = "competent" if ok else "not competent"
    return decision


def read_records(results_dir: str | os.PathLike[str], experiment: str, family: str, variant: str) -> list[dict[str, Any]]:
    """
    The velocity records of one (experiment, family, variant), in seed order (runs without one are left out).

    :param results_dir: root of the results layout
    :param experiment: experiment name
    :param family: family name
    :param variant: variant name
    :return: the records
    """
    folder = Path(results_dir) / experiment / family / variant
    paths = [path for path in folder.glob(f"seed*/{VELOCITY_FILE}") if path.parent.name[4:].isdigit()]
    return [read_json(path) for path in sorted(paths, key=lambda path: int(path.parent.name[4:]))]


FamilyRecords = list[tuple[Family, dict[str, list[dict[str, Any]]]]]
"""What :func:`oracle_family_records` returns: (family, label -> velocity records) per oracle family with a record."""


def oracle_family_records(results_dir: str | os.PathLike[str]) -> FamilyRecords:
    """
    The velocity records of each oracle family with an oracle record: ``"oracle"``'s, then those of the runs
    :data:`~pearl_paper.experiments.oracle.JUDGED_RUNS` names (labels without a record left out).

    :param results_dir: root of the results layout
    :return: (family, label -> records), in the order of the oracle experiment's families
    """
    found = []
    for family in ORACLE.families:
        oracle = read_records(results_dir, ORACLE.name, family.name, ORACLE.variants[0].name)
        if not oracle:
            continue
        records = {"oracle": oracle}
        for label, experiment, variant in JUDGED_RUNS[family.name]:
            judged = read_records(results_dir, experiment, family.name, variant)
            if judged:
                records[label] = judged
        found.append((family, records))
    return found


def per_task_errors(records: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """
    Each held-out task's adapted velocity error, averaged over the records (seeds) and repeats: shape (n_tasks,).

    :param records: velocity records measured on the same held-out tasks
    """
    n_tasks = len(records[0]["targets"])
    sums, counts = np.zeros(n_tasks), np.zeros(n_tasks)
    for record in records:
        for row in record["rows"]:
            if row["k"] >= 1 and math.isfinite(row["error"]):
                sums[row["task"]] += row["error"]
                counts[row["task"]] += 1
    return np.divide(sums, counts, out=np.full(n_tasks, math.nan), where=counts > 0)


def tracking_panels(found: FamilyRecords) -> list[dict[str, Any]]:
    """
    The panels of :func:`~pearl_paper.reproduce.figures.plot_tracking`: per oracle family with a record, each held-out
    task's target speed, the best constant's error on it and each agent's adapted error (seeds and repeats averaged).

    :param found: the records, as :func:`oracle_family_records` reads them
    """
    panels = []
    for family, records in found:
        targets = np.asarray(records["oracle"][0]["targets"], dtype=np.float64).reshape(
            len(records["oracle"][0]["targets"]), -1
        )
        constant = np.asarray(constant_references(targets)["constant"])
        panels.append(
            {
                "title": family.title,
                "speeds": np.linalg.norm(targets, axis=1),
                "constant_errors": np.linalg.norm(targets - constant, axis=1),
                "errors": {
                    ("Oracle" if label == "oracle" else label) + f" ({len(label_records)})": per_task_errors(label_records)
                    for label, label_records in records.items()
                },
            }
        )
    return panels


def _bin_cell(values: Sequence[float]) -> str:
    """A per-bin cell: the mean over seeds of the bin's error, "-" where no held-out target falls in the bin."""
    finite = [value for value in values if math.isfinite(value)]
    return f"{np.mean(finite):.3f}" if finite else "-"


def competence_section(
    results_dir: str | os.PathLike[str],
    rules: CompetenceRules = COMPETENCE_RULES,
    figure: Sequence[str] = (),
    found: FamilyRecords | None = None,
) -> list[str]:
    """
    The markdown of competence against the oracle: per oracle family with a record, the references, the oracle's and
    each judged meta-learner's held-out velocity error (k >= 1, per target-speed bin, k = 0), falls and return, and
    the verdicts of :data:`~pearl_paper.experiments.oracle.COMPETENCE_RULES`; then Highway-Merge's rule
    (:func:`~pearl_paper.reproduce.merge_competence.merge_competence_section`). Empty when no oracle record exists.

    :param results_dir: root of the results layout
    :param rules: the rules
    :param figure: lines shown after the velocity families' tables (the report's tracking figure), when there are any
    :param found: the velocity records already read by :func:`oracle_family_records` (None: read them)
    :return: the lines
    """
    out: list[str] = []
    for family, records in oracle_family_records(results_dir) if found is None else found:
        oracle = records["oracle"]
        decision = family_verdicts(family.name, records, rules)
        constant = decision.references["best_constant"]
        bins = list(next(iter(decision.runs["oracle"])).by_bin)
        if family.name in CALIBRATIONS:
            decision.learnable = "not judged: a calibration of the learner (one target), read its error and falls"
        elif len(oracle) < (declared := len(ORACLE.seeds_of(ORACLE_VARIANT.name, family.name))):
            decision.learnable += f" (provisional: {len(oracle)} of {declared} oracle seeds)"
        out += [
            f"#### {family.title}",
            "",
            f"References on the 20 held-out tasks: standing still {decision.references['standing']:.3f} m/s, the best "
            f"constant velocity {constant:.3f}. Learnable if the oracle's error <= {rules.oracle_fraction_of_constant} x "
            f"{constant:.3f} = {rules.oracle_fraction_of_constant * constant:.3f}: **{decision.learnable}**.",
            "",
            f"| agent (seeds) | velocity error, k >= 1 [seed range] | {' | '.join(bins)} | k = 0 | falls k >= 1 "
            "| return k >= 1 | verdict |",
            "|---|---|" + "---|" * len(bins) + "---|---|---|---|",
        ]
        for label, runs in decision.runs.items():
            adapted = [run.adapted for run in runs]
            returns = [np.mean([row["return"] for row in record["rows"] if row["k"] >= 1]) for record in records[label]]
            verdict = decision.learnable if label == "oracle" else decision.competent[label]
            out.append(
                f"| {'Oracle' if label == 'oracle' else label} ({len(runs)}) | {np.mean(adapted):.3f} "
                f"[{min(adapted):.3f}, {max(adapted):.3f}] | "
                + " | ".join(_bin_cell([run.by_bin[b] for run in runs]) for b in bins)
                + f" | {decision.mean(label, 'prior'):.3f} | {100 * decision.mean(label, 'adapted_violation'):.1f}% "
                f"| {np.mean(returns):.1f} | {verdict} |"
            )
        out += [""]
    if out:
        out = [
            "The velocity families: the held-out velocity error (m/s) of each run's committed model (`python -m "
            f"pearl_paper.reproduce velocity`): 20 held-out tasks x 2 repeats, deterministic, k = 0..{rules.n_adapt}; means "
            f"over seeds. A meta-learner is competent if its error is at most {rules.oracle_ratio} x the oracle's and at "
            f"most {rules.constant_fraction} x the best constant.",
            "",
            *out,
            *figure,
        ]
    out += merge_competence_section(results_dir, rules)
    if not out:
        return []
    return [
        "### Competence against the oracle",
        "",
        "Rules committed before the oracle's runs: `pearl_paper/experiments/oracle.py`.",
        "",
        *out,
    ]


def measure_experiments(
    results_dir: str | Path,
    experiments: Sequence[str],
    seeds: Sequence[int] | None = None,
    families: Sequence[str] | None = None,
    force: bool = False,
    echo: Callable[[str], None] = print,
) -> list[Path]:
    """
    Measure every finished run of the experiments' velocity families (under each run's lock; a run in training is
    skipped and reported).

    :param results_dir: root of the results layout
    :param experiments: experiment names
    :param seeds: model seeds (None: each experiment's declared seeds)
    :param families: family names (None: every velocity family of the experiments)
    :param force: measure runs that have a record again
    :param echo: progress output
    :return: the records written
    """
    from pearl_paper.reproduce.remeasure import measure_finished_runs

    def chosen(family: str) -> bool:
        return family in SPEED_BINS and (families is None or family in families)

    return measure_finished_runs(results_dir, experiments, lambda folder: measure_run(folder, force), seeds, chosen, echo)
