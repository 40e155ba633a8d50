"""Harness runs that survive interruption: a run killed inside an iteration or inside its meta-test, then run again,
writes the result.json metrics of an uninterrupted run, bit for bit (pearl_paper/reproduce/checkpoint.py)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from pearl_paper.reproduce import checkpoint
from pearl_paper.reproduce.cells import load_partway_curves
from pearl_paper.reproduce.checkpoint import CHECKPOINT_DIR, RunCheckpoint
from pearl_paper.reproduce.cli import main
from pearl_paper.reproduce.cli import main as reproduce_main
from pearl_paper.reproduce.curve import CURVE_FILE, read_curve
from pearl_paper.reproduce.layout import RESULT_FILE
from pearl_paper.reproduce.report import build_report
from pearl_paper.reproduce.runner import RunStopped, run_one
from sb3_pearl import PEARLPlus
from sb3_pearl.budgets import load_budget
from sb3_pearl.common.callbacks import StopOnSignalCallback
from tests.conftest import write_model_zip

RUN = ("safe-point", "safe-point", "alpha-0.1", 0, "smoke")
FOLDER = Path("safe-point", "safe-point", "alpha-0.1", "seed0")
METRICS = ("num_timesteps", "meta_test", "shift", "competence", "prior_critic", "diagnostics")


class Killed(Exception):
    """Stands in for SIGKILL: nothing after the raise runs, only what is on disk survives."""


def _kill_at(where: str, count: int) -> Any:
    def hook(point: str, n: int) -> None:
        if point == where and n == count:
            raise Killed(f"{where} {count}")

    return hook


def _metrics(result: dict[str, Any]) -> dict[str, Any]:
    def strip(value: Any) -> Any:  # wall times differ between runs, nothing else may
        if isinstance(value, dict):
            return {k: strip(v) for k, v in value.items() if k != "wall_time_s"}
        if isinstance(value, list):
            return [strip(v) for v in value]
        return value

    return strip({key: result[key] for key in METRICS})


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return run_one(*RUN, tmp_path_factory.mktemp("whole"), verbose=0)


@pytest.mark.parametrize(
    "where, count, phase",
    [
        ("step", 300, "train"),  # inside iteration 3 (steps 240-360): resumes from the checkpoint at its start (240)
        ("meta_test", 7, "evaluate"),  # inside the held-out meta-test: training done, the meta-test runs again
    ],
)
def test_an_interrupted_run_resumes_to_the_same_metrics(
    where: str, count: int, phase: str, uninterrupted: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(Killed):
        run_one(*RUN, tmp_path, verbose=0, checkpoint_interval_s=0.0, interrupt=_kill_at(where, count))
    folder = tmp_path / FOLDER
    assert not (folder / RESULT_FILE).exists()
    state = RunCheckpoint(folder).read_state()
    assert state is not None and state["phase"] == phase
    if phase == "train":
        assert state["num_timesteps"] == 240 and state["spent"]["cpu_s"] > 0
    else:
        assert state["num_timesteps"] == 400 and "meta_test" not in state["phases"]
    # `reproduce status` sees the resumable run, with its progress and the CPU time spent.
    assert main(["status", "safe-point", "--budget", "smoke", "--seeds", "0", "--family", "safe-point", "--variants",
                 "alpha-0.1", "--results-dir", str(tmp_path)]) == 0  # fmt: skip
    out = capsys.readouterr().out
    progress = "train 240/400 steps (60%), training only" if phase == "train" else "evaluate ("
    assert "safe-point safe-point alpha-0.1 seed0" in out and "resumable" in out and progress in out, out
    assert "0 finished, 1 resumable, 0 missing" in out
    if phase == "train":  # no finished sibling: the training's own rate still gives an estimate
        assert "unknown" not in out
        assert main(["status", "safe-point", "--budget", "smoke", "--seeds", "0,1", "--family", "safe-point", "--variants",
                     "alpha-0.1", "--results-dir", str(tmp_path)]) == 0  # fmt: skip
        missing = capsys.readouterr().out  # seed 1 at seed 0's rate: the 400 steps of training
        assert "alpha-0.1 seed1" in missing and "- (training only)" in missing and "unknown" not in missing, missing
    resumed = run_one(*RUN, tmp_path, verbose=0)
    assert _metrics(resumed) == _metrics(uninterrupted)
    assert json.loads((folder / RESULT_FILE).read_text())["meta_test"]["summary"] == uninterrupted["meta_test"]["summary"]
    assert not (folder / CHECKPOINT_DIR).exists()  # removed once result.json is written
    header = (folder / "progress.csv").read_text().splitlines()[0]
    assert "time/total_timesteps" in header  # the training log was continued, not restarted empty


def test_a_checkpoint_file_over_the_part_size_is_split_and_resumes_the_same(
    uninterrupted: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(checkpoint, "PART_BYTES", 4_000)  # as a cheetah-vel buffer over 50 MB, at the smoke preset's size
    with pytest.raises(Killed):
        run_one(*RUN, tmp_path, verbose=0, checkpoint_interval_s=0.0, interrupt=_kill_at("step", 300))
    folder = tmp_path / FOLDER / CHECKPOINT_DIR
    state = RunCheckpoint(folder.parent).read_state()
    assert state is not None and state["num_timesteps"] == 240
    parts = {key: name for key, name in state["files"].items() if key.startswith("replay.part")}
    assert "replay" not in state["files"] and len(parts) >= 2, state["files"]
    assert not (folder / "replay_240.pkl").exists()  # only the parts stay on disk
    assert all((folder / name).stat().st_size <= 4_000 for name in parts.values())
    assert (folder / state["files"]["model"]).is_file()  # the model stays whole: only the buffer grows with the run
    resumed = run_one(*RUN, tmp_path, verbose=0)
    assert _metrics(resumed) == _metrics(uninterrupted)


def test_status_projects_a_run_at_the_rate_between_its_last_two_checkpoints(tmp_path: Path) -> None:
    """A run whose first steps were cheap (PEARL's initial pool) is projected at its current rate, not its average."""
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.status import format_status, run_status

    folder = tmp_path / FOLDER / CHECKPOINT_DIR
    folder.mkdir(parents=True)
    write_model_zip(folder / "model_240.zip")
    state = {"phase": "train", "files": {"model": "model_240.zip"}, "num_timesteps": 240, "phases": {},
             "spent": {"cpu_s": 24.0, "wall_s": 30.0}}  # fmt: skip
    experiment = get_experiment("safe-point")

    def left(recent: dict[str, float] | None) -> list[float]:
        RunCheckpoint(folder.parent).write_state({**state, "recent": recent} if recent else state)
        rows = run_status(experiment, "smoke", [0, 1], tmp_path, ["safe-point"], ["alpha-0.1"])
        assert [row.status for row in rows] == ["resumable", "missing"] and all(row.training_only for row in rows)
        return [row.cpu_left_s for row in rows]

    # 400 steps at the smoke preset: 160 left. Average 0.1 s a step; the last 120 steps at 0.25 s a step.
    assert left(None) == pytest.approx([16.0, 40.0])  # a state of an earlier version: the average
    assert left({"cpu_s": 30.0, "steps": 120}) == pytest.approx([40.0, 24.0 + 40.0])  # seed 1: seed 0's projected total

    # the checkpoint's size: the files its state names and the state, not leftovers (a kill's temporary file)
    write_model_zip(folder / "model_240.zip", size=1_500_000)
    (folder / ".model_360.zip.tmp").write_bytes(b"t" * 9_000_000)
    rows = run_status(experiment, "smoke", [0, 1], tmp_path, ["safe-point"], ["alpha-0.1"])
    size = 1_500_000 + (folder / "state.json").stat().st_size
    assert [row.checkpoint_bytes for row in rows] == [size, 0]
    text = format_status(rows)
    assert f"{size / 1e6:.1f} MB" in text and "1 checkpoint(s)" in text and "commit part-way runs once per session" in text


def test_a_resumed_run_records_the_rate_between_its_checkpoints(tmp_path: Path) -> None:
    with pytest.raises(Killed):
        run_one(*RUN, tmp_path, verbose=0, checkpoint_interval_s=0.0, interrupt=_kill_at("step", 300))
    first = RunCheckpoint(tmp_path / FOLDER).read_state()
    assert first is not None and first["recent"]["steps"] == 120  # checkpoints every iteration: 120 and 240 steps
    assert 0 < first["recent"]["cpu_s"] < first["spent"]["cpu_s"]
    with pytest.raises(Killed):  # resumed at 240 (no checkpoint rewritten there), killed after the one at 360
        run_one(*RUN, tmp_path, verbose=0, checkpoint_interval_s=0.0, interrupt=_kill_at("step", 390))
    second = RunCheckpoint(tmp_path / FOLDER).read_state()
    assert second is not None and second["num_timesteps"] == 360 and second["recent"]["steps"] == 120
    spent_after_resume = second["spent"]["cpu_s"] - first["spent"]["cpu_s"]
    assert second["recent"]["cpu_s"] == pytest.approx(spent_after_resume)  # the resumed segment: 240 -> 360


def test_a_checkpoint_of_other_settings_is_refused(tmp_path: Path) -> None:
    with pytest.raises(Killed):
        run_one(*RUN, tmp_path, verbose=0, checkpoint_interval_s=0.0, interrupt=_kill_at("step", 150))
    checkpoint = RunCheckpoint(tmp_path / FOLDER)
    state = checkpoint.read_state()
    assert state is not None and state["num_timesteps"] == 120
    state["identity"]["n_timesteps"] = 12345  # as if the preset had changed since
    checkpoint.write_state(state)
    with pytest.raises(ValueError, match="written by a run with other settings.*--force"):
        run_one(*RUN, tmp_path, verbose=0)


CURVE = {"every": 120, "n_tasks": 2, "n_adapt": 2, "n_prior_trajectories": 2}


@pytest.fixture
def with_curve(monkeypatch: pytest.MonkeyPatch) -> None:
    """The smoke budget with a learning curve every 120 steps (the reference's protocol: 2 prior trajectories)."""
    import pearl_paper.reproduce.runner as runner

    def load(*args: Any) -> dict[str, Any]:
        return {**load_budget(*args), "curve": dict(CURVE)}

    monkeypatch.setattr(runner, "load_budget", load)


def test_a_learning_curve_changes_nothing_else_and_resumes(
    with_curve: None, uninterrupted: dict[str, Any], tmp_path: Path
) -> None:
    whole = run_one(*RUN, tmp_path / "whole", verbose=0)
    assert _metrics(whole) == _metrics(uninterrupted)  # the evaluations do not perturb training
    rows = read_curve(tmp_path / "whole" / FOLDER / CURVE_FILE)
    assert [row["env_steps"] for row in rows] == [120, 240, 360, 400]  # every 120 steps at iteration starts, and the end
    for row in rows:
        assert row["n_tasks"] == 2 and 0.0 <= row["k0_violation"] <= 1.0 and row["reference_return"] < 0
    with pytest.raises(Killed):  # killed inside iteration 3, after the points at 120 and 240
        run_one(*RUN, tmp_path / "cut", verbose=0, checkpoint_interval_s=0.0, interrupt=_kill_at("step", 300))
    # The run in progress: the report draws and lists its curve so far.
    partway = load_partway_curves(tmp_path / "cut")
    assert list(partway) == [("safe-point", "smoke", "safe-point")]
    run = partway[("safe-point", "smoke", "safe-point")]["alpha-0.1"][0]
    assert [row["env_steps"] for row in run["curve"]] == [120, 240] and run["num_timesteps"] == 240
    (tmp_path / "figures").mkdir()
    report = str(build_report(tmp_path / "cut", tmp_path / "figures", "figures"))
    assert "safe-point, runs in progress (budget `smoke`)" in report, report
    assert "| PEARL+ (alpha 0.1) | 0 | 240 |" in report and "curves_partway.png" in report
    assert (tmp_path / "figures" / "reproduce_safe-point_safe-point_smoke_curves_partway.png").is_file()
    run_one(*RUN, tmp_path / "cut", verbose=0)
    assert load_partway_curves(tmp_path / "cut") == {}  # finished: its curve is in result.json now
    resumed = read_curve(tmp_path / "cut" / FOLDER / CURVE_FILE)
    assert _without_wall_time(resumed) == _without_wall_time(rows)
    assert {row["competent"] for row in rows} <= {0.0, 1.0}  # the family's competence check at every point


def test_a_run_stopped_by_signal_adds_no_curve_point_at_its_stop(with_curve: None, tmp_path: Path) -> None:
    """Guards against: a PEARL run stopped at an env step returned from learn() normally, and the curve's end point
    was measured there (300: off the 120-step grid, on a model inside its iteration), then kept by the resumed run."""
    run_one(*RUN, tmp_path / "whole", verbose=0)
    whole = read_curve(tmp_path / "whole" / FOLDER / CURVE_FILE)
    stop = StopOnSignalCallback()

    def ask(point: str, n: int) -> None:  # the signal handler's request, at env step 300 (inside iteration 3)
        stop.requested = stop.requested or (point == "step" and n == 300)

    with pytest.raises(RunStopped, match=r"at 300 env steps"):
        run_one(*RUN, tmp_path / "cut", verbose=0, interrupt=ask, stop=stop)
    assert [row["env_steps"] for row in read_curve(tmp_path / "cut" / FOLDER / CURVE_FILE)] == [120, 240]
    run_one(*RUN, tmp_path / "cut", verbose=0)
    resumed = read_curve(tmp_path / "cut" / FOLDER / CURVE_FILE)
    assert [row["env_steps"] for row in resumed] == [120, 240, 360, 400]
    assert _without_wall_time(resumed) == _without_wall_time(whole)


def test_a_stop_asked_after_the_last_stop_point_stops_before_the_evaluations(
    with_curve: None, uninterrupted: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Guards against: a SIGTERM during the curve's end point (training over, no stop point left) was heard and then
    ignored: the child went on into the evaluations until the parent killed it."""
    from pearl_paper.reproduce import curve as curve_module

    stop = StopOnSignalCallback()
    end_point = curve_module.LearningCurve._on_training_end

    def asked_during(self: Any) -> None:
        stop.requested = True
        end_point(self)

    monkeypatch.setattr(curve_module.LearningCurve, "_on_training_end", asked_during)
    with pytest.raises(RunStopped, match=r"^at the end of training \(400 env steps\), before the evaluations$"):
        run_one(*RUN, tmp_path, verbose=0, stop=stop)
    state = RunCheckpoint(tmp_path / FOLDER).read_state()
    assert state is not None and state["phase"] == "evaluate" and not (tmp_path / FOLDER / RESULT_FILE).exists()
    monkeypatch.setattr(curve_module.LearningCurve, "_on_training_end", end_point)
    assert _metrics(run_one(*RUN, tmp_path, verbose=0)) == _metrics(uninterrupted)


def test_a_checkpoint_whose_model_is_missing_is_refused_not_restarted(tmp_path: Path) -> None:
    """Guards against: a state.json naming a missing model zip read as 'no checkpoint', and the run restarted from zero
    over its progress.csv and buffer (a manual copy of the checkpoint that forgot the zip)."""
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.status import run_status

    with pytest.raises(Killed):
        run_one(*RUN, tmp_path, verbose=0, checkpoint_interval_s=0.0, interrupt=_kill_at("step", 300))
    folder = tmp_path / FOLDER
    checkpoint = RunCheckpoint(folder)
    state = checkpoint.read_state()
    assert state is not None
    model = checkpoint.folder / state["files"]["model"]
    model.unlink()
    progress = (folder / "progress.csv").read_bytes()
    assert checkpoint.damage(state) == f"checkpoint damaged: {model} is missing"
    with pytest.raises(ValueError, match=r"checkpoint damaged: .* is missing: delete .*--force"):
        run_one(*RUN, tmp_path, verbose=0)
    assert (folder / "progress.csv").read_bytes() == progress and checkpoint.read_state() == state  # nothing touched
    (row,) = run_status(get_experiment("safe-point"), "smoke", [0], tmp_path, ["safe-point"], ["alpha-0.1"])
    assert row.status == "damaged" and row.progress == f"checkpoint damaged: {model} is missing"


def _without_wall_time(rows: list[dict[str, float]]) -> list[dict[str, float | None]]:
    return [{k: None if math.isnan(v) else v for k, v in row.items() if k != "wall_s"} for row in rows]


@pytest.mark.parametrize("snapshot_text", ["", "\x00\x00\x00", "a,b\n1,2,3\n"])
def test_an_empty_progress_snapshot_keeps_the_runs_progress_csv(tmp_path: Path, snapshot_text: str) -> None:
    """A progress snapshot that is empty or cannot be parsed is not restored over the run's progress.csv (which the
    resume would empty): the log is kept, with a warning naming the snapshot, and continues."""
    log = "time/total_timesteps,train/n_updates\n120,5\n240,10\n"
    (tmp_path / "progress.csv").write_text(log)
    snapshot = tmp_path / "progress_240.csv"
    snapshot.write_text(snapshot_text)
    with pytest.warns(UserWarning, match=r"progress_240.csv .*not restored: .*progress.csv kept"):
        logger = checkpoint.csv_logger_continuing(tmp_path, snapshot)
    logger.record("time/total_timesteps", 360)
    logger.record("train/n_updates", 15)
    logger.dump(360)
    logger.close()
    assert (tmp_path / "progress.csv").read_text() == log + "360,15\n"


ROOT = Path(__file__).resolve().parent.parent


# ----------------------------------------------------------------------------------------------
# reproduce status: a checkpoint whose model zip is cut is damaged, not resumable
# ----------------------------------------------------------------------------------------------
def test_status_calls_a_checkpoint_with_a_truncated_model_damaged(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Guards against: 'resumable', and the resume failed with advice for train.py users (load best_model.zip ...)."""
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.cli import resume_promise
    from pearl_paper.reproduce.status import run_status

    folder = tmp_path / "safe-point" / "safe-point" / "alpha-0.1" / "seed0"
    checkpoint = RunCheckpoint(folder)
    checkpoint.folder.mkdir(parents=True)
    model = checkpoint.folder / "model_240.zip"
    write_model_zip(model, size=5000)
    state = {"phase": "train", "files": {"model": model.name}, "num_timesteps": 240, "phases": {},
             "spent": {"cpu_s": 24.0, "wall_s": 30.0}}  # fmt: skip
    checkpoint.write_state(state)
    experiment = get_experiment("safe-point")
    assert [row.status for row in run_status(experiment, "smoke", [0], tmp_path, ["safe-point"], ["alpha-0.1"])] == [
        "resumable"
    ]
    model.write_bytes(model.read_bytes()[:2500])  # a copy or a save cut short
    (row,) = run_status(experiment, "smoke", [0], tmp_path, ["safe-point"], ["alpha-0.1"])
    assert row.status == "damaged" and row.progress.startswith(f"checkpoint damaged: {model} is not a readable zip (")
    args = ["safe-point", "--budget", "smoke", "--seeds", "0", "--family", "safe-point", "--variants", "alpha-0.1"]
    assert reproduce_main(["status", *args, "--results-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "1 run(s) with a damaged checkpoint (named in the progress column): delete the run's checkpoint/ folder" in out
    assert "0 finished, 0 resumable, 0 missing" in out
    assert reproduce_main(["run", *args, "--results-dir", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"seed0: stops at its resume, checkpoint damaged: {model} is not a readable zip (" in out
    assert "1 would stop at a damaged checkpoint" in out
    assert resume_promise(folder).startswith(f"checkpoint damaged: {model} is not a readable zip (")
    with pytest.raises(ValueError, match=r"checkpoint damaged: .* is not a readable zip .*: delete .*checkpoint, or rerun"):
        checkpoint.load_model(state, PEARLPlus, None)
    write_model_zip(model)  # a buffer the state names but that is empty
    checkpoint.write_state({**state, "files": {"model": model.name, "replay": "replay_240.pkl"}})
    (checkpoint.folder / "replay_240.pkl").write_bytes(b"")
    (row,) = run_status(experiment, "smoke", [0], tmp_path, ["safe-point"], ["alpha-0.1"])
    assert row.status == "damaged" and row.progress == f"checkpoint damaged: {checkpoint.folder / 'replay_240.pkl'} is empty"


# ----------------------------------------------------------------------------------------------
# SIGTERM to a `reproduce run` child mid-training: it stops at the next gradient step or env step, saves a checkpoint
# there, and the parent reports the run interrupted (resumable), not failed
# ----------------------------------------------------------------------------------------------
class StopAtGradientStep(StopOnSignalCallback):
    """The child's stop callback, asked to stop at its ``at``-th gradient step (as the signal handler would)."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at, self.seen = at, 0

    def on_gradient_step(self) -> bool:
        self.seen += 1
        self.requested = self.requested or self.seen == self.at
        return super().on_gradient_step()


@pytest.fixture(scope="module")
def uninterrupted_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return run_one(*RUN, tmp_path_factory.mktemp("whole"), verbose=0)


@pytest.mark.parametrize("where", ["env step", "gradient step"])
def test_a_stopped_harness_run_saves_a_checkpoint_there_and_resumes_to_the_same_metrics(
    where: str, uninterrupted_run: dict[str, Any], tmp_path: Path
) -> None:
    """Guards against: the child raised KeyboardInterrupt wherever it was and kept only its last periodic checkpoint (none in
    the first 10 minutes). The periodic checkpoints here are 10 minutes apart: the stop's is the only one."""
    if where == "env step":
        stop = StopOnSignalCallback()

        def ask(point: str, n: int) -> None:  # the signal handler's request, at env step 300 (inside an iteration)
            stop.requested = stop.requested or (point == "step" and n == 300)

        with pytest.raises(RunStopped, match=r"at 300 env steps"):
            run_one(*RUN, tmp_path, verbose=0, interrupt=ask, stop=stop)
    else:
        stop = StopAtGradientStep(7)  # events come between two steps of an iteration: the 7th after its 8th step
        with pytest.raises(RunStopped, match=r"^at 240 env steps and 8 gradient steps$"):
            run_one(*RUN, tmp_path, verbose=0, stop=stop)
    state = RunCheckpoint(tmp_path / FOLDER).read_state()
    assert state is not None and state["phase"] == "train" and 0 < state["num_timesteps"] < 400
    assert state["files"]["model"].startswith(f"model_{state['num_timesteps']}_u")  # the env steps and gradient steps
    resumed = run_one(*RUN, tmp_path, verbose=0)
    assert _metrics(resumed) == _metrics(uninterrupted_run)


def test_sigterm_to_a_harness_child_saves_a_checkpoint_and_the_parent_says_interrupted(tmp_path: Path) -> None:
    """Guards against: the child stopped at once (no checkpoint in its first 10 minutes) and the parent said FAILED
    (exit 130)."""
    from pearl_paper.reproduce.ownership import lock_holder

    folder = tmp_path / FOLDER
    command = [sys.executable, "-m", "pearl_paper.reproduce", "run", "safe-point", "--budget", "cpu", "--seeds", "0"]
    command += ["--family", "safe-point", "--variants", "alpha-0.1", "--results-dir", str(tmp_path)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    parent = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.time() + 120
        while "] learn " not in ((folder / "run.log").read_text() if (folder / "run.log").is_file() else ""):
            assert parent.poll() is None and time.time() < deadline, "the child did not start training"
            time.sleep(0.1)
        time.sleep(1.0)  # inside the training (90,000 steps at the cpu preset)
        child = lock_holder(folder)
        assert child is not None
        os.kill(child, signal.SIGTERM)
        out, _ = parent.communicate(timeout=120)
    finally:
        if parent.poll() is None:
            parent.kill()
    log = (folder / "run.log").read_text()
    state = RunCheckpoint(folder).read_state()
    assert state is not None and state["phase"] == "train" and state["num_timesteps"] > 0, log[-2000:]
    steps = f"{state['num_timesteps']:,}"
    assert f"run-one: stopped by SIGTERM at {steps} env steps and " in log, log[-2000:]
    assert parent.returncode == 130, out
    assert (
        f"safe-point safe-point alpha-0.1 seed0: interrupted (exit 143); the same `reproduce run` command resumes this "
        f"run from its checkpoint at {steps} env steps in " in out
    ), out
    assert "0 done, 0 skipped, 0 failed, 1 interrupted" in out and "FAILED" not in out
