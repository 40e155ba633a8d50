"""Gradient conflict of the two actor terms of PEARL+ (the prior term against the posterior term).

:func:`actor_gradient_conflict` compares one step's gradients; :func:`record_gradient_conflict` logs them
during training (``train/grad_conflict_*``, called from ``PEARL.train``); :func:`compute_gradient_conflict`
averages them over meta-batches for :func:`~sb3_pearl.pearl.diagnostics.compute_diagnostics`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import torch as th

from sb3_pearl.common.buffers import MetaReplayBuffer
from sb3_pearl.common.type_aliases import PEARLLosses

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL


def _flat_grad(loss: th.Tensor, params: list[th.nn.Parameter]) -> th.Tensor:
    """Gradient of ``loss`` w.r.t. ``params`` flattened to (P,); zeros if the loss does not depend on them."""
    if not loss.requires_grad:
        return th.zeros(sum(p.numel() for p in params), device=params[0].device)
    grads = th.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return th.cat([(th.zeros_like(p) if g is None else g).reshape(-1) for g, p in zip(grads, params)])


def actor_gradient_conflict(model: PEARL, losses: PEARLLosses) -> dict[str, float]:
    """
    Compare the two actor terms of one gradient step on the actor parameters.

    The graph of ``losses`` is kept (``retain_graph``), so the step's own backward pass can follow.

    :param model: the PEARL / PEARL+ model
    :param losses: the losses of the step (``model._compute_losses``)
    :return: ``ratio`` ``||prior_coef * g_prior|| / ||g_post||`` (0 for PEARL, nan if ``g_post`` is 0),
        ``cos`` the cosine of ``g_prior`` and ``g_post`` (nan if either is 0), and both norms
        ``prior_norm`` (weighted by ``prior_coef``) and ``post_norm``
    """
    params = [p for p in model.actor.parameters() if p.requires_grad]
    g_post = _flat_grad(losses.actor_loss, params)  # (P,)
    g_prior = _flat_grad(model.prior_coef * losses.prior_actor_loss, params)  # (P,)
    post_norm, prior_norm = float(g_post.norm()), float(g_prior.norm())
    ratio = prior_norm / post_norm if post_norm > 0 else math.nan
    cos = float(th.dot(g_prior, g_post)) / (prior_norm * post_norm) if prior_norm > 0 and post_norm > 0 else math.nan
    return {"ratio": ratio, "cos": cos, "prior_norm": prior_norm, "post_norm": post_norm}


def record_gradient_conflict(model: PEARL, losses: PEARLLosses, logs: dict[str, list[float]]) -> None:
    """
    Append ``grad_conflict_ratio`` and ``grad_conflict_cos`` of one step to the training logs (finite values only).

    :param model: the model being trained
    :param losses: the losses of the step
    :param logs: the ``train()`` log lists, keyed without the ``train/`` prefix
    """
    conflict = actor_gradient_conflict(model, losses)
    for key in ("ratio", "cos"):
        if math.isfinite(conflict[key]):
            logs.setdefault(f"grad_conflict_{key}", []).append(conflict[key])


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
        replay = buffer.rl.sample(tasks, model.batch_size, model.device, returns=model.prior_target == "mc")
        ctx = buffer.context.sample(tasks, model.embedding_batch_size, model.device)
        context = model.policy.make_context(ctx.observations, ctx.actions, ctx.rewards, ctx.next_observations)
        z0 = th.randn(len(tasks), model.latent_dim, device=model.device)  # one prior z per task
        per_batch.append(actor_gradient_conflict(model, model._compute_losses(replay, context, z0)))

    def mean_of(key: str) -> float:
        values = [entry[key] for entry in per_batch if math.isfinite(entry[key])]
        return float(np.mean(values)) if values else math.nan

    return {
        "prior_coef": model.prior_coef,
        "n_batches": n_batches,
        "ratio": mean_of("ratio"),
        "cos": mean_of("cos"),
        "prior_norm": mean_of("prior_norm"),
        "post_norm": mean_of("post_norm"),
        "ratio_per_batch": [entry["ratio"] for entry in per_batch],
        "cos_per_batch": [entry["cos"] for entry in per_batch],
    }
