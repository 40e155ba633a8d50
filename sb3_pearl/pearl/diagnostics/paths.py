"""The prior policy's paths on point-robot tasks: where ``pi(a | s, z0)`` goes before it has seen the task.

For families whose observation is the 2-D position (``PointGoalMeta-v0``, ``SafePointGoalMeta-v0``,
``SparsePointGoalMeta-v0``), the k = 0 trajectories drawn over each task's goal and hazard show at a glance
whether the prior policy heads for *some* goal (PEARL's behaviour: z0 acts as a task) or keeps clear of
the region where any task's hazard may lie (what PEARL+'s prior term should teach).

The rollouts derive their env seeds as :func:`~sb3_pearl.pearl.diagnostics.violations.compute_violations` does
(``derived_seed(seed, _VIOLATION, draw, task)``): given the same task list and z0 draws, in the same order, they
are the trajectories it counts. (The point families reset to the origin, so the seeds do not change them.)
``python -m sb3_pearl.diagnose RUN --paths out.png`` draws them (:func:`sb3_pearl.evaluation.figures.plot_prior_paths`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.seeding import derived_seed
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.pearl.diagnostics.rollouts import _VIOLATION, FixedZRollout, rollout_with_z

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL


def check_position_observation(model: PEARL) -> None:
    """
    Raise a ValueError unless the model observes a 2-D position (the point families).

    :param model: a PEARL / PEARL+ model
    """
    shape = model.observation_space.shape
    if shape is None or len(shape) != 1 or shape[0] != 2:
        raise ValueError(
            f"prior paths need a 2-D position observation (a point family such as SafePointGoalMeta-v0), got shape {shape}"
        )


def prior_paths(
    model: PEARL,
    env: gym.Env | VecEnv,
    tasks: list[Task],
    z0: np.ndarray,
    seed: int,
    max_steps: int | None = None,
) -> list[list[FixedZRollout]]:
    """
    Deterministic k = 0 rollouts of every prior draw on every task, on a 2-D position observation.

    :param model: a PEARL / PEARL+ model of a point family
    :param env: an env of that family
    :param tasks: the tasks (held-out tasks, as the diagnostics use)
    :param z0: prior draws, shape (n_z0, latent_dim)
    :param seed: seed of the env resets (the diagnostics' ``seed``)
    :param max_steps: trajectory cap
    :return: ``paths[j][i]``: task j, draw i
    """
    check_position_observation(model)
    if z0.ndim != 2 or z0.shape[1] != model.latent_dim:
        raise ValueError(f"z0 must have shape (n_z0, {model.latent_dim}), got {z0.shape}")
    return [
        [rollout_with_z(model, env, task, z, True, derived_seed(seed, _VIOLATION, i, j), max_steps) for i, z in enumerate(z0)]
        for j, task in enumerate(tasks)
    ]
