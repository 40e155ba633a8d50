"""NamedTuples exchanged between the buffers, the losses and the logger."""

from __future__ import annotations

from typing import NamedTuple

import torch as th


class ReturnTargets(NamedTuple):
    """
    Discounted returns of the transitions collected with z from the prior, from each row to the end of its trajectory
    piece (n-step: at most n rows), for a prior critic fitted to Monte-Carlo targets (``prior_target="mc"``). The
    target of row t whose piece ends k rows later is ``reward_scale * reward_sum - ent_coef * log_prob_sum +
    discount * V~(tail_observations, z0)``. Every tensor has leading shape ``(T, B)``.
    """

    reward_sum: th.Tensor  # (T, B, 1) sum_{i<k} gamma^i r_{t+i} (unscaled rewards)
    log_prob_sum: th.Tensor  # (T, B, 1) sum_{1<=i<k} gamma^i log pi(a_{t+i} | s_{t+i}, z) of the behaviour policy
    discount: th.Tensor  # (T, B, 1) gamma^k, 0 when the piece ends in a true termination
    tail_observations: th.Tensor  # (T, B, obs_dim) s_{t+k}, where the bootstrapped tail starts
    ready: th.Tensor  # (T, B, 1) 1.0 where the row's return is known (a prior-z row whose piece has ended)


class MetaReplaySamples(NamedTuple):
    """A replay batch for ``T`` tasks with ``B`` rows each (every tensor has leading shape ``(T, B)``)."""

    observations: th.Tensor  # (T, B, obs_dim)
    actions: th.Tensor  # (T, B, act_dim) scaled Box actions in [-1, 1], or (T, B, 1) Discrete indices
    rewards: th.Tensor  # (T, B, 1)
    next_observations: th.Tensor  # (T, B, obs_dim)
    dones: th.Tensor  # (T, B, 1) 1.0 on termination only (a time-limit truncation stores 0.0)
    prior_z: th.Tensor | None = None  # (T, B, 1) 1.0 where the transition was collected with z from the prior
    returns: ReturnTargets | None = None  # the prior-z rows' Monte-Carlo returns (sample(..., returns=True))


class PosteriorSample(NamedTuple):
    """q(z | c) for T tasks and one z per task."""

    mean: th.Tensor  # (T, latent_dim)
    var: th.Tensor  # (T, latent_dim)
    z: th.Tensor  # (T, latent_dim): a reparameterised sample (carries encoder gradients), or the mean


class PEARLLosses(NamedTuple):
    """The losses of one PEARL/PEARL+ gradient step (Algorithm 1), each a scalar tensor."""

    critic_loss: th.Tensor  # L_critic(b, z): reaches the critic and the encoder
    kl_loss: th.Tensor  # sum over tasks of KL(q(z|c) || N(0, I)): reaches the encoder only
    prior_critic_loss: th.Tensor  # L~_critic(b, z0): reaches the prior critic only (0 for PEARL / shared mode)
    actor_loss: th.Tensor  # L_actor(b, z.detach()): reaches the actor only
    prior_actor_loss: th.Tensor  # L_actor(b, z0): reaches the actor only
    ent_coef_loss: th.Tensor  # reaches log_ent_coef only (0 with a fixed ent_coef)
    ent_coef: th.Tensor  # the entropy coefficient used in this step
    z_mean: th.Tensor  # (T, latent_dim) posterior means, for logging
    z_var: th.Tensor  # (T, latent_dim) posterior variances, for logging


class TrainingPlan(NamedTuple):
    """
    What ``learn(total_timesteps)`` will still do.

    :param env_steps: env steps to collect
    :param gradient_steps: gradient steps to take
    :param initial_steps: env steps collected before the first gradient step (the model is untrained until then)
    :param first_updates: gradient steps after which the cost per gradient step is measured (the first iteration's)
    :param note: what the collection-only start is, e.g. ``"iteration 0: 2,000 steps with z from the prior on each
        of 100 training tasks"``
    """

    env_steps: int
    gradient_steps: int
    initial_steps: int = 0
    first_updates: int = 1
    note: str = ""
