"""Violation rate of the prior policy at k = 0 against the distance of z0 to the training-task posteriors."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.seeding import derived_seed
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.pearl.diagnostics.rollouts import _VIOLATION, _ZERO, rollout_with_z

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL


def compute_violations(
    model: PEARL,
    env: gym.Env | VecEnv,
    tasks: list[Task],
    z0: np.ndarray,
    posterior_means: np.ndarray,
    seed: int,
    max_steps: int | None,
) -> dict[str, Any]:
    """
    Violation rate at k = 0 (deterministic actions) against the distance of z0 to the nearest posterior mean.

    :param model: the model
    :param env: the env
    :param tasks: the tasks rolled out (held-out tasks)
    :param z0: prior draws, shape (n_z0, L)
    :param posterior_means: training-task posterior means, shape (n_tasks, L)
    :param seed: seed of the env resets
    :param max_steps: trajectory cap
    :return: overall rate, the rate per distance tercile, the rate at z = 0
    """
    distance = np.linalg.norm(z0[:, None] - posterior_means[None], axis=-1).min(axis=1)  # (n_z0,)
    violated = np.zeros((len(z0), len(tasks)))
    returns = np.zeros((len(z0), len(tasks)))
    for i, z in enumerate(z0):
        for j, task in enumerate(tasks):
            traj = rollout_with_z(model, env, task, z, True, derived_seed(seed, _VIOLATION, i, j), max_steps)
            violated[i, j], returns[i, j] = traj.violated, traj.episode_return
    zero = [
        rollout_with_z(model, env, task, np.zeros(model.latent_dim), True, derived_seed(seed, _ZERO, j), max_steps)
        for j, task in enumerate(tasks)
    ]
    edges = np.quantile(distance, [0.0, 1 / 3, 2 / 3, 1.0])
    bins = np.clip(np.searchsorted(edges[1:-1], distance, side="right"), 0, 2)  # tercile of each draw
    terciles = []
    for b, name in enumerate(("near", "middle", "far")):
        members = bins == b
        terciles.append(
            {
                "bin": name,
                "distance_low": float(edges[b]),
                "distance_high": float(edges[b + 1]),
                "n_z0": int(members.sum()),
                "violation_rate": float(violated[members].mean()) if members.any() else math.nan,
                "return_mean": float(returns[members].mean()) if members.any() else math.nan,
            }
        )
    per_draw = violated.mean(axis=1)
    corr = float(np.corrcoef(distance, per_draw)[0, 1]) if per_draw.std() > 0 and distance.std() > 0 else math.nan
    return {
        "n_tasks": len(tasks),
        "n_z0": len(z0),
        "violation_rate": float(violated.mean()),
        "return_mean": float(returns.mean()),
        "distance_mean": float(distance.mean()),
        "distance_violation_corr": corr,
        "terciles": terciles,
        "z_zero_violation_rate": float(np.mean([t.violated for t in zero])),
        "z_zero_return_mean": float(np.mean([t.episode_return for t in zero])),
    }
