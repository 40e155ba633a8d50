"""``PointGoalMeta-v0``: the reference point robot of PEARL (docs/references.md).

A 2-D point starting at the origin, actions in [-0.1, 0.1]^2 added to its position (clipped to
[-2, 2]^2), reward ``-||s - g||``, goal U[-1, 1]^2 (task ``{"goal": [x, y]}``), horizon 20.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_pearl.envs.checks import check_number, check_range
from sb3_pearl.envs.task_protocol import MetaTaskEnv, Task, non_finite_action_error


def finite_move(env: object, action: Any) -> np.ndarray:
    """
    A point robot's action as a float64 array of shape (2,), refused if it holds a nan or an inf (the fast form of
    :func:`~sb3_pearl.envs.task_protocol.refuse_non_finite_action`, for these microsecond steps).

    :param env: the env (for the message)
    :param action: the action given to ``step``
    :return: the action
    """
    move = np.asarray(action, dtype=np.float64).reshape(2)
    if not (math.isfinite(move[0]) and math.isfinite(move[1])):
        raise non_finite_action_error(env, move)
    return move


class PointGoalMetaEnv(MetaTaskEnv, gym.Env):
    """
    Point robot that must reach a goal it does not observe.

    :param goal_low: lower bound of each goal coordinate
    :param goal_high: upper bound of each goal coordinate
    :param max_step: half-width of the action box (displacement per step)
    :param render_mode: ``None`` or ``"rgb_array"``
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    trajectory_info_keys: ClassVar[tuple[str, ...]] = ("distance",)  # last value seen: the final distance to the goal
    # The time limit is set at registration (``max_episode_steps``); the env itself never truncates.

    def __init__(
        self,
        goal_low: float = -1.0,
        goal_high: float = 1.0,
        max_step: float = 0.1,
        render_mode: str | None = None,
    ) -> None:
        check_range("goal", goal_low, goal_high)
        check_number("max_step", max_step, 0.0, low_open=True, hint="half-width of the action box")
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
        action = np.clip(finite_move(self, action), -self.max_step, self.max_step)
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
