"""The Ray backend of the reproduction harness (``run --backend ray``) against the local one, on a local Ray of 2 CPUs.

Same seeds, same numbers: a smoke run gives the same ``result.json`` with both backends (all of it but wall times,
load averages and versions). The Ray backend skips complete runs, resumes an interrupted experiment (``Tuner.restore``),
and ships run folders back through Tune checkpoints when the workers do not see the results folder.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ray = pytest.importorskip("ray", reason='Ray is not installed: pip install -e ".[ray]" (part of the dev extra)')

from pearl_paper.experiments import get_experiment  # noqa: E402
from pearl_paper.reproduce.cli import main  # noqa: E402
from pearl_paper.reproduce.layout import RESULT_FILE, RunKey, run_dir  # noqa: E402
from pearl_paper.reproduce.ray_backend import init_ray, run_experiment_ray  # noqa: E402
from pearl_paper.reproduce.scheduler import RAY_MISSING, run_experiment  # noqa: E402

EXPERIMENT = get_experiment("safe-point")
VARIANTS = ["alpha-0", "alpha-0.1"]
SELECTION: dict[str, Any] = dict(families=["safe-point"], variants=VARIANTS)
KEYS = [RunKey("safe-point", "safe-point", variant, 0) for variant in VARIANTS]
NOT_COMPARED = {"wall_time_s", "cpu", "versions"}  # timings, load averages, package versions


def comparable(result: dict[str, Any]) -> dict[str, Any]:
    """A result.json without what differs between two runs of the same code (at any depth)."""

    def strip(value: Any) -> Any:
        if isinstance(value, dict):
            return {key: strip(item) for key, item in value.items() if key not in NOT_COMPARED}
        if isinstance(value, list):
            return [strip(item) for item in value]
        return value

    return strip(result)


def read(results_dir: Path, key: RunKey) -> dict[str, Any]:
    return json.loads((run_dir(results_dir, key) / RESULT_FILE).read_text())


@pytest.fixture(scope="module")
def local_results(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """
    The two smoke runs with the local backend (child processes, 2 at a time), and a local Ray of 2 CPUs started by
    the test meanwhile (the Ray backend uses a Ray initialised by its caller as it is).
    """
    results_dir = tmp_path_factory.mktemp("local")
    summaries: list[Any] = []
    local = threading.Thread(
        target=lambda: summaries.append(
            run_experiment(EXPERIMENT, "smoke", [0], results_dir, jobs=2, **SELECTION, echo=lambda line: None)
        )
    )
    local.start()
    started = init_ray(num_cpus=2)
    local.join()
    assert summaries and sorted(summaries[0].done) == sorted(KEYS) and not summaries[0].failed
    yield results_dir
    if started:
        ray.shutdown()


def test_ray_matches_local_resumes_and_ships_run_folders(
    local_results: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # first call: interrupted (SIGUSR1, Tune's stop signal, as Ctrl-C) once the first run is complete
    first = run_dir(tmp_path, KEYS[0]) / RESULT_FILE

    def interrupt() -> None:
        deadline = time.time() + 600  # a smoke run takes seconds idle, minutes on a machine busy with experiments
        while not first.exists() and time.time() < deadline:
            time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGUSR1)

    thread = threading.Thread(target=interrupt, daemon=True)
    thread.start()
    summary = run_experiment_ray(EXPERIMENT, "smoke", [0], tmp_path, jobs=1, **SELECTION)
    thread.join()
    # the first run's folder is complete; whether the driver collected its trial before the stop signal
    # depends on timing (a loaded machine), so it is reported as done or as interrupted
    assert first.exists() and KEYS[1] in summary.interrupted and not summary.failed
    assert set(summary.done) <= set(KEYS[:1]) and set(summary.done) | set(summary.interrupted) == set(KEYS)
    assert "run the same command again to resume" in capsys.readouterr().out
    mtime = first.stat().st_mtime_ns

    # second call: the same command resumes the Tune experiment; the complete run is not run again
    summary = run_experiment_ray(EXPERIMENT, "smoke", [0], tmp_path, jobs=1, **SELECTION)
    out = capsys.readouterr().out
    assert summary.done == KEYS[1:] and summary.skipped == KEYS[:1] and not summary.interrupted
    assert "resuming the Ray Tune experiment" in out and "[1/1]" in out
    assert first.stat().st_mtime_ns == mtime

    # same seeds, same numbers
    for key in KEYS:
        ours, theirs = read(tmp_path, key), read(local_results, key)
        assert ours["meta_test"]["rows"] and ours["meta_test"]["rows"] == theirs["meta_test"]["rows"]
        assert ours["meta_test"]["summary"] == theirs["meta_test"]["summary"]
        assert comparable(ours) == comparable(theirs)
        assert {"model.zip", "progress.csv", "run.log"} <= {p.name for p in run_dir(tmp_path, key).iterdir()}
        assert "done in" in (run_dir(tmp_path, key) / "run.log").read_text()

    # results/ is the truth: a run whose result.json is gone runs again, though Tune finished its trial; this time the
    # trial ships its run folder back as a Tune checkpoint (what it does when it does not see the results folder)
    folder = run_dir(tmp_path, KEYS[1])
    for path in folder.iterdir():
        path.unlink()
    summary = run_experiment_ray(
        EXPERIMENT, "smoke", [0], tmp_path, jobs=1, transfer="checkpoint", echo=lambda line: None, **SELECTION
    )
    assert summary.done == KEYS[1:] and summary.skipped == KEYS[:1] and first.stat().st_mtime_ns == mtime
    assert {"model.zip", "progress.csv", "run.log", "result.json"} == {p.name for p in folder.iterdir()}
    assert comparable(read(tmp_path, KEYS[1])) == comparable(read(local_results, KEYS[1]))


def test_ray_skips_complete_runs_of_either_backend(local_results: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mtimes = [(run_dir(local_results, key) / RESULT_FILE).stat().st_mtime_ns for key in KEYS]
    args = ["run", "safe-point", "--budget", "smoke", "--seeds", "0", "--family", "safe-point", "--variants", *VARIANTS]
    assert main([*args, "--results-dir", str(local_results), "--backend", "ray"]) == 0
    out = capsys.readouterr().out
    assert out.count("skip ") == 2 and "0 done, 2 skipped, 0 failed" in out
    assert [(run_dir(local_results, key) / RESULT_FILE).stat().st_mtime_ns for key in KEYS] == mtimes
    assert not (local_results / ".tune").exists()  # nothing to do: no Tune experiment


def test_ray_options_are_checked_before_anything_starts(
    local_results: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["run", "safe-point", "--budget", "smoke", "--seeds", "0", "--results-dir", str(tmp_path)]
    assert main([*args, "--gpus-per-run", "1"]) == 2
    assert "--gpus-per-run only apply to --backend ray" in capsys.readouterr().err
    assert main([*args, "--backend", "ray", "--gpus-per-run", "1"]) == 2  # the local Ray has no GPU
    assert "no node of the Ray cluster has 1 CPU(s) and 1 GPU(s)" in capsys.readouterr().err
    assert main([*args, "--backend", "ray", "--address", "ray://head:10001"]) == 2
    assert "give --storage-path" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "ray", None)  # Ray not installed
    monkeypatch.delitem(sys.modules, "pearl_paper.reproduce.ray_backend")
    monkeypatch.delitem(sys.modules, "pearl_paper.reproduce.ray_trial")
    assert main([*args, "--backend", "ray"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"error: {RAY_MISSING}" and 'pip install -e ".[ray]"' in err
    assert not any(tmp_path.iterdir())  # nothing started, nothing written
