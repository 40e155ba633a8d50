"""Reliability, second round (issue 40; docs/reliability.md, "Second round"): data lost or misreported, and one-line
errors for the unclear cases. Every test here failed before its fix."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from sb3_pearl.envs import FAMILIES
from tests.test_reliability import ENV_ID, tiny_finetune, tiny_maml, tiny_pearl


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
