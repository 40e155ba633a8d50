"""The gradient conflict of PEARL+'s two actor terms (the prior term against the posterior term), logged by ``train()``.

:func:`gradient_conflict` compares one step's gradients on the actor parameters; :func:`record_gradient_conflict`
adds them to the step's logs (``train/grad_conflict_*``) when ``grad_conflict_log_freq`` asks for it. They are part of
the update's own logging, so they live beside the losses; :mod:`sb3_pearl.pearl.diagnostics` averages the same
measure over meta-batches of a trained model.
"""

from __future__ import annotations

import math

import torch as th

from sb3_pearl.common.type_aliases import PEARLLosses


def _flat_grad(loss: th.Tensor, params: list[th.nn.Parameter]) -> th.Tensor:
    """Gradient of ``loss`` w.r.t. ``params`` flattened to (P,); zeros if the loss does not depend on them."""
    if not loss.requires_grad:
        return th.zeros(sum(p.numel() for p in params), device=params[0].device)
    grads = th.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return th.cat([(th.zeros_like(p) if g is None else g).reshape(-1) for g, p in zip(grads, params)])


def gradient_conflict(actor: th.nn.Module, prior_coef: float, losses: PEARLLosses) -> dict[str, float]:
    """
    Compare the two actor terms of one gradient step on the actor parameters.

    The graph of ``losses`` is kept (``retain_graph``), so the step's own backward pass can follow.

    :param actor: the model's actor
    :param prior_coef: the weight of the prior term (0 for PEARL)
    :param losses: the losses of the step (``model._compute_losses``)
    :return: ``ratio`` ``||prior_coef * g_prior|| / ||g_post||`` (0 for PEARL, nan if ``g_post`` is 0),
        ``cos`` the cosine of ``g_prior`` and ``g_post`` (nan if either is 0), and both norms
        ``prior_norm`` (weighted by ``prior_coef``) and ``post_norm``
    """
    params = [p for p in actor.parameters() if p.requires_grad]
    g_post = _flat_grad(losses.actor_loss, params)  # (P,)
    g_prior = _flat_grad(prior_coef * losses.prior_actor_loss, params)  # (P,)
    post_norm, prior_norm = float(g_post.norm()), float(g_prior.norm())
    ratio = prior_norm / post_norm if post_norm > 0 else math.nan
    cos = float(th.dot(g_prior, g_post)) / (prior_norm * post_norm) if prior_norm > 0 and post_norm > 0 else math.nan
    return {"ratio": ratio, "cos": cos, "prior_norm": prior_norm, "post_norm": post_norm}


def record_gradient_conflict(
    actor: th.nn.Module, prior_coef: float, losses: PEARLLosses, logs: dict[str, list[float]]
) -> None:
    """
    Append ``grad_conflict_ratio`` and ``grad_conflict_cos`` of one step to the training logs (finite values only).

    :param actor: the actor of the model being trained
    :param prior_coef: the weight of the prior term (0 for PEARL)
    :param losses: the losses of the step
    :param logs: the ``train()`` log lists, keyed without the ``train/`` prefix
    """
    conflict = gradient_conflict(actor, prior_coef, losses)
    for key in ("ratio", "cos"):
        if math.isfinite(conflict[key]):
            logs.setdefault(f"grad_conflict_{key}", []).append(conflict[key])
