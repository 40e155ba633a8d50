"""A scripted, task-independent policy with the adaptation API, so that the meta-test protocol can roll it out.

:class:`ScriptedPolicy` never adapts: ``observe`` and ``adapt`` do nothing, so every trajectory k acts as
k = 0 does. It is the bar of the prior-optimality gap (``pearl_paper.reproduce.prior_measures``, the paper's harness): what a
prior policy, which acts before it has seen any data of the task, could score with no task data at all.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


class ScriptedPolicy:
    """
    An observation -> action function as an :class:`~sb3_pearl.common.adaptation.AdaptiveModel`.

    :param policy: maps one observation (obs_dim,) to one action in env units
    :param name: what the policy does, for reports
    """

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray], name: str) -> None:
        self.policy = policy
        self.name = name

    def reset_adaptation(self) -> None:
        """Nothing to forget."""

    def observe(self, obs: np.ndarray, action: Any, reward: float, next_obs: np.ndarray, done: bool) -> None:
        """Data are ignored: the policy is task-independent."""

    def adapt(self) -> None:
        """Nothing to adapt."""

    def predict(
        self, observation: Any, state: Any = None, episode_start: Any = None, deterministic: bool = False
    ) -> tuple[np.ndarray, Any]:
        """The scripted action for one observation (obs_dim,) or a batch (N, obs_dim)."""
        obs = np.asarray(observation, dtype=np.float32)
        if obs.ndim == 1:
            return np.asarray(self.policy(obs)), state
        return np.stack([np.asarray(self.policy(row)) for row in obs]), state
