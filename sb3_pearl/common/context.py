"""Context inference for PEARL: product of Gaussians and the KL to the unit Gaussian prior.

Each context transition ``c_n`` gives a Gaussian factor ``N(mu_n, var_n)`` over the latent z; the
posterior ``q(z | c_1..N)`` is their normalised product (Rakelly et al. 2019, Section 4.1):

    var = 1 / sum_n (1 / var_n),    mu = var * sum_n (mu_n / var_n).
"""

from __future__ import annotations

import torch as th

MIN_VAR = 1e-7


def product_of_gaussians(mu: th.Tensor, var: th.Tensor, mask: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
    """
    Combine per-transition Gaussian factors into one Gaussian per task.

    :param mu: factor means, shape ``(T, N, L)``
    :param var: factor variances (> 0), shape ``(T, N, L)``; clamped to at least ``1e-7``
    :param mask: optional ``(T, N)`` weights in {0, 1}; a 0 drops the transition. A task with no
        transition left gets the prior N(0, I).
    :return: posterior means and variances, each of shape ``(T, L)``
    """
    if mu.shape != var.shape or mu.dim() != 3:
        raise ValueError(f"mu and var must both have shape (T, N, L), got {tuple(mu.shape)} and {tuple(var.shape)}")
    precision = 1.0 / th.clamp(var, min=MIN_VAR)  # (T, N, L)
    if mask is not None:
        if mask.shape != mu.shape[:2]:
            raise ValueError(f"mask must have shape (T, N) = {tuple(mu.shape[:2])}, got {tuple(mask.shape)}")
        precision = precision * mask.unsqueeze(-1)
    # The unit prior enters only when a task has no data at all (all precisions masked to 0).
    empty = precision.sum(dim=1) == 0  # (T, L)
    total_precision = precision.sum(dim=1) + empty.to(precision.dtype)  # (T, L)
    post_var = 1.0 / total_precision
    post_mu = post_var * (precision * mu).sum(dim=1)  # (T, L)
    return post_mu, post_var


def kl_to_standard_normal(mu: th.Tensor, var: th.Tensor) -> th.Tensor:
    """
    KL(N(mu, diag(var)) || N(0, I)) per row, summed over the latent dimensions.

    :param mu: means, shape ``(..., L)``
    :param var: variances, shape ``(..., L)``
    :return: shape ``(...)``
    """
    var = th.clamp(var, min=MIN_VAR)
    return 0.5 * (var + mu.pow(2) - 1.0 - th.log(var)).sum(dim=-1)
