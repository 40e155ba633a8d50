"""``HalfCheetahVelMeta-v0``: PEARL's cheetah-vel, a target forward velocity per task.

Gymnasium's ``HalfCheetah-v5`` (model, observation, ``frame_skip=5``, dt = 0.05 s, reused through
subclassing) with the forward reward replaced by PEARL's velocity-tracking reward
(Rakelly et al. 2019, itself MAML's goal-velocity cheetah; docs/references.md):

``reward = -|v - v*| - 0.05 * |a|^2`` (``ctrl_cost_weight = 0.05`` instead of Gymnasium's 0.1).

- Task ``{"velocity": v*}``, ``v* ~ U[0, 3]`` m/s (PEARL's range; MAML used U[0, 2]).
- Horizon 200 steps (PEARL's ``max_path_length``): 10 s of simulated time.
- The cheetah cannot fall: no termination, ``info["cost"]`` is always 0.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium.envs.mujoco.half_cheetah_v5 import HalfCheetahEnv
from gymnasium.utils import EzPickle

from sb3_pearl.envs.checks import check_number, check_range
from sb3_pearl.envs.locomotion import ignore_mujoco_warning
from sb3_pearl.envs.task_protocol import MetaTaskEnv, Task, refuse_non_finite_action


class HalfCheetahVelMetaEnv(MetaTaskEnv, HalfCheetahEnv):
    """
    HalfCheetah (Gymnasium v5) that must run at a target forward velocity it does not observe.

    :param velocity_low: lower bound of the target velocity (m/s)
    :param velocity_high: upper bound of the target velocity (m/s)
    :param ctrl_cost_weight: weight of ``|a|^2`` in the reward (PEARL: 0.05)
    :param kwargs: passed to Gymnasium's ``HalfCheetahEnv`` (``frame_skip``, ``reset_noise_scale``,
        ``render_mode``, ...)
    """

    trajectory_info_keys: ClassVar[tuple[str, ...]] = ("velocity_error",)  # the trajectory's mean |v - v*| (m/s)
    _velocity_error_sum: float = 0.0
    _velocity_error_steps: int = 0

    def __init__(
        self,
        velocity_low: float = 0.0,
        velocity_high: float = 3.0,
        ctrl_cost_weight: float = 0.05,
        **kwargs: Any,
    ) -> None:
        check_range("velocity", velocity_low, velocity_high)
        check_number("ctrl_cost_weight", ctrl_cost_weight, 0.0, hint="weight of |a|^2 in the reward")
        self.velocity_low = float(velocity_low)
        self.velocity_high = float(velocity_high)
        self._init_task()  # before the MuJoCo init: nothing may read the task before it exists
        with ignore_mujoco_warning("compiler attribute 'settotalmass' is deprecated"):  # Gymnasium's half_cheetah.xml
            HalfCheetahEnv.__init__(self, ctrl_cost_weight=ctrl_cost_weight, **kwargs)
        EzPickle.__init__(self, velocity_low, velocity_high, ctrl_cost_weight, **kwargs)

    def _sample_task(self, rng: np.random.Generator) -> Task:
        return {"velocity": float(rng.uniform(self.velocity_low, self.velocity_high))}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """
        Apply a pending task (``set_task``) and reset the cheetah.

        :param seed: seed of the reset noise
        :param options: passed to the base env
        :return: observation and info (with ``cost = 0.0``)
        """
        self._apply_pending_task()
        self._velocity_error_sum, self._velocity_error_steps = 0.0, 0
        obs, info = super().reset(seed=seed, options=options)
        info["cost"] = 0.0
        return obs, info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:  # type: ignore[override]
        """
        Step the cheetah (Gymnasium's step, whose reward is :meth:`_get_rew`'s); a non-finite action is refused.

        :param action: torques, in [-1, 1]^6
        :return: observation, reward, terminated (always False), truncated, info
        """
        refuse_non_finite_action(self, action)
        obs, reward, terminated, truncated, info = super().step(action)
        self._velocity_error_sum -= info["reward_forward"]
        self._velocity_error_steps += 1
        info["velocity_error"] = self._velocity_error_sum / self._velocity_error_steps  # the trajectory's so far
        return obs, reward, terminated, truncated, info

    def _get_rew(self, x_velocity: float, action: np.ndarray) -> tuple[float, dict[str, float]]:
        # Called once per step by HalfCheetahEnv.step, whose info is built from this dict: putting
        # the cost here avoids wrapping step() (the cheetah is fast, every microsecond shows).
        velocity_reward = -abs(x_velocity - self._task["velocity"])
        ctrl_cost = self.control_cost(action)
        return velocity_reward - ctrl_cost, {"reward_forward": velocity_reward, "reward_ctrl": -ctrl_cost, "cost": 0.0}
