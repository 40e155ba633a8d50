"""``PointMazeGoalMeta-v0``: reach an unobserved goal cell of a maze (gymnasium-robotics' PointMaze).

Gymnasium-robotics' ``PointMaze`` turned into a task family: the *goal cell is the task*. The env
holds a ``PointMazeEnv`` and delegates to it (a force-actuated ball, actions in [-1, 1]^2, velocity
clipped to 5 m/s, dt = 0.01 s, the walls, the dense reward ``exp(-||xy - goal||)`` are all its own);
it is not a subclass because ``GoalEnv.reset`` insists on a ``Dict`` observation space, and the
goal must leave the observation.

- Maze: ``"medium"`` by default (gymnasium-robotics' ``MEDIUM_MAZE``, 8 x 8 with 26 free cells):
  the U-maze has only 7 free cells, i.e. 6 goals, too few for disjoint train and test sets; the
  medium maze gives 25 goal cells with paths of 1 to 11 cells from the start, and dead ends, so
  inferring the goal from rewards is a real exploration problem. ``maze="umaze"``, ``"open"``,
  ``"large"`` or a custom map (a list of rows of 0 = free / 1 = wall) are kwargs.
- Start: fixed cell ``start_cell = (1, 1)`` (top-left corner), plus gymnasium-robotics' reset noise
  U[-0.25, 0.25]^2 m.
- Task ``{"goal_cell": [i, j], "goal": [x, y]}``: a cell drawn uniformly from ``goal_cells`` (default:
  every free cell but the start) and a point drawn once per task uniformly within
  ``goal_noise = 0.25`` m of its centre (gymnasium-robotics' per-reset goal noise, frozen into the
  task so that the task stays fixed across the episodes of a meta-test; the goal does not move
  within a task). Passing disjoint ``goal_cells`` to the train and the test env gives held-out cells. Cells are
  integers: a task's ``goal_cell`` (and the ``start_cell`` / ``goal_cells`` kwargs) given as integer-valued floats
  (``[6.0, 2.0]``, as JSON or YAML may hold them) are converted to ints explicitly, any other float is refused.
- Observation: the flat ``observation`` entry of PointMaze, ``[x, y, vx, vy]`` (a ``Box``);
  ``desired_goal`` is left out (the goal is what meta-RL must infer) and ``achieved_goal`` repeats
  ``x, y``.
- Reward: PointMaze's dense reward ``exp(-distance)`` in (0, 1]; the episode never terminates
  (``continuing_task=True``, goal kept when reached); ``info["success"]`` is PointMaze's
  ``distance <= 0.45``; no safety constraint, ``info["cost"]`` is always 0.
- Horizon 300 steps (3 s): the farthest goal is 11 cells (11 m) away and the ball moves at most
  5 m/s, so it needs at least 220 steps plus the corners; a scripted waypoint controller reaches
  every goal of the medium maze within 300 steps (``tests/test_envs_point.py``). Gymnasium-robotics'
  own limit (600) would double the cost of meta-training and reach no further goal.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium_robotics.envs.maze.maps import LARGE_MAZE, MEDIUM_MAZE, OPEN, U_MAZE
from gymnasium_robotics.envs.maze.point_maze import PointMazeEnv

from sb3_pearl.envs.checks import check_number
from sb3_pearl.envs.task_protocol import MetaTaskEnv, Task, refuse_non_finite_action

MAZES: dict[str, list[list[int | str]]] = {"umaze": U_MAZE, "open": OPEN, "medium": MEDIUM_MAZE, "large": LARGE_MAZE}


def free_cells(maze_map: Sequence[Sequence[int | str]]) -> list[tuple[int, int]]:
    """
    The cells of a maze map that are not walls, row by row.

    :param maze_map: rows of cells, ``1`` for a wall
    :return: ``(row, column)`` of every free cell
    """
    return [(i, j) for i, row in enumerate(maze_map) for j, cell in enumerate(row) if cell != 1]


def maze_cell(name: str, cell: Any) -> tuple[int, int]:
    """
    A maze cell given as a kwarg, as ``(row, column)`` ints: two integers, or integer-valued floats (``6.0``, as YAML or
    JSON may give them), which are converted; a bool, a non-integer or non-finite float, or anything else is refused.

    :param name: the kwarg (and index), for the message
    :param cell: the value
    :return: the cell
    """
    values = list(cell) if isinstance(cell, (Sequence, np.ndarray)) and not isinstance(cell, str) else None
    ok = values is not None and len(values) == 2
    for value in values or []:
        number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
        ok = ok and number and math.isfinite(float(value)) and float(value) == int(value)
    if not ok:
        raise ValueError(f"{name} must be [row, column], two integers (e.g. [6, 2]), got {cell!r}")
    assert values is not None
    return int(values[0]), int(values[1])


class PointMazeGoalMetaEnv(MetaTaskEnv, gym.Env):
    """
    PointMaze ball that must reach a goal cell it does not observe (wraps a ``PointMazeEnv``).

    :param maze: ``"umaze"``, ``"open"``, ``"medium"``, ``"large"`` or a map (rows of 0 = free, 1 = wall)
    :param start_cell: ``(row, column)`` of the start cell: two integers; integer-valued floats (``1.0``) are converted to
        ints, other values refused (:func:`maze_cell`)
    :param goal_cells: the cells goals are drawn from (each as ``start_cell``); ``None``: every free cell but the start
    :param goal_noise: half-width of the uniform offset of the goal from its cell centre (m, < 0.5)
    :param reward_type: PointMaze's ``"dense"`` (``exp(-distance)``) or ``"sparse"`` (``distance <= 0.45``)
    :param render_mode: ``None``, ``"human"``, ``"rgb_array"`` or ``"depth_array"``
    :param kwargs: passed to gymnasium-robotics' ``PointMazeEnv`` (and its MuJoCo env)
    """

    metadata = dict(PointMazeEnv.metadata)
    trajectory_info_keys: ClassVar[tuple[str, ...]] = ("distance",)  # last value seen: the final distance to the goal

    def __init__(
        self,
        maze: str | Sequence[Sequence[int | str]] = "medium",
        start_cell: Sequence[int] = (1, 1),
        goal_cells: Sequence[Sequence[int]] | None = None,
        goal_noise: float = 0.25,
        reward_type: str = "dense",
        render_mode: str | None = None,
        **kwargs: Any,
    ) -> None:
        if isinstance(maze, str):
            if maze not in MAZES:
                raise ValueError(f"maze must be one of {sorted(MAZES)} or a map, got {maze!r}")
            maze_map = [list(row) for row in MAZES[maze]]
        else:
            maze_map = [[0 if cell in (0, "0") else cell for cell in row] for row in maze]
            if not maze_map or any(len(row) != len(maze_map[0]) for row in maze_map):
                raise ValueError("maze map must be a non-empty list of rows of equal length")
        free = free_cells(maze_map)
        start = maze_cell("start_cell", start_cell)
        if start not in free:
            raise ValueError(f"start_cell {start} is not a free cell of the maze")
        if goal_cells is None:
            cells = [cell for cell in free if cell != start]
        else:
            cells = [maze_cell(f"goal_cells[{index}]", cell) for index, cell in enumerate(goal_cells)]
            bad = [cell for cell in cells if cell not in free or cell == start]
            if bad:
                raise ValueError(f"goal_cells {bad} are walls, outside the maze or the start cell")
        if not cells:
            raise ValueError("goal_cells is empty: the task distribution needs at least one goal cell")
        check_number("goal_noise", goal_noise, 0.0, 0.5, high_open=True, hint="a goal stays inside its cell")
        if reward_type not in ("dense", "sparse"):
            raise ValueError(f"reward_type must be 'dense' or 'sparse', got {reward_type!r}")
        self.start_cell = start
        self.goal_cells = cells
        self.goal_noise = float(goal_noise)
        self._maze_shape = (len(maze_map), len(maze_map[0]))
        self._init_task()
        self.maze_env = PointMazeEnv(
            maze_map=maze_map,
            render_mode=render_mode,
            reward_type=reward_type,
            continuing_task=True,
            reset_target=False,
            **kwargs,
        )
        self.maze = self.maze_env.maze
        self.render_mode = render_mode
        self.action_space = self.maze_env.action_space
        self.observation_space = self.maze_env.observation_space["observation"]  # type: ignore[index]

    # -- task protocol ---------------------------------------------------------------------
    def _cell_centre(self, cell: Sequence[int]) -> np.ndarray:
        # gymnasium-robotics' Maze.cell_rowcol_to_xy, usable before the maze is built (scaling 1)
        n_rows, n_cols = self._maze_shape
        return np.array([cell[1] + 0.5 - n_cols / 2, n_rows / 2 - (cell[0] + 0.5)])

    def _sample_task(self, rng: np.random.Generator) -> Task:
        cell = self.goal_cells[int(rng.integers(len(self.goal_cells)))]
        goal = self._cell_centre(cell) + rng.uniform(-self.goal_noise, self.goal_noise, size=2)
        return {"goal_cell": [cell[0], cell[1]], "goal": goal.tolist()}

    def _validate_task(self, task: Task) -> None:
        super()._validate_task(task)
        cell = tuple(int(c) for c in task["goal_cell"])
        if cell not in free_cells(self.maze.maze_map) or cell == self.start_cell:
            raise ValueError(f"PointMazeGoalMetaEnv.set_task: goal_cell {cell} is a wall or the start cell")
        offset = np.asarray(task["goal"], dtype=np.float64) - self._cell_centre(cell)
        if offset.shape != (2,) or np.abs(offset).max() >= 0.5:
            raise ValueError(f"PointMazeGoalMetaEnv.set_task: goal {task['goal']} is not inside goal_cell {cell}")

    def _task_goal(self) -> np.ndarray:
        return np.asarray(self._task["goal"], dtype=np.float64)

    # -- gymnasium API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """
        Apply a pending task (``set_task``), put the ball on the start cell and the goal of the task.

        :param seed: seed of the reset noise
        :param options: ``{"reset_cell": (row, column)}`` overrides the start cell; the goal is the task's
        :return: observation ``[x, y, vx, vy]`` and info (with ``cost = 0.0``)
        """
        super().reset(seed=seed)
        self._apply_pending_task()
        reset_cell = self.start_cell if options is None else options.get("reset_cell", self.start_cell)
        base_options = {"goal_cell": np.asarray(self._task["goal_cell"]), "reset_cell": np.asarray(reset_cell)}
        obs, info = self.maze_env.reset(seed=seed, options=base_options)
        self.maze_env.goal = self._task_goal()  # the base drew a noisy goal in the cell: use the task's
        self.maze_env.update_target_site_pos()
        info["success"] = bool(np.linalg.norm(obs["achieved_goal"] - self.maze_env.goal) <= 0.45)
        info["cost"] = 0.0
        return obs["observation"], info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """
        Push the ball; PointMaze's reward for the task's goal, the goal left out of the observation.

        :param action: force, in [-1, 1]^2
        :return: observation ``[x, y, vx, vy]``, reward, terminated (always False), truncated, info
        """
        refuse_non_finite_action(self, action)
        obs, reward, terminated, truncated, info = self.maze_env.step(action)
        info["cost"] = 0.0
        info["distance"] = float(np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"]))  # the ball's, to the goal (m)
        return obs["observation"], float(reward), terminated, truncated, info

    @property
    def goal(self) -> np.ndarray:
        """The goal position in force (that of the task since the last reset)."""
        return self._task_goal()

    def render(self) -> Any:  # type: ignore[override]
        return self.maze_env.render()

    def close(self) -> None:
        self.maze_env.close()
