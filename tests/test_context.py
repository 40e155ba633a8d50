"""Product of Gaussians and KL against closed-form numbers."""

from __future__ import annotations

import math

import pytest
import torch as th

from sb3_pearl.common.context import kl_to_standard_normal, product_of_gaussians


def test_product_of_two_gaussians_closed_form() -> None:
    # N(1, 1) * N(3, 3): precision 1 + 1/3 = 4/3 -> var 0.75; mean 0.75 * (1/1 + 3/3) = 1.5
    mu = th.tensor([[[1.0], [3.0]]])  # (T=1, N=2, L=1)
    var = th.tensor([[[1.0], [3.0]]])
    post_mu, post_var = product_of_gaussians(mu, var)
    assert post_mu.shape == (1, 1)
    assert post_var.item() == pytest.approx(0.75)
    assert post_mu.item() == pytest.approx(1.5)


def test_product_is_per_task_and_per_dimension() -> None:
    mu = th.tensor([[[0.0, 2.0], [4.0, 2.0]], [[1.0, -1.0], [1.0, -1.0]]])  # (T=2, N=2, L=2)
    var = th.tensor([[[1.0, 2.0], [1.0, 2.0]], [[4.0, 0.5], [4.0, 0.5]]])
    post_mu, post_var = product_of_gaussians(mu, var)
    assert th.allclose(post_var, th.tensor([[0.5, 1.0], [2.0, 0.25]]))
    assert th.allclose(post_mu, th.tensor([[2.0, 2.0], [1.0, -1.0]]))


def test_mask_drops_transitions_and_empty_task_is_prior() -> None:
    mu = th.tensor([[[1.0], [3.0]], [[5.0], [7.0]]])
    var = th.tensor([[[1.0], [3.0]], [[2.0], [2.0]]])
    mask = th.tensor([[1.0, 0.0], [0.0, 0.0]])
    post_mu, post_var = product_of_gaussians(mu, var, mask)
    assert post_mu[0].item() == pytest.approx(1.0) and post_var[0].item() == pytest.approx(1.0)
    assert post_mu[1].item() == pytest.approx(0.0) and post_var[1].item() == pytest.approx(1.0)


def test_variance_is_clamped() -> None:
    post_mu, post_var = product_of_gaussians(th.zeros(1, 1, 1), th.zeros(1, 1, 1))
    assert post_var.item() == pytest.approx(1e-7)


def test_kl_closed_form() -> None:
    # KL(N(1.5, 0.75) || N(0, 1)) = 0.5 * (0.75 + 1.5^2 - 1 - ln 0.75)
    kl = kl_to_standard_normal(th.tensor([[1.5]]), th.tensor([[0.75]]))
    assert kl.item() == pytest.approx(0.5 * (0.75 + 2.25 - 1.0 - math.log(0.75)))
    # summed over latent dimensions; zero at the prior
    assert kl_to_standard_normal(th.zeros(3, 4), th.ones(3, 4)).tolist() == [0.0, 0.0, 0.0]
    two = kl_to_standard_normal(th.tensor([[1.5, 1.5]]), th.tensor([[0.75, 0.75]]))
    assert two.item() == pytest.approx(2 * kl.item())


def test_shape_errors_are_explicit() -> None:
    with pytest.raises(ValueError, match=r"\(T, N, L\)"):
        product_of_gaussians(th.zeros(2, 3), th.zeros(2, 3))
    with pytest.raises(ValueError, match="mask"):
        product_of_gaussians(th.zeros(1, 2, 3), th.ones(1, 2, 3), th.ones(2, 2))
