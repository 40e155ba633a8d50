"""`reproduce reward-profile`: falls against living steps in a part-way run's replay buffer."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pearl_paper.reproduce.cli import main
from pearl_paper.reproduce.reward_profile import REWARD_PROFILE_FILE, reward_profile

HAZARD_ENV = "SafePointGoalMeta-v0"  # its episodes terminate in the hazard: falls, in the profile's terms


def test_reward_profile_by_hand() -> None:
    """Six transitions in windows of four: one fall (done, no time-out), one time-out that is not a fall."""
    rewards = np.array([-1.0, -0.5, -300.0, -1.5, -2.0, -100.0])
    dones = np.array([0, 0, 1, 0, 1, 1])
    timeouts = np.array([0, 0, 0, 0, 1, 0])
    heights = np.array([0.5, 0.6, 1.1, 0.5, 0.4, 0.1])
    profile = reward_profile(rewards, dones, timeouts, heights, window=4)
    assert profile["transitions"] == 6 and profile["falls"] == 2 and profile["window"] == 4
    first, second = profile["windows"]
    assert (first["start"], first["end"], first["falls"]) == (0, 4, 1)
    assert first["falls_per_1k"] == pytest.approx(250.0)
    assert first["living_reward_mean"] == pytest.approx(-1.0)  # (-1 - 0.5 - 1.5) / 3
    assert first["fall_reward_mean"] == pytest.approx(-300.0)
    assert first["fall_share_of_reward_magnitude"] == pytest.approx(300.0 / 303.0)
    assert (second["start"], second["end"], second["falls"]) == (4, 6, 1)
    assert second["living_reward_mean"] == pytest.approx(-2.0)  # the time-out is a living step
    assert second["fall_share_of_reward_magnitude"] == pytest.approx(100.0 / 102.0)
    assert profile["fall_heights"] == {"min": 0.1, "median": pytest.approx(0.6), "max": 1.1}


def test_reward_profile_without_falls_and_bad_input() -> None:
    profile = reward_profile(np.array([1.0, 2.0]), np.zeros(2), np.zeros(2), np.zeros(2), window=10)
    assert profile["falls"] == 0 and math.isnan(profile["windows"][0]["fall_reward_mean"])
    assert profile["windows"][0]["fall_share_of_reward_magnitude"] == 0.0
    with pytest.raises(ValueError, match=r"dones must have shape \(2,\) like rewards"):
        reward_profile(np.array([1.0, 2.0]), np.zeros(3), np.zeros(2), np.zeros(2), window=10)
    with pytest.raises(ValueError, match="window must be a positive number"):
        reward_profile(np.array([1.0]), np.zeros(1), np.zeros(1), np.zeros(1), window=0)


def _checkpointed_run(folder: Path, buffer_size: int) -> Any:
    """A FineTune run's checkpoint at 150 env steps in ``folder``, as a part-way harness run leaves it."""
    from pearl_paper.reproduce.checkpoint import RunCheckpoint
    from sb3_pearl import FineTune

    model = FineTune(
        "MlpPolicy",
        HAZARD_ENV,
        n_train_tasks=4,
        n_test_tasks=2,
        learning_starts=10,
        batch_size=8,
        buffer_size=buffer_size,
        seed=0,
    ).learn(150)
    checkpoint = RunCheckpoint(folder)
    files = checkpoint.save_model(model, None)
    checkpoint.write_state({"phase": "train", "files": files, "num_timesteps": 150})
    return model.replay_buffer


@pytest.mark.parametrize("buffer_size", [1000, 100])  # part-filled, and full after wrapping (oldest rows from pos on)
def test_reward_profile_command_reads_the_checkpoints_buffer(tmp_path: Path, buffer_size: int) -> None:
    buffer = _checkpointed_run(tmp_path, buffer_size)
    assert main(["reward-profile", str(tmp_path), "--window", "40"]) == 0
    profile = json.loads((tmp_path / REWARD_PROFILE_FILE).read_text())
    n = min(150, buffer_size)
    order = np.r_[buffer.pos : buffer_size, 0 : buffer.pos] if buffer.full else np.arange(n)
    falls = (buffer.dones[order, 0] > 0) & (buffer.timeouts[order, 0] == 0)
    assert profile["num_timesteps"] == 150 and profile["transitions"] == n
    assert [w["falls"] for w in profile["windows"]] == [int(falls[i : i + 40].sum()) for i in range(0, n, 40)]
    assert profile["falls"] > 0  # the hazard ends some of the random episodes
    living = buffer.rewards[order, 0][:40][~falls[:40]]
    assert profile["windows"][0]["living_reward_mean"] == pytest.approx(float(living.mean()))


def test_a_wrapped_buffer_is_read_oldest_first() -> None:
    """A full buffer of 5 rows after 7 transitions (reward = transition index, a fall at transition 4): rows 2-4 were
    written before rows 0-1, so the profile reads transitions 2, 3, 4, 5, 6 in that order."""
    from gymnasium import spaces
    from stable_baselines3.common.buffers import ReplayBuffer

    from pearl_paper.reproduce.reward_profile import buffer_reward_profile

    box = spaces.Box(-10.0, 10.0, (2,), np.float32)
    buffer = ReplayBuffer(5, box, spaces.Box(-1.0, 1.0, (1,), np.float32), handle_timeout_termination=True)
    for index in range(7):
        next_obs = np.array([[float(index), 0.0]], dtype=np.float32)
        infos = [{"TimeLimit.truncated": index == 6}]
        buffer.add(next_obs, next_obs, np.zeros((1, 1)), np.array([float(index)]), np.array([index in (4, 6)]), infos)
    assert buffer.full and buffer.pos == 2
    profile = buffer_reward_profile(buffer, window=3)
    assert [(w["start"], w["end"], w["falls"]) for w in profile["windows"]] == [(0, 3, 1), (3, 5, 0)]
    assert profile["windows"][0]["living_reward_mean"] == pytest.approx(2.5)  # transitions 2 and 3
    assert profile["windows"][0]["fall_reward_mean"] == pytest.approx(4.0)  # transition 4; 6 is a time-out
    assert profile["windows"][1]["living_reward_mean"] == pytest.approx(5.5)  # transitions 5 and 6
    assert profile["fall_heights"]["max"] == 4.0  # the fall's next observation, first entry


def test_reward_profile_command_refuses_a_folder_without_checkpoint(tmp_path: Path, capsys: Any) -> None:
    assert main(["reward-profile", str(tmp_path)]) == 2
    assert "has no checkpoint/ folder: give a part-way run's folder" in capsys.readouterr().err
    assert not (tmp_path / REWARD_PROFILE_FILE).exists()
    assert main(["reward-profile", str(tmp_path / "typo")]) == 2
    assert not (tmp_path / "typo").exists()  # nothing is created for a mistyped folder


def test_reward_profile_command_refuses_a_run_in_training_and_a_checkpoint_without_buffer(tmp_path: Path, capsys: Any) -> None:
    from pearl_paper.reproduce.checkpoint import RunCheckpoint
    from pearl_paper.reproduce.ownership import run_lock

    _checkpointed_run(tmp_path, 1000)
    with run_lock(tmp_path):  # another process training the run
        assert main(["reward-profile", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "is being run by another process" in err and "Traceback" not in err
    assert not (tmp_path / REWARD_PROFILE_FILE).exists()
    checkpoint = RunCheckpoint(tmp_path)
    state = checkpoint.read_state()
    assert state is not None
    state["files"] = {key: name for key, name in state["files"].items() if not key.startswith("replay")}
    checkpoint.write_state(state)
    assert main(["reward-profile", str(tmp_path)]) == 2
    assert "holds no replay buffer" in capsys.readouterr().err
