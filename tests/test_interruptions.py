"""Signals and stops: SIGTERM, Ctrl-C or an exception during train.py saves what the resume needs and says where,
and a signal during the set-up leaves no run folder; a stop lands within one gradient step at any budget and resumes
exactly; periodic checkpoints taken inside an iteration's gradient steps resume exactly; the ETA comes from the first
gradient steps instead of after a whole iteration. Harness runs stopped the same way are in
tests/test_reproduce_resume.py."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

import tests.faulty_envs as faulty_envs
from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.common.callbacks import StopOnSignalCallback, gradient_step_event
from sb3_pearl.evaluation import progress
from sb3_pearl.evaluation.callbacks import MetaTestCallback, ResumableCheckpointCallback, checkpoint_replay_buffer_path
from sb3_pearl.evaluation.progress import TrainingProgressCallback
from sb3_pearl.registry import constructor_parameters
from sb3_pearl.zoo import MetaExperimentManager, train
from sb3_pearl.zoo.flags import parse_project_flags
from sb3_pearl.zoo.usage import UsageError
from tests.conftest import (
    ENV_ID,
    TINY_ZOO,
    Completed,
    run_in_process,
    tiny_finetune,
    tiny_maml,
    tiny_pearl,
    write_model_zip,
)

NOISY_ENV = "NoisyResetSafePointGoalMeta-v0"  # its resets draw from the env's RNG: the env state must resume too
TOTAL = 660  # tiny PEARL: iteration 0 = 240 env steps and 5 gradient steps, then 140 env steps and 5 per iteration


class StopAfter(BaseCallback):
    """Asks to stop at the ``after``-th gradient-step event (between two gradient steps)."""

    def __init__(self, after: int) -> None:
        super().__init__()
        self.after, self.events = after, 0

    def _on_step(self) -> bool:
        return True

    def on_gradient_step(self) -> bool:
        self.events += 1
        return self.events < self.after


def _make(tiny_kwargs: dict[str, Any], cls: type[PEARL] = PEARLPlus) -> PEARL:
    kwargs = {**tiny_kwargs, "seed": 0}
    if cls is PEARL:
        kwargs.pop("prior_critic_arch", None)
    return cls("MlpPolicy", gym.make(NOISY_ENV), **kwargs)


def _weights(model: PEARL) -> dict[str, th.Tensor]:
    return {key: value.clone() for key, value in model.policy.state_dict().items()}


def _same(a: PEARL, b: PEARL) -> bool:
    expected = _weights(a)
    return all(th.equal(value, expected[key]) for key, value in _weights(b).items())


@pytest.mark.parametrize("cls", [PEARL, PEARLPlus])
@pytest.mark.parametrize("reload", [False, True], ids=["same-process", "save-load"])
def test_a_stop_between_gradient_steps_resumes_bit_identically(
    tmp_path: Path, tiny_kwargs: dict[str, Any], cls: type[PEARL], reload: bool
) -> None:
    unsplit = _make(tiny_kwargs, cls).learn(TOTAL)
    split = _make(tiny_kwargs, cls)
    # events come between two steps: 4 in iteration 0 (5 steps), then the 3rd of iteration 1 stops after its 3rd step
    split.learn(TOTAL, callback=StopAfter(7))
    assert split.num_timesteps == 380 and split._n_updates == 5 + 3 and split._pending_gradient_steps == 2
    assert split.n_iterations == 1  # the interrupted iteration is not counted until its steps are trained
    assert split.training_plan(TOTAL).gradient_steps == 2 + 2 * 5  # the pending steps first, then two iterations
    if reload:
        split.save(tmp_path / "model")
        split.save_replay_buffer(tmp_path / "buffer")
        th.manual_seed(123), np.random.seed(123)  # whatever happens in between: the saved RNG streams continue
        split = cls.load(tmp_path / "model", env=gym.make(NOISY_ENV))
        split.load_replay_buffer(tmp_path / "buffer.pkl")
        assert split._pending_gradient_steps == 2
    split.learn(TOTAL - split.num_timesteps, reset_num_timesteps=False)
    assert split._pending_gradient_steps == 0 and split.n_iterations == unsplit.n_iterations
    assert split.num_timesteps == unsplit.num_timesteps and split._n_updates == unsplit._n_updates
    assert _same(unsplit, split)


def test_a_stop_in_the_last_iterations_gradient_steps_trains_them_on_resume(tiny_kwargs: dict[str, Any]) -> None:
    """The budget's env steps are all collected; a learn() of 0 more env steps still trains the pending steps."""
    unsplit = _make(tiny_kwargs).learn(TOTAL)
    split = _make(tiny_kwargs)
    split.learn(TOTAL, callback=StopAfter(4 + 4 + 4 + 2))  # the 3rd iteration after iteration 0 stops after 2 steps
    assert split.num_timesteps == TOTAL and split._pending_gradient_steps == 3
    split.learn(0, reset_num_timesteps=False)
    assert split._n_updates == unsplit._n_updates and _same(unsplit, split)


def test_periodic_checkpoints_inside_gradient_steps_resume_bit_identically(
    tmp_path: Path, tiny_kwargs: dict[str, Any]
) -> None:
    unsplit = _make(tiny_kwargs).learn(TOTAL)
    checkpoints = ResumableCheckpointCallback(0, str(tmp_path), "checkpoint", every_s=1e-9, keep_last=True)
    run = _make(tiny_kwargs).learn(TOTAL, callback=checkpoints)
    assert _same(unsplit, run)  # saving changes nothing in the run
    inside = [paths for paths in checkpoints.saved if "_u" in Path(paths[0]).name]
    assert inside, "no checkpoint was taken between two gradient steps"
    assert len(list(tmp_path.glob("checkpoint_*.zip"))) == 1  # keep_last: only the latest is on disk
    # a checkpoint taken between two gradient steps resumes exactly (re-taken: keep_last deleted the older ones)
    again = ResumableCheckpointCallback(0, str(tmp_path / "again"), "checkpoint", every_s=1e-9)
    _make(tiny_kwargs).learn(TOTAL, callback=[again, StopAfter(6)])
    model_path = next(paths[0] for paths in reversed(again.saved) if "_u" in Path(paths[0]).name)
    buffer_path = checkpoint_replay_buffer_path(model_path)
    assert buffer_path is not None and Path(buffer_path).is_file()
    resumed = PEARLPlus.load(model_path, env=gym.make(NOISY_ENV))
    resumed.load_replay_buffer(buffer_path)
    assert resumed._pending_gradient_steps > 0
    resumed.learn(TOTAL - resumed.num_timesteps, reset_num_timesteps=False)
    assert resumed._n_updates == unsplit._n_updates and _same(unsplit, resumed)


def test_a_periodic_checkpoints_zip_is_written_after_its_buffer(
    tmp_path: Path, tiny_kwargs: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Guards against: the zip written first, so a kill during the (slow) buffer write left a newest checkpoint with no
    buffer, which --resume then found and refused."""
    model = _make(tiny_kwargs)

    def killed(*args: Any, **kwargs: Any) -> None:
        raise KeyboardInterrupt("killed while the model is written")

    monkeypatch.setattr(model, "save", killed)
    with pytest.raises(KeyboardInterrupt):
        model.learn(TOTAL, callback=ResumableCheckpointCallback(0, str(tmp_path), "checkpoint", every_s=1e-9))
    assert list(tmp_path.glob("checkpoint_replay_buffer_*.pkl")) and not list(tmp_path.glob("checkpoint_*.zip"))


def test_every_callback_hears_the_gradient_step_and_a_signal_stops_there() -> None:
    heard: list[str] = []

    class Listener(BaseCallback):
        def __init__(self, name: str, answer: bool) -> None:
            super().__init__()
            self.name, self.answer = name, answer

        def _on_step(self) -> bool:
            return True

        def on_gradient_step(self) -> bool:
            heard.append(self.name)
            return self.answer

    class Plain(BaseCallback):  # no on_gradient_step: not asked
        def _on_step(self) -> bool:
            return True

    callbacks = CallbackList([Listener("a", False), CallbackList([Listener("b", True)]), Plain()])
    assert gradient_step_event(callbacks) is False and heard == ["a", "b"]  # one says stop; all are told
    stop = StopOnSignalCallback()
    assert stop.on_gradient_step() and not stop.stopped
    stop.requested = True
    assert not stop.on_gradient_step() and stop.stopped


def test_the_eta_comes_from_the_first_gradient_steps(tiny_kwargs: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    """With a 30-step first iteration, the cost and the ETA are printed after 20 timed steps, inside the iteration."""
    model = _make({**tiny_kwargs, "num_train_steps_per_itr": 30})
    printed_at: list[int] = []
    callback = TrainingProgressCallback(progress_bar=False)
    report = callback._report

    def recording_report() -> None:
        printed_at.append(model._n_updates)
        report()

    callback._report = recording_report  # type: ignore[method-assign]
    model.learn(300, callback=callback)
    out = capsys.readouterr().out
    assert printed_at == [progress.FIRST_TIMED_UPDATES]  # once, after 20 of the iteration's 30 gradient steps
    assert "So far: 240 env steps in " in out and "20 gradient steps in " in out and "ETA of the whole run: " in out


def test_the_training_line_keeps_moving_during_gradient_steps(
    tiny_kwargs: dict[str, Any], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(progress, "TRAINING_LINE_S", 0.0)  # a line at every gradient step
    _make(tiny_kwargs).learn(300, callback=TrainingProgressCallback(progress_bar=False))
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("Training: ")]
    assert len(lines) >= 5 and "gradient steps" in lines[0] and "ETA" in lines[-1] and "ETA ?" not in lines[-1]


def test_checkpoint_minutes_flag() -> None:
    assert parse_project_flags(["--algo", "pearl"]).checkpoint_minutes == 10.0
    flags = parse_project_flags(["--algo", "pearl", "--checkpoint-minutes", "2.5"])
    assert flags.checkpoint_minutes == 2.5 and "--checkpoint-minutes" not in flags.zoo_args
    for bad in ("-1", "nan", "soon"):
        with pytest.raises(UsageError, match="--checkpoint-minutes takes minutes >= 0"):
            parse_project_flags(["--algo", "pearl", "--checkpoint-minutes", bad])
    with pytest.raises(ValueError, match="every_s must be > 0"):
        ResumableCheckpointCallback(0, "x", every_s=0.0)


def test_the_projects_flags_take_the_equals_form() -> None:
    """Guards against: --budget=cpu, --checkpoint-minutes=5 failing with 'unrecognized arguments' where -n=, --seed= work."""
    command = ["--algo", "pearl", "--env", "HalfCheetahVelMeta-v0", "--budget=cpu", "--checkpoint-minutes=5"]
    flags = parse_project_flags(command)
    assert flags.budget == "cpu" and flags.checkpoint_minutes == 5.0
    assert not any(arg.startswith(("--budget", "--checkpoint-minutes")) for arg in flags.zoo_args)
    assert flags.command[-4:] == ["--budget", "cpu", "--checkpoint-minutes", "5"]  # the resume command is built from it


def test_an_interrupted_harness_run_says_whether_a_checkpoint_exists(tmp_path: Path) -> None:
    """A child of `reproduce run` stopped before its first checkpoint promised a resume from a checkpoint that did not
    exist; it now says which of the two the same command will do."""
    from pearl_paper.reproduce.checkpoint import RunCheckpoint
    from pearl_paper.reproduce.cli import resume_promise

    assert "no checkpoint was written yet" in resume_promise(tmp_path) and "starts this run anew" in resume_promise(tmp_path)
    checkpoint = RunCheckpoint(tmp_path)
    checkpoint.folder.mkdir()
    write_model_zip(checkpoint.folder / "model_1200.zip")
    checkpoint.write_state({"phase": "train", "files": {"model": "model_1200.zip"}, "num_timesteps": 1200})
    assert resume_promise(tmp_path).endswith("resumes this run from its checkpoint at 1,200 env steps")


def test_the_demo_names_an_empty_or_foreign_remeasured_record(tmp_path: Path) -> None:
    """`make demo` on a zero-byte meta_test_large.json gave a JSON traceback naming no file."""
    from pearl_paper import demo

    (tmp_path / "meta_test_large.json").write_text("")
    with pytest.raises(ValueError, match=r"meta_test_large.json is not valid JSON .*truncated or edited"):
        demo.remeasured_meta_test(tmp_path)
    (tmp_path / "meta_test_large.json").write_text('{"summary": []}')
    with pytest.raises(ValueError, match=r"meta_test_large.json is not a re-measured record .*reproduce remeasure"):
        demo.remeasured_meta_test(tmp_path)


# ----------------------------------------------------------------------------------------------
# SIGTERM and exceptions during train.py save the model and say where
# ----------------------------------------------------------------------------------------------
ROOT = Path(__file__).resolve().parent.parent


def start_train(folder: Path, env_id: str, *extra: str, new_session: bool = False) -> subprocess.Popen[str]:
    conf = folder / "conf.yml"
    conf.write_text(yaml.safe_dump({env_id: TINY_ZOO}))
    command = [sys.executable, str(ROOT / "train.py"), "--algo", "pearlplus", "--env", env_id, "-f", str(folder / "logs")]
    command += ["-conf", str(conf), "--seed", "1", "--num-threads", "1", "--gym-packages", "tests.faulty_envs", *extra]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "MPLBACKEND": "Agg"}
    return subprocess.Popen(
        command,
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=new_session,  # its own process group, as a terminal's foreground job
    )


def _until_training(proc: subprocess.Popen[str]) -> list[str]:
    """The output up to the logger's first iteration (training has started)."""
    assert proc.stdout is not None
    output = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        output.append(line)
        if "n_updates" in line or not line:
            break
    assert any("n_updates" in line for line in output), "".join(output)
    return output


def test_sigterm_saves_the_model_and_says_where(tmp_path: Path) -> None:
    proc = start_train(tmp_path, ENV_ID)
    output = _until_training(proc)
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=60)
    text = "".join(output) + rest
    model_path = tmp_path / "logs" / "pearlplus" / f"{ENV_ID}_1" / f"{ENV_ID}.zip"
    assert proc.returncode == 128 + signal.SIGTERM, text[-3000:]
    assert "Received SIGTERM: stopping training where it resumes exactly" in text
    assert f"the model is saved to {model_path} with its replay buffer" in text
    assert PEARLPlus.load(model_path).num_timesteps > 0


def test_ctrl_c_with_subprocess_envs_stops_cleanly(tmp_path: Path) -> None:
    """Guards against: Ctrl-C reached the SubprocVecEnv workers too (the terminal signals its whole foreground process
    group), they died, and the stop ended in BrokenPipeError with no replay buffer and no interrupted.json."""
    proc = start_train(tmp_path, ENV_ID, "--vec-env", "subproc", new_session=True)
    output = _until_training(proc)
    os.killpg(proc.pid, signal.SIGINT)
    rest, _ = proc.communicate(timeout=90)
    text = "".join(output) + rest
    run = tmp_path / "logs" / "pearlplus" / f"{ENV_ID}_1"
    assert proc.returncode == 128 + signal.SIGINT, text[-3000:]
    assert "Traceback" not in text and "Received SIGINT: stopping training where it resumes exactly" in text
    record = json.loads((run / "interrupted.json").read_text())
    assert record["during"] == "training" and record["exact_resume"] and Path(record["replay_buffer"]).is_file()


def test_shielded_subprocess_workers_outlive_a_stop_signal() -> None:
    """The workers ignore SIGINT and SIGTERM (the main process stops them and closes them): their ignored-signal mask
    says so, whatever the disposition they inherited, and they answer after both signals."""
    from sb3_pearl.zoo.interruptions import SignalShieldedSubprocVecEnv

    vec_env = SignalShieldedSubprocVecEnv([lambda: gym.make("Pendulum-v1")])
    vec_env.reset()
    worker = vec_env.processes[0]
    status = Path(f"/proc/{worker.pid}/status").read_text()
    ignored = int(status.split("SigIgn:")[1].split()[0], 16)
    assert all(ignored >> (signum - 1) & 1 for signum in (signal.SIGINT, signal.SIGTERM)), hex(ignored)
    for signum in (signal.SIGINT, signal.SIGTERM):
        os.kill(worker.pid, signum)
        worker.join(timeout=1.0)
        assert worker.is_alive(), signal.Signals(signum).name
    vec_env.step(np.zeros((1, 1), dtype=np.float32))
    vec_env.close()
    assert not worker.is_alive()


def test_exception_during_training_saves_the_model_and_reraises(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    env_id = "FailingSafePointGoalMeta-v0"
    conf = tmp_path / "conf.yml"
    conf.write_text(yaml.safe_dump({env_id: TINY_ZOO}))
    argv = ["--algo", "pearlplus", "--env", env_id, "-f", str(tmp_path / "logs"), "-conf", str(conf), "--seed", "1"]
    with pytest.raises(RuntimeError, match=r"the simulator crashed \(on purpose\)"):  # re-raised, so the exit status is 1
        train([*argv, "--num-threads", "1", "--gym-packages", "tests.faulty_envs"])  # train.py's entry point, in-process
    model_path = tmp_path / "logs" / "pearlplus" / f"{env_id}_1" / f"{env_id}.zip"
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert f"Training stopped by RuntimeError at 200 timesteps: the model reached so far is saved to {model_path}" in text
    assert PEARLPlus.load(model_path).num_timesteps == 200


# ----------------------------------------------------------------------------------------------
# SIGTERM and Ctrl-C alike: stopped where the run resumes exactly, buffer saved, run marked cut
# ----------------------------------------------------------------------------------------------
SIGNAL_ENV = "SignalSafePointGoalMeta-v0"


def _copy_zip_data(source: Path, target: Path, **changes: Any) -> None:
    """Copy a model zip with entries of its ``data`` changed (None: removed), as another version would have written it."""
    with zipfile.ZipFile(source) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(entries["data"])
    for key, value in changes.items():
        assert key in data, key
        if value is None:
            del data[key]
        else:
            data[key] = value
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(target, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)


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


def test_a_resume_with_other_hyperparameters_is_refused(tmp_path: Path) -> None:
    """Guards against: --resume passed the YAML / -params values of the resuming command to load(), so an edited entry
    silently changed a run documented as continuing bit for bit; the budget (-n) may change."""
    faulty_envs.send_signals({200: signal.SIGTERM})
    logs = tmp_path / "logs"
    model = logs / "pearlplus" / f"{SIGNAL_ENV}_1" / f"{SIGNAL_ENV}.zip"
    assert _train_signal_env(tmp_path, logs, check=False).returncode == 128 + signal.SIGTERM
    faulty_envs.send_signals({})
    assert "gamma" not in TINY_ZOO and constructor_parameters(PEARLPlus)["gamma"].default == 0.99
    refused = _train_signal_env(tmp_path, logs, "--resume", str(model), "-params", "batch_size:8", "gamma:0.9", check=False)
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0, refused.stderr[-2000:]
    assert f"--resume {model}: the hyperparameters differ from the run's (" in refused.stderr
    assert f"batch_size: {TINY_ZOO['batch_size']!r} in the run, 8 now" in refused.stderr
    assert "gamma: not set (the model's 0.99) in the run, 0.9 now" in refused.stderr
    # a run trained under another default (its zip holds gamma 0.95, its config.yml no gamma): the default is no proof
    older = model.parent / "older_default.zip"
    _copy_zip_data(model, older, gamma=0.95)
    refused = _train_signal_env(
        tmp_path, logs, "--resume", str(older), "--resume-without-buffer", "-params", "gamma:0.99", check=False
    )
    assert refused.returncode == 2 and "gamma: not set (the model's 0.95) in the run, 0.99 now" in refused.stderr
    # a longer budget is allowed, and so is a key the run did not set given at its default (an entry that gained it)
    resumed = _train_signal_env(tmp_path, logs, "--resume", str(model), "-n", "480", "-params", "gamma:0.99")
    assert "Resuming at 200 timesteps: 280 to go" in resumed.stdout


def test_a_resumed_run_evaluates_and_checkpoints_on_the_uninterrupted_runs_grid(tmp_path: Path) -> None:
    """Guards against: the resumed run's callbacks counted calls from 0, so a run cut at 200 evaluated at 290 and 410
    where the uninterrupted run evaluates at 240 and 360; --save-freq checkpoints likewise."""
    faulty_envs.send_signals({200: signal.SIGTERM})
    logs = tmp_path / "logs"
    every = ["--eval-freq", "120", "--save-freq", "120"]
    assert _train_signal_env(tmp_path, logs, *every, check=False).returncode == 128 + signal.SIGTERM
    cut = logs / "pearlplus" / f"{SIGNAL_ENV}_1"
    faulty_envs.send_signals({})
    _train_signal_env(tmp_path, logs, *every, "--resume", str(cut / f"{SIGNAL_ENV}.zip"))
    resumed = logs / "pearlplus" / f"{SIGNAL_ENV}_2"
    assert _evaluated_timesteps(cut) == [120]  # ... which the resumed run's history continues
    assert _evaluated_timesteps(resumed) == [120, 240, 360]
    with open(resumed / "meta_test_history.csv", newline="") as file:
        returns = [(float(row["return_mean"]), int(row["timesteps"])) for row in csv.DictReader(file)]  # n_adapt=0
    best_at = max(returns, key=lambda entry: (entry[0], -entry[1]))[1]
    assert PEARLPlus.load(resumed / "best_model.zip").num_timesteps == best_at  # the best of the whole run
    # a resume that evaluates otherwise (another meta_test eval_seed: other validation tasks) starts its own history
    other = _train_signal_env(
        tmp_path, logs, *every, "--resume", str(cut / f"{SIGNAL_ENV}.zip"), "-params", "meta_test:dict(eval_seed=7)"
    )
    assert "evaluated with other meta-test settings" in other.stdout
    assert _evaluated_timesteps(logs / "pearlplus" / f"{SIGNAL_ENV}_3") == [240, 360]


def test_a_resume_with_nothing_to_train_still_continues_the_runs_evaluations(tmp_path: Path) -> None:
    """Guards against: a resume of a finished run (0 env steps to go) skipped learn(), where the evaluation callback
    carries the cut run's history and best model, so its folder had neither."""
    faulty_envs.send_signals({})
    logs = tmp_path / "logs"
    _train_signal_env(tmp_path, logs, "--eval-freq", "120", "--save-replay-buffer")
    done = logs / "pearlplus" / f"{SIGNAL_ENV}_1"
    resumed = _train_signal_env(tmp_path, logs, "--eval-freq", "120", "--resume", str(done / f"{SIGNAL_ENV}.zip"))
    assert "Resuming at 420 timesteps: 0 to go" in resumed.stdout
    again = logs / "pearlplus" / f"{SIGNAL_ENV}_2"
    assert _evaluated_timesteps(again) == _evaluated_timesteps(done) == [120, 240, 360]
    assert (again / "best_model.zip").read_bytes() == (done / "best_model.zip").read_bytes()
    assert (again / f"{SIGNAL_ENV}.zip").is_file() and (again / "meta_test.json").is_file()  # saved, meta-tested


def _evaluated_timesteps(run: Path) -> list[int]:
    with open(run / "meta_test_history.csv", newline="") as file:
        return sorted({int(row["timesteps"]) for row in csv.DictReader(file)})


def test_a_resumed_run_with_two_envs_evaluates_on_the_uninterrupted_runs_grid(tmp_path: Path) -> None:
    """Guards against: the resumed callbacks started counting at num_timesteps // n_envs, which with two envs runs
    behind the calls made (PEARL steps one env alone while the other idles at a collection's end), so the resumed run
    evaluated off the uninterrupted run's grid."""
    every = ["--eval-freq", "50", "-params", "n_envs:2"]
    faulty_envs.send_signals({})
    _train_signal_env(tmp_path, tmp_path / "full", *every)
    full = _evaluated_timesteps(tmp_path / "full" / "pearlplus" / f"{SIGNAL_ENV}_1")
    faulty_envs.send_signals({580: signal.SIGTERM})  # env steps of training and evaluations: cut after idle calls
    logs = tmp_path / "cut"
    assert _train_signal_env(tmp_path, logs, *every, check=False).returncode == 128 + signal.SIGTERM
    cut = logs / "pearlplus" / f"{SIGNAL_ENV}_1"
    model = PEARLPlus.load(cut / f"{SIGNAL_ENV}.zip")
    assert model.num_vec_env_steps != model.num_timesteps // 2  # the case the old counter got wrong
    faulty_envs.send_signals({})
    _train_signal_env(tmp_path, logs, *every, "--resume", str(cut / f"{SIGNAL_ENV}.zip"))
    assert len(full) >= 4 and _evaluated_timesteps(logs / "pearlplus" / f"{SIGNAL_ENV}_2") == full


def test_every_algorithm_counts_its_vec_env_steps_saves_the_count_and_restarts_it_with_the_step_count(
    tiny_kwargs: dict[str, Any], tmp_path: Path
) -> None:
    """Guards against: a collection that does not advance the VecEnv-step count (a resumed run's callbacks then fall
    back to num_timesteps // n_envs), a zip without it, or a new learn() that keeps it (its callbacks start mid-grid)."""
    for model in (tiny_pearl(tiny_kwargs), tiny_finetune(), tiny_maml()):
        name = type(model).__name__
        model.learn(150)
        assert model.num_vec_env_steps == model.num_timesteps >= 150, name  # one env: one env step per VecEnv step
        model.save(tmp_path / name)
        loaded = type(model).load(tmp_path / f"{name}.zip", env=model.get_env())
        assert loaded.num_vec_env_steps == model.num_vec_env_steps, name
        loaded.learn(60, reset_num_timesteps=True)
        assert loaded.num_vec_env_steps == loaded.num_timesteps < model.num_timesteps, name


def _write_history(folder: Path, rows: list[tuple[int, float]], n: int = 2) -> None:
    """A meta_test_history.csv of evaluations (timesteps, adapted return) with k = 0..1 over n trajectories each."""
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "meta_test_history.csv", "w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["timesteps", "k", "n", "return_mean"])
        for timesteps, adapted in rows:
            writer.writerows([[timesteps, 0, n, adapted - 1.0], [timesteps, 1, n, adapted]])


@pytest.mark.parametrize(
    ("history", "n", "best_model_at", "carried", "best"),
    [
        ([(100, 5.0), (200, 7.0), (300, 6.0)], 2, 200, [100, 200], 7.0),  # past the resume point: dropped
        ([(100, 5.0), (200, 7.0), (300, 7.0)], 2, 200, [100, 200], 7.0),  # a tie later is not the saved best
        ([(100, 5.0), (300, 9.0)], 2, 300, [100], None),  # the saved best is past the resume point: this run's own
        ([(100, 5.0), (200, 7.0)], 2, 100, [100, 200], None),  # best_model.zip is another evaluation's model
        ([(100, 5.0), (200, 7.0)], 3, 200, [], None),  # other trajectories per k: nothing carried
    ],
)
def test_a_resumed_runs_evaluations_continue_the_cut_runs_history_and_best_model(
    tiny_kwargs: dict[str, Any],
    tmp_path: Path,
    history: list[tuple[int, float]],
    n: int,
    best_model_at: int,
    carried: list[int],
    best: float | None,
) -> None:
    """Guards against: a resumed run's folder held only the evaluations after the resume and a best_model.zip that was
    the best since the resume (worse than the cut run's best), or carried evaluations of a cut run measured past the
    checkpoint it resumes from, or measured with other settings, or a best score with another evaluation's model
    (a cut run that was itself resumed past its own cut run's best)."""
    model = _make(tiny_kwargs)
    cut, resumed = tmp_path / "cut", tmp_path / "resumed"
    _write_history(cut, history, n)
    model.num_timesteps = best_model_at
    model.save(cut / "best_model")
    model.num_timesteps = 250  # resumed from a checkpoint at 250 env steps
    folders = {"best_model_save_path": str(resumed), "log_path": str(resumed), "resumes": str(cut)}
    callback = MetaTestCallback(gym.make(NOISY_ENV), 50, n_tasks=2, n_adapt=1, **folders)
    callback.init_callback(model)
    assert (_evaluated_timesteps(resumed) if carried else []) == carried
    assert (resumed / "meta_test_history.csv").exists() == bool(carried)
    assert (resumed / "best_model.zip").exists() == (best is not None)
    if best is not None:
        assert (resumed / "best_model.zip").read_bytes() == (cut / "best_model.zip").read_bytes()
        assert callback.best_mean_reward == best
        callback.best_mean_reward = best + 1.0  # a better evaluation of this run: a later learn() keeps it
        callback.init_callback(model)
        assert callback.best_mean_reward == best + 1.0
    else:
        assert callback.best_mean_reward == -float("inf")


def test_an_unreadable_history_of_the_cut_run_starts_the_resumed_history_anew(
    tiny_kwargs: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Guards against: a cut history with an empty field (a file cut short, edited) failed the resume with a ValueError."""
    model = _make(tiny_kwargs)
    model.num_timesteps = 250
    cut, resumed = tmp_path / "cut", tmp_path / "resumed"
    cut.mkdir()
    (cut / "meta_test_history.csv").write_text("timesteps,k,n,return_mean\n100,0,2,-3.0\n,1,2,\n")
    callback = MetaTestCallback(gym.make(NOISY_ENV), 50, n_tasks=2, n_adapt=1, log_path=str(resumed), resumes=str(cut))
    callback.init_callback(model)
    assert "meta_test_history.csv cannot be read" in capsys.readouterr().out
    assert not (resumed / "meta_test_history.csv").exists() and callback.best_mean_reward == -float("inf")


def test_a_model_saved_before_vec_env_steps_were_counted_loads_with_its_env_steps(
    tiny_kwargs: dict[str, Any], tmp_path: Path
) -> None:
    """Guards against: a zip without num_vec_env_steps loaded with 0, so after one resume the next checkpoint saved only
    the VecEnv steps since that resume and a second resume put the callbacks off the grid."""
    model = _make(tiny_kwargs)
    model.learn(150)
    model.save(tmp_path / "new.zip")
    assert PEARLPlus.load(tmp_path / "new.zip").num_vec_env_steps == model.num_timesteps
    _copy_zip_data(tmp_path / "new.zip", tmp_path / "old.zip", num_vec_env_steps=None)  # what the older version wrote
    loaded = type(model).load(tmp_path / "old.zip", env=model.get_env())
    assert loaded.num_vec_env_steps == model.num_timesteps  # one env
    loaded.learn(100, reset_num_timesteps=False)
    assert loaded.num_vec_env_steps == loaded.num_timesteps > model.num_timesteps


def test_call_counting_callbacks_start_at_the_models_env_steps(tiny_kwargs: dict[str, Any], tmp_path: Path) -> None:
    """A resumed model's callbacks count on from its env steps (per VecEnv step), a new model's from 0."""
    model = _make(tiny_kwargs)
    checkpoints = ResumableCheckpointCallback(120, str(tmp_path), "rl_model")
    checkpoints.init_callback(model)
    assert checkpoints.n_calls == 0
    model.num_timesteps = 250  # as loaded from a checkpoint at 250 env steps
    for callback in (ResumableCheckpointCallback(120, str(tmp_path), "rl_model"), MetaTestCallback(gym.make(NOISY_ENV), 120)):
        callback.init_callback(model)
        assert callback.n_calls == 250, type(callback).__name__
    model.num_vec_env_steps = 130  # a model that counted its VecEnv steps (two envs, some idle): that count
    for callback in (ResumableCheckpointCallback(120, str(tmp_path), "rl_model"), MetaTestCallback(gym.make(NOISY_ENV), 120)):
        callback.init_callback(model)
        assert callback.n_calls == 130, type(callback).__name__


@pytest.mark.parametrize(
    ("during", "said"),
    [
        ("final meta-test", ["Received SIGTERM: stopping the final meta-test (the model is saved)"]),
        # guards against: a signal during the final save only said 'finishing the save first', the whole final
        # meta-test then ran, and interrupted.json said it was not written
        (
            "final save",
            ["Received SIGTERM: finishing the save first", "SIGTERM came during the save: the final meta-test is skipped"],
        ),
    ],
)
def test_a_signal_after_training_keeps_the_model_and_writes_no_meta_test(
    during: str, said: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """docs/reliability.md: a signal during the final meta-test (or the final save before it) leaves no meta_test.* (no
    partial numbers), the trained model saved, interrupted.json saying when, and the exit code 128 + signal."""
    if during == "final meta-test":
        faulty_envs.send_signals({420 + 10: signal.SIGTERM})  # training takes env steps 1-420; the meta-test follows
    else:
        from rl_zoo3.exp_manager import ExperimentManager

        save = ExperimentManager.save_trained_model

        def save_then_signalled(self: Any, model: Any) -> None:
            os.kill(os.getpid(), signal.SIGTERM)  # arrives while the model is being saved
            save(self, model)

        monkeypatch.setattr(ExperimentManager, "save_trained_model", save_then_signalled)
        faulty_envs.send_signals({})
    logs = tmp_path / "logs"
    run = logs / "pearlplus" / f"{SIGNAL_ENV}_1"
    cut = _train_signal_env(tmp_path, logs, check=False)
    assert cut.returncode == 128 + signal.SIGTERM, cut.stdout[-2000:] + cut.stderr[-2000:]
    for line in [*said, f"Stopped by SIGTERM during the {during}: training is complete"]:
        assert line in cut.stdout
    record = json.loads((run / "interrupted.json").read_text())
    assert record["signal"] == "SIGTERM" and record["during"] == during and record["num_timesteps"] == 420
    assert record["resume"] is None and not any(run.glob("meta_test.*"))
    assert PEARLPlus.load(run / f"{SIGNAL_ENV}.zip").num_timesteps == 420


# ----------------------------------------------------------------------------------------------
# SIGTERM during train.py's set-up: no half-made run folder; enjoy's latest run is the latest with a model
# ----------------------------------------------------------------------------------------------
def test_sigterm_during_the_set_up_leaves_no_run_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Guards against: the process died at once (no handler before training), leaving <algo>/<env>_<n>/ without a model."""

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
