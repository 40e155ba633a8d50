"""``Walker2dVelMeta-v0``: the paper's Walker-2D-Vel, a target forward velocity per task.

Gymnasium's ``Walker2d-v5`` (its model, observation, health check, healthy reward and control cost,
all reused through subclassing) with the forward-velocity reward replaced by a tracking term:

``reward = -|v - v*| + healthy_reward - ctrl_cost_weight * |a|^2`` (healthy reward 1, control cost
weight 1e-3: the Gymnasium v5 defaults), and the episode terminates on an unhealthy pose (torso
height outside (0.8, 2.0) or torso angle outside (-1, 1), Gymnasium's ranges) with
``info["cost"] = 1.0`` on that step only.

Choices and where they come from:

- Task ``{"velocity": v*}``, ``v* ~ U[0, 2]`` m/s. The paper defers to PEARL (Rakelly et al. 2019)
  for the configuration and neither gives a Walker velocity range. MAML (Finn et al. 2017) used
  U[0, 2] for the cheetah and U[0, 3] for the ant; ProMP's ``Walker2DRandVelEnv`` (Rothfuss et al.
  2019) used U[0, 10], far beyond what Walker2d reaches in a 200-step episode. U[0, 2] is MAML's
  cheetah range, reachable from rest within the horizon.
- Horizon 200 steps (PEARL's ``max_path_length``), with Gymnasium's ``frame_skip=4`` (dt = 0.008 s,
  gym's Walker2d default): 1.6 s of simulated time. ``frame_skip=8`` (a 3.2 s episode, the
  setting of ProMP's walker) is a constructor kwarg; the velocity range should then be revisited.
- Unhealthy penalty (see :mod:`sb3_pearl.envs.locomotion`): by default ``max(|v*_low|, |v*_high|)``
  = 2 per skipped step, the largest velocity error of a walker that stands still, so standing
  still and healthy always beats falling.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium.envs.mujoco.walker2d_v5 import Walker2dEnv
from gymnasium.utils import EzPickle

from sb3_pearl.envs.checks import check_range
from sb3_pearl.envs.locomotion import LocomotionTaskEnv, validate_locomotion_kwargs
from sb3_pearl.envs.task_protocol import Task, refuse_non_finite_action


class Walker2dVelMetaEnv(LocomotionTaskEnv, Walker2dEnv):
    """
    Walker2d (Gymnasium v5) that must walk at a target forward velocity it does not observe.

    :param velocity_low: lower bound of the target velocity (m/s)
    :param velocity_high: upper bound of the target velocity (m/s)
    :param unhealthy_penalty: penalty per step skipped by a fall, added once on the unhealthy
        step; ``None``: ``max(|velocity_low|, |velocity_high|)``
    :param max_episode_steps: horizon used to size the penalty (keep equal to the registered limit)
    :param kwargs: passed to Gymnasium's ``Walker2dEnv`` (``frame_skip``, ``ctrl_cost_weight``,
        ``healthy_reward``, ``healthy_z_range``, ``reset_noise_scale``, ``render_mode``, ...)
    """

    tracks_velocity: ClassVar[bool] = True
    trajectory_info_keys: ClassVar[tuple[str, ...]] = ("velocity_error",)  # the trajectory's mean |v - v*| (m/s)

    def __init__(
        self,
        velocity_low: float = 0.0,
        velocity_high: float = 2.0,
        unhealthy_penalty: float | None = None,
        max_episode_steps: int = 200,
        **kwargs: Any,
    ) -> None:
        check_range("velocity", velocity_low, velocity_high)
        self.velocity_low = float(velocity_low)
        self.velocity_high = float(velocity_high)
        if unhealthy_penalty is None:
            unhealthy_penalty = max(abs(self.velocity_low), abs(self.velocity_high))
        validate_locomotion_kwargs(kwargs, unhealthy_penalty, max_episode_steps)
        self.unhealthy_penalty = float(unhealthy_penalty)
        self.max_episode_steps = int(max_episode_steps)
        self._init_task()  # before the MuJoCo init: nothing may read the task before it exists
        Walker2dEnv.__init__(self, **kwargs)
        # Walker2dEnv recorded its own positional args; pickling must rebuild *this* class
        EzPickle.__init__(self, velocity_low, velocity_high, unhealthy_penalty, max_episode_steps, **kwargs)

    def _sample_task(self, rng: np.random.Generator) -> Task:
        return {"velocity": float(rng.uniform(self.velocity_low, self.velocity_high))}

    def _get_rew(self, x_velocity: float, action: np.ndarray) -> tuple[float, dict[str, float]]:
        velocity_reward = -abs(x_velocity - self._task["velocity"])
        healthy_reward = self.healthy_reward
        ctrl_cost = self.control_cost(action)
        reward_info = {"reward_forward": velocity_reward, "reward_ctrl": -ctrl_cost, "reward_survive": healthy_reward}
        return velocity_reward + healthy_reward - ctrl_cost, reward_info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:  # type: ignore[override]
        """
        Step the walker; the reward tracks the task velocity, an unhealthy pose costs 1 and terminates.

        :param action: torques, in [-1, 1]^6
        :return: observation, reward, terminated, truncated, info
        """
        refuse_non_finite_action(self, action)
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, self._finish_step(reward, terminated, info), terminated, truncated, info
