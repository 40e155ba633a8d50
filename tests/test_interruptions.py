"""Stops and checkpoints between two gradient steps: a stop lands within one gradient step at any budget and resumes
exactly; periodic checkpoints taken inside an iteration's gradient steps resume exactly; the ETA comes from the first
gradient steps instead of after a whole iteration."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

import tests.faulty_envs  # noqa: F401  (registers the noisy-reset family)
from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.common.callbacks import gradient_step_event
from sb3_pearl.evaluation import progress
from sb3_pearl.evaluation.callbacks import ResumableCheckpointCallback, checkpoint_replay_buffer_path
from sb3_pearl.evaluation.progress import TrainingProgressCallback
from sb3_pearl.zoo.flags import parse_project_flags
from sb3_pearl.zoo.interruptions import StopOnSignalCallback
from sb3_pearl.zoo.usage import UsageError
from tests.conftest import write_model_zip

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


def test_a_part_filled_sac_buffer_is_saved_compact_and_loads_to_the_same_rows(tmp_path: Path) -> None:
    """SB3 pickles all buffer_size rows of a replay buffer; the project's save keeps the filled ones (a checkpoint of a
    part-way 500k Ant run was 1.8 GB), and the load restores the full allocation, rows past pos zero as SB3 makes them."""
    from sb3_pearl import FineTune

    kwargs: dict[str, Any] = dict(n_train_tasks=4, n_test_tasks=2, learning_starts=10, batch_size=8, seed=0)
    model = FineTune("MlpPolicy", NOISY_ENV, buffer_size=100_000, **kwargs)  # far more rows than are filled
    model.learn(150)
    model.save_replay_buffer(tmp_path / "buffer")
    full = model.replay_buffer
    assert (tmp_path / "buffer.pkl").stat().st_size < 0.05 * full.observations.nbytes
    other = FineTune("MlpPolicy", NOISY_ENV, buffer_size=100_000, **kwargs)
    other.load_replay_buffer(tmp_path / "buffer.pkl")
    buffer = other.replay_buffer
    assert (buffer.pos, buffer.full, buffer.buffer_size) == (full.pos, full.full, full.buffer_size)
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        np.testing.assert_array_equal(getattr(buffer, name), getattr(full, name))
    assert full.observations.shape[0] == 100_000  # the model's own buffer was left whole by the save


def test_an_older_checkpoint_is_compacted_in_place_and_loads_the_same_buffer(tmp_path: Path) -> None:
    """`reproduce compact`: a checkpoint written with the whole allocation (before compact buffers) is rewritten with
    the filled rows only; the state names the new parts, the old ones are gone, and loading it gives the same buffer."""
    import pickle

    from pearl_paper.reproduce.checkpoint import PART_BYTES, RunCheckpoint
    from sb3_pearl import FineTune

    kwargs: dict[str, Any] = dict(n_train_tasks=4, n_test_tasks=2, learning_starts=10, batch_size=8, seed=0)
    model = FineTune("MlpPolicy", NOISY_ENV, buffer_size=200_000, **kwargs).learn(150)
    checkpoint = RunCheckpoint(tmp_path)
    files = checkpoint.save_model(model, None)
    whole = pickle.dumps(model.replay_buffer)  # as an older save wrote it: every allocated row
    assert len(whole) > PART_BYTES / 10
    files = {key: name for key, name in files.items() if not key.startswith("replay")}
    files.update(checkpoint._write_parts("replay_150.pkl", whole, "replay"))
    checkpoint.write_state({"phase": "train", "files": files, "num_timesteps": 150})
    before, after = checkpoint.compact_replay()
    assert before == len(whole) and after < before / 20
    state = checkpoint.read_state()
    assert state is not None and "replay_150.pkl" not in state["files"].values()
    assert not (checkpoint.folder / "replay_150.pkl").exists() and any(checkpoint.folder.glob("replay_150_compact*"))
    resumed = checkpoint.load_model(state, FineTune, gym.make(NOISY_ENV))
    for name in ("observations", "actions", "rewards", "dones"):
        np.testing.assert_array_equal(getattr(resumed.replay_buffer, name), getattr(model.replay_buffer, name))
    files_before = dict(checkpoint.read_state()["files"])  # type: ignore[index]
    mtimes = {name: (checkpoint.folder / name).stat().st_mtime_ns for name in files_before.values()}
    again, again_after = checkpoint.compact_replay()  # compact already: nothing is rewritten
    assert again == again_after and checkpoint.read_state()["files"] == files_before  # type: ignore[index]
    assert all((checkpoint.folder / name).stat().st_mtime_ns == mtime for name, mtime in mtimes.items())


def test_a_buffer_that_keeps_next_observations_in_place_is_not_compacted() -> None:
    """With optimize_memory_usage SB3 keeps the last next observation in observations[pos]: cutting at pos would lose
    it, so such a buffer is pickled whole."""
    from stable_baselines3.common.buffers import ReplayBuffer

    from sb3_pearl.common.persistence import compact_buffer

    env = gym.make(NOISY_ENV)
    buffer = ReplayBuffer(
        100, env.observation_space, env.action_space, optimize_memory_usage=True, handle_timeout_termination=False
    )
    for _ in range(3):
        obs = env.observation_space.sample()[None]
        buffer.add(obs, obs + 1, env.action_space.sample()[None], np.zeros(1), np.zeros(1), [{}])
    assert compact_buffer(buffer) is buffer
    plain = ReplayBuffer(100, env.observation_space, env.action_space)
    compact = compact_buffer(plain)
    assert compact is not plain and compact_buffer(compact) is compact  # compacting twice changes nothing


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
