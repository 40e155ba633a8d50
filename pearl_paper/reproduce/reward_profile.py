"""Where a part-way run's reward comes from: falls against living steps, read from its checkpoint's replay buffer.

A fall (an unhealthy pose: the episode terminates without a time-out) on the locomotion families carries the
unhealthy penalty, one reward of ``unhealthy_penalty`` times the steps it skips. :func:`reward_profile` measures, in
windows of the buffer's transitions (in the order they were collected), how often falls happen, what a fall's reward
and a living step's reward are, and which share of the reward's magnitude the falls hold; and, per fall, the first
entry of the next observation, which on the MuJoCo locomotion families (their observation leaves out the torso's x,
y) is the torso's height, so a fall above the healthy range (a jump) is told from one below it (a collapse).

``python -m pearl_paper.reproduce reward-profile RUN_FOLDER`` writes it as ``reward_profile.json`` in the run's
folder (a small record to commit; the checkpoint it was read from is not).
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import numpy as np

from pearl_paper.reproduce.checkpoint import RunCheckpoint
from pearl_paper.reproduce.layout import write_json_atomic
from sb3_pearl.evaluation.meta_test import json_value

REWARD_PROFILE_FILE = "reward_profile.json"


def reward_profile(
    rewards: np.ndarray, dones: np.ndarray, timeouts: np.ndarray, next_heights: np.ndarray, window: int
) -> dict[str, Any]:
    """
    The reward profile of ``n`` transitions in the order they were collected.

    :param rewards: shape (n,), the env's rewards (unscaled)
    :param dones: shape (n,), 1 where the episode ended (termination or time-out)
    :param timeouts: shape (n,), 1 where it ended by the time limit
    :param next_heights: shape (n,), the first entry of each next observation (the torso height on the locomotion families)
    :param window: transitions per window (the last window may be shorter)
    :return: ``{"transitions", "falls", "window", "windows": [...], "fall_heights": {...}}``; each window holds
        ``start``, ``end``, ``falls``, ``falls_per_1k``, ``living_reward_mean``, ``fall_reward_mean`` (nan without a
        fall; null in the file), ``fall_share_of_reward_magnitude`` (sum of |r| over falls / sum of |r|)
    """
    arrays = {"rewards": rewards, "dones": dones, "timeouts": timeouts, "next_heights": next_heights}
    n = len(rewards)
    for name, array in arrays.items():
        if np.ndim(array) != 1 or len(array) != n:
            raise ValueError(f"{name} must have shape ({n},) like rewards, got {np.shape(array)}")
    if window < 1:
        raise ValueError(f"window must be a positive number of transitions, got {window}")
    rewards = np.asarray(rewards, dtype=np.float64)
    fall = (np.asarray(dones) > 0) & (np.asarray(timeouts) == 0)
    windows = []
    for start in range(0, n, window):
        end = min(start + window, n)
        r, f = rewards[start:end], fall[start:end]
        magnitude = float(np.abs(r).sum())
        windows.append(
            {
                "start": start,
                "end": end,
                "falls": int(f.sum()),
                "falls_per_1k": 1000.0 * float(f.mean()),
                "living_reward_mean": float(r[~f].mean()) if (~f).any() else float("nan"),
                "fall_reward_mean": float(r[f].mean()) if f.any() else float("nan"),
                "fall_share_of_reward_magnitude": float(np.abs(r[f]).sum()) / magnitude if magnitude > 0 else 0.0,
            }
        )
    heights = np.asarray(next_heights, dtype=np.float64)[fall]
    return {
        "transitions": n,
        "falls": int(fall.sum()),
        "window": window,
        "windows": windows,
        "fall_heights": {
            "min": float(heights.min()) if heights.size else float("nan"),
            "median": float(np.median(heights)) if heights.size else float("nan"),
            "max": float(heights.max()) if heights.size else float("nan"),
        },
    }


def buffer_reward_profile(buffer: Any, window: int) -> dict[str, Any]:
    """
    :func:`reward_profile` of an SB3 ``ReplayBuffer`` of one env, its transitions oldest first (a full buffer has
    wrapped: the rows from ``pos`` on were written before those up to ``pos``).

    :param buffer: the replay buffer
    :param window: transitions per window
    :return: the profile
    """
    name = type(buffer).__name__
    if not all(hasattr(buffer, key) for key in ("rewards", "dones", "timeouts", "next_observations", "pos", "full")):
        raise ValueError(f"the replay buffer is a {name}, not an SB3 ReplayBuffer of transitions")
    if buffer.next_observations is None:
        raise ValueError(f"the {name} keeps no next observations (optimize_memory_usage): the fall heights cannot be read")
    if getattr(buffer, "n_envs", 1) != 1:
        raise ValueError(f"the {name} holds {buffer.n_envs} envs' transitions; the profile reads a buffer of one env")
    if buffer.full:
        order = np.r_[buffer.pos : buffer.buffer_size, 0 : buffer.pos]
    else:
        order = np.arange(buffer.pos)
    next_observations = buffer.next_observations.reshape(buffer.next_observations.shape[0], -1)  # (size, obs_dim)
    return reward_profile(
        buffer.rewards[order, 0],
        buffer.dones[order, 0],
        buffer.timeouts[order, 0],
        next_observations[order, 0],
        window,
    )


def checkpoint_reward_profile(run_folder: str | Path, window: int = 20_000) -> Path:
    """
    Write ``reward_profile.json`` into a part-way run's folder from its checkpoint's replay buffer.

    :param run_folder: the run's folder (with a ``checkpoint/`` of a run whose learner keeps one SB3 replay buffer:
        the oracle, Fine-Tune)
    :param window: transitions per window
    :return: the file written
    """
    checkpoint = RunCheckpoint(run_folder)
    state = checkpoint.read_state()
    if state is None:
        raise ValueError(f"{run_folder} has no checkpoint to read: give a part-way run's folder")
    damage = checkpoint.damage(state)
    if damage is not None:
        raise ValueError(f"{checkpoint.folder}: {damage}")
    data = checkpoint.replay_bytes(state.get("files") or {})
    if data is None:
        raise ValueError(f"{checkpoint.folder} holds no replay buffer (a learner with its own buffers per task?)")
    try:
        buffer = pickle.loads(data)
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError) as error:
        raise ValueError(f"{checkpoint.folder}: its replay buffer does not unpickle ({error!r})") from None
    try:
        profile = buffer_reward_profile(buffer, window)
    except ValueError as error:
        raise ValueError(f"{checkpoint.folder}: {error}") from None
    profile["num_timesteps"] = int(state["num_timesteps"])
    path = Path(run_folder) / REWARD_PROFILE_FILE
    write_json_atomic(path, json_value(profile))  # nan (a window without falls) as null
    return path


__all__ = ["REWARD_PROFILE_FILE", "buffer_reward_profile", "checkpoint_reward_profile", "reward_profile"]
