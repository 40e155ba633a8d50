"""Episode sampling for MAML: rollouts of many tasks over a VecEnv, and batches of observed episodes.

:func:`collect_episodes` rolls out the meta-parameters ``theta`` or one parameter set per task
(pre- and post-adaptation phases of training). For the adaptation API (meta-test),
:func:`observed_action` stores an observed action the way the sampler does and
:func:`episodes_to_batch` pads the recorded trajectories into the same :class:`EpisodeBatch` layout.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.adaptation import stored_action
from sb3_pearl.common.divergence import check_env_step
from sb3_pearl.common.tasks import set_vec_env_task
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.maml.policies import MAMLPolicy, Params
from sb3_pearl.maml.type_aliases import EpisodeBatch

if TYPE_CHECKING:
    from sb3_pearl.maml.maml import MAML

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


def collect_episodes(
    model: MAML, tasks: list[Task], params: Params | None, callback: BaseCallback | None = None
) -> tuple[EpisodeBatch, bool]:
    """
    Roll out ``model.episodes_per_task`` trajectories on each task, spreading them over the envs.

    Each env keeps running episodes of its current task (the task sticks across auto-resets) and
    switches (``set_task`` then an explicit reset) only when that task has no episode left.
    Adds the env steps taken to ``model.num_timesteps``.

    :param model: the MAML model (its env, policy, device, ``episodes_per_task`` and ``max_episode_steps``)
    :param tasks: the ``T`` tasks
    :param params: per-task parameters (every tensor with leading dimension ``T``), or None for ``theta``
    :param callback: called once per VecEnv step; None during tests
    :return: the padded episodes and whether training should continue (callback result)
    """
    assert model.env is not None and model.max_episode_steps is not None
    env = model.env
    policy = model.policy
    n_envs = env.num_envs
    n_tasks, n_eps, horizon = len(tasks), model.episodes_per_task, model.max_episode_steps
    obs_dim = policy.obs_dim
    observations = np.zeros((n_tasks, n_eps, horizon, obs_dim), dtype=np.float32)
    actions = np.zeros((n_tasks, n_eps, horizon, act_store_dim(policy)), dtype=np.float32)
    rewards = np.zeros((n_tasks, n_eps, horizon), dtype=np.float32)
    lengths = np.zeros((n_tasks, n_eps), dtype=np.int64)

    next_episode = np.zeros(n_tasks, dtype=np.int64)  # next unassigned episode of each task
    env_slot: list[tuple[int, int] | None] = [None] * n_envs  # (task, episode) run by each env
    env_t = np.zeros(n_envs, dtype=np.int64)

    def pick_task(preferred: int | None) -> int | None:
        if preferred is not None and next_episode[preferred] < n_eps:
            return preferred
        busy = {slot[0] for slot in env_slot if slot is not None}
        remaining = n_eps - next_episode
        candidates = [j for j in range(n_tasks) if remaining[j] > 0]
        if not candidates:
            return None
        # a task nobody runs first, then the one with most episodes left
        return max(candidates, key=lambda j: (j not in busy, remaining[j]))

    # Initial assignment: one task per env, applied by a reset of all envs.
    for i in range(n_envs):
        task_idx = pick_task(None)
        if task_idx is None:
            break
        env_slot[i] = (task_idx, int(next_episode[task_idx]))
        next_episode[task_idx] += 1
        set_vec_env_task(env, tasks[task_idx], [i])
    obs = np.asarray(env.reset(), dtype=np.float32).reshape(n_envs, obs_dim)

    continue_training = True
    while any(slot is not None for slot in env_slot):
        active = [i for i in range(n_envs) if env_slot[i] is not None]
        with th.no_grad():
            obs_t = th.as_tensor(obs, device=model.device)
            if params is None:
                raw = policy.sample(obs_t)
            else:
                task_of_env = th.as_tensor([slot[0] if slot is not None else 0 for slot in env_slot], device=model.device)
                env_params = {name: value[task_of_env] for name, value in params.items()}
                raw = policy.batched_distribution(obs_t.unsqueeze(1), env_params).sample().squeeze(1)
        new_obs, step_rewards, dones, infos = env.step(env_actions(policy, raw))
        # Divergence guard: a non-finite observation or reward is an error naming the env, task and timestep.
        check_env_step(env, new_obs, step_rewards, dones, infos, model.num_timesteps, type(model).__name__, active)
        new_obs = np.asarray(new_obs, dtype=np.float32).reshape(n_envs, obs_dim)
        raw_np = raw.cpu().numpy().reshape(n_envs, -1)

        for i in active:
            slot = env_slot[i]
            assert slot is not None
            task_idx, ep_idx = slot
            t = env_t[i]
            observations[task_idx, ep_idx, t] = obs[i]
            actions[task_idx, ep_idx, t] = raw_np[i]
            rewards[task_idx, ep_idx, t] = step_rewards[i]
            env_t[i] += 1
            if not (dones[i] or env_t[i] >= horizon):
                continue
            lengths[task_idx, ep_idx] = env_t[i]
            env_t[i] = 0
            next_task = pick_task(task_idx)
            if next_task is None:
                env_slot[i] = None
                continue
            env_slot[i] = (next_task, int(next_episode[next_task]))
            next_episode[next_task] += 1
            if next_task != task_idx:
                set_vec_env_task(env, tasks[next_task], [i])
                new_obs[i] = reset_one(env, i)
            elif not dones[i]:  # cut at max_episode_steps before the env's own limit
                new_obs[i] = reset_one(env, i)
            # else: the VecEnv auto-reset already started a new episode of the same (sticky) task
        obs = new_obs

        model.num_timesteps += len(active)
        if callback is not None:
            # the callback sees the rollout's locals, with the model as "self" (as when this was a method)
            callback.update_locals({**locals(), "self": model})
            if not callback.on_step():
                continue_training = False
                break
    return EpisodeBatch(observations, actions, rewards, lengths), continue_training


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
