"""Soft actor-critic math shared by every algorithm of the project, for Box and Discrete actions.

Networks take an input ``x`` (for PEARL: the observation concatenated with z). Box actions use a
tanh-Gaussian actor and critics on ``cat(x, a)``; Discrete actions use a categorical actor and
critics that output one Q value per action, so that the soft state value is an exact expectation
over actions (soft discrete SAC, Christodoulou 2019):

    Box:       V(s) = Q(s, a~pi) - alpha * log pi(a|s)
    Discrete:  V(s) = sum_a pi(a|s) * (Q(s, a) - alpha * log pi(a|s))

The actor loss is ``-mean(V)`` computed with frozen critic parameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch as th
from torch import nn

CriticFn = Callable[[th.Tensor], th.Tensor]  # x -> (n_critics, N, out)


class PolicyEval(NamedTuple):
    """The actor evaluated on a batch of N inputs."""

    actions: th.Tensor | None  # Box: reparameterised actions (N, A); Discrete: None
    probs: th.Tensor | None  # Discrete: (N, n_actions); Box: None
    log_prob: th.Tensor  # Box: (N, 1); Discrete: (N, n_actions)

    def split(self, n: int) -> tuple[PolicyEval, PolicyEval]:
        """Split the rows into the first ``n`` and the rest."""

        def cut(t: th.Tensor | None) -> tuple[th.Tensor | None, th.Tensor | None]:
            return (None, None) if t is None else (t[:n], t[n:])

        (a1, a2), (p1, p2), (l1, l2) = cut(self.actions), cut(self.probs), cut(self.log_prob)
        assert l1 is not None and l2 is not None
        return PolicyEval(a1, p1, l1), PolicyEval(a2, p2, l2)


def evaluate_policy(actor: nn.Module, x: th.Tensor) -> PolicyEval:
    """Sample (Box) or enumerate (Discrete) the actor's actions on inputs ``x`` (N, in_dim)."""
    if hasattr(actor, "probs"):
        probs, log_probs = actor.probs(x)  # type: ignore[operator]
        return PolicyEval(None, probs, log_probs)
    actions, log_prob = actor.action_log_prob(x)  # type: ignore[operator]
    return PolicyEval(actions, None, log_prob.reshape(-1, 1))


def q_of_policy(critic_fn: CriticFn, x: th.Tensor, pe: PolicyEval) -> th.Tensor:
    """Min over critics of Q at the policy's actions: Box (N, 1), Discrete (N, n_actions)."""
    q_input = x if pe.actions is None else th.cat([x, pe.actions], dim=-1)
    return critic_fn(q_input).min(dim=0).values


def q_of_actions(critic_fn: CriticFn, x: th.Tensor, actions: th.Tensor, discrete: bool) -> th.Tensor:
    """Q of every critic at stored actions (Box: (N, A) scaled; Discrete: (N, 1) indices) -> (n_critics, N, 1)."""
    if discrete:
        q_all = critic_fn(x)  # (n_critics, N, n_actions)
        index = actions.long().unsqueeze(0).expand(q_all.shape[0], -1, -1)  # (n_critics, N, 1)
        return q_all.gather(-1, index)
    return critic_fn(th.cat([x, actions], dim=-1))


CQL_RANDOM_ACTIONS = 4  # uniform actions per row in the Box form of the conservative penalty


def conservative_gap(
    critic_fn: CriticFn, x: th.Tensor, pe: PolicyEval, q_data: th.Tensor, n_random: int = CQL_RANDOM_ACTIONS
) -> th.Tensor:
    """
    CQL(H)'s gap per critic and row (Kumar et al. 2020, eq. 4): a soft maximum of the critic over actions minus the
    critic at the stored action. Minimising it pushes the critic down on actions the data do not cover and up on
    those they do; gradients reach the critic only (the actions enter detached).

    Discrete: ``logsumexp_a Q(s, a) - Q(s, a_data)``, exact over the actions. Box (actions scaled to [-1, 1]^d):
    ``log E_mu[exp(Q) / mu]`` estimated by importance sampling over ``n_random`` uniform actions (density 2^-d) and the
    policy's sampled action (density ``pi``): ``logsumexp_i (Q(s, a_i) - log mu(a_i)) - log(n_random + 1)`` (CQL's
    practical form). Bounded below by the critic's value at any of those actions, unlike ``Q(s, pi) - Q(s, a_data)``.

    :param critic_fn: the critic (not frozen)
    :param x: critic inputs without the action (N, in_dim)
    :param pe: the policy evaluated on the same rows (its actions and log-probabilities are detached here)
    :param q_data: the critic at the stored actions, (n_critics, N, 1) (:func:`q_of_actions`)
    :param n_random: uniform actions per row (Box)
    :return: (n_critics, N, 1)
    """
    if pe.actions is None:
        return th.logsumexp(critic_fn(x), dim=-1, keepdim=True) - q_data
    n, action_dim = pe.actions.shape
    uniform = th.rand(n_random, n, action_dim, device=x.device) * 2.0 - 1.0  # (R, N, A) in [-1, 1]^d
    actions = th.cat([uniform, pe.actions.detach().unsqueeze(0)])  # (R + 1, N, A)
    inputs = th.cat([x.unsqueeze(0).expand(n_random + 1, -1, -1), actions], dim=-1).reshape((n_random + 1) * n, -1)
    q = critic_fn(inputs).reshape(q_data.shape[0], n_random + 1, n)  # (n_critics, R + 1, N)
    log_density = th.cat(
        [
            th.full((n_random, n), -action_dim * math.log(2.0), device=x.device),  # uniform on [-1, 1]^d
            pe.log_prob.detach().reshape(1, n),
        ]
    )  # (R + 1, N)
    soft_max = th.logsumexp(q - log_density.unsqueeze(0), dim=1) - math.log(n_random + 1)  # (n_critics, N)
    return soft_max.unsqueeze(-1) - q_data


def soft_value(q: th.Tensor, pe: PolicyEval, ent_coef: th.Tensor) -> th.Tensor:
    """Soft state value (N, 1) from the policy's Q values (:func:`q_of_policy`)."""
    if pe.probs is None:
        return q - ent_coef * pe.log_prob
    return (pe.probs * (q - ent_coef * pe.log_prob)).sum(dim=-1, keepdim=True)


def entropy_log_prob(pe: PolicyEval) -> th.Tensor:
    """E[log pi] per row (N, 1): the sampled log-probability (Box) or its exact expectation (Discrete)."""
    if pe.probs is None:
        return pe.log_prob
    return (pe.probs * pe.log_prob).sum(dim=-1, keepdim=True)


def critic_regression_loss(q: th.Tensor, target: th.Tensor, coef: float = 1.0, weights: th.Tensor | None = None) -> th.Tensor:
    """
    ``coef`` * sum over critics of the mean squared Bellman error.

    PEARL uses ``coef=1`` (the reference sums plain MSEs, which sets the critic/KL balance of the
    encoder); SB3's SAC, and so the discrete SAC of Fine-Tune, uses 0.5.

    :param q: Q values (n_critics, N, 1)
    :param target: Bellman targets (N, 1)
    :param coef: factor on the sum
    :param weights: (N, 1) 0/1 row weights: the mean runs over the rows with weight 1 only (None: every row)
    """
    if q.dim() != 3 or target.shape != q.shape[1:]:
        raise ValueError(f"expected q (n_critics, N, 1) and target (N, 1), got {tuple(q.shape)} and {tuple(target.shape)}")
    squared = (q - target.unsqueeze(0)).pow(2)  # (n_critics, N, 1)
    if weights is None:
        return coef * squared.mean(dim=(1, 2)).sum()
    return coef * (masked_mean(squared, weights.unsqueeze(0), dims=(1, 2))).sum()


def masked_mean(values: th.Tensor, weights: th.Tensor, dims: tuple[int, ...] = (0, 1)) -> th.Tensor:
    """
    Mean of ``values`` over the entries whose 0/1 ``weights`` are 1 (broadcast), along ``dims``; 0 when there are none.

    :param values: e.g. (N, 1) per-row losses
    :param weights: 0/1 weights broadcastable to ``values``
    :param dims: dimensions to average over
    """
    weights = weights.expand_as(values)
    return (values * weights).sum(dim=dims) / weights.sum(dim=dims).clamp(min=1.0)
