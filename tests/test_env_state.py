"""The envs' mid-episode state saved with a model (sb3_pearl.common.env_state): every family continues bit for bit."""

from __future__ import annotations

import re
import threading
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

import sb3_pearl  # noqa: F401  (registers the families)
from pearl_paper.reproduce.checkpoint import RunCheckpoint
from sb3_pearl import PEARLPlus
from sb3_pearl.common import env_state
from sb3_pearl.common.env_state import EnvStateError, capture_env_state, restore_env_state
from tests.conftest import TINY


def vec_env(env_id: str, n_envs: int = 2, seed: int = 0) -> DummyVecEnv:
    env = DummyVecEnv([lambda: Monitor(gym.make(env_id)) for _ in range(n_envs)])
    env.seed(seed)
    env.reset()
    return env


def transitions(env: DummyVecEnv, actions: list[np.ndarray]) -> list[tuple[np.ndarray, ...]]:
    return [tuple(np.copy(x) for x in env.step(action)[:3]) for action in actions]


# The paper's families (MuJoCo Walker / Ant: MjData; highway-env: the road, its vehicles and the observation type that
# points back to its env), the safe point robot, and the point maze, which composes gymnasium-robotics' maze env.
@pytest.mark.parametrize(
    "env_id",
    ["Walker2dVelMeta-v0", "AntVelMeta-v0", "HighwayMergeMeta-v0", "SafePointGoalMeta-v0", "PointMazeGoalMeta-v0"],
)
def test_a_restored_env_continues_its_episodes_bit_for_bit(env_id: str) -> None:
    env = vec_env(env_id)
    rng = np.random.default_rng(0)
    space = env.action_space
    actions = [np.stack([space.sample() for _ in range(2)]) for _ in range(40)]
    if isinstance(space, gym.spaces.Box):
        actions = [rng.uniform(space.low, space.high, size=(2, *space.shape)).astype(space.dtype) for _ in range(40)]
    transitions(env, actions[:15])  # mid-episode
    state = capture_env_state(env)
    assert state is not None
    expected = transitions(env, actions[15:])  # runs past episode ends (auto-resets) for the short-episode families

    other = vec_env(env_id, seed=123)  # another seed, another state
    transitions(other, actions[:3])
    assert restore_env_state(other, state)
    for (obs, reward, done), (obs2, reward2, done2) in zip(expected, transitions(other, actions[15:])):
        np.testing.assert_array_equal(obs, obs2)
        np.testing.assert_array_equal(reward, reward2)
        np.testing.assert_array_equal(done, done2)


def test_an_env_of_another_structure_is_left_alone() -> None:
    state = capture_env_state(vec_env("SafePointGoalMeta-v0"))
    assert state is not None
    assert not restore_env_state(vec_env("SafePointGoalMeta-v0", n_envs=3), state)  # another number of envs
    bare = DummyVecEnv([lambda: gym.make("SafePointGoalMeta-v0")] * 2)  # no Monitor: another wrapper chain
    assert not restore_env_state(bare, state)
    normalized = VecNormalize(vec_env("SafePointGoalMeta-v0"))  # VecEnv wrappers are looked through
    assert capture_env_state(normalized) is not None and restore_env_state(normalized, state)


def test_envs_in_other_processes_and_unpicklable_state_are_not_captured() -> None:
    subproc = SubprocVecEnv([lambda: gym.make("SafePointGoalMeta-v0")], start_method="fork")
    try:
        assert capture_env_state(subproc) is None
    finally:
        subproc.close()
    env = vec_env("SafePointGoalMeta-v0")
    env.envs[0].unwrapped.lock = threading.Lock()  # type: ignore[attr-defined]
    with pytest.warns(UserWarning, match=r"state of env 0 cannot be saved: SafePointGoalMetaEnv\.lock does not pickle"):
        assert capture_env_state(env) is None


def test_a_snapshot_another_mujoco_cannot_read_is_a_clear_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """MuJoCo 4.0.1 refuses an MjData pickled by 4.0.0 ("Invalid serialized mjModel"): evaluation loads warn and reset,
    the harness' exact resume stops with both versions and what to do."""
    import mujoco

    env = vec_env("HalfCheetahVelMeta-v0", n_envs=1)
    transitions(env, [np.zeros((1, 6), dtype=np.float32)] * 5)
    state = capture_env_state(env)
    assert state is not None and state["mujoco"] == mujoco.__version__  # recorded with the snapshot

    model = PEARLPlus("MlpPolicy", "HalfCheetahVelMeta-v0", seed=0, **{**TINY, "num_initial_steps": 30})
    model.learn(30)  # mid-episode: the zip holds the envs' open episodes
    model.save(tmp_path / "model.zip")
    checkpoint = RunCheckpoint(tmp_path / "run")
    files = checkpoint.save_model(model, None)

    def refuse(self: Any) -> Any:
        raise ValueError("Invalid serialized mjModel.")

    monkeypatch.setattr(env_state._Unpickler, "load", refuse)
    with pytest.raises(ValueError, match="Invalid serialized mjModel") as same_version:  # the same MuJoCo: a bug, raised whole
        restore_env_state(vec_env("HalfCheetahVelMeta-v0", n_envs=1), state)
    assert not isinstance(same_version.value, EnvStateError)
    monkeypatch.setattr(env_state, "_mujoco_version", lambda: "9.9.9")  # this process now has another release
    saved = re.escape(mujoco.__version__)
    with pytest.raises(
        EnvStateError, match=rf"written with MuJoCo {saved} and this process has MuJoCo 9\.9\.9.*mujoco=={saved}"
    ):
        restore_env_state(vec_env("HalfCheetahVelMeta-v0", n_envs=1), state)

    with pytest.warns(UserWarning, match=r"Invalid serialized mjModel.*pip install mujoco==.*new episodes instead"):
        loaded = PEARLPlus.load(tmp_path / "model.zip", env=gym.make("HalfCheetahVelMeta-v0"))
    assert loaded._last_obs is None  # reset before its next learn(), as SB3 does; the weights are whole
    for name, tensor in model.policy.state_dict().items():
        assert th.equal(tensor, loaded.policy.state_dict()[name])
    loaded.learn(10, reset_num_timesteps=False)  # and it trains on from fresh episodes
    assert loaded.num_timesteps > model.num_timesteps

    with pytest.raises(EnvStateError, match=r"pip install mujoco==.*or restart the run from zero with --force"):
        checkpoint.load_model(
            {"files": files, "num_timesteps": model.num_timesteps}, PEARLPlus, gym.make("HalfCheetahVelMeta-v0")
        )
