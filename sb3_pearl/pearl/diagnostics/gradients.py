"""Gradient conflict of the two actor terms of PEARL+ (the prior term against the posterior term).

:func:`compute_gradient_conflict` averages :func:`actor_gradient_conflict` (a model's
:func:`~sb3_pearl.pearl.gradient_conflict.gradient_conflict`) over
meta-batches for :func:`~sb3_pearl.pearl.diagnostics.compute_diagnostics` (the per-step measure and its training log
live in :mod:`sb3_pearl.pearl.gradient_conflict`, beside the update that logs them).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import torch as th

from sb3_pearl.common.buffers import MetaReplayBuffer
from sb3_pearl.common.type_aliases import PEARLLosses
from sb3_pearl.pearl.diagnostics.prior import prior_term
from sb3_pearl.pearl.gradient_conflict import gradient_conflict, record_gradient_conflict

__all__ = ["actor_gradient_conflict", "compute_gradient_conflict", "record_gradient_conflict"]

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL


def actor_gradient_conflict(model: PEARL, losses: PEARLLosses) -> dict[str, float]:
    """
    :func:`~sb3_pearl.pearl.gradient_conflict.gradient_conflict` of a model's two actor terms in one step.

    :param model: the PEARL / PEARL+ model
    :param losses: the losses of the step (``model._compute_losses``)
    :return: ``ratio``, ``cos``, ``prior_norm`` and ``post_norm`` (see ``gradient_conflict``)
    """
    return gradient_conflict(model.actor, prior_term(model).coef, losses)


def compute_gradient_conflict(model: PEARL, buffer: MetaReplayBuffer, n_batches: int) -> dict[str, Any]:
    """
    :func:`actor_gradient_conflict` on ``n_batches`` meta-batches sampled like ``train()`` does.

    :param model: the model
    :param buffer: the replay and context data to sample from
    :param n_batches: meta-batches
    :return: the mean ratio and cosine, and the values per batch
    """
    candidates = buffer.tasks_with_data()
    per_batch = []
    for _ in range(n_batches):
        tasks = np.random.choice(candidates, size=model.meta_batch, replace=len(candidates) < model.meta_batch)
        replay = buffer.rl.sample(tasks, model.batch_size, model.device, returns=prior_term(model).monte_carlo)
        ctx = buffer.context.sample(tasks, model.embedding_batch_size, model.device)
        context = model.policy.make_context(ctx.observations, ctx.actions, ctx.rewards, ctx.next_observations)
        z0 = th.randn(len(tasks), model.latent_dim, device=model.device)  # one prior z per task
        per_batch.append(actor_gradient_conflict(model, model._compute_losses(replay, context, z0)))

    def mean_of(key: str) -> float:
        values = [entry[key] for entry in per_batch if math.isfinite(entry[key])]
        return float(np.mean(values)) if values else math.nan

    return {
        "prior_coef": prior_term(model).coef,
        "n_batches": n_batches,
        "ratio": mean_of("ratio"),
        "cos": mean_of("cos"),
        "prior_norm": mean_of("prior_norm"),
        "post_norm": mean_of("post_norm"),
        "ratio_per_batch": [entry["ratio"] for entry in per_batch],
        "cos_per_batch": [entry["cos"] for entry in per_batch],
    }
