"""The losses of one PEARL / PEARL+ gradient step (Algorithm 1 of the paper), for T tasks at once.

Every network runs once per step on the rows of all tasks, shaped ``(T * B, ...)``. The losses
touch disjoint parameter sets, so their sum (:meth:`PEARL._total_loss`) back-propagated once gives
every optimizer its own gradient:

- KL(q(z|c) || N(0, I)) and the critic loss reach the encoder (and the critic), nothing else does;
- the prior critic's soft Bellman loss under z0 reaches the prior critic only (with ``prior_data="prior"``, on the
  rows collected with z from the prior only, as is the actor's prior term), and so does its conservative penalty
  (``prior_conservative_weight``: the z0 policy's actions enter it detached); its target is computed without
  gradients, from the prior critic's target network or (``prior_target="main"``) the critic's;
- the actor terms L(b, z.detach()) and, for PEARL+, L(b, z0) read the critics through frozen
  parameters and reach the actor only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch as th

from sb3_pearl.common.context import kl_to_standard_normal
from sb3_pearl.common.soft_actor_critic import (
    conservative_gap,
    critic_regression_loss,
    entropy_log_prob,
    evaluate_policy,
    masked_mean,
    q_of_actions,
    q_of_policy,
    soft_value,
)
from sb3_pearl.common.type_aliases import MetaReplaySamples, PEARLLosses

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL


def compute_losses(model: PEARL, replay: MetaReplaySamples, context: th.Tensor, z0: th.Tensor) -> PEARLLosses:
    """
    Losses of one gradient step for T tasks, vectorised: every network runs once on the rows of all tasks.

    :param model: the PEARL / PEARL+ model (its networks and settings)
    :param replay: RL batch, tensors of leading shape (T, B)
    :param context: context transitions (T, N, context_dim)
    :param z0: prior latents (T, latent_dim), one per task
    :return: the losses; summing them and calling backward gives every network its own gradient
    """
    n_tasks, batch = replay.rewards.shape[:2]
    rows = n_tasks * batch
    discrete = model.policy.discrete
    obs = replay.observations.reshape(rows, -1)
    next_obs = replay.next_observations.reshape(rows, -1)
    actions = replay.actions.reshape(rows, -1)
    rewards = model.reward_scale * replay.rewards.reshape(rows, 1)
    not_done = 1.0 - replay.dones.reshape(rows, 1)
    ent_coef = model._current_ent_coef()

    # Task inference: q(z | c) per task, one z per task held across its rows.
    posterior = model.sample_posterior(context)  # mean, var, z: (T, L) each; z carries encoder gradients
    kl_loss = kl_to_standard_normal(posterior.mean, posterior.var).sum()  # summed over tasks, as the reference
    z_rows = posterior.z.repeat_interleave(batch, dim=0)  # (T*B, L)
    z0_rows = z0.repeat_interleave(batch, dim=0)  # (T*B, L)
    x_post = th.cat([obs, z_rows.detach()], dim=-1)  # actor input with the detached posterior z
    x_prior = th.cat([obs, z0_rows], dim=-1)
    use_prior = model.uses_prior_term

    # Actor on the posterior rows and, for PEARL+, the prior rows: one forward.
    pe_all = evaluate_policy(model.actor, th.cat([x_post, x_prior]) if use_prior else x_post)
    pe_post, pe_prior = pe_all.split(rows)

    # Soft Bellman targets with z detached (posterior) and z0 (prior critic): one actor forward.
    with th.no_grad():
        x_next = th.cat([next_obs, z_rows.detach()], dim=-1)
        x0_next = th.cat([next_obs, z0_rows], dim=-1)
        next_pe_all = evaluate_policy(model.actor, th.cat([x_next, x0_next]) if model.prior_critic is not None else x_next)
        next_pe, next_pe0 = next_pe_all.split(rows)
        v_next = soft_value(q_of_policy(model.critic_target, x_next, next_pe), next_pe, ent_coef)
        target = rewards + not_done * model.gamma * v_next  # (T*B, 1)

    # Critic Q(s, a, z): the only loss (with the KL) that reaches the encoder.
    x_critic = th.cat([obs, z_rows], dim=-1)
    critic_loss = critic_regression_loss(q_of_actions(model.critic, x_critic, actions, discrete), target)

    # prior_data="prior": the prior terms fit and score only the rows collected with z from the prior.
    prior_rows = None
    if model.prior_data == "prior":
        if replay.prior_z is None:
            raise ValueError("prior_data='prior' needs replay batches with prior_z flags (TaskReplayBuffer.sample)")
        prior_rows = replay.prior_z.reshape(rows, 1)  # (T*B, 1) 0/1

    # Prior critic Q~(s, a, z0) (Q~(s, a) with prior_critic_input="state"): its own soft Bellman loss under z0,
    # bootstrapped from its own target network (the paper) or from the critic's target at z0 (prior_target="main").
    prior_critic_loss = th.zeros((), device=model.device)
    if model.prior_critic is not None:
        assert model.prior_critic_target is not None
        prior_features = model.policy.prior_critic_features
        with th.no_grad():
            if model.prior_target == "main":
                q0_next = q_of_policy(model.critic_target, x0_next, next_pe0)
            else:
                q0_next = q_of_policy(model.prior_critic_target, prior_features(next_obs, z0_rows), next_pe0)
            target0 = rewards + not_done * model.gamma * soft_value(q0_next, next_pe0, ent_coef)  # (T*B, 1)
        x0_critic = prior_features(obs, z0_rows)
        q0 = q_of_actions(model.prior_critic, x0_critic, actions, discrete)  # (n_prior_critics, T*B, 1)
        prior_critic_loss = critic_regression_loss(q0, target0, weights=prior_rows)
        if model.prior_conservative_weight > 0:
            # Conservative penalty (CQL): push Q~ down at the z0 policy's actions, up at the stored ones.
            gap = conservative_gap(model.prior_critic, x0_critic, pe_prior, q0)  # (n_prior_critics, T*B, 1)
            weights = None if prior_rows is None else prior_rows.unsqueeze(0)
            penalty = gap.mean(dim=(1, 2)) if weights is None else masked_mean(gap, weights, dims=(1, 2))
            prior_critic_loss = prior_critic_loss + model.prior_conservative_weight * penalty.sum()

    # Actor: L_actor(b, z.detach()) and, for PEARL+, L_actor(b, z0); critics frozen.
    actor_loss = -soft_value(q_of_policy(model.critic.forward_frozen, x_post, pe_post), pe_post, ent_coef).mean()
    prior_actor_loss = th.zeros((), device=model.device)
    if use_prior:
        if model.prior_critic is not None:
            x0_actor_term = model.policy.prior_critic_features(obs, z0_rows)  # (T*B, obs_dim [+ L])
            prior_q = q_of_policy(model.prior_critic.forward_frozen, x0_actor_term, pe_prior)
        else:  # "shared": Q(s, a, z0)
            prior_q = q_of_policy(model.critic.forward_frozen, x_prior, pe_prior)
        prior_values = soft_value(prior_q, pe_prior, ent_coef)  # (T*B, 1)
        prior_actor_loss = -(prior_values.mean() if prior_rows is None else masked_mean(prior_values, prior_rows))

    ent_coef_loss = th.zeros((), device=model.device)
    if model.log_ent_coef is not None:
        assert isinstance(model.target_entropy, float)
        ent_coef_loss = -(model.log_ent_coef * (entropy_log_prob(pe_post) + model.target_entropy).detach()).mean()

    return PEARLLosses(
        critic_loss=critic_loss,
        kl_loss=kl_loss,
        prior_critic_loss=prior_critic_loss,
        actor_loss=actor_loss,
        prior_actor_loss=prior_actor_loss,
        ent_coef_loss=ent_coef_loss,
        ent_coef=ent_coef,
        z_mean=posterior.mean.detach(),
        z_var=posterior.var.detach(),
    )
