"""Reliability, third round, the last weak cases (docs/reliability.md, "Third round"): each answers in one line that names
the flag or file and the fix. Every test here failed before its fix."""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import gymnasium as gym
import numpy as np
import pytest

from pearl_paper.reproduce.checkpoint import RunCheckpoint
from pearl_paper.reproduce.cli import main as reproduce_main
from pearl_paper.reproduce.runner import RunStopped, run_one
from sb3_pearl import PEARLPlus
from sb3_pearl.common import atomic, persistence
from sb3_pearl.common.callbacks import StopOnSignalCallback
from sb3_pearl.diagnose import main as diagnose_main
from sb3_pearl.zoo import MetaExperimentManager, enjoy, train
from sb3_pearl.zoo.usage import program_name
from tests.conftest import TINY_ZOO_PARAMS, run_in_process, write_model_zip
from tests.test_reproduce_resume import FOLDER, RUN, _metrics

ENV_ID = "SafePointGoalMeta-v0"
ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def point_goal_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A PointGoal model: the same spaces and task keys as SafePointGoal, another family."""
    path = tmp_path_factory.mktemp("point_goal") / "model.zip"
    PEARLPlus("MlpPolicy", "PointGoalMeta-v0", n_train_tasks=2, n_test_tasks=1, seed=0).save(path)
    return path


# ----------------------------------------------------------------------------------------------
# A model of another task family: the message names the env id to pass
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("flag", ["-i", "--resume"])
def test_train_py_with_a_model_of_another_family_names_the_env_to_pass(
    tmp_path: Path, point_goal_model: Path, flag: str
) -> None:
    """Before: the constructor's advice ('give it an env of that family'), which a train.py user cannot follow."""
    extra = ["--resume-without-buffer"] if flag == "--resume" else []
    proc = run_in_process(
        train,
        *("--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "logs"), "-n", "200", flag, str(point_goal_model)),
        *extra,
        *("-params", *TINY_ZOO_PARAMS),
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert f"{flag} {point_goal_model} was not trained on {ENV_ID}: the model was trained on PointGoalMetaEnv tasks" in line
    assert line.endswith("; pass --env PointGoalMeta-v0"), line
    assert not list((tmp_path / "logs" / "pearlplus").iterdir())  # refused before anything was trained or kept


def test_diagnose_with_a_model_of_another_family_names_the_env_id_to_pass(
    point_goal_model: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: the constructor's ValueError as a traceback."""
    with pytest.raises(SystemExit) as exit_info:
        diagnose_main([str(point_goal_model), "--env-id", ENV_ID, "--n-tasks", "1"])
    assert exit_info.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"{point_goal_model} was not trained on {ENV_ID}: the model was trained on PointGoalMetaEnv tasks" in line
    assert line.endswith("; pass --env-id PointGoalMeta-v0"), line


def test_the_libraries_family_error_names_the_families_env_id(point_goal_model: Path) -> None:
    with pytest.raises(ValueError, match=r"give it an env of that family: PointGoalMeta-v0$"):
        PEARLPlus.load(point_goal_model, env=gym.make(ENV_ID))


# ----------------------------------------------------------------------------------------------
# An output folder that os.access calls writable (root) but that cannot be written: tried, not asked
# ----------------------------------------------------------------------------------------------
def _read_only_for_root(monkeypatch: pytest.MonkeyPatch, folder: Path) -> None:
    """``folder`` as root sees a read-only mount: ``os.access`` says writable, creating anything in it fails."""
    real_mkdir = os.mkdir

    def mkdir(path: str | os.PathLike[str], *args: int, **kwargs: int) -> None:
        if Path(path).parent == folder:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", mkdir)
    assert os.access(folder, os.W_OK | os.X_OK)


def test_train_py_log_folder_that_root_cannot_write_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: accepted, then a PermissionError / OSError traceback from os.makedirs."""
    locked = tmp_path / "mount"
    locked.mkdir()
    _read_only_for_root(monkeypatch, locked)
    refused = run_in_process(
        train, "--algo", "pearlplus", "--env", ENV_ID, "-f", str(locked / "logs"), "-n", "60", check=False
    )
    lines = [line for line in refused.stderr.strip().splitlines() if line.strip()]
    assert refused.returncode == 2 and len(lines) == 1, lines
    assert f"-f {locked / 'logs'}: {locked} is not writable (Read-only file system)" in lines[0], lines
    assert list(locked.iterdir()) == []


def test_results_dir_that_root_cannot_write_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    locked = tmp_path / "mount"
    locked.mkdir()
    _read_only_for_root(monkeypatch, locked)
    argv = ["run", "safe-point", "--budget", "smoke", "--seeds", "0", "--results-dir", str(locked / "results")]
    assert reproduce_main(argv) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [
        f"error: --results-dir {locked / 'results'}: {locked} is not writable (Read-only file system)"
    ]
    assert list(locked.iterdir()) == []


@pytest.mark.skipif(
    not os.path.isdir("/sys") or os.access("/sys", os.W_OK) is False, reason="needs /sys, writable per os.access"
)
def test_a_log_folder_under_sys_is_one_line(tmp_path: Path) -> None:
    """The real case: root's os.access says /sys is writable; creating a folder there fails (EPERM or EROFS)."""
    target = f"/sys/sb3-pearl-logs-{os.getpid()}"
    refused = run_in_process(train, "--algo", "pearlplus", "--env", ENV_ID, "-f", target, "-n", "60", check=False)
    lines = [line for line in refused.stderr.strip().splitlines() if line.strip()]
    assert refused.returncode == 2 and len(lines) == 1 and f"-f {target}: /sys is not writable (" in lines[0], lines


# ----------------------------------------------------------------------------------------------
# SIGTERM during train.py's set-up: no half-made run folder; enjoy's latest run is the latest with a model
# ----------------------------------------------------------------------------------------------
def test_sigterm_during_the_set_up_leaves_no_run_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: the process died at once (no handler before training), leaving <algo>/<env>_<n>/ without a model."""

    def signalled(manager: MetaExperimentManager, model: object) -> None:  # after the folder is reserved, before learn
        if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, before):  # the signal would kill pytest here
            raise AssertionError("no SIGTERM handler during the set-up: the process dies and leaves its run folder")
        os.kill(os.getpid(), signal.SIGTERM)

    logs, before = tmp_path / "logs", signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(MetaExperimentManager, "_check_held_out_tasks", signalled)
    proc = run_in_process(train, "--algo", "pearlplus", "--env", ENV_ID, "-f", str(logs), "-n", "200", check=False)
    assert proc.returncode == 128 + signal.SIGTERM, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "Stopped by SIGTERM before training: nothing trained or saved, no run folder kept" in proc.stdout
    assert list((logs / "pearlplus").iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is before  # the previous handler is back


def test_enjoy_skips_a_newer_run_folder_without_a_model(tmp_path: Path) -> None:
    """A run killed before its first save (SIGKILL: nothing can clean up) left <env>_2 without a model; <env>_1 has one.
    Before: 'No model found ... <env>_2/<env>.zip'."""
    runs = tmp_path / "pearlplus"
    PEARLPlus("MlpPolicy", ENV_ID, n_train_tasks=2, n_test_tasks=1, seed=0).save(runs / f"{ENV_ID}_1" / f"{ENV_ID}.zip")
    (runs / f"{ENV_ID}_2" / ENV_ID).mkdir(parents=True)
    args = ("--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path), "--no-render", "--n-tasks", "1", "--n-adapt", "0")
    proc = run_in_process(enjoy, *args)
    assert (
        f"Loading the latest run with a model, {runs / f'{ENV_ID}_1'}: {ENV_ID}_2 holds none (a run stopped before its "
        "first save; --exp-id chooses)" in proc.stdout
    )
    refused = run_in_process(enjoy, *args, "--exp-id", "2", check=False)  # an explicit choice is kept
    assert refused.returncode == 2 and f"No model found for pearlplus on {ENV_ID}" in refused.stderr


# ----------------------------------------------------------------------------------------------
# An empty checkpoint replay buffer: the advice works, --resume-without-buffer goes on
# ----------------------------------------------------------------------------------------------
def test_resume_with_an_empty_checkpoint_buffer_names_it_and_the_flag_works(tmp_path: Path) -> None:
    """Before: '... not a complete replay buffer pickle ...; train without it', also with --resume-without-buffer."""
    logs = tmp_path / "logs"
    base = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(logs), "--seed", "1", "--eval-freq", "1000"]
    run_in_process(train, *base, "-n", "300", "--save-freq", "100", "-params", *TINY_ZOO_PARAMS)
    run = logs / "pearlplus" / f"{ENV_ID}_1"
    checkpoint, buffer = run / "rl_model_120_steps.zip", run / "rl_model_replay_buffer_120_steps.pkl"
    buffer.write_bytes(b"")
    resume = [*base, "-n", "300", "--resume", str(checkpoint)]
    refused = run_in_process(train, *resume, "-params", *TINY_ZOO_PARAMS, check=False)
    problem = f"{buffer} is not a complete replay buffer pickle (0 bytes: the file is empty)"
    assert refused.returncode == 2 and refused.stderr.strip().splitlines()[-1].endswith(
        f"{problem}: add --resume-without-buffer to resume from an empty buffer (the run then differs from the "
        "uninterrupted one)"
    )
    resumed = run_in_process(train, *resume, "--resume-without-buffer", "-params", *TINY_ZOO_PARAMS)
    assert f"Warning: {problem}: going on from an empty replay buffer (--resume-without-buffer)" in resumed.stdout
    assert "Resuming at 120 timesteps: 180 to go" in resumed.stdout
    assert (logs / "pearlplus" / f"{ENV_ID}_2" / f"{ENV_ID}.zip").is_file()
    # rl_zoo3's own <folder>/replay_buffer.pkl, loaded with -i, is checked the same way
    pickle_path = run / "replay_buffer.pkl"
    pickle_path.write_bytes(b"\x80\x05")
    model = str(run / f"{ENV_ID}.zip")
    refused = run_in_process(train, *base, "-n", "100", "-i", model, "-params", *TINY_ZOO_PARAMS, check=False)
    assert refused.returncode == 2 and refused.stderr.strip().splitlines()[-1].endswith(
        f"{pickle_path} is not a complete replay buffer pickle (EOFError: Ran out of input): move it away to continue "
        "training from an empty buffer"
    )


# ----------------------------------------------------------------------------------------------
# Disk full at train.py's final save: one line naming the file; nothing older overwritten
# ----------------------------------------------------------------------------------------------
def test_a_full_disk_at_the_final_save_is_one_line_naming_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: three to five chained tracebacks (zipfile, atomic_write, rl_zoo3) naming no file."""
    real_atomic_write = atomic.atomic_write
    model_file = tmp_path / "logs" / "pearlplus" / f"{ENV_ID}_1" / f"{ENV_ID}.zip"

    @contextlib.contextmanager
    def full_disk(path: str | os.PathLike[str], mode: str = "wb", **kwargs: Any) -> Iterator[IO[Any]]:
        with real_atomic_write(path, mode, **kwargs) as file:
            if Path(path) == model_file:
                file.write(b"PK\x03\x04 half a zip")
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as a write to the full device raises it
            yield file

    monkeypatch.setattr(persistence, "atomic_write", full_disk)
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "logs"), "-n", "200", "--eval-freq", "1000"]
    proc = run_in_process(train, *argv, "-params", *TINY_ZOO_PARAMS, check=False)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines() == [
        f"{program_name()}: error: saving the trained model failed: cannot write {model_file}: No space left on device "
        "(ENOSPC); "
        "nothing older was overwritten (every save writes a temporary file and renames it into place, and the "
        "temporary file was removed): free space (or choose another -f) and train again"
    ]
    assert not model_file.exists() and not [path for path in model_file.parent.iterdir() if ".tmp" in path.name]


def test_a_write_error_keeps_the_previous_file_and_names_it(tmp_path: Path) -> None:
    """What the message promises: the previous file is kept, the temporary one removed, the error names the file."""
    destination = tmp_path / "model.zip"
    destination.write_bytes(b"the previous model")
    with (
        pytest.raises(OSError, match=rf"cannot write {destination}: No space left on device$") as raised,
        atomic.atomic_write(destination) as file,
    ):
        file.write(b"half a zip")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert raised.value.errno == errno.ENOSPC
    assert destination.read_bytes() == b"the previous model" and os.listdir(tmp_path) == ["model.zip"]


# ----------------------------------------------------------------------------------------------
# reproduce status: a checkpoint whose model zip is cut is damaged, not resumable
# ----------------------------------------------------------------------------------------------
def test_status_calls_a_checkpoint_with_a_truncated_model_damaged(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'resumable', and the resume failed with advice for train.py users (load best_model.zip ...)."""
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
# A bad task for a SubprocVecEnv: refused in this process, the workers alive
# ----------------------------------------------------------------------------------------------
def test_a_bad_task_for_a_subprocess_vec_env_is_one_line_and_the_env_lives() -> None:
    """Before: the worker died on set_task's ValueError; the parent got an empty EOFError and a dead VecEnv."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv, VecCheckNan

    from sb3_pearl.common.tasks import set_vec_env_task
    from sb3_pearl.evaluation.meta_test import SingleEnvRunner

    fork = {"start_method": "fork"}
    env = VecCheckNan(make_vec_env(ENV_ID, n_envs=2, vec_env_cls=SubprocVecEnv, vec_env_kwargs=fork))  # wrapped
    try:
        good = env.env_method("get_task", indices=[0])[0]
        bad = {"goal": np.array([np.nan, 1.0])}
        with pytest.raises(
            ValueError, match=r"^set_task\(\{'goal': .*\}\): SafePointGoalMetaEnv.set_task: task keys \['goal'\] != "
        ):
            set_vec_env_task(env, bad, [1])
        with pytest.raises(ValueError, match=r"refused before it reached the SubprocVecEnv's worker processes, which die"):
            set_vec_env_task(env, {**good, "goal": np.array([np.nan, 1.0])})
        set_vec_env_task(env, good, [1])  # the workers are alive and take a good task
        assert env.env_method("get_task") == [good, good]
    finally:
        env.close()
    single = make_vec_env(ENV_ID, n_envs=1, vec_env_cls=SubprocVecEnv, vec_env_kwargs=fork)
    try:  # the meta-test's runner on a one-env SubprocVecEnv
        with pytest.raises(ValueError, match=r"set_task\(.*\): SafePointGoalMetaEnv"):
            SingleEnvRunner(single).set_task(bad)
        assert single.env_method("get_task")[0].keys() == good.keys()
    finally:
        single.close()


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
    """Before: the child raised KeyboardInterrupt wherever it was and kept only its last periodic checkpoint (none in
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
    """Before: the child stopped at once (no checkpoint in its first 10 minutes) and the parent said FAILED (exit 130)."""
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
