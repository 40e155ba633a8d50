"""Calibration of the prior critic Q~(s0, a0, z0) against Monte-Carlo soft returns of the z0 policy."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.seeding import derived_seed
from sb3_pearl.common.soft_actor_critic import evaluate_policy, q_of_actions, q_of_policy, soft_value
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.pearl.diagnostics.prior import prior_term
from sb3_pearl.pearl.diagnostics.rollouts import _CALIBRATION, rollout_with_z

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL


def _critic_for_prior(model: PEARL) -> tuple[Any, str]:
    """The critic that scores the prior term: Q~ (separate) or Q (shared mode, PEARL), with its name."""
    prior = prior_term(model)
    if prior.critic is not None:
        if model.policy.prior_critic_input == "state":
            return prior.critic, "prior critic Q~(s, a) (z-free)"
        return prior.critic, "prior critic Q~(s, a, z0)"
    if prior.critic_mode == "shared":
        return model.critic, "critic Q(s, a, z0) (prior_critic='shared': the prior term's critic)"
    return model.critic, "critic Q(s, a, z0) (PEARL has no prior critic)"


def _state_z(observations: th.Tensor, z: th.Tensor) -> th.Tensor:
    return th.cat([observations, z], dim=-1)


def rank_correlation(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation (average ranks for ties); nan when either side is constant or has < 3 values."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if len(x) < 3 or x.std() == 0 or y.std() == 0:
        return math.nan
    rx, ry = _average_ranks(x), _average_ranks(y)
    return float(np.corrcoef(rx, ry)[0, 1])


def _average_ranks(values: np.ndarray) -> np.ndarray:
    order = np.argsort(values, kind="mergesort")
    ranks = np.empty(len(values))
    ranks[order] = np.arange(len(values), dtype=float)
    for value in np.unique(values):  # ties share their mean rank
        tied = values == value
        ranks[tied] = ranks[tied].mean()
    return ranks


def _relative_error(prediction: np.ndarray, target: np.ndarray) -> float:
    """mean |prediction - target| / mean |target| (nan when the targets are all 0)."""
    scale = np.abs(target).mean()
    return float(np.abs(prediction - target).mean() / scale) if scale > 0 else math.nan


def error_measures(q: np.ndarray, target: np.ndarray) -> dict[str, float]:
    """
    The calibration's error measures of predictions ``q`` against the Monte-Carlo targets, both of shape
    (n_z0, n_tasks), and the same measures for the task-blind reference (each pair predicted by its row's mean).

    :param q: the critic's values, one per (z0, task) pair
    :param target: the bootstrapped Monte-Carlo soft returns of the same pairs
    :return: ``bias``, ``abs_error_mean``, ``relative_error``, ``rank_corr``, ``task_blind_relative_error``,
        ``task_blind_rank_corr``
    """
    if q.ndim != 2 or q.shape != target.shape:
        raise ValueError(f"q and target must both have shape (n_z0, n_tasks), got {q.shape} and {target.shape}")
    blind = np.repeat(target.mean(axis=1, keepdims=True), target.shape[1], axis=1)  # (n_z0, n_tasks): the row's mean
    return {
        "bias": float((q - target).mean()),
        "abs_error_mean": float(np.abs(q - target).mean()),
        "relative_error": _relative_error(q, target),
        "rank_corr": rank_correlation(q.ravel(), target.ravel()),
        "task_blind_relative_error": _relative_error(blind, target),
        "task_blind_rank_corr": rank_correlation(blind.ravel(), target.ravel()),
    }


def compute_calibration(
    model: PEARL,
    env: gym.Env | VecEnv,
    tasks: list[Task],
    z0: np.ndarray,
    seed: int,
    max_steps: int | None,
) -> dict[str, Any]:
    """
    The prior critic at start states against Monte-Carlo returns of the z0 policy.

    Q~ is fitted (reward-scaled soft Bellman target, time limits bootstrapped) to

        Q~(s0, a0, z0) = E[ sum_{t>=0} gamma^t * reward_scale * r_t - ent_coef * sum_{t>=1} gamma^t * log pi(a_t | s_t, z0) ]

    under the *stochastic* policy ``pi(. | ., z0)``, averaged over the training tasks the meta-batches
    mix (the prior critic does not see the task). For each z0 and training task one stochastic
    trajectory from ``s0`` is rolled out; ``a0`` is its first action. ``mc_return`` is that sum over
    the trajectory; ``mc_return_bootstrapped`` adds ``gamma^T * V~(s_T, z0)`` when the trajectory was
    cut by the time limit (as the training target does; 0 after a true termination). A calibrated
    critic has ``bias = q - mc_return_bootstrapped`` near 0. The first-class measures (result.json
    ``prior_critic``, ``reproduce report``) are ``bias``, ``relative_error`` = mean ``|Q~ - MC|`` over the
    (z0, task) pairs divided by mean ``|MC|`` (scale-free: 0.25 means errors a quarter the size of the
    returns) and ``rank_corr``, Spearman's rank correlation of Q~ and MC over every (z0, task) pair
    (does Q~ order start states and prior draws as their returns do?).

    The prior critic does not see the task, so part of ``|Q~ - MC|`` is the spread of the returns over tasks (and over
    a single stochastic trajectory), which no task-blind critic removes. ``task_blind_relative_error`` and
    ``task_blind_rank_corr`` are the same two measures for the *task-blind reference*: every (z0, task) pair
    predicted by its z0's bootstrapped return averaged over the tasks rolled out, the value a task-blind critic
    fitted exactly by its squared loss would have (in-sample; it ignores what s0 and a0 add). It is a reference, not
    a strict floor: the relative error is an L1 measure, and a per-z0 median would score lower. The bootstrapped
    tail of a time-limited trajectory is the measured critic's own, so the reference moves a little with the critic.

    :param model: the model
    :param env: the env
    :param tasks: the training tasks rolled out
    :param z0: prior draws, shape (n_z0, L)
    :param seed: seed of the env resets
    :param max_steps: trajectory cap (a cut trajectory is bootstrapped like a time limit)
    :return: means over (z0, task) and the correlation over z0 draws of Q~ with the returns
    """
    critic, critic_name = _critic_for_prior(model)
    critic_features = model.policy.prior_critic_features if critic is prior_term(model).critic else _state_z
    ent_coef = model._current_ent_coef()
    discrete = model.policy.discrete
    q = np.zeros((len(z0), len(tasks)))
    mc = np.zeros_like(q)
    boot = np.zeros_like(q)
    env_returns = np.zeros_like(q)
    lengths = np.zeros_like(q)
    for i, z in enumerate(z0):
        z_t = th.as_tensor(z, dtype=th.float32, device=model.device)
        for j, task in enumerate(tasks):
            traj = rollout_with_z(model, env, task, z_t, False, derived_seed(seed, _CALIBRATION, i, j), max_steps)
            discounts = model.gamma ** np.arange(traj.length)  # (T,)
            soft = model.reward_scale * traj.rewards
            soft[1:] -= float(ent_coef) * traj.log_probs[1:]  # the entropy bonus enters from t = 1 on
            mc[i, j] = float((discounts * soft).sum())
            ends = th.as_tensor(traj.observations[[0, -1]], device=model.device)  # (2, obs_dim): s_0 and s_T
            x = th.cat([ends, z_t.expand(2, -1)], dim=-1)  # (2, obs_dim + L): the actor's input
            x_q = critic_features(ends, z_t.expand(2, -1))  # the critic's input (z-free for Q~(s, a))
            with th.no_grad():
                a0 = th.as_tensor(traj.actions[:1], device=model.device)  # (1, act_dim)
                q[i, j] = float(q_of_actions(critic, x_q[:1], a0, discrete).min(dim=0).values)
                tail = 0.0
                if not traj.terminated:
                    pe = evaluate_policy(model.actor, x[1:])
                    tail = float(soft_value(q_of_policy(critic, x_q[1:], pe), pe, ent_coef))
            boot[i, j] = mc[i, j] + model.gamma**traj.length * tail
            env_returns[i, j] = traj.episode_return
            lengths[i, j] = traj.length
    q_z, boot_z = q.mean(axis=1), boot.mean(axis=1)  # per z0 draw, averaged over tasks
    corr = float(np.corrcoef(q_z, boot_z)[0, 1]) if q_z.std() > 0 and boot_z.std() > 0 else math.nan
    return {
        "critic": critic_name,
        "n_tasks": len(tasks),
        "n_z0": len(z0),
        "gamma": model.gamma,
        "reward_scale": model.reward_scale,
        "ent_coef": float(ent_coef),
        "q_mean": float(q.mean()),
        "mc_return_mean": float(mc.mean()),
        "mc_return_bootstrapped_mean": float(boot.mean()),
        **error_measures(q, boot),
        "q_std_over_z0": float(q_z.std()),
        "mc_std_over_z0": float(boot_z.std()),
        "q_mc_corr_over_z0": corr,
        "env_return_mean": float(env_returns.mean()),
        "length_mean": float(lengths.mean()),
    }
