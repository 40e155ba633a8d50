"""Rollouts of ``pi(a | s, z)`` with a fixed z, fresh context data from prior rollouts, and the posteriors it gives.

The rollouts bypass the adaptation API: the model's ``current_z`` and observed context are left untouched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.buffers import MetaReplayBuffer
from sb3_pearl.common.seeding import derived_seed
from sb3_pearl.common.soft_actor_critic import evaluate_policy
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.evaluation.meta_test import SingleEnvRunner

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL

# Purposes mixed into the env seeds so that the rollouts of different measurements differ.
_CONTEXT, _VIOLATION, _ZERO, _CALIBRATION = range(4)


@dataclass
class FixedZRollout:
    """One trajectory of ``pi(a | s, z)`` with z held fixed."""

    observations: np.ndarray  # (T + 1, obs_dim): s_0 .. s_T (s_T: the observation after the last step)
    actions: np.ndarray  # (T, act_dim) network units: scaled Box actions in [-1, 1] or (T, 1) Discrete indices
    rewards: np.ndarray  # (T,) env rewards (not reward-scaled)
    log_probs: np.ndarray  # (T,) log pi(a_t | s_t, z) of the actions taken (nan for deterministic actions)
    cost: float  # sum of info["cost"]
    terminated: bool  # the episode ended in a terminal state (not a time limit or max_steps)

    @property
    def length(self) -> int:
        return len(self.rewards)

    @property
    def episode_return(self) -> float:
        return float(self.rewards.sum())

    @property
    def violated(self) -> bool:
        return self.cost > 0.0


def _act(model: PEARL, obs: np.ndarray, z: th.Tensor, deterministic: bool) -> tuple[np.ndarray, Any, float]:
    """Network action (act_dim,), env action and log-probability of ``pi(. | obs, z)``."""
    policy = model.policy
    x = th.cat([th.as_tensor(obs, dtype=th.float32, device=model.device).reshape(1, -1), z.reshape(1, -1)], dim=-1)
    with th.no_grad():
        if deterministic and not policy.discrete:
            action, log_prob = policy.actor(x, deterministic=True), math.nan
        else:
            pe = evaluate_policy(policy.actor, x)  # Box: a sampled action (1, A); Discrete: probs (1, n_actions)
            if pe.probs is not None:
                index = int(pe.probs.argmax()) if deterministic else int(th.multinomial(pe.probs[0], 1))
                return np.array([index], dtype=np.float32), index, float(pe.log_prob[0, index])
            assert pe.actions is not None
            action, log_prob = pe.actions, float(pe.log_prob)
    scaled = action.cpu().numpy().reshape(-1)
    env_action = policy.unscale_action(scaled).reshape(model.action_space.shape)  # type: ignore[arg-type]
    return scaled.astype(np.float32), env_action, log_prob


def rollout_with_z(
    model: PEARL,
    env: gym.Env | VecEnv,
    task: Task,
    z: th.Tensor | np.ndarray,
    deterministic: bool = True,
    seed: int | None = None,
    max_steps: int | None = None,
) -> FixedZRollout:
    """
    Roll out ``pi(a | s, z)`` on ``task`` with ``z`` held for the whole trajectory.

    The adaptation state of the model (``current_z``, observed context) is not touched.

    :param model: a PEARL / PEARL+ model
    :param env: a task-family env (gymnasium env, possibly wrapped, or a VecEnv of one env)
    :param task: the task, set with ``set_task`` before the reset
    :param z: the latent, shape (latent_dim,)
    :param deterministic: deterministic actions (the meta-test's default) or samples of the policy
    :param seed: seed of the env reset (None: not seeded)
    :param max_steps: stop after this many steps (None: until the episode ends)
    :return: the trajectory
    """
    runner = env if isinstance(env, SingleEnvRunner) else SingleEnvRunner(env)
    z_t = th.as_tensor(np.asarray(z.cpu() if isinstance(z, th.Tensor) else z), dtype=th.float32, device=model.device)
    runner.set_task(task)
    runner.seed(seed)
    obs = np.asarray(runner.reset(), dtype=np.float32)
    observations, actions, rewards, log_probs = [obs], [], [], []
    cost, terminated, done = 0.0, False, False
    while not done:
        action, env_action, log_prob = _act(model, obs, z_t, deterministic)
        next_obs, reward, terminated, truncated, info = runner.step(env_action)
        cost += float(info.get("cost", 0.0))
        obs = np.asarray(next_obs, dtype=np.float32)
        observations.append(obs)
        actions.append(action)
        rewards.append(reward)
        log_probs.append(log_prob)
        done = terminated or truncated or (max_steps is not None and len(rewards) >= max_steps)
    return FixedZRollout(
        observations=np.stack(observations),
        actions=np.stack(actions),
        rewards=np.asarray(rewards, dtype=np.float64),
        log_probs=np.asarray(log_probs, dtype=np.float64),
        cost=cost,
        terminated=bool(terminated),
    )


def _collect_context(
    model: PEARL, env: gym.Env | VecEnv, tasks: list[int], n_steps: int, seed: int, max_steps: int | None
) -> MetaReplayBuffer:
    """Fresh data of training tasks: ``n_steps`` per task with z from the prior (one per trajectory), stochastic actions."""
    buffer = MetaReplayBuffer(len(model.train_tasks), n_steps, n_steps, model.observation_space, model.action_space)
    for task in tasks:
        n_trajectory = 0
        while buffer.rl.size[task] < n_steps:
            z = th.randn(model.latent_dim, device=model.device)
            left = n_steps - int(buffer.rl.size[task])
            cap = left if max_steps is None else min(left, max_steps)
            seed_t = derived_seed(seed, _CONTEXT, task, n_trajectory)
            traj = rollout_with_z(model, env, model.train_tasks[task], z, False, seed_t, cap)
            for t in range(traj.length):
                done = traj.terminated and t == traj.length - 1
                row = (traj.observations[t], traj.actions[t], float(traj.rewards[t]), traj.observations[t + 1], done)
                buffer.rl.add(task, *row)
                buffer.context.add(task, *row)
            n_trajectory += 1
    return buffer


def _posteriors(model: PEARL, buffers: list[MetaReplayBuffer], tasks: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Posterior means and variances (n_tasks, L) from ``embedding_batch_size`` context transitions per task."""
    means, variances = [], []
    for buffer, task in zip(buffers, tasks):
        ctx = buffer.context.sample(np.array([task]), model.embedding_batch_size, model.device)
        with th.no_grad():
            context = model.policy.make_context(ctx.observations, ctx.actions, ctx.rewards, ctx.next_observations)
            mean, var = model.encoder.posterior(context)  # (1, L) each
        means.append(mean[0].cpu().numpy())
        variances.append(var[0].cpu().numpy())
    return np.stack(means).astype(np.float64), np.stack(variances).astype(np.float64)
