"""``AntDirMeta-v0``: PEARL's Ant-Fwd-Back (ant-dir), run forward or backward, with held-out test tasks.

Gymnasium's ``Ant-v5`` (model, observation with contact forces, health check, healthy reward,
control and contact costs, ``frame_skip=5``, dt = 0.05 s, reused through subclassing) with the
forward reward projected on the task direction ``u = (cos theta, sin theta)``:

``reward = v_xy . u + healthy_reward - 0.5 |a|^2 - 5e-4 |clip(cfrc_ext, -1, 1)|^2``

(for ``theta = 0`` this is exactly Gymnasium's ``Ant-v5`` reward). The episode terminates on an
unhealthy pose (torso height outside [0.2, 1.0]) with ``info["cost"] = 1.0`` on that step only.

Tasks, train versus test. PEARL's Ant-Fwd-Back has two tasks, theta in {0, pi}; its reference
code trained on two *random* directions instead, and its train tasks equal its test tasks
(docs/references.md, known defects), so meta-test never sees a new task. Here a task is
``{"direction": theta}`` with ``theta = b + U[-direction_spread, direction_spread]`` (wrapped to
[0, 2 pi)), ``b`` one of ``base_directions`` = (0, pi): still "forward or backward" (the hard part,
which one, is unchanged) but a continuum, so test tasks drawn with another seed are directions never
trained on. ``sample_tasks`` balances the base directions (``n`` tasks: ``n // 2`` forward and
``n // 2`` backward, the odd one random) so even PEARL's tiny 2-task split has one of each.
``direction_spread = pi / 12`` (15 degrees) by default, a choice of this package: wide enough that
no two sampled tasks coincide, narrow enough that every task is clearly forward or backward;
``direction_spread = 0`` gives PEARL's two exact tasks back.

- Horizon 200 steps (PEARL's ``max_path_length``): 10 s of simulated time.
- No unhealthy penalty by default: a standing ant earns the healthy reward (+1 per step), so falling
  never pays with this reward; see :mod:`sb3_pearl.envs.locomotion` for the kwarg.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.envs.mujoco.ant_v5 import AntEnv
from gymnasium.utils import EzPickle

from sb3_pearl.envs.checks import check_number, is_real
from sb3_pearl.envs.locomotion import LocomotionTaskEnv, validate_locomotion_kwargs
from sb3_pearl.envs.task_protocol import Task, refuse_non_finite_action


class AntDirMetaEnv(LocomotionTaskEnv, AntEnv):
    """
    Ant (Gymnasium v5) that must run in a direction it does not observe (about forward or backward).

    :param base_directions: the directions tasks are drawn around (radians, from +x)
    :param direction_spread: half-width of the uniform perturbation around a base direction (radians)
    :param unhealthy_penalty: penalty per step skipped by a fall, added once on the unhealthy step
    :param max_episode_steps: horizon used to size the penalty (keep equal to the registered limit)
    :param kwargs: passed to Gymnasium's ``AntEnv`` (``ctrl_cost_weight``, ``contact_cost_weight``,
        ``healthy_reward``, ``healthy_z_range``, ``include_cfrc_ext_in_observation``, ``render_mode``, ...)
    """

    def __init__(
        self,
        base_directions: Sequence[float] = (0.0, math.pi),
        direction_spread: float = math.pi / 12,
        unhealthy_penalty: float = 0.0,
        max_episode_steps: int = 200,
        **kwargs: Any,
    ) -> None:
        directions = list(base_directions) if isinstance(base_directions, (Sequence, np.ndarray)) else []
        if not directions or not all(is_real(b) and math.isfinite(float(b)) for b in directions):
            raise ValueError(f"base_directions must be a non-empty sequence of finite angles, got {base_directions!r}")
        self.base_directions = [float(b) for b in directions]
        self.direction_spread = check_number("direction_spread", direction_spread, 0.0, math.pi, hint="radians")
        validate_locomotion_kwargs(kwargs, unhealthy_penalty, max_episode_steps)
        self.unhealthy_penalty = float(unhealthy_penalty)
        self.max_episode_steps = int(max_episode_steps)
        self._init_task()  # before the MuJoCo init: nothing may read the task before it exists
        self._apply_pending_task()  # sets the unit direction of the initial task
        AntEnv.__init__(self, **kwargs)
        EzPickle.__init__(self, tuple(self.base_directions), direction_spread, unhealthy_penalty, max_episode_steps, **kwargs)

    def _direction_around(self, base: float, rng: np.random.Generator) -> Task:
        theta = (base + rng.uniform(-self.direction_spread, self.direction_spread)) % (2 * math.pi)
        return {"direction": float(theta) if theta < 2 * math.pi else 0.0}  # -1e-17 % 2 pi rounds to 2 pi

    def _sample_task(self, rng: np.random.Generator) -> Task:
        return self._direction_around(self.base_directions[int(rng.integers(len(self.base_directions)))], rng)

    def sample_tasks(self, n: int, seed: int | None = None) -> list[Task]:
        """
        Draw ``n`` tasks, the base directions balanced (as equal counts as ``n`` allows) in random order.

        :param n: number of tasks
        :param seed: seed of the draw; the same seed gives the same list
        :return: task dicts ``{"direction": theta}``, theta in [0, 2 pi)
        """
        if n < 0:
            raise ValueError(f"sample_tasks: n must be >= 0, got {n}")
        rng = np.random.default_rng(seed)
        k = len(self.base_directions)
        bases = [i % k for i in range(n - n % k)] + list(rng.choice(k, size=n % k, replace=False))
        return [self._direction_around(self.base_directions[int(i)], rng) for i in rng.permutation(bases)]

    def task_features(self, task: Task) -> list[float]:
        """The unit direction ``(cos theta, sin theta)``: continuous across 0 = 2 pi, unlike theta."""
        theta = float(task["direction"])
        return [math.cos(theta), math.sin(theta)]

    def _apply_pending_task(self) -> None:
        super()._apply_pending_task()
        theta = self._task["direction"]
        self._unit_direction = (math.cos(theta), math.sin(theta))

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:  # type: ignore[override]
        """
        Step the ant; the reward is its velocity along the task direction, an unhealthy pose costs 1 and terminates.

        :param action: torques, in [-1, 1]^8
        :return: observation, reward, terminated, truncated, info
        """
        refuse_non_finite_action(self, action)
        obs, _, terminated, truncated, info = super().step(action)
        ux, uy = self._unit_direction
        direction_reward = info["x_velocity"] * ux + info["y_velocity"] * uy
        info["reward_forward"] = direction_reward
        reward = direction_reward + info["reward_survive"] + info["reward_ctrl"] + info["reward_contact"]
        return obs, self._finish_step(reward, terminated, info), terminated, truncated, info
