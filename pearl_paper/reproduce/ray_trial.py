"""The worker side of the ``ray`` backend: the Tune function trainable that runs one (family, variant, seed).

:func:`run_trial` calls the same single-run code as the local backend (:func:`~pearl_paper.reproduce.runner.run_one`),
with the run's stdout and stderr in its ``run.log``. It writes into the driver's results folder when it sees it (a
shared filesystem, recognised by the ``.sb3_pearl_results_id`` file the driver writes there); otherwise it runs in a
scratch folder and reports the run folder as a Tune checkpoint, which the driver copies with
:func:`copy_run_folder`. The driver side is :mod:`pearl_paper.reproduce.ray_backend`.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
import time
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ray import tune

from pearl_paper.reproduce.layout import LOG_FILE, MODEL_FILE, PROGRESS_FILE, RESULT_FILE, RunKey, discard_result, run_dir
from pearl_paper.reproduce.runner import existing_result, run_one
from pearl_paper.reproduce.scheduler import RUN_ENV

RESULTS_ID_FILE = ".sb3_pearl_results_id"
SHIPPED_FILES = (MODEL_FILE, PROGRESS_FILE, LOG_FILE)  # then RESULT_FILE, last


def run_key(run: dict[str, Any]) -> RunKey:
    """The :class:`RunKey` of a trial's ``config["run"]``."""
    return RunKey(run["experiment"], run["family"], run["variant"], int(run["seed"]))


def sees_results_dir(results_dir: str, results_id: str) -> bool:
    """
    Whether this machine sees the driver's results folder (a shared filesystem).

    :param results_dir: the driver's results folder (absolute)
    :param results_id: the content of its ``.sb3_pearl_results_id`` file
    :return: the file is here, with that content
    """
    try:
        return (Path(results_dir) / RESULTS_ID_FILE).read_text().strip() == results_id
    except OSError:
        return False


@contextlib.contextmanager
def _output_to(path: Path) -> Iterator[None]:
    """Send this process's stdout and stderr (file descriptors 1 and 2, hence C code too) to ``path``."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(path, "wb") as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def _run_logged(key: RunKey, budget_preset: str, root: Path) -> str | None:
    """
    :func:`~pearl_paper.reproduce.runner.run_one` with its output in the run folder's ``run.log``.

    :return: None on success, else a one-line reason (the traceback is in ``run.log``)
    """
    folder = run_dir(root, key)
    with _output_to(folder / LOG_FILE):
        try:
            run_one(key.experiment, key.family, key.variant, key.seed, budget_preset, root)
        except Exception as error:
            traceback.print_exc()
            return f"{type(error).__name__}: {error}"
    return None if (folder / RESULT_FILE).is_file() else f"no {RESULT_FILE} written"


def run_trial(config: dict[str, Any]) -> None:
    """
    The Tune function trainable: one (family, variant, seed) run, written where the driver finds it.

    ``config["run"]`` holds the run's key, ``budget``, ``results_dir`` (the driver's, absolute), ``results_id``,
    ``force``, ``transfer`` (``auto``, ``shared`` or ``checkpoint``) and ``gpus`` (per run).

    :param config: the trial's config
    :raises RuntimeError: the run failed (Tune retries it up to ``--retries`` times)
    """
    run = config["run"]
    key, budget_preset = run_key(run), run["budget"]
    os.environ.update(RUN_ENV)
    if not run["gpus"]:
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # device="auto" must not put a CPU run on a GPU of its node
    shared = run["transfer"] == "shared" or (
        run["transfer"] == "auto" and sees_results_dir(run["results_dir"], run["results_id"])
    )
    root = Path(run["results_dir"]) if shared else Path(tempfile.mkdtemp(prefix="sb3_pearl_run_"))
    folder = run_dir(root, key)
    started = time.time()
    try:
        if shared and not run["force"] and existing_result(folder, budget_preset) is not None:
            tune.report({"skipped": True, "shipped": False, "wall_s": 0.0})
            return
        folder.mkdir(parents=True, exist_ok=True)
        if run["force"]:
            discard_result(folder)  # result.json and the records of the model the rerun replaces
        failure = _run_logged(key, budget_preset, root)
        metrics = {"skipped": False, "shipped": not shared, "wall_s": time.time() - started, "failed": failure is not None}
        if shared:
            tune.report(metrics)
        else:  # the run folder goes back to the driver through Tune's storage (run.log alone if it failed)
            tune.report(metrics, checkpoint=tune.Checkpoint.from_directory(str(folder)))
        if failure is not None:
            where = folder / LOG_FILE if shared else f"{LOG_FILE} of the run folder"
            raise RuntimeError(f"{key.label()} failed: {failure} (traceback in {where})")
    finally:
        if not shared:
            shutil.rmtree(root, ignore_errors=True)


def trial_name(trial: Any) -> str:
    """Trial names in Tune's messages: ``<family>/<variant>/seed<N>``."""
    run = trial.config["run"]
    return f"{run['family']}/{run['variant']}/seed{run['seed']}"


def trial_dirname(trial: Any) -> str:
    """Trial folders under the Tune experiment: ``<family>_<variant>_seed<N>_<trial id>``."""
    run = trial.config["run"]
    return f"{run['family']}_{run['variant']}_seed{run['seed']}_{trial.trial_id}"


def copy_run_folder(source: Path, folder: Path) -> bool:
    """
    Copy a shipped run folder into the results layout: ``model.zip``, ``progress.csv``, ``run.log``, then
    ``result.json`` last and atomically (temporary file + ``os.replace``), as a run writes it.

    :param source: the checkpoint folder
    :param folder: the run folder on the driver
    :return: whether a ``result.json`` was copied
    """
    folder.mkdir(parents=True, exist_ok=True)
    for name in SHIPPED_FILES:
        if (source / name).is_file():
            shutil.copyfile(source / name, folder / name)
    if not (source / RESULT_FILE).is_file():
        return False
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{RESULT_FILE}.", suffix=".tmp")
    os.close(fd)
    try:
        shutil.copyfile(source / RESULT_FILE, tmp)
        os.replace(tmp, folder / RESULT_FILE)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return True


__all__ = [
    "RESULTS_ID_FILE",
    "SHIPPED_FILES",
    "copy_run_folder",
    "run_key",
    "run_trial",
    "sees_results_dir",
    "trial_dirname",
    "trial_name",
]
