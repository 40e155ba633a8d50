"""The losses of one PEARL / PEARL+ gradient step (Algorithm 1 of the paper), for T tasks at once.

Every network runs once per step on the rows of all tasks, shaped ``(T * B, ...)``. The losses
touch disjoint parameter sets, so their sum (:meth:`PEARL._total_loss`; PEARL+'s adds its prior terms) back-propagated
once gives every optimizer its own gradient:

- KL(q(z|c) || N(0, I)) and the critic loss reach the encoder (and the critic), nothing else does;
- the prior critic's soft Bellman loss under z0 reaches the prior critic only (with ``prior_data="prior"``, on the
  rows collected with z from the prior only, as is the actor's prior term), and so does its conservative penalty
  (``prior_conservative_weight``: the z0 policy's actions enter it detached); its target is computed without
  gradients, from the prior critic's target network or (``prior_target="main"``) the critic's, or is the Monte-Carlo
  return of the prior-z rows with a bootstrapped tail (``prior_target="mc"``: it is then fitted on those rows only);
- the actor terms L(b, z.detach()) and, for PEARL+, L(b, z0) read the critics through frozen
  parameters and reach the actor only.

:func:`compute_losses` reads only its arguments: the networks (the policy), the batch, the posterior sample, z0, the
entropy coefficient and the model's :class:`LossSettings`; :meth:`PEARL._compute_losses <sb3_pearl.PEARL>` gathers them.
"""

from __future__ import annotations

from typing import NamedTuple

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
from sb3_pearl.common.type_aliases import MetaReplaySamples, PEARLLosses, PosteriorSample
from sb3_pearl.pearl.policies import PEARLPolicy


class LossSettings(NamedTuple):
    """
    The coefficients and switches of a gradient step: the model's settings (:meth:`PEARL._loss_settings`). The prior
    term's switches are PEARL+'s (:meth:`PEARLPlus._loss_settings <sb3_pearl.PEARLPlus>` sets them); their defaults
    are PEARL's: no prior term.
    """

    gamma: float  # discount factor
    reward_scale: float  # rewards are multiplied by it in the critic targets
    target_entropy: float  # target of a learned entropy coefficient
    prior_term: bool = False  # the actor is also trained on z0 (PEARL+ with prior_coef > 0)
    prior_data: str = "all"  # the replay rows the prior terms use: "all" or "prior" (collected with z from the prior)
    prior_target: str = "prior"  # the prior critic's target: "prior" (its own target network), "main" (the critic's) or "mc"
    prior_conservative_weight: float = 0.0  # weight of the prior critic's conservative (CQL) penalty; 0: off


def compute_losses(
    policy: PEARLPolicy,
    replay: MetaReplaySamples,
    posterior: PosteriorSample,
    z0: th.Tensor,
    ent_coef: th.Tensor,
    log_ent_coef: th.Tensor | None,
    settings: LossSettings,
) -> PEARLLosses:
    """
    Losses of one gradient step for T tasks, vectorised: every network runs once on the rows of all tasks.

    :param policy: the networks: encoder (through ``posterior``), actor, critic and its target, prior critic and its
        target (None for PEARL and ``prior_critic="shared"``)
    :param replay: RL batch, tensors of leading shape (T, B)
    :param posterior: q(z | c) of each task's context and one z per task drawn from it, carrying the encoder's
        gradients (:meth:`~sb3_pearl.pearl.pearl.PEARL.sample_posterior`), each (T, latent_dim)
    :param z0: prior latents (T, latent_dim), one per task
    :param ent_coef: the entropy coefficient of this step (detached)
    :param log_ent_coef: the learned log entropy coefficient (its loss is computed), or None for a fixed one
    :param settings: the coefficients and switches
    :return: the losses; summing them and calling backward gives every network its own gradient
    """
    n_tasks, batch = replay.rewards.shape[:2]
    rows = n_tasks * batch
    discrete = policy.discrete
    obs = replay.observations.reshape(rows, -1)
    next_obs = replay.next_observations.reshape(rows, -1)
    actions = replay.actions.reshape(rows, -1)
    rewards = settings.reward_scale * replay.rewards.reshape(rows, 1)
    not_done = 1.0 - replay.dones.reshape(rows, 1)
    device = rewards.device

    # Task inference: the KL of q(z | c) per task; each task's z is held across its rows.
    kl_loss = kl_to_standard_normal(posterior.mean, posterior.var).sum()  # summed over tasks, as the reference
    z_rows = posterior.z.repeat_interleave(batch, dim=0)  # (T*B, L)
    z0_rows = z0.repeat_interleave(batch, dim=0)  # (T*B, L)
    x_post = th.cat([obs, z_rows.detach()], dim=-1)  # actor input with the detached posterior z
    x_prior = th.cat([obs, z0_rows], dim=-1)
    use_prior = settings.prior_term

    # Actor on the posterior rows and, for PEARL+, the prior rows: one forward.
    pe_all = evaluate_policy(policy.actor, th.cat([x_post, x_prior]) if use_prior else x_post)
    pe_post, pe_prior = pe_all.split(rows)

    # The prior critic's target: one step (the paper) or, with prior_target="mc", the prior-z rows' Monte-Carlo
    # returns, each bootstrapped from the state its window ends in (sb3_pearl.pearl.returns).
    if settings.prior_target == "mc":
        if replay.returns is None:
            raise ValueError("prior_target='mc' needs replay batches with returns (TaskReplayBuffer.sample(returns=True))")
        boot_obs = replay.returns.tail_observations.reshape(rows, -1)  # (T*B, obs_dim) s_{t+k}
        returned = settings.reward_scale * replay.returns.reward_sum.reshape(rows, 1)
        returned = returned - ent_coef * replay.returns.log_prob_sum.reshape(rows, 1)  # (T*B, 1)
        boot_discount = replay.returns.discount.reshape(rows, 1)  # gamma^k, 0 after a termination
    else:
        boot_obs, returned, boot_discount = next_obs, rewards, not_done * settings.gamma

    # Soft Bellman targets with z detached (posterior) and z0 (prior critic): one actor forward.
    with th.no_grad():
        x_next = th.cat([next_obs, z_rows.detach()], dim=-1)
        x0_next = th.cat([boot_obs, z0_rows], dim=-1)
        next_pe_all = evaluate_policy(policy.actor, th.cat([x_next, x0_next]) if policy.prior_critic is not None else x_next)
        next_pe, next_pe0 = next_pe_all.split(rows)
        v_next = soft_value(q_of_policy(policy.critic_target, x_next, next_pe), next_pe, ent_coef)
        target = rewards + not_done * settings.gamma * v_next  # (T*B, 1)

    # Critic Q(s, a, z): the only loss (with the KL) that reaches the encoder.
    x_critic = th.cat([obs, z_rows], dim=-1)
    critic_loss = critic_regression_loss(q_of_actions(policy.critic, x_critic, actions, discrete), target)

    # prior_data="prior": the prior terms fit and score only the rows collected with z from the prior.
    prior_rows = None
    if settings.prior_data == "prior":
        if replay.prior_z is None:
            raise ValueError("prior_data='prior' needs replay batches with prior_z flags (TaskReplayBuffer.sample)")
        prior_rows = replay.prior_z.reshape(rows, 1)  # (T*B, 1) 0/1

    # Prior critic Q~(s, a, z0) (Q~(s, a) with prior_critic_input="state"): its own soft Bellman loss under z0,
    # bootstrapped from its own target network (the paper) or from the critic's target at z0 (prior_target="main"),
    # or fitted to the Monte-Carlo returns of the prior-z rows whose return is known (prior_target="mc").
    prior_critic_loss = th.zeros((), device=device)
    if policy.prior_critic is not None:
        assert policy.prior_critic_target is not None
        prior_features = policy.prior_critic_features
        with th.no_grad():
            if settings.prior_target == "main":
                q0_next = q_of_policy(policy.critic_target, x0_next, next_pe0)
            else:
                q0_next = q_of_policy(policy.prior_critic_target, prior_features(boot_obs, z0_rows), next_pe0)
            target0 = returned + boot_discount * soft_value(q0_next, next_pe0, ent_coef)  # (T*B, 1)
        x0_critic = prior_features(obs, z0_rows)
        q0 = q_of_actions(policy.prior_critic, x0_critic, actions, discrete)  # (n_prior_critics, T*B, 1)
        fitted_rows = prior_rows
        if settings.prior_target == "mc":
            assert replay.returns is not None
            fitted_rows = replay.returns.ready.reshape(rows, 1)  # (T*B, 1) 0/1: only prior-z rows have a return
        prior_critic_loss = critic_regression_loss(q0, target0, weights=fitted_rows)
        if settings.prior_conservative_weight > 0:
            # Conservative penalty (CQL): push Q~ down at the z0 policy's actions, up at the stored ones.
            gap = conservative_gap(policy.prior_critic, x0_critic, pe_prior, q0)  # (n_prior_critics, T*B, 1)
            weights = None if fitted_rows is None else fitted_rows.unsqueeze(0)
            penalty = gap.mean(dim=(1, 2)) if weights is None else masked_mean(gap, weights, dims=(1, 2))
            prior_critic_loss = prior_critic_loss + settings.prior_conservative_weight * penalty.sum()

    # Actor: L_actor(b, z.detach()) and, for PEARL+, L_actor(b, z0); critics frozen.
    actor_loss = -soft_value(q_of_policy(policy.critic.forward_frozen, x_post, pe_post), pe_post, ent_coef).mean()
    prior_actor_loss = th.zeros((), device=device)
    if use_prior:
        if policy.prior_critic is not None:
            x0_actor_term = policy.prior_critic_features(obs, z0_rows)  # (T*B, obs_dim [+ L])
            prior_q = q_of_policy(policy.prior_critic.forward_frozen, x0_actor_term, pe_prior)
        else:  # "shared": Q(s, a, z0)
            prior_q = q_of_policy(policy.critic.forward_frozen, x_prior, pe_prior)
        prior_values = soft_value(prior_q, pe_prior, ent_coef)  # (T*B, 1)
        prior_actor_loss = -(prior_values.mean() if prior_rows is None else masked_mean(prior_values, prior_rows))

    ent_coef_loss = th.zeros((), device=device)
    if log_ent_coef is not None:
        ent_coef_loss = -(log_ent_coef * (entropy_log_prob(pe_post) + settings.target_entropy).detach()).mean()

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
