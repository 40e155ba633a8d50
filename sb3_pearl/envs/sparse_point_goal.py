"""``SparsePointGoalMeta-v0``: PEARL's sparse point robot.

The point robot of ``PointGoalMeta-v0`` (start at the origin, actions in [-0.1, 0.1]^2 added to the
position, horizon 20) with PEARL's sparse variant of the task (Rakelly et al. 2019, docs/references.md):
goals on the upper half of the unit circle, and a reward only within ``reward_radius = 0.2`` of the
goal,

``reward = 1 - ||s - g||`` if ``||s - g|| <= 0.2``, else ``0``

(the sparse reward of PEARL's reference: the dense ``-||s - g||`` zeroed outside the radius and
shifted by +1 inside it so that reaching the goal is always positive; its meta-training also used
the sparse reward). ``info`` also carries the dense ``-||s - g||`` (``"dense_reward"``) and the
distance, for diagnostics.

- Task ``{"goal": [cos a, sin a]}``, ``a ~ U[0, pi]`` (PEARL spaced its goals evenly on the half
  circle; a uniform draw gives held-out test goals for another seed).
- No safety constraint: ``info["cost"]`` is always 0.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sb3_pearl.envs.checks import check_number, check_range
from sb3_pearl.envs.point_goal import PointGoalMetaEnv, finite_move
from sb3_pearl.envs.task_protocol import Task


class SparsePointGoalMetaEnv(PointGoalMetaEnv):
    """
    Point robot with goals on an arc and a reward only near the goal.

    :param goal_angle_low: smallest goal angle (radians, counter-clockwise from +x)
    :param goal_angle_high: largest goal angle (radians)
    :param goal_radius: distance of the goals from the origin
    :param reward_radius: distance to the goal within which the reward is non-zero
    :param max_step: half-width of the action box (displacement per step)
    :param render_mode: ``None`` or ``"rgb_array"``
    """

    def __init__(
        self,
        goal_angle_low: float = 0.0,
        goal_angle_high: float = math.pi,
        goal_radius: float = 1.0,
        reward_radius: float = 0.2,
        max_step: float = 0.1,
        render_mode: str | None = None,
    ) -> None:
        check_range("goal_angle", goal_angle_low, goal_angle_high)
        check_number("goal_radius", goal_radius, 0.0, 2.0, low_open=True, high_open=True, hint="the robot lives in [-2, 2]^2")
        check_number("reward_radius", reward_radius, 0.0, low_open=True, hint="distance to the goal with a reward")
        self.goal_angle_low = float(goal_angle_low)
        self.goal_angle_high = float(goal_angle_high)
        self.goal_radius = float(goal_radius)
        self.reward_radius = float(reward_radius)
        super().__init__(max_step=max_step, render_mode=render_mode)
        self._goal_x, self._goal_y = self._task["goal"]

    def _sample_task(self, rng: np.random.Generator) -> Task:
        angle = rng.uniform(self.goal_angle_low, self.goal_angle_high)
        return {"goal": [self.goal_radius * math.cos(angle), self.goal_radius * math.sin(angle)]}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """
        Apply a pending task (``set_task``) and put the robot back at the origin.

        :param seed: seed of the env's generator (the start is deterministic)
        :param options: unused
        :return: observation and info (with ``cost = 0.0``)
        """
        obs, info = super().reset(seed=seed, options=options)
        self._goal_x, self._goal_y = self._task["goal"]
        return obs, info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """
        Move the point; the reward is ``1 - distance`` within ``reward_radius`` of the goal, else 0.

        The motion is the parent's (clipped action added to the position, position clipped to
        [-2, 2]^2); the step is written out here, with a scalar distance, to stay as fast as the
        parent's step (this env is so cheap that one extra call shows in steps/s).

        :param action: displacement, clipped to the action box
        :return: observation, reward, terminated, truncated, info (with ``distance`` and ``dense_reward``)
        """
        action = np.clip(finite_move(self, action), -self.max_step, self.max_step)
        self._pos = np.clip(self._pos + action, -2.0, 2.0)
        distance = math.hypot(self._pos[0] - self._goal_x, self._pos[1] - self._goal_y)
        reward = 1.0 - distance if distance <= self.reward_radius else 0.0
        return self._obs(), reward, False, False, {"cost": 0.0, "distance": distance, "dense_reward": -distance}

    def _draw_extras(self, img: np.ndarray, world_x: np.ndarray, world_y: np.ndarray) -> None:
        goal = self.goal
        mask = (world_x - goal[0]) ** 2 + (world_y - goal[1]) ** 2 <= self.reward_radius**2
        img[mask] = (200, 235, 200)
