"""Runs of an experiment as separate processes, ``jobs`` at a time, with a progress line and an ETA per finished run.

This is the ``local`` backend of ``python -m pearl_paper.reproduce run`` (the default). Every (family,
variant, seed) is its own child process (``python -m pearl_paper.reproduce run-one``) with
``OMP_NUM_THREADS=1`` / ``MKL_NUM_THREADS=1`` (and one torch thread inside), its stdout and stderr in
the run folder's ``run.log``. A run whose ``result.json`` exists is skipped unless ``force``; a run
whose result was written with another budget preset is an error.

What both backends share lives here: :func:`plan_runs`, :func:`select_pending` (the idempotence rule),
:class:`Progress` (the progress lines) and :class:`RunSummary`. The ``ray`` backend, each run a Ray
Tune trial, is :mod:`pearl_paper.reproduce.ray_backend` (optional: ``pip install -e ".[ray]"``), loaded
through :func:`load_ray_backend`.
"""

from __future__ import annotations

import importlib
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, BinaryIO

from pearl_paper.experiments.spec import Experiment
from pearl_paper.reproduce.checkpoint import RunCheckpoint, resume_promise
from pearl_paper.reproduce.layout import LOG_FILE, RESULT_FILE, RunKey, discard_result, run_dir
from pearl_paper.reproduce.ownership import LOCKED_EXIT, PARENT_PID_ENV, lock_holder
from pearl_paper.reproduce.runner import existing_result, run_kwargs
from sb3_pearl.budgets import load_budget

#: environment of every run, whatever the backend: one thread per run (torch also gets ``set_num_threads(1)``)
RUN_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
#: the checkout that holds ``pearl_paper``: the package is not installed (the wheel holds ``sb3_pearl`` alone), so a
#: child finds it, and the same checkout's ``sb3_pearl``, through ``PYTHONPATH`` whatever its working directory
CHECKOUT = Path(__file__).resolve().parents[2]
RAY_MISSING = '--backend ray needs Ray, which is not installed: pip install -e ".[ray]"'


class BackendUnavailableError(RuntimeError):
    """A backend whose optional dependency is not installed (``--backend ray`` without Ray)."""


def load_ray_backend() -> ModuleType:
    """
    Import :mod:`pearl_paper.reproduce.ray_backend`, or say in one line how to install Ray.

    :return: the module
    :raises BackendUnavailableError: Ray cannot be imported
    """
    try:
        return importlib.import_module("pearl_paper.reproduce.ray_backend")
    except ImportError as error:
        if (error.name or "").split(".")[0] == "ray":
            raise BackendUnavailableError(RAY_MISSING) from error
        raise


@dataclass
class RunSummary:
    """What a backend did: runs done, skipped (complete already), failed, and not finished (interrupted)."""

    done: list[RunKey] = field(default_factory=list)
    skipped: list[RunKey] = field(default_factory=list)
    failed: list[RunKey] = field(default_factory=list)
    interrupted: list[RunKey] = field(default_factory=list)


def plan_runs(
    experiment: Experiment,
    budget_preset: str,
    seeds: Sequence[int] | None,
    families: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
) -> list[RunKey]:
    """
    The runs of an experiment, every budget and variant override checked before anything starts.

    :param experiment: the experiment
    :param budget_preset: the budget preset
    :param seeds: model seeds (None: each variant's declared seeds on each family, :meth:`Experiment.seeds_of`)
    :param families: family names (None: all of the experiment's)
    :param variants: variant names (None: all)
    :return: the runs, family by family, variant by variant, seed by seed
    """
    # a family or variant named twice is one run, not two (dict.fromkeys keeps the first occurrence's order)
    chosen_families = [experiment.family(n) for n in dict.fromkeys(families)] if families else list(experiment.families)
    chosen_variants = [experiment.variant(n) for n in dict.fromkeys(variants)] if variants else list(experiment.variants)
    if seeds is not None:
        seeds = list(dict.fromkeys(seeds))
        if not seeds:
            raise ValueError("no seeds to run")
        bad = [s for s in seeds if s == experiment.eval_seed or s < 0]
        if bad:
            raise ValueError(
                f"seeds {bad} are not allowed: model seeds must be >= 0 and differ from eval_seed {experiment.eval_seed}"
            )
    runs: list[RunKey] = []
    for family in chosen_families:
        for variant in chosen_variants:
            budget = load_budget(budget_preset, family.budget_name, variant.algo)
            run_kwargs(budget, variant, f"{experiment.name} {family.name} (preset {budget_preset})")
            chosen_seeds = experiment.seeds_of(variant.name, family.name) if seeds is None else seeds
            # a shared variant's runs live in (and are run as part of) the experiment that owns them
            runs.extend(RunKey(experiment.owner(variant.name), family.name, variant.name, seed) for seed in chosen_seeds)
    return runs


def undeclared_seeds(experiment: Experiment, runs: Sequence[RunKey]) -> dict[tuple[str, str], list[int]]:
    """
    The planned seeds a variant does not declare on a family (:meth:`Experiment.seeds_of`): ``--seeds`` applies to
    every chosen variant and family, and the report shows only the declared seeds, so such a run trains but no table
    counts it.

    :param experiment: the experiment
    :param runs: the planned runs (:func:`plan_runs`)
    :return: (family, variant) -> its undeclared seeds, in plan order (only the pairs that have some)
    """
    undeclared: dict[tuple[str, str], list[int]] = {}
    for run in runs:
        extra = undeclared.get((run.family, run.variant), [])
        if run.seed not in experiment.seeds_of(run.variant, run.family) and run.seed not in extra:
            undeclared.setdefault((run.family, run.variant), []).append(run.seed)
    return undeclared


def select_pending(
    runs: Sequence[RunKey],
    budget_preset: str,
    results_dir: str | os.PathLike[str],
    force: bool,
    summary: RunSummary,
    echo: Callable[[str], None] = print,
) -> list[RunKey]:
    """
    The idempotence rule of both backends: a run whose ``result.json`` exists is skipped unless ``force``.

    :param runs: the planned runs
    :param budget_preset: the preset of the requested runs (a result of another preset is an error)
    :param results_dir: root of the results layout
    :param force: rerun complete runs
    :param summary: receives the skipped runs
    :param echo: where the skip lines go
    :return: the runs to do
    """
    pending: list[RunKey] = []
    for key in runs:
        folder = run_dir(results_dir, key)
        if not force and existing_result(folder, budget_preset) is not None:
            RunCheckpoint(folder).remove()  # a kill between result.json and the clean-up may have left one
            summary.skipped.append(key)
            echo(f"skip {key.label()}: {folder / RESULT_FILE} exists (--force reruns it)")
            continue
        pending.append(key)
    return pending


def format_duration(seconds: float) -> str:
    """``1h02m`` or ``3m07s``; ``?`` for nan."""
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{secs:02d}s"


@dataclass
class Progress:
    """
    The progress line of a finished run: ``[n/total] label: status in 0m09s; elapsed 0m30s, ETA 1m12s``.

    The ETA is ``ceil(remaining / slots)`` times the mean duration of the runs done so far.

    :param total: runs to do
    :param slots: runs at a time
    :param echo: where the lines go
    """

    total: int
    slots: int
    echo: Callable[[str], None] = print
    started: float = field(default_factory=time.time)
    durations: list[float] = field(default_factory=list)
    finished: int = 0

    def line(self, key: RunKey, ok: bool, elapsed: float, failure: str = "") -> None:
        """
        Count a finished run and echo its line.

        :param key: the run
        :param ok: it wrote its result.json
        :param elapsed: its wall time in seconds
        :param failure: the status of a failed run (``FAILED (...)``)
        """
        self.finished += 1
        if ok:
            self.durations.append(elapsed)
        remaining = max(self.total - self.finished, 0)
        mean = sum(self.durations) / len(self.durations) if self.durations else math.nan
        eta = math.ceil(remaining / max(self.slots, 1)) * mean if remaining else 0.0
        status = "done" if ok else failure or "FAILED"
        self.echo(
            f"[{self.finished}/{self.total}] {key.label()}: {status} in {format_duration(elapsed)}; "
            f"elapsed {format_duration(time.time() - self.started)}, ETA {format_duration(eta)}"
        )


def child_env() -> dict[str, str]:
    """
    The environment of one run's child process: this one's, with :data:`RUN_ENV` and the checkout first on the path.

    :return: the environment
    """
    path = [str(CHECKOUT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, **RUN_ENV, "PYTHONPATH": os.pathsep.join(dict.fromkeys(path))}


def child_command(key: RunKey, budget_preset: str, results_dir: str | os.PathLike[str]) -> list[str]:
    """The command line of one run's child process."""
    return [
        sys.executable,
        "-m",
        "pearl_paper.reproduce",
        "run-one",
        *("--experiment", key.experiment, "--family", key.family, "--variant", key.variant),
        *("--seed", str(key.seed), "--budget", budget_preset, "--results-dir", str(results_dir)),
    ]


def run_experiment(
    experiment: Experiment,
    budget_preset: str,
    seeds: Sequence[int] | None,
    results_dir: str | os.PathLike[str],
    jobs: int = 1,
    families: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
    force: bool = False,
    echo: Callable[[str], None] = print,
    poll_s: float = 0.5,
) -> RunSummary:
    """
    Run every planned (family, variant, seed) as a child process, ``jobs`` at a time.

    :param experiment: the experiment
    :param budget_preset: ``smoke``, ``cpu`` or ``paper``
    :param seeds: model seeds (None: each variant's declared seeds)
    :param results_dir: root of the results layout
    :param jobs: runs at a time
    :param families: family names (None: all)
    :param variants: variant names (None: all)
    :param force: rerun runs that have a result.json
    :param echo: where progress lines go
    :param poll_s: seconds between checks of the running children
    :return: the runs done, skipped and failed
    """
    if jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {jobs}")
    summary = RunSummary()
    runs = plan_runs(experiment, budget_preset, seeds, families, variants)
    pending = select_pending(runs, budget_preset, results_dir, force, summary, echo)
    total = len(pending)
    echo(f"{experiment.name}: {total} run(s) to do, {len(summary.skipped)} skipped, budget {budget_preset}, {jobs} at a time")
    env = child_env()
    running: dict[RunKey, tuple[subprocess.Popen[bytes], float, BinaryIO]] = {}
    progress = Progress(total, jobs, echo)
    queue = list(pending)
    forced: set[RunKey] = set()
    previous = _raise_on_sigterm()
    try:
        while queue or running:
            while queue and len(running) < jobs:
                key = queue.pop(0)
                folder = run_dir(results_dir, key)
                folder.mkdir(parents=True, exist_ok=True)
                owner = lock_holder(folder)
                if owner is not None:  # another command trains it: share the work, never train a run twice
                    summary.skipped.append(key)
                    progress.total -= 1
                    echo(f"skip {key.label()}: being run by another process (pid {owner})")
                    continue
                if force and key not in forced:
                    forced.add(key)
                    discard_result(folder)  # result.json and the records of the model the rerun replaces
                    RunCheckpoint(folder).remove()  # --force: from zero
                elif not force and (folder / RESULT_FILE).is_file():  # finished meanwhile (by another command)
                    summary.skipped.append(key)
                    progress.total -= 1
                    echo(f"skip {key.label()}: {folder / RESULT_FILE} exists (--force reruns it)")
                    continue
                log = open(folder / LOG_FILE, "ab")  # noqa: SIM115  (closed when the child ends; appended: resumed runs)
                process = subprocess.Popen(
                    child_command(key, budget_preset, results_dir),
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    env={**env, PARENT_PID_ENV: str(os.getpid())},  # the child dies with this process (ownership.py)
                )
                running[key] = (process, time.time(), log)
            finished = [key for key, (process, _, _) in running.items() if process.poll() is not None]
            if not finished:
                time.sleep(poll_s)
                continue
            for key in finished:
                process, start, log_file = running.pop(key)
                log_file.close()
                elapsed = time.time() - start
                folder = run_dir(results_dir, key)
                if process.returncode == LOCKED_EXIT:  # lost the race for the lock: the other owner finishes it
                    summary.skipped.append(key)
                    progress.total -= 1
                    echo(f"skip {key.label()}: being run by another process")
                    continue
                ok = process.returncode == 0 and (folder / RESULT_FILE).is_file()
                if not ok and process.returncode in STOPPED_EXITS:  # a signal to the child (not from here): resumable
                    summary.interrupted.append(key)
                    progress.line(key, False, elapsed, f"interrupted (exit {process.returncode}); {resume_promise(folder)}")
                    continue
                (summary.done if ok else summary.failed).append(key)
                progress.line(key, ok, elapsed, f"FAILED (exit {process.returncode}, see {folder / LOG_FILE})")
    except KeyboardInterrupt:  # Ctrl-C (SIGINT) or SIGTERM: stop the children cleanly, say what is left
        _stop_children(running)
        summary.interrupted.extend(running)
        echo(
            f"interrupted: {len(running)} run(s) stopped ({', '.join(key.label() for key in running) or 'none'}), "
            f"{len(queue)} not started; run the same command"
            + (" without --force" if force else "")
            + " again to complete them (each stopped run resumes from its last checkpoint, docs/reproduce.md)"
        )
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return summary


# A child stopped by SIGTERM or SIGINT (a scheduler, the OOM guard of a cluster, Ctrl-C in its terminal): interrupted,
# not failed; the same command resumes it from the checkpoint the stop saved.
STOPPED_EXITS = (128 + signal.SIGTERM, 128 + signal.SIGINT)


def _raise_on_sigterm() -> Any:
    """In the main thread: make SIGTERM raise KeyboardInterrupt, as Ctrl-C does; return the previous handler."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, handler)


def _stop_children(running: dict[RunKey, tuple[subprocess.Popen[bytes], float, BinaryIO]], grace_s: float = 60.0) -> None:
    """SIGTERM every child, wait up to ``grace_s`` for all, then SIGKILL the rest."""
    for process, _, _ in running.values():
        if process.poll() is None:
            process.terminate()
    deadline = time.time() + grace_s
    for process, _, log in running.values():
        try:
            process.wait(timeout=max(deadline - time.time(), 0.1))
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()


__all__ = [
    "RAY_MISSING",
    "RUN_ENV",
    "BackendUnavailableError",
    "Progress",
    "RunSummary",
    "child_command",
    "child_env",
    "format_duration",
    "load_ray_backend",
    "plan_runs",
    "run_experiment",
    "select_pending",
]
