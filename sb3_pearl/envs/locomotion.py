"""Shared pieces of the MuJoCo task families (Gymnasium v5 locomotion envs with a task).

:class:`LocomotionTaskEnv` is the task mixin for a Gymnasium v5 MuJoCo env: it goes first in the
bases (``class Walker2dVelMetaEnv(LocomotionTaskEnv, Walker2dEnv)``), applies a pending task at
``reset()``, counts the steps of the episode and turns the base env's unhealthy termination into
``info["cost"] = 1.0`` plus an optional *unhealthy penalty*.

Why a penalty: the task rewards are negative errors (``-|v - v*|``, ``-||xy - goal||_1``), so once the
error exceeds the healthy reward, ending the episode early by falling over is worth *more* return
than staying up (an unhealthy step is the last one, every step after it would have been negative).
The paper states that unhealthy poses "carry very heavy penalty" (Section VI) but gives no value; the
point families of this package use the same device (``SafePointGoalMeta-v0``'s ``crash_penalty``): the
terminal unhealthy step is penalised by ``unhealthy_penalty`` times the number of steps the fall
skips (``max_episode_steps - t``), so falling is never better than standing still as long as the
per-step reward of standing still is above ``-unhealthy_penalty``. Each family derives its default
from its task ranges (documented there); ``unhealthy_penalty=0`` gives the bare reward formula.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, ClassVar

import numpy as np

from sb3_pearl.envs.checks import check_count, check_number
from sb3_pearl.envs.task_protocol import MetaTaskEnv


@contextmanager
def ignore_mujoco_warning(prefix: str) -> Iterator[None]:
    """
    Drop the MuJoCo warnings that start with ``prefix`` inside the block; any other is printed as MuJoCo prints it.

    E.g. the deprecation of ``settotalmass`` by MuJoCo >= 3.3, which Gymnasium's own ``half_cheetah.xml`` uses
    (the model is Gymnasium's, the fix is theirs).

    :param prefix: the start of the message
    """
    import mujoco

    previous = mujoco.get_mju_user_warning()

    def handler(message: str) -> None:
        if message.startswith(prefix):
            return
        if previous is not None:
            previous(message)
        else:
            print(f"WARNING: {message}\n", file=sys.stderr, flush=True)

    mujoco.set_mju_user_warning(handler)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


class LocomotionTaskEnv(MetaTaskEnv):
    """
    Task mixin for Gymnasium v5 MuJoCo envs with health termination (goes first in the bases).

    The subclass sets ``self.unhealthy_penalty`` and ``self.max_episode_steps`` and calls
    :meth:`_init_task` *before* the MuJoCo base ``__init__``; its ``step`` calls
    :meth:`_finish_step` once with the base env's outputs.
    """

    unhealthy_penalty: float
    max_episode_steps: int
    _elapsed_steps: int = 0
    # Velocity families (Walker2D-vel, Ant3D-vel): ``info["velocity_error"]`` is the mean of ``-reward_forward`` over the
    # episode's steps so far, so the meta-test records each trajectory's velocity error (trajectory_info_keys).
    tracks_velocity: ClassVar[bool] = False
    _velocity_error_sum: float = 0.0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """
        Apply a pending task (``set_task``) and reset the base env.

        :param seed: seed of the base env's reset noise
        :param options: passed to the base env
        :return: observation and info (with ``cost = 0.0``)
        """
        self._apply_pending_task()
        self._elapsed_steps = 0
        self._velocity_error_sum = 0.0
        obs, info = super().reset(seed=seed, options=options)  # type: ignore[misc]
        info["cost"] = 0.0
        return obs, info

    def _finish_step(self, reward: float, terminated: bool, info: dict[str, Any]) -> float:
        """
        Count the step, set ``info["cost"]`` and apply the unhealthy penalty on a terminal step.

        Only the base env's health check terminates these envs, so ``terminated`` *is* the
        unhealthy flag (the time limit truncates, it never terminates).

        :param reward: the step's task reward
        :param terminated: the base env's termination flag
        :param info: the step's info dict (updated in place)
        :return: the reward, penalised on the unhealthy step
        """
        self._elapsed_steps += 1
        if self.tracks_velocity:
            self._velocity_error_sum -= float(info["reward_forward"])
            info["velocity_error"] = self._velocity_error_sum / self._elapsed_steps
        if terminated:
            penalty = self.unhealthy_penalty * max(self.max_episode_steps - self._elapsed_steps, 0)
            info["cost"] = 1.0
            info["unhealthy_penalty"] = penalty
            return reward - penalty
        info["cost"] = 0.0
        return reward


def validate_locomotion_kwargs(base_kwargs: dict[str, Any], unhealthy_penalty: float, max_episode_steps: int) -> None:
    """
    Reject keyword arguments that would break the cost bookkeeping of :class:`LocomotionTaskEnv`.

    :param base_kwargs: kwargs forwarded to the Gymnasium base env
    :param unhealthy_penalty: penalty per skipped step
    :param max_episode_steps: horizon used for the penalty
    """
    if base_kwargs.get("terminate_when_unhealthy", True) is not True:
        raise ValueError(
            "terminate_when_unhealthy must stay True: these task families end the episode on an unhealthy "
            "pose and report it as info['cost'] = 1 on that step (paper, Section V-A-1)"
        )
    check_number("unhealthy_penalty", unhealthy_penalty, 0.0, hint="penalty per step a fall skips")
    check_count("max_episode_steps", max_episode_steps, 1, hint="the horizon the penalty is sized by")
