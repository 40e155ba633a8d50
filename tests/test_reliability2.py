"""Reliability, second round (issue 40; docs/reliability.md, "Second round"): data lost or misreported, and one-line
errors for the unclear cases. Every test here failed before its fix."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml

import tests.faulty_envs as faulty_envs
from pearl_paper.reproduce.cells import load_groups
from pearl_paper.reproduce.cli import main
from pearl_paper.reproduce.layout import write_json_atomic
from pearl_paper.reproduce.ownership import RunLockedError, lock_holder, run_lock
from sb3_pearl import PEARLPlus
from sb3_pearl.diagnose import main as diagnose_main
from sb3_pearl.envs import FAMILIES
from sb3_pearl.evaluation.figures import main as plots_main
from sb3_pearl.zoo import enjoy, train
from sb3_pearl.zoo.safe_config import load_run_yaml
from tests.conftest import TINY_ZOO_PARAMS, Completed, run_in_process
from tests.test_reliability import ENV_ID, TINY_ZOO, tiny_finetune, tiny_maml, tiny_pearl


# ----------------------------------------------------------------------------------------------
# Non-finite values are refused where they enter: predict's observation, every family's action
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("env_id", sorted(FAMILIES))
def test_every_family_refuses_a_non_finite_action(env_id: str) -> None:
    env = gym.make(env_id)
    env.reset(seed=0)
    good = env.action_space.sample()
    for bad in (float("nan"), float("inf")):
        action = np.full(env.action_space.shape, bad) if env.action_space.shape else bad
        with pytest.raises(ValueError, match=r"\.step: the action \[?(nan|inf).* is not finite: refused rather than stepped"):
            env.step(action)
    env.step(good)  # the env is still usable
    env.close()


def test_a_nan_action_is_not_counted_as_a_safe_step() -> None:
    env = gym.make(ENV_ID)  # before: stepped, position nan, cost 0.0
    env.reset(seed=0)
    with pytest.raises(ValueError, match="SafePointGoalMetaEnv.step: the action"):
        env.step(np.array([np.nan, 0.0], dtype=np.float32))


@pytest.mark.parametrize("algo", ["pearlplus", "finetune", "maml"])
def test_predict_refuses_a_non_finite_observation(algo: str, tiny_kwargs: dict[str, Any]) -> None:
    model = {"pearlplus": lambda: tiny_pearl(tiny_kwargs, seed=0), "finetune": tiny_finetune, "maml": tiny_maml}[algo]()
    model.reset_adaptation()
    obs = np.array([np.nan, 0.0], dtype=np.float32)
    with pytest.raises(ValueError, match=r"\.predict\(\): the observation holds a non-finite value \(\[nan, 0.0\]\)"):
        model.predict(obs, deterministic=True)
    action, _ = model.predict(np.zeros(2, dtype=np.float32), deterministic=True)
    assert np.isfinite(action).all()


@pytest.mark.parametrize("algo", ["pearlplus", "finetune", "maml"])
def test_learn_refuses_a_negative_budget(algo: str, tiny_kwargs: dict[str, Any]) -> None:
    model = {"pearlplus": lambda: tiny_pearl(tiny_kwargs, seed=0), "finetune": tiny_finetune, "maml": tiny_maml}[algo]()
    with pytest.raises(ValueError, match=r"learn\(\): total_timesteps must be >= 0 \(env steps to train on\), got -1"):
        model.learn(-1)
    assert model.num_timesteps == 0


# ----------------------------------------------------------------------------------------------
# Reports: each result owns its place (no copy, no result in another run's folder)
# ----------------------------------------------------------------------------------------------
def _write_result(results: Path, seed: int, folder_seed: int | None = None, experiment_folder: str = "safe-point") -> Path:
    path = results / experiment_folder / "safe-point" / "alpha-0" / f"seed{seed if folder_seed is None else folder_seed}"
    summary = [{"k": 0, "n": 1, "return_mean": -1.0 - seed, "violation_rate": 0.0}]
    result = {"experiment": "safe-point", "family": "safe-point", "variant": "alpha-0", "seed": seed, "budget_preset": "smoke"}
    write_json_atomic(path / "result.json", {**result, "meta_test": {"summary": summary}})
    return path / "result.json"


def test_report_refuses_a_copy_of_a_result_naming_both_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    results, page = tmp_path / "results", tmp_path / "results.md"
    real = _write_result(results, 0)
    assert set(load_groups(results)[("safe-point", "smoke", "safe-point")]["alpha-0"]) == {0}
    backup = _write_result(results, 0, experiment_folder="safe-point.bak")  # a backup copy beside the real folder
    assert main(["report", "--results-dir", str(results), "--out", str(page)]) == 2
    assert (
        f"error: {real} and {backup} both hold the result of safe-point smoke safe-point alpha-0 seed0"
        in capsys.readouterr().err
    )
    assert not page.exists()


def test_report_and_status_refuse_a_result_in_another_runs_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    results = tmp_path / "results"
    moved = _write_result(results, 0, folder_seed=1)  # seed1/result.json says seed 0 (beside seed0's: both files named)
    with pytest.raises(
        ValueError, match=rf"{moved} holds the result of another run: seed 'seed0' \(its folder says 'seed1'\)"
    ):
        load_groups(results)
    assert main(["status", "safe-point", "--results-dir", str(results), "--seeds", "0-1", "--budget", "smoke"]) == 2
    assert f"error: {moved} holds the result of another run" in capsys.readouterr().err


def test_report_out_on_a_folder_and_status_of_a_missing_folder_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results = tmp_path / "results"
    _write_result(results, 0)
    assert main(["report", "--results-dir", str(results), "--out", str(tmp_path)]) == 2
    assert (
        capsys.readouterr().err
        == f"error: --out {tmp_path} is a folder: give the markdown file to write, e.g. {tmp_path / 'results.md'}\n"
    )
    assert not (tmp_path / "figures").exists()  # nothing written beside it
    assert main(["status", "safe-point", "--results-dir", str(tmp_path / "nowhere")]) == 2
    assert "error: --results-dir" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# SIGTERM and Ctrl-C alike: stopped where the run resumes exactly, buffer saved, run marked cut
# ----------------------------------------------------------------------------------------------
SIGNAL_ENV = "SignalSafePointGoalMeta-v0"


def _train_signal_env(tmp_path: Path, folder: Path, *extra: str, check: bool = True) -> Completed:
    conf = tmp_path / "conf.yml"  # iteration 0 = 4 x 30 = 120 steps, then 5 x (30 + 30) = 300
    conf.write_text(yaml.safe_dump({SIGNAL_ENV: {**TINY_ZOO, "n_timesteps": 420, "meta_test": "dict(n_adapt=0)"}}))
    command = ["--algo", "pearlplus", "--env", SIGNAL_ENV, "-f", str(folder), "-conf", str(conf), "--seed", "1"]
    command += ["--num-threads", "1", "--eval-episodes", "1", "--gym-packages", "tests.faulty_envs", *extra]
    return run_in_process(train, *command, check=check)


def _policy_weights(path: Path) -> list[th.Tensor]:
    return list(PEARLPlus.load(path).policy.state_dict().values())


def test_a_signal_cuts_the_run_saves_what_the_resume_needs_and_the_resume_is_exact(tmp_path: Path) -> None:
    faulty_envs.send_signals({})
    _train_signal_env(tmp_path, tmp_path / "full")
    full = _policy_weights(tmp_path / "full" / "pearlplus" / f"{SIGNAL_ENV}_1" / f"{SIGNAL_ENV}.zip")
    for signum in (signal.SIGINT, signal.SIGTERM):
        name = signal.Signals(signum).name
        logs = tmp_path / name
        run = logs / "pearlplus" / f"{SIGNAL_ENV}_1"
        faulty_envs.send_signals({200: signum})  # inside iteration 1 (steps 120-420)
        cut = _train_signal_env(tmp_path, logs, check=False)
        assert cut.returncode == 128 + signum, cut.stdout[-2000:] + cut.stderr[-2000:]
        assert f"Received {name}: stopping training where it resumes exactly" in cut.stdout
        assert f"Stopped by {name} at 200 of 420 timesteps, " in cut.stdout  # ... and what was trained:
        assert "gradient steps trained: the run is cut" in cut.stdout
        record = json.loads((run / "interrupted.json").read_text())
        assert record["signal"] == name and record["during"] == "training" and record["exact_resume"]
        assert record["num_timesteps"] == 200 and record["replay_buffer"] == str(run / "replay_buffer.pkl")
        assert not (run / "meta_test.json").exists()  # skipped for both signals
        assert (run / "replay_buffer.pkl").is_file()  # without --save-replay-buffer: the resume needs it
        assert record["resume"].endswith(f"--resume {run / f'{SIGNAL_ENV}.zip'}")
        resumed = _train_signal_env(tmp_path, logs, "--resume", str(run / f"{SIGNAL_ENV}.zip"))
        assert "Resuming at 200 timesteps: 220 to go" in resumed.stdout
        again = _policy_weights(logs / "pearlplus" / f"{SIGNAL_ENV}_2" / f"{SIGNAL_ENV}.zip")
        assert all(th.equal(a, b) for a, b in zip(full, again, strict=True)), name


def test_a_signal_during_the_final_meta_test_keeps_the_model_and_writes_no_meta_test(tmp_path: Path) -> None:
    """docs/reliability.md: a signal during the final meta-test leaves no meta_test.* (no partial numbers), the trained
    model saved, interrupted.json saying when, and the exit code 128 + signal."""
    faulty_envs.send_signals({420 + 10: signal.SIGTERM})  # training takes env steps 1-420; the meta-test follows
    logs = tmp_path / "logs"
    run = logs / "pearlplus" / f"{SIGNAL_ENV}_1"
    cut = _train_signal_env(tmp_path, logs, check=False)
    assert cut.returncode == 128 + signal.SIGTERM, cut.stdout[-2000:] + cut.stderr[-2000:]
    assert "Received SIGTERM: stopping the final meta-test (the model is saved)" in cut.stdout
    assert "Stopped by SIGTERM during the final meta-test" in cut.stdout
    record = json.loads((run / "interrupted.json").read_text())
    assert record["signal"] == "SIGTERM" and record["during"] == "final meta-test" and record["num_timesteps"] == 420
    assert not any(run.glob("meta_test.*"))
    assert PEARLPlus.load(run / f"{SIGNAL_ENV}.zip").num_timesteps == 420


def test_a_resume_without_its_replay_buffer_is_refused_in_one_line(tmp_path: Path) -> None:
    model = tmp_path / "model.zip"
    model.write_bytes(b"")  # the check comes before anything reads it
    refused = run_in_process(train, "--algo", "pearlplus", "--env", ENV_ID, "--resume", str(model), check=False)
    assert refused.returncode == 2
    assert refused.stderr.strip().count("\n") == 0
    assert f"--resume {model}: no replay buffer beside it ({tmp_path / 'replay_buffer.pkl'})" in refused.stderr
    assert "add --resume-without-buffer to go on anyway" in refused.stderr


# ----------------------------------------------------------------------------------------------
# Run folders: reserved atomically; a refused set-up leaves none behind
# ----------------------------------------------------------------------------------------------
def _train_at_the_barrier(barrier: Any, logs: str, seed: int) -> None:  # a forked child: train.py's entry point
    barrier.wait(timeout=60)
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", logs, "--seed", str(seed), "-n", "60", "--num-threads", "1"]
    argv += ["--eval-freq", "-1", "-params", *TINY_ZOO_PARAMS]
    os._exit(run_in_process(train, *argv, check=False).returncode)


def test_runs_started_together_on_one_folder_each_get_their_own(tmp_path: Path) -> None:
    context = multiprocessing.get_context("fork")
    seeds = (1, 2, 3)
    barrier = context.Barrier(len(seeds))
    children = [context.Process(target=_train_at_the_barrier, args=(barrier, str(tmp_path), seed)) for seed in seeds]
    for child in children:
        child.start()
    for child in children:
        child.join(timeout=240)
    assert [child.exitcode for child in children] == [0, 0, 0]
    runs = sorted((tmp_path / "pearlplus").iterdir())
    assert [run.name for run in runs] == [f"{ENV_ID}_{n}" for n in (1, 2, 3)]  # before: 2 or 3 runs in one folder
    found = set()
    for run in runs:
        seed = load_run_yaml(run / ENV_ID / "args.yml")["seed"]
        found.add(seed)
        assert PEARLPlus.load(run / f"{ENV_ID}.zip").seed == seed
        monitor = (run / "0.monitor.csv").read_text().splitlines()
        assert sum(line.startswith("#") for line in monitor) == 1  # one writer
    assert found == set(seeds)


def test_a_refused_hyperparameter_leaves_no_run_folder(tmp_path: Path) -> None:
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path), "--seed", "1", "-params", "latent_dim:-3"]
    refused = run_in_process(train, *argv, check=False)
    assert refused.returncode == 2 and "latent_dim" in refused.stderr
    assert not any((tmp_path / "pearlplus").iterdir())  # before: <EnvId>_1 with its monitor file and config


# ----------------------------------------------------------------------------------------------
# The harness's run.lock: removed when the run ends, exclusive while it runs
# ----------------------------------------------------------------------------------------------
def test_the_run_lock_is_removed_when_the_run_ends_and_stays_exclusive(tmp_path: Path) -> None:
    lock = tmp_path / "run.lock"
    with run_lock(tmp_path):
        assert lock.read_text() == f"{os.getpid()}\n" and lock_holder(tmp_path) == os.getpid()
    assert not lock.exists() and lock_holder(tmp_path) is None  # before: left behind by every run
    with pytest.raises(RuntimeError, match="the run failed"), run_lock(tmp_path):
        raise RuntimeError("the run failed")
    assert not lock.exists()
    holding, release = threading.Event(), threading.Event()

    def waiter() -> None:  # opens the lock file while the first owner holds it, then waits for it
        with run_lock(tmp_path, wait_s=10):
            holding.set()
            release.wait(10)

    thread = threading.Thread(target=waiter)
    with run_lock(tmp_path):
        thread.start()
        time.sleep(0.3)
    assert holding.wait(10)
    assert lock_holder(tmp_path) == os.getpid()  # the waiter holds the file at the path, not the one removed
    with pytest.raises(RunLockedError), run_lock(tmp_path, wait_s=0.0):
        pass  # so a third process is refused
    release.set()
    thread.join(10)
    assert not lock.exists()


# ----------------------------------------------------------------------------------------------
# Unclear cases: one line naming what to fix
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "extra, message",
    [
        (["--env-kwargs", "hazrd_radius:0.3"], "--env-kwargs / env_kwargs: SafePointGoalMeta-v0 does not take 'hazrd_radius'"),
        (["--seed", "-5"], "--seed must be an integer in [0, 4294967295] (omit it for a random seed), got '-5'"),
        (["--seed", str(2**32)], "--seed must be an integer in [0, 4294967295]"),
        (["-params", "learning_rate:float('nan')"], "learning_rate must be a finite number >= 0"),
        (["-f", "FILE"], "is a file, not a folder: give a folder for the run folders"),
        (["-f", "FILE/logs"], "is a file, not a folder"),
    ],
)
def test_train_py_mistakes_are_one_line(tmp_path: Path, extra: list[str], message: str) -> None:
    (tmp_path / "file").write_text("")
    extra = [arg.replace("FILE", str(tmp_path / "file")) for arg in extra]
    logs = tmp_path / "logs"
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(logs), "-n", "60", *extra]
    refused = run_in_process(train, *argv, check=False)
    assert refused.returncode == 2, refused.stdout[-2000:] + refused.stderr[-2000:]
    assert "Traceback" not in refused.stderr
    lines = [line for line in refused.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], lines  # one line, naming what to fix
    assert not logs.exists() or not any(logs.rglob("*.csv"))  # no run folder left


def test_train_py_on_a_folder_it_cannot_write_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """-f on a folder without write permission (faked: the tests may run as root, who may write anywhere)."""
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access

    def access(path: str, mode: int, **kwargs: Any) -> bool:
        return False if Path(path) == locked else real_access(path, mode, **kwargs)

    monkeypatch.setattr(os, "access", access)
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(locked / "logs"), "-n", "60"]
    refused = run_in_process(train, *argv, check=False)
    lines = [line for line in refused.stderr.strip().splitlines() if line.strip()]
    assert refused.returncode == 2 and len(lines) == 1 and f"{locked} is not writable" in lines[0], lines
    assert list(locked.iterdir()) == []


def test_a_truncated_model_is_named_by_enjoy_and_diagnose(
    tmp_path: Path, tiny_kwargs: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "logs" / "pearlplus" / f"{ENV_ID}_1"
    run.mkdir(parents=True)
    tiny_pearl(tiny_kwargs, seed=0).save(tmp_path / "model.zip")
    data = (tmp_path / "model.zip").read_bytes()
    (run / f"{ENV_ID}.zip").write_bytes(data[: len(data) // 2])
    expected = f"{run / f'{ENV_ID}.zip'} is not a readable zip"  # diagnose said "not a PEARL / PEARL+ model"
    argv = ["--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "logs"), "--no-render", "--n-tasks", "1"]
    refused = run_in_process(enjoy, *argv, check=False)
    assert refused.returncode == 2 and expected in refused.stderr and "Traceback" not in refused.stderr
    with pytest.raises(SystemExit) as exit_info:
        diagnose_main([str(run / f"{ENV_ID}.zip"), "--env-id", ENV_ID])
    assert exit_info.value.code == 2
    assert expected in capsys.readouterr().err  # the same words as enjoy's, not "not a PEARL / PEARL+ model"


def test_save_to_a_path_it_cannot_write_names_the_destination(
    tmp_path: Path, tiny_kwargs: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    model = tiny_pearl(tiny_kwargs, seed=0)
    (tmp_path / "file").write_text("")
    with pytest.raises(OSError, match=rf"cannot write {tmp_path / 'file' / 'model.zip'}: {tmp_path / 'file'} is a file"):
        model.save(tmp_path / "file" / "model.zip")

    def refused(*args: Any, **kwargs: Any) -> Any:  # what a folder without write permission gives (tests run as root)
        raise PermissionError(13, "Permission denied", str(tmp_path / ".model.x1y2.tmp.zip"))

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    with pytest.raises(PermissionError, match=rf"cannot write {tmp_path / 'model.zip'}: Permission denied in {tmp_path}$"):
        model.save(tmp_path / "model.zip")


def test_plots_names_a_truncated_meta_test_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "meta_test.json").write_text('{"config": {"algo": "pearl"}, "summ')
    with pytest.raises(SystemExit) as exit_info:
        plots_main([str(tmp_path), "-o", str(tmp_path / "out.png")])
    assert exit_info.value.code == 2
    assert f"{tmp_path / 'meta_test.json'} is not valid JSON" in capsys.readouterr().err
