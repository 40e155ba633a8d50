"""The ``ray`` backend of ``python -m pearl_paper.reproduce run``: every (family, variant, seed) is a Ray Tune trial.

Optional (``pip install -e ".[ray]"``); usage in docs/scale.md. The engine is Ray Tune, nothing home-made:

- the runs are a ``tune.grid_search`` over their keys, run by a ``tune.Tuner`` with the function trainable
  :func:`~pearl_paper.reproduce.ray_trial.run_trial`, which calls the same single-run code as the local backend
  (:func:`~pearl_paper.reproduce.runner.run_one`, its stdout and stderr in the run folder's ``run.log``);
- resources per run: ``tune.with_resources`` (``--cpus-per-run``, default 1; ``--gpus-per-run``, default 0, and a
  run without a GPU is kept off the GPUs); ``--jobs`` caps the runs at a time (``max_concurrent_trials``);
- a failed trial is retried ``--retries`` times (``FailureConfig(max_failures=...)``);
- the experiment state lives under ``RunConfig(storage_path=...)`` (default ``<results-dir>/.tune``), in a folder
  named after the planned runs: running the same command again after an interruption resumes it
  (``Tuner.can_restore`` / ``Tuner.restore``; unfinished and failed trials run again, finished ones do not).

Idempotence is the local backend's (:func:`~pearl_paper.reproduce.scheduler.select_pending`): the driver only submits
runs without a ``result.json``, and a trial whose ``result.json`` appeared in the meantime returns at once.

Where results land: always in ``<results-dir>`` **on the driver**, in the same layout. A trial writes into it
directly when it can see it (a filesystem shared by the driver and the workers, recognised by the
``.sb3_pearl_results_id`` file the driver writes there). Otherwise it runs in a scratch folder and returns its
run folder as a Tune checkpoint, which the driver copies into ``<results-dir>`` (``result.json`` last and
atomically); Ray then needs a ``--storage-path`` that every node can reach (cloud storage or NFS).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import ray
from ray import tune

from pearl_paper.experiments.spec import Experiment
from pearl_paper.reproduce.layout import LOG_FILE, RESULT_FILE, RunKey, run_dir
from pearl_paper.reproduce.ray_trial import RESULTS_ID_FILE, copy_run_folder, run_key, run_trial, trial_dirname, trial_name
from pearl_paper.reproduce.scheduler import RUN_ENV, Progress, RunSummary, plan_runs, select_pending

TUNE_DIR = ".tune"
PLAN_FILE = "sb3_pearl_runs.json"  # in the Tune experiment's folder: the runs it was created with
TRANSFERS = ("auto", "shared", "checkpoint")


@dataclass
class _Driver:
    """What the callbacks of one experiment need on the driver (looked up by experiment path, never pickled)."""

    results_dir: Path
    pending: list[RunKey]
    progress: Progress
    echo: Callable[[str], None]
    retries: int
    started: dict[str, float] = field(default_factory=dict)
    failed: set[RunKey] = field(default_factory=set)


_DRIVERS: dict[str, _Driver] = {}


class ProgressCallback(tune.Callback):
    """
    Progress lines, and the copy of shipped run folders as their trials end, on the driver.

    Tune pickles its callbacks with the experiment (``Tuner.restore`` brings them back), so the callback holds only
    the experiment path and finds the live driver state in a module registry. Where Tune runs its loop elsewhere
    (Ray Client, ``ray://``), the registry is empty there: no lines, and the driver copies the folders after the fit.

    :param experiment_path: the Tune experiment's path, the registry key
    """

    def __init__(self, experiment_path: str) -> None:
        self.experiment_path = experiment_path

    def _driver(self) -> _Driver | None:
        return _DRIVERS.get(self.experiment_path)

    def on_trial_start(self, iteration: int, trials: list[Any], trial: Any, **info: Any) -> None:
        driver = self._driver()
        if driver is not None:
            driver.started.setdefault(trial.trial_id, time.time())

    def on_checkpoint(self, iteration: int, trials: list[Any], trial: Any, checkpoint: Any, **info: Any) -> None:
        driver = self._driver()
        if driver is not None:
            with checkpoint.as_directory() as source:
                copy_run_folder(Path(source), run_dir(driver.results_dir, run_key(trial.config["run"])))

    def on_trial_recover(self, iteration: int, trials: list[Any], trial: Any, **info: Any) -> None:
        driver = self._driver()
        if driver is not None:
            key = run_key(trial.config["run"])
            driver.echo(f"retry {key.label()}: attempt {trial.num_failures + 1} of {driver.retries + 1} (Tune retries it)")

    def _finished(self, trial: Any, ok: bool, failure: str = "") -> None:
        driver = self._driver()
        if driver is None:
            return
        key = run_key(trial.config["run"])
        if (trial.last_result or {}).get("skipped"):  # complete since it was submitted (a restored trial, another driver)
            if key in driver.pending:
                driver.echo(f"skip {key.label()}: {run_dir(driver.results_dir, key) / RESULT_FILE} exists")
                driver.progress.total -= 1
            return
        elapsed = time.time() - driver.started.get(trial.trial_id, time.time())
        driver.progress.line(key, ok, elapsed, failure)

    def on_trial_complete(self, iteration: int, trials: list[Any], trial: Any, **info: Any) -> None:
        driver = self._driver()
        if driver is not None:
            ok = (run_dir(driver.results_dir, run_key(trial.config["run"])) / RESULT_FILE).is_file()
            self._finished(trial, ok, "FAILED (the trial ended without a result.json)")

    def on_trial_error(self, iteration: int, trials: list[Any], trial: Any, **info: Any) -> None:
        driver = self._driver()
        if driver is not None:
            driver.failed.add(run_key(trial.config["run"]))
            folder = run_dir(driver.results_dir, run_key(trial.config["run"]))
            where = folder / LOG_FILE if (folder / LOG_FILE).is_file() else trial.error_file or trial.path
            self._finished(trial, False, f"FAILED after {trial.num_failures} attempt(s), see {where}")


def init_ray(address: str | None = None, num_cpus: int | None = None) -> bool:
    """
    Connect to a Ray cluster, or start a local one, unless Ray is initialised already.

    Workers get ``OMP_NUM_THREADS=1`` / ``MKL_NUM_THREADS=1`` through the job's runtime env.

    :param address: ``auto``, ``HOST:PORT``, ``ray://HOST:PORT``, or None: Ray's default (``RAY_ADDRESS``, else a
        cluster that ``ray start`` started on this machine, else a new local Ray)
    :param num_cpus: CPUs of a local Ray (None: all)
    :return: whether this call started the connection (then the caller shuts it down)
    :raises ValueError: no Ray cluster at ``address``
    """
    if ray.is_initialized():
        return False
    kwargs: dict[str, Any] = {
        "log_to_driver": False,
        "logging_level": logging.WARNING,
        "runtime_env": {"env_vars": dict(RUN_ENV)},
    }
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address is None:
        kwargs.update(include_dashboard=False, num_cpus=num_cpus)
    elif num_cpus is not None:
        raise ValueError("num_cpus applies to a local Ray, not to a cluster given by its address")
    try:
        ray.init(address=address, **kwargs)
    except ConnectionError as error:  # e.g. --address auto on a machine where `ray start` was not run
        raise ValueError(f"--address {address}: {error}") from error
    return True


def run_slots(cpus_per_run: float, gpus_per_run: float, jobs: int | None) -> int:
    """
    How many runs the cluster fits at a time (checked against every alive node).

    :raises ValueError: no node can hold one run
    """
    nodes = [node.get("Resources", {}) for node in ray.nodes() if node.get("Alive")]
    slots = 0
    for resources in nodes:
        fit = math.floor(resources.get("CPU", 0.0) / cpus_per_run + 1e-9)
        if gpus_per_run > 0:
            fit = min(fit, math.floor(resources.get("GPU", 0.0) / gpus_per_run + 1e-9))
        slots += fit
    if slots == 0:
        cluster = ", ".join(f"{r.get('CPU', 0):g} CPU / {r.get('GPU', 0):g} GPU" for r in nodes) or "no alive node"
        raise ValueError(
            f"no node of the Ray cluster has {cpus_per_run:g} CPU(s) and {gpus_per_run:g} GPU(s) for a run "
            f"(nodes: {cluster}); lower --cpus-per-run / --gpus-per-run or add nodes"
        )
    return min(slots, jobs) if jobs else slots


def ensure_results_id(results_dir: Path) -> str:
    """The id in ``<results-dir>/.sb3_pearl_results_id`` (written once), by which a worker recognises a shared folder."""
    path = results_dir / RESULTS_ID_FILE
    if not path.is_file():
        results_dir.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=results_dir, prefix=f"{RESULTS_ID_FILE}.", suffix=".tmp")
        with os.fdopen(fd, "w") as file:
            file.write(uuid.uuid4().hex + "\n")
        os.replace(tmp, path)
    return path.read_text().strip()


def experiment_name(experiment: Experiment, budget_preset: str, results_dir: Path, runs: Sequence[RunKey]) -> str:
    """The Tune experiment's name: the same planned runs into the same results give the same name (hence resume)."""
    plan = json.dumps([str(results_dir), budget_preset, sorted(key.label() for key in runs)])
    return f"{experiment.name}_{budget_preset}_{hashlib.sha1(plan.encode()).hexdigest()[:10]}"


@contextlib.contextmanager
def _quiet_tune() -> Iterator[None]:
    """
    Tune's own console output off during a fit (the progress lines are ours); restored after.

    Tune's warnings stay, except those of its loop about an interruption (they name ``Tuner.restore``; the driver says
    to run the same command again) and about trials that never reported (interrupted before their first result); its
    errors stay.
    """
    saved = os.environ.get("RAY_AIR_NEW_OUTPUT")
    quiet = ("ray.tune.tune", "ray.tune.analysis.experiment_analysis")  # interruptions; trials that never reported
    loggers = {name: logging.getLogger(name) for name in ("ray.tune", *quiet)}
    levels = {name: logger.level for name, logger in loggers.items()}
    os.environ["RAY_AIR_NEW_OUTPUT"] = "0"
    loggers["ray.tune"].setLevel(logging.WARNING)
    for name in quiet:
        loggers[name].setLevel(logging.ERROR)
    try:
        yield
    finally:
        for name, logger in loggers.items():
            logger.setLevel(levels[name])
        if saved is None:
            os.environ.pop("RAY_AIR_NEW_OUTPUT", None)
        else:
            os.environ["RAY_AIR_NEW_OUTPUT"] = saved


def _collect(grid: Any, driver: _Driver, summary: RunSummary | None) -> set[RunKey]:
    """
    After a fit: copy the run folders shipped as checkpoints that the callbacks did not copy (Ray Client), and sort the
    fit's runs into ``summary``: done (a result.json on the driver), failed (an error, seen by the callbacks or in the
    result grid). Runs of neither kind were interrupted.

    :param grid: the fit's result grid
    :param driver: the driver state (results folder, the runs asked for, the failures the callbacks saw)
    :param summary: where the runs go (None: copy only)
    :return: the runs whose trials reported (they ended, one way or the other)
    """
    failed, reported = set(driver.failed), set()
    for index in range(len(grid)):
        result = grid[index]
        run = (result.config or {}).get("run")  # None for a trial that never reported (interrupted, crashed early)
        if run is None:
            continue
        key = run_key(run)
        reported.add(key)
        folder = run_dir(driver.results_dir, key)
        if not (folder / RESULT_FILE).is_file() and result.checkpoint is not None:
            with result.checkpoint.as_directory() as source:
                copy_run_folder(Path(source), folder)
        if result.error is not None:
            failed.add(key)
    if summary is None:
        return reported
    for key in driver.pending:
        if key in summary.done or key in summary.failed:
            continue
        if (run_dir(driver.results_dir, key) / RESULT_FILE).is_file():
            summary.done.append(key)
        elif key in failed:
            summary.failed.append(key)
    return reported


def _unfinished(grid: Any) -> int:
    """Trials of a result grid that neither finished nor failed (the experiment was interrupted)."""
    return len(grid) - grid.num_terminated - grid.num_errors


def _filesystem(path: str) -> tuple[Any, str]:
    """The pyarrow filesystem of a local path or a storage URI (``s3://``, ``gs://``, ...), and the path in it."""
    import pyarrow.fs

    return pyarrow.fs.FileSystem.from_uri(path) if "://" in path else (pyarrow.fs.LocalFileSystem(), path)


def _delete_experiment(path: str) -> None:
    """Remove a Tune experiment's state before a fresh one takes its name."""
    import pyarrow.fs

    filesystem, fs_path = _filesystem(path)
    if filesystem.get_file_info(fs_path).type != pyarrow.fs.FileType.NotFound:
        filesystem.delete_dir(fs_path)


def _write_plan(path: str, keys: Sequence[RunKey]) -> None:
    """Record the runs a Tune experiment was created with (Tune creates trials lazily under ``max_concurrent_trials``)."""
    filesystem, fs_path = _filesystem(path)
    filesystem.create_dir(fs_path)
    with filesystem.open_output_stream(f"{fs_path}/{PLAN_FILE}") as stream:
        stream.write(json.dumps([key._asdict() for key in keys]).encode())


def _read_plan(path: str) -> list[RunKey] | None:
    """The runs recorded by :func:`_write_plan`, or None if the file is missing or unreadable."""
    filesystem, fs_path = _filesystem(path)
    try:
        with filesystem.open_input_stream(f"{fs_path}/{PLAN_FILE}") as stream:
            return [RunKey(**entry) for entry in json.loads(stream.read().decode())]
    except (OSError, ValueError, TypeError):
        return None


def _check_options(
    jobs: int | None,
    cpus_per_run: float,
    gpus_per_run: float,
    retries: int,
    transfer: str,
    address: str | None,
    storage: str | None,
) -> None:
    if jobs is not None and jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {jobs}")
    if not cpus_per_run > 0:
        raise ValueError(f"--cpus-per-run must be > 0, got {cpus_per_run}")
    if gpus_per_run < 0:
        raise ValueError(f"--gpus-per-run must be >= 0, got {gpus_per_run}")
    if retries < 0:
        raise ValueError(f"--retries must be >= 0, got {retries}")
    if transfer not in TRANSFERS:
        raise ValueError(f"transfer must be one of {TRANSFERS}, got {transfer!r}")
    if address is not None and address.startswith("ray://") and storage is None:
        raise ValueError(
            "--address ray://... runs Tune's loop on the head node: give --storage-path on storage that the cluster and "
            "this machine share (s3://..., gs://... or an NFS path mounted at the same place), so that the run folders "
            "come back here"
        )


def run_experiment_ray(
    experiment: Experiment,
    budget_preset: str,
    seeds: Sequence[int] | None,
    results_dir: str | os.PathLike[str],
    jobs: int | None = None,
    families: Sequence[str] | None = None,
    variants: Sequence[str] | None = None,
    force: bool = False,
    address: str | None = None,
    cpus_per_run: float = 1.0,
    gpus_per_run: float = 0.0,
    retries: int = 1,
    storage_path: str | None = None,
    transfer: str = "auto",
    echo: Callable[[str], None] = print,
) -> RunSummary:
    """
    Run every planned (family, variant, seed) as a Ray Tune trial; results in ``results_dir`` on this machine.

    :param experiment: the experiment
    :param budget_preset: ``smoke``, ``cpu`` or ``paper``
    :param seeds: model seeds (None: each variant's declared seeds)
    :param results_dir: root of the results layout (on the driver)
    :param jobs: runs at a time at most (None: as many as the cluster's resources fit)
    :param families: family names (None: all)
    :param variants: variant names (None: all)
    :param force: rerun runs that have a result.json (and start a fresh Tune experiment)
    :param address: the Ray cluster (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``); None: Ray's default
        (``RAY_ADDRESS``, a ``ray start`` cluster of this machine, else a local Ray). A Ray initialised by the caller is
        used as it is.
    :param cpus_per_run: CPUs Ray reserves per run
    :param gpus_per_run: GPUs per run (fractions share a GPU); 0: the run sees no GPU
    :param retries: times Tune retries a failed run
    :param storage_path: Tune's storage (default ``<results_dir>/.tune``): a path or URI every node reaches
    :param transfer: ``auto`` (shared folder if the trial sees it, else ship it back), ``shared`` or ``checkpoint``
    :param echo: where progress lines go
    :return: the runs done, skipped, failed and interrupted
    """
    _check_options(jobs, cpus_per_run, gpus_per_run, retries, transfer, address, storage_path)
    summary = RunSummary()
    results = Path(results_dir).resolve()
    runs = plan_runs(experiment, budget_preset, seeds, families, variants)
    pending = select_pending(runs, budget_preset, results, force, summary, echo)
    if not pending:
        echo(f"{experiment.name}: 0 run(s) to do, {len(summary.skipped)} skipped, budget {budget_preset}")
        return summary
    started_ray = init_ray(address)
    storage = str(results / TUNE_DIR) if storage_path is None else storage_path
    if "://" not in storage:
        storage = str(Path(storage).resolve())  # Tune wants an absolute path; a URI is taken as it is
    path = f"{storage.rstrip('/')}/{experiment_name(experiment, budget_preset, results, runs)}"
    try:
        slots = run_slots(cpus_per_run, gpus_per_run, jobs)
        results_id = ensure_results_id(results)
        echo(
            f"{experiment.name}: {len(pending)} run(s) to do, {len(summary.skipped)} skipped, budget {budget_preset}, "
            f"on Ray: {slots} at a time, {cpus_per_run:g} CPU / {gpus_per_run:g} GPU per run; Tune experiment {path}"
        )
        driver = _DRIVERS[path] = _Driver(results, list(pending), Progress(len(pending), slots, echo), echo, retries)
        trainable = tune.with_resources(run_trial, {"cpu": cpus_per_run, "gpu": gpus_per_run})
        todo = set(pending)
        with _quiet_tune():
            if not force and tune.Tuner.can_restore(path):  # the same runs were started before: continue that experiment
                echo(f"resuming the Ray Tune experiment {path}: what it did not finish (or failed) runs again")
                tuner = tune.Tuner.restore(path, trainable, resume_unfinished=True, restart_errored=True)
                expected = _read_plan(path)
                grid = tuner.fit()
                reported = _collect(grid, driver, summary)
                settled = set(summary.skipped) | set(summary.done) | set(summary.failed)
                if _unfinished(grid) or (expected is not None and not set(expected) <= settled | reported):
                    todo.clear()  # interrupted again (some runs have no trial yet): nothing more now
                todo -= settled  # the rest (e.g. a run whose result.json was deleted) runs in a fresh experiment
            if todo:
                _delete_experiment(path)
                configs = [
                    {
                        **key._asdict(),
                        "budget": budget_preset,
                        "results_dir": str(results),
                        "results_id": results_id,
                        "force": force,
                        "transfer": transfer,
                        "gpus": gpus_per_run,
                    }
                    for key in pending
                    if key in todo
                ]
                tuner = tune.Tuner(
                    trainable,
                    param_space={"run": tune.grid_search(configs)},
                    tune_config=tune.TuneConfig(
                        max_concurrent_trials=jobs, trial_name_creator=trial_name, trial_dirname_creator=trial_dirname
                    ),
                    run_config=tune.RunConfig(
                        name=path.rsplit("/", 1)[1],
                        storage_path=storage,
                        failure_config=tune.FailureConfig(max_failures=retries),
                        callbacks=[ProgressCallback(path)],
                        verbose=0,
                    ),
                )
                _write_plan(path, [key for key in pending if key in todo])
                _collect(tuner.fit(), driver, summary)
    finally:
        _DRIVERS.pop(path, None)
        if started_ray:
            ray.shutdown()
    settled = set(summary.done) | set(summary.failed)
    summary.interrupted = [key for key in pending if key not in settled]
    if summary.interrupted:
        echo(
            f"interrupted: {len(summary.interrupted)} run(s) not finished; run the same command again to resume "
            f"the Tune experiment {path}"
        )
    return summary


__all__ = [
    "TRANSFERS",
    "TUNE_DIR",
    "ProgressCallback",
    "ensure_results_id",
    "experiment_name",
    "init_ray",
    "run_experiment_ray",
    "run_slots",
]
