"""``AntGoalMeta-v0``: PEARL's Ant-Goal-2D, reach a goal position on the plane.

Gymnasium's ``Ant-v5`` (model, health check, healthy reward, control and contact costs,
``frame_skip=5``, dt = 0.05 s, reused through subclassing) with the forward reward replaced by
PEARL's goal term, the negative L1 distance of the torso to the goal (docs/references.md):

``reward = -(|x - g_x| + |y - g_y|) + healthy_reward - 0.5 |a|^2 - 5e-4 |clip(cfrc_ext, -1, 1)|^2``

The episode terminates on an unhealthy pose (torso height outside [0.2, 1.0]) with
``info["cost"] = 1.0`` on that step only (docs/envs.md: the ant families' safety is the unhealthy pose;
PEARL's ant-goal never terminated, docs/references.md).

Choices and where they come from:

- Task ``{"goal": [g_x, g_y]}``, uniform (in area) on the disk of radius 3 (PEARL's ant-goal):
  ``r = sqrt(U[r_low^2, r_high^2])``, angle U[0, 2 pi); ``goal_radius_low > 0`` gives an annulus
  (a shifted test distribution, e.g. goals farther than any training goal).
- The observation keeps the torso's x, y (``exclude_current_positions_from_observation=False``,
  as PEARL's ant-goal): the reward depends on the position, so a policy must see it.
- Horizon 200 steps (PEARL's ``max_path_length``): 10 s of simulated time.
- Unhealthy penalty (see :mod:`sb3_pearl.envs.locomotion`): by default ``goal_radius_high * sqrt(2)``
  (about 4.24) per skipped step, the largest L1 distance from the start to a goal, so standing still
  and healthy always beats falling.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
from gymnasium.envs.mujoco.ant_v5 import AntEnv
from gymnasium.utils import EzPickle

from sb3_pearl.envs.checks import check_range
from sb3_pearl.envs.locomotion import LocomotionTaskEnv, validate_locomotion_kwargs
from sb3_pearl.envs.task_protocol import Task, refuse_non_finite_action


class AntGoalMetaEnv(LocomotionTaskEnv, AntEnv):
    """
    Ant (Gymnasium v5) that must reach a goal position it does not observe.

    :param goal_radius_low: smallest distance of a goal from the start (m)
    :param goal_radius_high: largest distance of a goal from the start (m)
    :param unhealthy_penalty: penalty per step skipped by a fall, added once on the unhealthy
        step; ``None``: ``goal_radius_high * sqrt(2)``
    :param max_episode_steps: horizon used to size the penalty (keep equal to the registered limit)
    :param exclude_current_positions_from_observation: drop the torso's x, y from the observation
        (default False: the goal is a position)
    :param kwargs: passed to Gymnasium's ``AntEnv`` (``ctrl_cost_weight``, ``contact_cost_weight``,
        ``healthy_reward``, ``healthy_z_range``, ``include_cfrc_ext_in_observation``, ``render_mode``, ...)
    """

    trajectory_info_keys: ClassVar[tuple[str, ...]] = ("distance",)  # last value seen: the final distance to the goal

    def __init__(
        self,
        goal_radius_low: float = 0.0,
        goal_radius_high: float = 3.0,
        unhealthy_penalty: float | None = None,
        max_episode_steps: int = 200,
        exclude_current_positions_from_observation: bool = False,
        **kwargs: Any,
    ) -> None:
        check_range("goal_radius", goal_radius_low, goal_radius_high, min_value=0.0)
        self.goal_radius_low = float(goal_radius_low)
        self.goal_radius_high = float(goal_radius_high)
        if unhealthy_penalty is None:
            unhealthy_penalty = self.goal_radius_high * math.sqrt(2.0)
        validate_locomotion_kwargs(kwargs, unhealthy_penalty, max_episode_steps)
        self.unhealthy_penalty = float(unhealthy_penalty)
        self.max_episode_steps = int(max_episode_steps)
        self._init_task()  # before the MuJoCo init: nothing may read the task before it exists
        self._apply_pending_task()  # sets the goal of the initial task
        AntEnv.__init__(self, exclude_current_positions_from_observation=exclude_current_positions_from_observation, **kwargs)
        EzPickle.__init__(
            self,
            goal_radius_low,
            goal_radius_high,
            unhealthy_penalty,
            max_episode_steps,
            exclude_current_positions_from_observation,
            **kwargs,
        )

    def _sample_task(self, rng: np.random.Generator) -> Task:
        radius = math.sqrt(rng.uniform(self.goal_radius_low**2, self.goal_radius_high**2))
        angle = rng.uniform(0.0, 2 * math.pi)
        return {"goal": [radius * math.cos(angle), radius * math.sin(angle)]}

    def _validate_task(self, task: Task) -> None:
        super()._validate_task(task)
        if len(task["goal"]) != 2:
            raise ValueError(f"AntGoalMetaEnv.set_task: goal must be [x, y], got {task['goal']!r}")

    def _apply_pending_task(self) -> None:
        super()._apply_pending_task()
        self._goal = (float(self._task["goal"][0]), float(self._task["goal"][1]))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:  # type: ignore[override]
        """
        Step the ant; the reward is minus its L1 distance to the goal, an unhealthy pose costs 1 and terminates.

        :param action: torques, in [-1, 1]^8
        :return: observation, reward, terminated, truncated, info
        """
        refuse_non_finite_action(self, action)
        obs, _, terminated, truncated, info = super().step(action)
        goal_x, goal_y = self._goal
        goal_reward = -(abs(info["x_position"] - goal_x) + abs(info["y_position"] - goal_y))
        info["reward_forward"] = goal_reward
        info["distance"] = math.hypot(info["x_position"] - goal_x, info["y_position"] - goal_y)  # Euclidean, m
        reward = goal_reward + info["reward_survive"] + info["reward_ctrl"] + info["reward_contact"]
        return obs, self._finish_step(reward, terminated, info), terminated, truncated, info
