"""Episode sampling for MAML: the data side of rollouts over a VecEnv, and batches of observed episodes.

``MAML._collect_episodes`` rolls out the meta-parameters ``theta`` or one parameter set per task
(pre- and post-adaptation phases of training) with :func:`pick_task`, :func:`env_actions` and
:func:`reset_one`. For the adaptation API (meta-test), :func:`observed_action` stores an observed
action the way the sampler does and :func:`episodes_to_batch` pads the recorded trajectories into the
same :class:`EpisodeBatch` layout.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.adaptation import stored_action
from sb3_pearl.maml.policies import MAMLPolicy
from sb3_pearl.maml.type_aliases import EpisodeBatch

# One recorded episode: observations, stored actions and rewards, one entry per step.
Episode = tuple[list[np.ndarray], list[np.ndarray], list[float]]


def act_store_dim(policy: MAMLPolicy) -> int:
    """
    Width of a stored action: the action dimension for Box actions, 1 (the index) for Discrete ones.

    :param policy: the MAML policy
    :return: the last dimension of :attr:`EpisodeBatch.actions`
    """
    return policy.action_dim if policy.continuous else 1


def env_actions(policy: MAMLPolicy, raw: th.Tensor) -> np.ndarray:
    """
    Raw policy samples -> actions for the env (Box: clip to [-1, 1] and rescale to the box).

    :param policy: the MAML policy
    :param raw: samples of the policy's distribution, shape ``(n_envs, act_dim)`` or ``(n_envs,)``
    :return: the actions to send to the env
    """
    if policy.continuous:
        return policy.unscale_action(raw.clamp(-1.0, 1.0).cpu().numpy())
    return raw.cpu().numpy()


def reset_one(env: VecEnv, env_idx: int) -> np.ndarray:
    """
    Reset one env of a VecEnv explicitly.

    :param env: the VecEnv
    :param env_idx: index of the env to reset
    :return: its first observation, float32
    """
    obs = env.env_method("reset", indices=[env_idx])[0][0]
    return np.asarray(obs, dtype=np.float32)


def pick_task(
    preferred: int | None, next_episode: np.ndarray, n_eps: int, env_slot: list[tuple[int, int] | None]
) -> int | None:
    """
    The task an env runs next: its current one while it has episodes left, else a task nobody runs,
    then the one with most episodes left.

    :param preferred: the env's current task, or None (initial assignment)
    :param next_episode: index of the next unassigned episode of each task, shape ``(T,)``
    :param n_eps: episodes per task
    :param env_slot: the (task, episode) run by each env, None for an idle env
    :return: the task index, or None when every episode is assigned
    """
    if preferred is not None and next_episode[preferred] < n_eps:
        return preferred
    busy = {slot[0] for slot in env_slot if slot is not None}
    remaining = n_eps - next_episode
    candidates = [j for j in range(len(next_episode)) if remaining[j] > 0]
    if not candidates:
        return None
    # a task nobody runs first, then the one with most episodes left
    return max(candidates, key=lambda j: (j not in busy, remaining[j]))


def episodes_to_batch(episodes: list[Episode], obs_dim: int, store_dim: int) -> EpisodeBatch:
    """
    Pad the episodes recorded on one task into an :class:`EpisodeBatch` with ``T = 1``.

    :param episodes: the episodes (observations, stored actions, rewards), at least one
    :param obs_dim: size of a flattened observation
    :param store_dim: width of a stored action (see :func:`act_store_dim`)
    :return: the batch, padded to the longest episode
    """
    horizon = max(len(ep[2]) for ep in episodes)
    n_eps = len(episodes)
    observations = np.zeros((1, n_eps, horizon, obs_dim), dtype=np.float32)
    actions = np.zeros((1, n_eps, horizon, store_dim), dtype=np.float32)
    rewards = np.zeros((1, n_eps, horizon), dtype=np.float32)
    lengths = np.zeros((1, n_eps), dtype=np.int64)
    for e, (ep_obs, ep_actions, ep_rewards) in enumerate(episodes):
        n = len(ep_rewards)
        observations[0, e, :n] = np.stack(ep_obs)
        actions[0, e, :n] = np.stack(ep_actions)
        rewards[0, e, :n] = ep_rewards
        lengths[0, e] = n
    return EpisodeBatch(observations, actions, rewards, lengths)


def observed_action(policy: MAMLPolicy, action_space: spaces.Space, action: Any) -> np.ndarray:
    """
    An action passed to ``observe()`` as the sampler stores it: for Box actions, the raw (unclipped,
    normalised) sample behind the env action when it is the one :meth:`MAML.predict` just returned.

    :param policy: the MAML policy (its ``last_raw_actions`` come from the last ``predict``)
    :param action_space: the model's action space
    :param action: the action sent to the env
    :return: float32 array, shape ``(act_dim,)`` for Box, ``(1,)`` for Discrete
    """
    stored = stored_action(action_space, action)
    if policy.continuous:
        scaled = stored
        raw = policy.last_raw_actions
        # Recover the unclipped sample behind the (clipped) env action when it is the one predict() returned.
        if raw is not None and raw.shape[0] == 1:
            raw_np = raw.cpu().numpy().reshape(-1)
            if np.allclose(np.clip(raw_np, -1.0, 1.0), scaled, atol=1e-5):
                scaled = raw_np
        stored = np.asarray(scaled, dtype=np.float32).reshape(-1)
    return stored
