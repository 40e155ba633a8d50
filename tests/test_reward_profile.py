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


def test_reward_profile_command_refuses_a_folder_without_checkpoint(tmp_path: Path, capsys: Any) -> None:
    assert main(["reward-profile", str(tmp_path)]) == 2
    assert "has no checkpoint to read: give a part-way run's folder" in capsys.readouterr().err
    assert not (tmp_path / REWARD_PROFILE_FILE).exists()
