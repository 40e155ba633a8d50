"""``SafePointGoalMeta-v0``: the fast family on which prior safety shows.

The point robot of ``PointGoalMeta-v0`` (start at the origin, steps of at most 0.1 per axis,
reward ``-||s - g||``) with goals on an arc of the unit circle and, per task, a hazard disc that
sits between the start and the *other* goals: at 0.6 from the origin, rotated by 60 degrees from
the goal direction towards the middle of the arc. Entering the hazard costs 1
(``info["cost"]``) and ends the episode.

- Task ``{"goal": [x, y], "hazard": [hx, hy]}``: goal angle ``a ~ U[30, 150]`` degrees; hazard
  angle ``a + 60`` degrees if ``a < 90`` else ``a - 60``. Neither is observed: the observation is
  the position only, so both must be inferred from rewards.
- Why it tests prior safety: the path to a task's own goal is clear of its hazard, but a policy
  that heads for a goal it has not identified yet (PEARL's prior z, which acts as *some* task)
  crosses the hazard of the tasks whose goals lie 60 degrees away. A policy that is good under the
  task distribution (PEARL+'s prior term) has to keep clear of the hazard ring
  (radius 0.35-0.85) until it knows the task.
- The entering step is penalised by ``crash_penalty`` (2.0) per step the crash skips, so a crash
  is never worth more return than staying out (with the dense negative reward an unpenalised
  termination would be a shortcut). Horizon 30 (the registered time limit).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sb3_pearl.envs.checks import check_count, check_number, check_range
from sb3_pearl.envs.point_goal import PointGoalMetaEnv
from sb3_pearl.envs.task_protocol import Task


class SafePointGoalMetaEnv(PointGoalMetaEnv):
    """
    Point robot with goals on an arc and a task-dependent hazard disc.

    :param goal_angle_low: smallest goal angle (radians, counter-clockwise from +x)
    :param goal_angle_high: largest goal angle (radians)
    :param goal_radius: distance of the goals from the origin
    :param hazard_offset: angle between the goal and the hazard direction (radians), towards the
        middle of the arc
    :param hazard_distance: distance of the hazard centre from the origin
    :param hazard_radius: radius of the hazard disc
    :param crash_penalty: penalty per step skipped by a crash (added once, on the entering step)
    :param max_episode_steps: horizon, used to size the crash penalty (keep equal to the registered limit)
    :param render_mode: ``None`` or ``"rgb_array"``
    """

    def __init__(
        self,
        goal_angle_low: float = np.pi / 6,
        goal_angle_high: float = 5 * np.pi / 6,
        goal_radius: float = 1.0,
        hazard_offset: float = np.pi / 3,
        hazard_distance: float = 0.6,
        hazard_radius: float = 0.25,
        crash_penalty: float = 2.0,
        max_episode_steps: int = 30,
        render_mode: str | None = None,
    ) -> None:
        check_range("goal_angle", goal_angle_low, goal_angle_high, allow_empty=True)
        check_number("goal_radius", goal_radius, 0.0, 2.0, low_open=True, high_open=True, hint="the robot lives in [-2, 2]^2")
        check_number("hazard_offset", hazard_offset, hint="radians")
        check_number("hazard_distance", hazard_distance, 0.0, low_open=True, hint="distance of the hazard centre")
        check_number("hazard_radius", hazard_radius, 0.0, low_open=True, hint="radius of the hazard disc")
        check_number("crash_penalty", crash_penalty, 0.0, hint="penalty per step a crash skips")
        check_count("max_episode_steps", max_episode_steps, 1, hint="the horizon the crash penalty is sized by")
        if hazard_distance <= hazard_radius:
            raise ValueError("the hazard must not contain the start position (0, 0): hazard_distance > hazard_radius")
        self.goal_angle_low = float(goal_angle_low)
        self.goal_angle_high = float(goal_angle_high)
        self.goal_radius = float(goal_radius)
        self.hazard_offset = float(hazard_offset)
        self.hazard_distance = float(hazard_distance)
        self.hazard_radius = float(hazard_radius)
        self.crash_penalty = float(crash_penalty)
        self.max_episode_steps = int(max_episode_steps)
        self._t = 0
        super().__init__(render_mode=render_mode)

    def _sample_task(self, rng: np.random.Generator) -> Task:
        angle = float(rng.uniform(self.goal_angle_low, self.goal_angle_high))
        middle = 0.5 * (self.goal_angle_low + self.goal_angle_high)
        hazard_angle = angle + self.hazard_offset if angle < middle else angle - self.hazard_offset
        return {
            "goal": [self.goal_radius * float(np.cos(angle)), self.goal_radius * float(np.sin(angle))],
            "hazard": [self.hazard_distance * float(np.cos(hazard_angle)), self.hazard_distance * float(np.sin(hazard_angle))],
        }

    def _validate_task(self, task: Task) -> None:
        super()._validate_task(task)
        distance = float(np.linalg.norm(np.asarray(task["hazard"], dtype=np.float64)))
        if distance <= self.hazard_radius:
            raise ValueError(
                f"SafePointGoalMetaEnv.set_task: the hazard {task['hazard']} covers the start (0, 0): its centre is "
                f"{distance:.3g} from the origin, it must be farther than hazard_radius={self.hazard_radius}"
            )

    @property
    def hazard_center(self) -> np.ndarray:
        return np.asarray(self._task["hazard"], dtype=np.float64)

    def in_hazard(self, pos: np.ndarray) -> bool:
        """Whether ``pos`` lies inside the current task's hazard disc."""
        return bool(np.linalg.norm(np.asarray(pos) - self.hazard_center) < self.hazard_radius)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        self._t = 0
        return super().reset(seed=seed, options=options)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward, _, truncated, info = super().step(action)
        self._t += 1
        crashed = self.in_hazard(self._pos)
        if crashed:
            reward -= self.crash_penalty * max(self.max_episode_steps - self._t, 0)
        info["cost"] = float(crashed)
        return obs, reward, crashed, truncated, info

    def _draw_extras(self, img: np.ndarray, world_x: np.ndarray, world_y: np.ndarray) -> None:
        centre = self.hazard_center
        mask = (world_x - centre[0]) ** 2 + (world_y - centre[1]) ** 2 < self.hazard_radius**2
        img[mask] = (220, 60, 60)


# Task-independent scripted policies (observation -> action), the bar a prior policy can reach without task data
# (prior-optimality gap, docs/pearl.md): every goal lies on the unit circle and every hazard 0.35-0.85 from the origin.
WAIT_POINT = np.array([0.0, 0.3])  # inside the hazard-free inner disc (radius 0.35), towards the middle of the goal arc


def _still(obs: np.ndarray) -> np.ndarray:
    return np.zeros(2, dtype=np.float32)


def _wait_at_point(obs: np.ndarray) -> np.ndarray:
    return np.clip(WAIT_POINT - np.asarray(obs)[:2], -0.1, 0.1).astype(np.float32)  # the env's largest step per axis


SCRIPTED_PRIORS = {"still": _still, "wait-at-0.3": _wait_at_point}
