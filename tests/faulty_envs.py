"""Task families that fail on purpose, for the reliability tests (``train.py --gym-packages tests.faulty_envs``).

- ``FailingSafePointGoalMeta-v0``: the SafePoint family whose ``step`` raises after ``fail_after`` steps;
- ``NonFiniteSafePointGoalMeta-v0``: the SafePoint family whose reward (or observation) turns nan / inf
  after ``fail_after`` steps;
- ``NoisyResetSafePointGoalMeta-v0``: a start drawn from the env's RNG (exact resume must restore it);
- ``SignalSafePointGoalMeta-v0``: NoisyReset that sends a signal to its own process at a chosen step.
"""

from __future__ import annotations

import os
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_pearl.envs.safe_point_goal import SafePointGoalMetaEnv


class FailingSafePointGoalEnv(SafePointGoalMetaEnv):
    """SafePoint whose ``step`` raises ``RuntimeError`` after ``fail_after`` steps of this env instance."""

    def __init__(self, fail_after: int = 200, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.fail_after = fail_after
        self.n_steps = 0

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.n_steps += 1
        if self.n_steps > self.fail_after:
            raise RuntimeError("the simulator crashed (on purpose)")
        return super().step(action)


class NonFiniteSafePointGoalEnv(SafePointGoalMetaEnv):
    """SafePoint whose ``what`` (``"reward"`` or ``"obs"``) becomes ``value`` after ``fail_after`` steps."""

    def __init__(self, fail_after: int = 50, what: str = "reward", value: float = float("nan"), **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.fail_after, self.what, self.value = fail_after, what, value
        self.n_steps = 0

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = super().step(action)
        self.n_steps += 1
        if self.n_steps > self.fail_after:
            if self.what == "reward":
                reward = self.value
            else:
                obs = np.full_like(obs, self.value)
        return obs, reward, terminated, truncated, info


for _env_id, _cls in (
    ("FailingSafePointGoalMeta-v0", FailingSafePointGoalEnv),
    ("NonFiniteSafePointGoalMeta-v0", NonFiniteSafePointGoalEnv),
):
    if _env_id not in gym.registry:
        gym.register(_env_id, entry_point=_cls, max_episode_steps=30)


class NoisyResetSafePointGoalEnv(SafePointGoalMetaEnv):
    """SafePoint whose start position is drawn from the env's ``np_random`` (the env RNG matters for exact resume)."""

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = super().reset(seed=seed, options=options)
        self._pos = self.np_random.uniform(-0.05, 0.05, size=2)
        return self._obs(), info


if "NoisyResetSafePointGoalMeta-v0" not in gym.registry:
    gym.register("NoisyResetSafePointGoalMeta-v0", entry_point=NoisyResetSafePointGoalEnv, max_episode_steps=30)


SIGNALS: dict[int, int] = {}  # env steps taken in this process -> the signal the step sends to the process itself
_steps_taken = [0]


class SignalSafePointGoalEnv(NoisyResetSafePointGoalEnv):
    """
    NoisyReset SafePoint whose step number ``n`` (counted over the process) sends ``SIGNALS[n]`` to the process itself:
    a SIGTERM / Ctrl-C at a chosen step, for the interruption tests (``tests/test_interruptions.py``).
    """

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        result = super().step(action)
        _steps_taken[0] += 1
        if _steps_taken[0] in SIGNALS:
            os.kill(os.getpid(), SIGNALS.pop(_steps_taken[0]))
        return result


def send_signals(plan: dict[int, int]) -> None:
    """Send ``plan[n]`` at the ``n``-th env step from now (counted over every ``SignalSafePointGoalMeta-v0`` env)."""
    SIGNALS.clear()
    SIGNALS.update(plan)
    _steps_taken[0] = 0


if "SignalSafePointGoalMeta-v0" not in gym.registry:
    gym.register("SignalSafePointGoalMeta-v0", entry_point=SignalSafePointGoalEnv, max_episode_steps=30)
