"""Containers passed between MAML's sampler, advantage computation, inner loop and TRPO outer loop."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch as th


class EpisodeBatch(NamedTuple):
    """Trajectories of ``T`` tasks, ``E`` episodes each, padded to ``H`` steps (numpy arrays)."""

    observations: np.ndarray  # (T, E, H, obs_dim) float32
    actions: np.ndarray  # (T, E, H, act_dim) raw normalised Box actions, or (T, E, H, 1) Discrete indices
    rewards: np.ndarray  # (T, E, H) float32, 0 after the end of an episode
    lengths: np.ndarray  # (T, E) int64, steps of each episode


class TaskSamples(NamedTuple):
    """The valid steps of one task's trajectories, flattened, as tensors for the losses."""

    observations: th.Tensor  # (N, obs_dim)
    actions: th.Tensor  # (N, act_dim) float for Box, (N,) long for Discrete
    advantages: th.Tensor  # (N,)


class OldPolicy(NamedTuple):
    """The sampling (adapted) policy on one task's post-adaptation data, detached."""

    log_prob: th.Tensor  # (N,)
    distribution: th.distributions.Distribution  # batch shape (N,)


class TRPOInfo(NamedTuple):
    """Outcome of one TRPO meta-update."""

    surrogate_before: float
    surrogate_after: float
    kl: float  # mean KL(old || new) after the step (0 if rejected)
    step_size: float  # multiplier of the CG direction that was applied (0 if rejected)
    n_backtracks: int
    accepted: bool
