"""Point-robot task families: ``PointGoalMeta-v0`` and ``SafePointGoalMeta-v0``.

``PointGoalMeta-v0`` is the reference point robot of PEARL (REFERENCE.md): a 2-D point starting
at the origin, actions in [-0.1, 0.1]^2 added to its position, reward ``-||s - g||``, goal
U[-1, 1]^2, horizon 20.

``SafePointGoalMeta-v0`` is the small family on which the paper's claim must show: goals on an
arc of the unit circle (angles in [30, 150] degrees by default), a disc-shaped hazard of radius
0.3 centred at (0, 0.5) between the start and the goals. Straight lines to about 55% of the goals
cross it, so a policy heading for a goal it has not identified yet is unsafe unless it learned a
detour. Entering the hazard costs 1 (``info["cost"]``) and ends the episode; the step that enters
it is also penalised by ``crash_penalty`` times the steps the crash skips, so that a crash is
never worth more return than staying out (with the dense ``-distance`` reward, an unpenalised
termination would be a shortcut). Horizon 30, position clipped to [-2, 2]^2.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_pearl.envs.task_protocol import MetaTaskEnv, Task


class PointGoalMetaEnv(MetaTaskEnv, gym.Env):
    """
    Point robot that must reach a goal it does not observe.

    :param goal_low: lower bound of each goal coordinate
    :param goal_high: upper bound of each goal coordinate
    :param max_step: half-width of the action box (displacement per step)
    :param render_mode: ``None`` or ``"rgb_array"``
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    # The time limit is set at registration (``max_episode_steps``); the env itself never truncates.

    def __init__(
        self,
        goal_low: float = -1.0,
        goal_high: float = 1.0,
        max_step: float = 0.1,
        render_mode: str | None = None,
    ) -> None:
        if goal_low >= goal_high:
            raise ValueError(f"goal_low ({goal_low}) must be < goal_high ({goal_high})")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.goal_low = float(goal_low)
        self.goal_high = float(goal_high)
        self.max_step = float(max_step)
        self.render_mode = render_mode
        self.observation_space = spaces.Box(-2.0, 2.0, shape=(2,), dtype=np.float32)
        self.action_space = spaces.Box(-max_step, max_step, shape=(2,), dtype=np.float32)
        self._pos = np.zeros(2, dtype=np.float64)
        self._init_task()

    # -- task protocol ---------------------------------------------------------------------
    def _sample_task(self, rng: np.random.Generator) -> Task:
        return {"goal": rng.uniform(self.goal_low, self.goal_high, size=2).tolist()}

    @property
    def goal(self) -> np.ndarray:
        return np.asarray(self._task["goal"], dtype=np.float64)

    # -- gymnasium API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._apply_pending_task()
        self._pos = np.zeros(2, dtype=np.float64)
        return self._obs(), {"cost": 0.0}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(2), -self.max_step, self.max_step)
        self._pos = np.clip(self._pos + action, -2.0, 2.0)
        distance = float(np.linalg.norm(self._pos - self.goal))
        return self._obs(), -distance, False, False, {"cost": 0.0, "distance": distance}

    def _obs(self) -> np.ndarray:
        return self._pos.astype(np.float32)

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        if self.render_mode != "rgb_array":
            return None
        return self._draw()

    def _draw(self, size: int = 128) -> np.ndarray:
        img = np.full((size, size, 3), 255, dtype=np.uint8)
        yy, xx = np.mgrid[0:size, 0:size]
        world_x = (xx + 0.5) / size * 4.0 - 2.0  # pixels -> [-2, 2]
        world_y = 2.0 - (yy + 0.5) / size * 4.0
        self._draw_extras(img, world_x, world_y)
        for centre, radius, colour in ((self.goal, 0.08, (40, 160, 40)), (self._pos, 0.06, (30, 60, 200))):
            mask = (world_x - centre[0]) ** 2 + (world_y - centre[1]) ** 2 <= radius**2
            img[mask] = colour
        return img

    def _draw_extras(self, img: np.ndarray, world_x: np.ndarray, world_y: np.ndarray) -> None:
        """Hook for subclasses to draw static scenery (hazards) under the agent and goal."""


class SafePointGoalMetaEnv(PointGoalMetaEnv):
    """
    Point robot with goals on an arc and a hazard disc between the start and the goals.

    :param goal_angle_low: smallest goal angle (radians, counter-clockwise from +x)
    :param goal_angle_high: largest goal angle (radians)
    :param goal_radius: distance of the goals from the origin
    :param hazard_center: centre of the hazard disc
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
        hazard_center: tuple[float, float] = (0.0, 0.5),
        hazard_radius: float = 0.3,
        crash_penalty: float = 2.0,
        max_episode_steps: int = 30,
        render_mode: str | None = None,
    ) -> None:
        if goal_angle_low > goal_angle_high:
            raise ValueError(f"goal_angle_low ({goal_angle_low}) must be <= goal_angle_high ({goal_angle_high})")
        self.goal_angle_low = float(goal_angle_low)
        self.goal_angle_high = float(goal_angle_high)
        self.goal_radius = float(goal_radius)
        self.hazard_center = np.asarray(hazard_center, dtype=np.float64)
        self.hazard_radius = float(hazard_radius)
        if np.linalg.norm(self.hazard_center) <= self.hazard_radius:
            raise ValueError("the hazard must not contain the start position (0, 0)")
        self.crash_penalty = float(crash_penalty)
        self.max_episode_steps = int(max_episode_steps)
        self._t = 0
        super().__init__(render_mode=render_mode)

    def _sample_task(self, rng: np.random.Generator) -> Task:
        angle = rng.uniform(self.goal_angle_low, self.goal_angle_high)
        return {"goal": [self.goal_radius * float(np.cos(angle)), self.goal_radius * float(np.sin(angle))]}

    def in_hazard(self, pos: np.ndarray) -> bool:
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
        mask = (world_x - self.hazard_center[0]) ** 2 + (world_y - self.hazard_center[1]) ** 2 < self.hazard_radius**2
        img[mask] = (220, 60, 60)
