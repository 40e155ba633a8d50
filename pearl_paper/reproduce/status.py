"""``reproduce status``: which planned runs are finished, resumable (a checkpoint) or missing, and the CPU time left;
``reproduce run --dry-run``: what the run would do with each (:func:`format_dry_run`).

CPU time still needed, per run: a resumable run in training, its CPU seconds per env step times the steps left, plus
the evaluation time of its finished siblings; a run in evaluation, that evaluation time; a missing run, the mean CPU
time of the finished runs of the same family and algorithm in the plan. The rate is the one between the run's last two
checkpoints where it has two (its average otherwise): PEARL's first iteration collects its initial pool with a few
gradient steps, so a run's average rate after it is several times too low (a cheetah-vel run: 0.12 CPU hours for its
first 200k steps, ~6 for the 300k after them). Where no run of that family and algorithm has finished, the
evaluation's cost is unknown and the estimate counts the training only (said in the progress column): a resumable
run's own rate, a missing run's the projected training time of its siblings in training (unknown when there is none
either).
Finished runs written before the CPU time was recorded count their wall time.

A run whose checkpoint's model zip is cut or corrupt (or whose replay buffer is missing or empty) is "damaged", not
resumable (:meth:`~pearl_paper.reproduce.checkpoint.RunCheckpoint.damage`): its resume would stop; the estimate counts it
as a run to start anew.

A resumable run also shows the size of its checkpoint (the files its state names): a part-way run is carried to the
next session by committing that checkpoint, and each commit of one adds its size to the repository's history (a
Walker2D-vel replay buffer at the reference's networks grows by ~110 bytes per env step held).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any, NamedTuple

from pearl_paper.experiments.spec import Experiment
from pearl_paper.reproduce.checkpoint import RunCheckpoint
from pearl_paper.reproduce.layout import RESULT_FILE, RunKey, read_run_result, run_dir
from pearl_paper.reproduce.runner import existing_result
from pearl_paper.reproduce.scheduler import plan_runs
from pearl_paper.reproduce.stats import mean_finite
from sb3_pearl.budgets import load_budget

DAMAGED_FIX = "delete the run's checkpoint/ folder (or add --force), and `reproduce run` starts it anew"


class RunStatus(NamedTuple):
    """One planned run."""

    key: RunKey
    status: str  # "finished", "resumable", "damaged" (its checkpoint), "missing", "awaiting" (the rule) or "unselected"
    progress: str
    cpu_spent_s: float
    cpu_left_s: float  # nan: unknown
    training_only: bool = False  # cpu_left_s counts the training only (no finished sibling gives the evaluation's cost)
    checkpoint_bytes: int = 0  # the run's checkpoint on disk (the files its state names), 0 without one


def _finished_cpu(result: dict[str, Any]) -> tuple[float, float]:
    """(total, evaluation) seconds of a finished run: CPU time where recorded, else wall time."""
    wall = result.get("wall_time_s") or {}
    total = float((result.get("cpu") or {}).get("cpu_time_s") or wall.get("total") or math.nan)
    evaluation = float(wall.get("total", math.nan)) - float(wall.get("train", math.nan))
    return total, evaluation


def run_status(
    experiment: Experiment,
    budget_preset: str,
    seeds: Sequence[int] | None,
    results_dir: str | os.PathLike[str],
    families: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
) -> list[RunStatus]:
    """
    The status of every planned run.

    :param experiment: the experiment
    :param budget_preset: the budget preset
    :param seeds: model seeds (None: each variant's declared seeds)
    :param results_dir: root of the results layout
    :param families: family names (None: all)
    :param variants: variant names (None: all)
    :return: one row per planned run, in plan order
    """
    keys = plan_runs(experiment, budget_preset, seeds, families, variants)
    held: dict[str, str] = {}  # after_selection variant -> "awaiting" / "unselected" (only when not named explicitly)
    if variants is None and experiment.after_selection:
        from pearl_paper.reproduce.prior_report import selection_gate

        gate = selection_gate(experiment, budget_preset, results_dir)
        held = dict.fromkeys(gate.held, "unselected" if gate.final else "awaiting")
    finished: dict[RunKey, dict[str, Any]] = {}
    for key in keys:
        path = run_dir(results_dir, key) / RESULT_FILE
        if path.is_file():
            finished[key] = read_run_result(path)

    def siblings(key: RunKey) -> list[tuple[float, float]]:
        algo = experiment.variant(key.variant).algo
        return [
            _finished_cpu(result)
            for other, result in finished.items()
            if other.family == key.family and experiment.variant(other.variant).algo == algo
        ]

    states = {key: RunCheckpoint(run_dir(results_dir, key)).read_state() for key in keys if key not in finished}

    def n_timesteps(key: RunKey) -> int:
        family, algo = experiment.family(key.family).budget_name, experiment.variant(key.variant).algo
        return int(load_budget(budget_preset, family, algo)["n_timesteps"])

    def per_step(state: dict[str, Any]) -> float:
        """CPU seconds per env step of a run in training: between its last two checkpoints, else its average."""
        recent = state.get("recent") or {}
        if recent.get("steps", 0) > 0:
            return float(recent["cpu_s"]) / int(recent["steps"])
        done = int(state["num_timesteps"])
        return float(state["spent"]["cpu_s"]) / done if done > 0 else math.nan

    def training_left(key: RunKey, state: dict[str, Any]) -> float:
        return per_step(state) * (n_timesteps(key) - int(state["num_timesteps"]))

    def projected_training(key: RunKey) -> float:
        """The mean projected training CPU time of this family and algorithm's runs in training (nan: none)."""
        algo = experiment.variant(key.variant).algo
        totals = [
            float(state["spent"]["cpu_s"]) + training_left(other, state)
            for other, state in states.items()
            if state is not None and state["phase"] == "train" and int(state["num_timesteps"]) > 0
            if other.family == key.family and experiment.variant(other.variant).algo == algo
        ]
        return mean_finite(totals)

    rows = []
    for key in keys:
        if key in finished:
            total, _ = _finished_cpu(finished[key])
            rows.append(RunStatus(key, "finished", "done", total, 0.0))
            continue
        known = siblings(key)
        evaluation = mean_finite([e for _, e in known])
        state = states[key]
        size = RunCheckpoint(run_dir(results_dir, key)).size_bytes(state) if state is not None else 0
        if key.variant in held:
            # planned by `run` only if the selection rule picks it: its cost is counted apart (format_status); one
            # started with --variants keeps its checkpoint, resumed by naming it again
            why = "awaiting the selection rule" if held[key.variant] == "awaiting" else "not selected by the rule"
            spent = 0.0
            if state is not None:
                spent = float(state["spent"]["cpu_s"])
                why += f", checkpoint at {int(state['num_timesteps'])} steps (--variants {key.variant})"
            left = mean_finite([t for t, _ in known]) if known else projected_training(key)
            left = left - spent if math.isfinite(left) else left
            rows.append(RunStatus(key, held[key.variant], why, spent, left, checkpoint_bytes=size))
            continue
        if state is None:
            # no finished sibling: the training alone, as projected for its siblings in training (a lower bound)
            left = mean_finite([t for t, _ in known]) if known else projected_training(key)
            partial = not known and math.isfinite(left)
            rows.append(RunStatus(key, "missing", "- (training only)" if partial else "-", 0.0, left, partial))
            continue
        damage = RunCheckpoint(run_dir(results_dir, key)).damage(state)
        if damage is not None:  # the run stops at its resume: it restarts from zero once the checkpoint is deleted
            left = mean_finite([t for t, _ in known]) if known else projected_training(key)
            spent = float(state["spent"]["cpu_s"])
            rows.append(RunStatus(key, "damaged", damage, spent, left, not known and math.isfinite(left), size))
            continue
        n_total = n_timesteps(key)
        done, cpu = int(state["num_timesteps"]), float(state["spent"]["cpu_s"])
        partial = False
        if state["phase"] == "train":
            left = training_left(key, state) + (evaluation if math.isfinite(evaluation) else 0.0)
            progress = f"train {done}/{n_total} steps ({100 * done / n_total:.0f}%)"
            partial = not math.isfinite(evaluation)  # no finished sibling says what its evaluation costs
            if partial:
                progress += ", training only"
        else:
            left = evaluation
            progress = f"evaluate ({', '.join(p for p in state['phases'] if not p.endswith('_s')) or 'starting'})"
        rows.append(RunStatus(key, "resumable", progress, cpu, left, partial, size))
    return rows


def _hours(seconds: float) -> str:
    return "unknown" if not math.isfinite(seconds) else f"{seconds / 3600:.2f} h"


def _cpu_left(rows: Sequence[RunStatus]) -> str:
    """The CPU time the resumable and missing runs still need, as ``status`` and ``run --dry-run`` say it."""
    left = [r.cpu_left_s for r in rows if r.status in ("resumable", "damaged", "missing")]
    unknown = sum(not math.isfinite(v) for v in left)
    total = sum(v for v in left if math.isfinite(v))
    partial = sum(r.training_only for r in rows)
    return (
        f"CPU time left {'at least ' if partial else ''}{_hours(total)} (one core)"
        + (f", plus {unknown} run(s) of unknown cost" if unknown else "")
        + (f"; {partial} estimate(s) count the training only" if partial else "")
    )


def format_dry_run(
    rows: Sequence[RunStatus],
    experiment: Experiment,
    budget_preset: str,
    results_dir: str | os.PathLike[str],
    force: bool = False,
) -> str:
    """
    What ``reproduce run --dry-run`` prints: for every planned run what the same command without ``--dry-run`` would do
    with it (the rule of :func:`~pearl_paper.reproduce.scheduler.select_pending` and of the runner's resume): a finished
    run (its ``result.json`` present) is skipped, a run with a checkpoint resumes from it (one with a damaged checkpoint
    stops there), any other starts; with ``force`` every run starts from zero. Then the counts and the CPU time left
    (:func:`run_status`'s estimate).

    :param rows: :func:`run_status` of the planned runs (the selection rule already applied: no held variant)
    :param experiment: the experiment
    :param budget_preset: the budget preset
    :param results_dir: root of the results layout
    :param force: ``--force``
    :return: one line per run, then the totals
    :raises ValueError: a finished run of another budget preset, as the run itself would refuse it (without ``force``)
    """
    lines: list[str] = []
    counts = {"skip": 0, "resume": 0, "start": 0, "damaged": 0}
    for row in rows:
        key = row.key
        variant = experiment.variant(key.variant)
        entry = load_budget(budget_preset, experiment.family(key.family).budget_name, variant.algo)
        plan = f"{variant.algo}, {entry['n_timesteps']} steps, meta-test {entry['meta_test']}"
        result = run_dir(results_dir, key) / RESULT_FILE
        if row.status == "finished" and not force:
            existing_result(result.parent, budget_preset)  # another preset's result: the run's own error
            counts["skip"] += 1
            lines.append(f"{key.label()}: done, skipped ({result} exists; --force reruns it)")
        elif row.status == "resumable" and not force:
            counts["resume"] += 1
            lines.append(f"{key.label()}: resumes from its checkpoint ({row.progress}): {plan}")
        elif row.status == "damaged" and not force:
            counts["damaged"] += 1
            lines.append(f"{key.label()}: stops at its resume, {row.progress}: {DAMAGED_FIX}")
        else:
            counts["start"] += 1
            why = ""
            if force and row.status == "finished":
                why = " from zero (--force replaces its result.json)"
            elif force and row.status in ("resumable", "damaged"):
                why = " from zero (--force drops its checkpoint)"
            lines.append(f"{key.label()}: starts{why}: {plan}")
    total = (
        f"Dry run, nothing started: {counts['skip']} done (skipped), {counts['resume']} would resume from a checkpoint, "
        f"{counts['start']} would start"
    ) + (f", {counts['damaged']} would stop at a damaged checkpoint" if counts["damaged"] else "")
    lines.append(total + ("" if force else f"; {_cpu_left(rows)}"))
    return "\n".join(lines)


def format_status(rows: Sequence[RunStatus]) -> str:
    """The table ``reproduce status`` prints, with the totals."""
    hours = _hours

    def megabytes(size: int) -> str:
        return f"{size / 1e6:.1f} MB" if size else ""

    lines = [f"{'run':<58} {'status':<10} {'progress':<40} {'CPU spent':>10} {'CPU left':>10} {'checkpoint':>11}"]
    for row in rows:
        spent_h, left_h = hours(row.cpu_spent_s), hours(row.cpu_left_s)
        lines.append(
            f"{row.key.label():<58} {row.status:<10} {row.progress:<40} {spent_h:>10} {left_h:>10}"
            f" {megabytes(row.checkpoint_bytes):>11}"
        )
    counts = {s: sum(r.status == s for r in rows) for s in ("finished", "resumable", "missing", "awaiting")}
    finished, resumable, missing = counts["finished"], counts["resumable"], counts["missing"]
    lines.append(f"{finished} finished, {resumable} resumable, {missing} missing; {_cpu_left(rows)}")
    checkpoints = [r.checkpoint_bytes for r in rows if r.checkpoint_bytes]
    if checkpoints:
        lines.append(
            f"{len(checkpoints)} checkpoint(s), {megabytes(sum(checkpoints))} in all: committing one adds its size to the "
            "repository's history, so commit part-way runs once per session"
        )
    if counts["awaiting"]:
        each = mean_finite([r.cpu_left_s for r in rows if r.status == "awaiting"])
        cost = f"about {hours(each)} each" if math.isfinite(each) else "cost unknown"
        lines.append(
            f"{counts['awaiting']} run(s) await the selection rule ({cost}, not in the total): "
            "`reproduce run` plans the selected designs' runs once every run the rule reads is complete."
        )
    unselected = sum(r.status == "unselected" for r in rows)
    if unselected:
        lines.append(f"{unselected} run(s) of designs the selection rule did not select: not planned, not counted.")
    damaged = sum(r.status == "damaged" for r in rows)
    if damaged:
        lines.append(f"{damaged} run(s) with a damaged checkpoint (named in the progress column): {DAMAGED_FIX}")
    if counts["resumable"] or counts["missing"]:
        lines.append("The same `reproduce run` command completes them (resumable runs continue from their checkpoints).")
    return "\n".join(lines)
