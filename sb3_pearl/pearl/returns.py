"""Monte-Carlo (or n-step) returns of the trajectories collected with z from the prior (``prior_target="mc"``).

A prior critic bootstrapped from itself (the paper's form) drifts far above the z0 policy's value on every family we
trained (docs/results.md, "The prior critic"). With ``prior_target="mc"`` it is fitted instead to the discounted
return the z0 policy actually collected: for row t of a trajectory piece that ends K rows later, with
``k = min(n, K - t)`` (``n = prior_return_steps``, 0: the whole piece),

    G_t = reward_scale * sum_{i<k} gamma^i r_{t+i} - ent_coef * sum_{1<=i<k} gamma^i log pi_b(a_{t+i} | s_{t+i}, z)
          + gamma^k * V~(s_{t+k}, z0)        (the tail: 0 when the piece ended in a true termination)

the soft return of the calibration measure (:mod:`sb3_pearl.pearl.diagnostics.calibration`), with the entropy bonus
from t + 1 on as in the soft Bellman target. A piece ends when its trajectory ends (termination or time limit), when
the collection segment ends (the next segment resets the env) or when the iteration is trained while an env is inside
one: only the last two are *cuts*, bootstrapped like a time limit. The reward and log-probability sums are stored
unscaled and apart, so that the target uses the reward scale and entropy coefficient of the step that reads it.

``pi_b`` is the policy that collected the piece: its log-probabilities are recorded as the actions are drawn
(:meth:`~sb3_pearl.pearl.policies.PEARLPolicy.act_with_log_prob`, the same random draws as ``act``: a model without
Monte-Carlo targets collects bit-identical data). They are not recomputed from the stored actions: a saturated Box
action (tanh = +-1 in float32) cannot be inverted to the Gaussian sample that produced it.

The buffer is a ring per task: before a row is overwritten, the open piece holding it (its oldest row: a piece longer
than the capacity, or two envs on one task) is cut there (``PEARL._cut_before_overwrite``), so that no return is
written on a row that holds another transition.

The replay buffer keeps 100k rows per task, so the returns it holds are those of many past z0 policies: the prior
critic fits a mixture of their values, which lags the current z0 policy (docs/pearl.md, "mc").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np


class PieceReturns(NamedTuple):
    """The returns of every row of one trajectory piece of K rows, each array (K,)."""

    reward_sum: np.ndarray  # sum_{i<k} gamma^i r_{t+i}
    log_prob_sum: np.ndarray  # sum_{1<=i<k} gamma^i log pi_b(a_{t+i})
    discount: np.ndarray  # gamma^k, 0 when the row's window reaches a true termination
    tail: np.ndarray  # index (in the piece) of the last row of the window: its next observation starts the tail


def piece_returns(rewards: np.ndarray, log_probs: np.ndarray, gamma: float, terminated: bool, horizon: int) -> PieceReturns:
    """
    The discounted sums of every row of a trajectory piece, each row's window ``k = min(horizon, K - t)`` rows long.

    :param rewards: (K,) rewards of the piece, in order
    :param log_probs: (K,) log-probabilities of its actions under the policy that collected it
    :param gamma: discount factor
    :param terminated: the piece ends in a true termination (no tail after its last row)
    :param horizon: n of the n-step return; 0: every window reaches the end of the piece (Monte-Carlo)
    :return: the sums, each (K,)
    """
    if rewards.ndim != 1 or log_probs.shape != rewards.shape:
        raise ValueError(f"expected rewards and log_probs of shape (K,), got {rewards.shape} and {log_probs.shape}")
    n_rows = len(rewards)
    rows = np.arange(n_rows)
    end = np.minimum(rows + horizon, n_rows) if horizon > 0 else np.full(n_rows, n_rows)  # (K,) one past each window
    k = end - rows
    # Suffix sums S_t = sum_{i>=0} gamma^i x_{t+i} (S_K = 0) give every window:
    # sum_{i<k} gamma^i x_{t+i} = S_t - gamma^k S_end.
    powers = gamma ** k.astype(np.float64)

    def suffix(x: np.ndarray) -> np.ndarray:
        sums = np.zeros(n_rows + 1)
        for t in range(n_rows - 1, -1, -1):
            sums[t] = x[t] + gamma * sums[t + 1]
        return sums

    reward_suffix, log_prob_suffix = suffix(rewards.astype(np.float64)), suffix(log_probs.astype(np.float64))
    reward_sum = reward_suffix[rows] - powers * reward_suffix[end]
    # The entropy window starts one row later: sum_{1<=i<k} gamma^i lp_{t+i} = gamma * (S_{t+1} - gamma^(k-1) S_end).
    log_prob_sum = gamma * (log_prob_suffix[rows + 1] - gamma ** (k - 1.0) * log_prob_suffix[end])
    discount = np.where((end == n_rows) & terminated, 0.0, powers)
    return PieceReturns(reward_sum, log_prob_sum, discount, end - 1)


@dataclass
class PendingPiece:
    """A trajectory piece being collected with z from the prior: its task and the buffer rows it filled."""

    task: int
    rows: list[int] = field(default_factory=list)
    log_probs: list[float] = field(default_factory=list)  # log pi_b(a | s, z) of each row's action, as it was drawn
