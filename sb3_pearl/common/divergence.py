"""Divergence guard: non-finite env outputs are errors that name the env, task and step; non-finite updates are skipped.

- :func:`check_env_step`: called by every collection loop (PEARL's ``collect_iteration``, Fine-Tune's
  ``_store_transition``, MAML's ``_collect_episodes``) right after ``env.step``. The fast path is one
  ``np.isfinite`` over the VecEnv's rewards and observations; a non-finite value raises
  :class:`NonFiniteEnvError` naming the env id, the env index, its task and the timestep, instead of
  storing it (one reward of 1e30 or nan would otherwise poison the critic and its Adam state).
- :class:`NonFiniteUpdateGuard`: PEARL's ``train()`` asks it, once per gradient step and with one device
  sync, whether the total loss and every gradient are finite; a non-finite step is skipped (no optimizer
  step, no target update), and ``max_consecutive`` skipped steps in a row raise :class:`DivergenceError`
  naming the non-finite losses and the likely fixes. The weights stay those of the last finite step.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import torch as th


class NonFiniteEnvError(ValueError):
    """The env returned a non-finite observation or reward."""


class DivergenceError(RuntimeError):
    """Training produced non-finite losses or gradients (or actions) too many times in a row."""


def _describe_env(env: Any, index: int) -> tuple[str, Any]:
    """The env id (or class name) and the task in force of env ``index`` of a VecEnv (for messages only)."""
    try:
        spec = env.get_attr("spec", indices=[index])[0]
        name = spec.id if spec is not None else type(env.get_attr("unwrapped", indices=[index])[0]).__name__
    except Exception:  # the message must not fail: any VecEnv, any env
        name = "the env"
    try:
        task = env.get_attr("_task", indices=[index])[0]
    except Exception:
        task = "unknown"
    return name, task


def check_env_step(
    env: Any,
    observations: Any,
    rewards: Any,
    dones: Any,
    infos: list[dict[str, Any]],
    timestep: int,
    algorithm: str,
    active: Iterable[int] | None = None,
) -> None:
    """
    Raise :class:`NonFiniteEnvError` if a VecEnv step returned a non-finite observation or reward.

    :param env: the VecEnv that was stepped
    :param observations: the observations it returned, ``(n_envs, ...)``
    :param rewards: the rewards, ``(n_envs,)``
    :param dones: the done flags (the terminal observation of a finished episode is checked too)
    :param infos: the infos (with ``terminal_observation`` for finished episodes)
    :param timestep: the model's timestep count before this step
    :param algorithm: the algorithm's name, for the message
    :param active: the env indices whose transitions are stored (default: all)
    """
    observations = np.asarray(observations)
    rewards = np.asarray(rewards)
    done_indices = np.flatnonzero(dones)
    terminals = (np.asarray(infos[i].get("terminal_observation", 0.0), dtype=np.float64) for i in done_indices)
    if np.isfinite(rewards).all() and np.isfinite(observations).all() and all(np.isfinite(t).all() for t in terminals):
        return
    indices = range(len(rewards)) if active is None else active
    for index in indices:
        terminal = infos[index].get("terminal_observation") if index in done_indices else None
        for what, value in (
            ("reward", rewards[index]),
            ("observation", observations[index]),
            ("terminal observation", terminal),
        ):
            if value is None or np.isfinite(np.asarray(value, dtype=np.float64)).all():
                continue
            name, task = _describe_env(env, index)
            shown = np.asarray(value).tolist()
            raise NonFiniteEnvError(
                f"{name} returned a non-finite {what} ({shown}) at timestep {timestep} (env index {index}, task {task}): "
                f"{algorithm} stops rather than train on it. Check the env's dynamics and reward for this task (an "
                "unbounded reward, a division by zero, a simulator that blew up) or the wrapper that produced it"
            )


def check_finite_actions(actions: np.ndarray, timestep: int, algorithm: str) -> None:
    """
    Raise :class:`DivergenceError` if the policy produced non-finite actions (its weights diverged).

    :param actions: the actions about to be sent to the env
    :param timestep: the model's timestep count
    :param algorithm: the algorithm's name, for the message
    """
    if not np.isfinite(actions).all():
        raise DivergenceError(
            f"{algorithm}'s policy produced non-finite actions at timestep {timestep}: its weights diverged. "
            "Likely fixes: a lower learning_rate, a smaller reward_scale or rescaled rewards"
        )


class NonFiniteUpdateGuard:
    """
    Skip gradient steps whose loss or gradients are not finite; stop after ``max_consecutive`` in a row.

    :param algorithm: the algorithm's name, for the messages
    :param max_consecutive: skipped steps in a row that stop training with :class:`DivergenceError`
    """

    def __init__(self, algorithm: str, max_consecutive: int = 10) -> None:
        if max_consecutive < 1:
            raise ValueError(f"max_consecutive must be >= 1, got {max_consecutive}")
        self.algorithm = algorithm
        self.max_consecutive = max_consecutive
        self.consecutive = 0
        self.skipped = 0

    @staticmethod
    def is_finite(total_loss: th.Tensor, parameters: list[th.Tensor]) -> bool:
        """
        Whether ``total_loss`` and the gradients of ``parameters`` are all finite: one device sync.

        :param total_loss: the summed loss (after ``backward``)
        :param parameters: the parameters that are about to be stepped
        :return: True when the update can be applied
        """
        flags = th.isfinite(total_loss.detach()).reshape(1)
        grads = [p.grad for p in parameters if p.grad is not None]
        if grads:
            norms = th._foreach_norm(grads) if hasattr(th, "_foreach_norm") else [th.linalg.vector_norm(g) for g in grads]
            flags = th.cat([flags, th.isfinite(th.stack(norms))])
        return bool(flags.all().item())

    def ok(self) -> None:
        """Record a finite (applied) update."""
        self.consecutive = 0

    def skip(self, losses: Mapping[str, th.Tensor], context: Mapping[str, Any]) -> None:
        """
        Record a skipped update; raise :class:`DivergenceError` after ``max_consecutive`` in a row.

        :param losses: the step's losses by name (only read here, on the slow path)
        :param context: settings named in the message as likely fixes (``learning_rate``, ``reward_scale``, ...)
        """
        self.consecutive += 1
        self.skipped += 1
        values = {name: float(value.detach().float().mean().item()) for name, value in losses.items()}
        bad = [f"{name}={value}" for name, value in values.items() if not math.isfinite(value)]
        cause = f"non-finite {', '.join(bad)}" if bad else "finite losses but a non-finite gradient"
        if self.consecutive == 1:
            warnings.warn(f"{self.algorithm}: skipped a gradient step with {cause}; the weights are unchanged", stacklevel=3)
        if self.consecutive >= self.max_consecutive:
            settings = ", ".join(f"{name}={value}" for name, value in context.items())
            raise DivergenceError(
                f"{self.algorithm}: {self.consecutive} gradient steps in a row had a non-finite loss or gradient (the "
                f"last: {cause}); training stopped and the weights are those of the last finite step. Likely fixes: a "
                f"lower learning_rate, a smaller reward_scale or rescaled env rewards (they enter the critic targets "
                f"times reward_scale), bounded rewards from the env. Settings: {settings}"
            )


__all__ = [
    "DivergenceError",
    "NonFiniteEnvError",
    "NonFiniteUpdateGuard",
    "check_env_step",
    "check_finite_actions",
]
