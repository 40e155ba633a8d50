"""Pure TRPO math used by MAML's outer loop.

Fisher-vector products of the mean KL (:func:`fisher_vector_product`), the conjugate-gradient solver
for the step direction (:func:`conjugate_gradient`) and the backtracking line search that accepts a
step only when the surrogate improves within the KL bound (:func:`line_search`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch as th
from torch.nn.utils import parameters_to_vector

from sb3_pearl.maml.type_aliases import TRPOInfo


def fisher_vector_product(grad_kl: th.Tensor, parameters: list[th.Tensor], vector: th.Tensor, damping: float) -> th.Tensor:
    """
    Damped Fisher-vector product ``(F + damping I) v``, as the Hessian-vector product of the mean KL.

    :param grad_kl: flat gradient of the mean KL w.r.t. ``parameters``, computed with ``create_graph=True``
    :param parameters: the parameters the KL was differentiated against
    :param vector: ``v``, shape ``(P,)``
    :param damping: coefficient of the identity added to ``F``
    :return: ``F v + damping * v``, shape ``(P,)``, detached
    """
    hvp = th.autograd.grad(grad_kl @ vector, parameters, retain_graph=True)
    return parameters_to_vector(hvp).detach() + damping * vector


def conjugate_gradient(
    fvp: Callable[[th.Tensor], th.Tensor], b: th.Tensor, n_iters: int = 10, residual_tol: float = 1e-10
) -> th.Tensor:
    """
    Solve ``F x = b`` for a symmetric positive definite ``F`` given only as a product ``fvp(v) = F v``.

    :param fvp: function returning ``F v``
    :param b: right-hand side, shape ``(P,)``
    :param n_iters: maximum number of iterations
    :param residual_tol: stop when the squared residual norm falls below this
    :return: the approximate solution, shape ``(P,)``
    """
    x = th.zeros_like(b)
    r = b.clone()
    p = b.clone()
    r_dot = r @ r
    for _ in range(n_iters):
        fp = fvp(p)
        alpha = r_dot / (p @ fp + 1e-12)
        x = x + alpha * p
        r = r - alpha * fp
        new_r_dot = r @ r
        if new_r_dot < residual_tol:
            break
        p = r + (new_r_dot / r_dot) * p
        r_dot = new_r_dot
    return x


def write_vector(vector: th.Tensor, parameters: list[th.Tensor]) -> None:
    """
    Copy a flat vector into the parameters, in place.

    Unlike ``torch.nn.utils.vector_to_parameters`` (which makes each parameter a view into ``vector``), every
    parameter keeps its own storage: matrix products then do not depend on where a view happens to start in
    memory, so a model saved and loaded computes bit for bit what the original does (exact resume).

    :param vector: flat values, shape ``(P,)``
    :param parameters: the parameters, ``P`` elements in all
    """
    offset = 0
    with th.no_grad():
        for param in parameters:
            n = param.numel()
            param.copy_(vector[offset : offset + n].view_as(param))
            offset += n


def line_search(
    evaluate: Callable[[], tuple[th.Tensor, th.Tensor]],
    parameters: list[th.Tensor],
    direction: th.Tensor,
    shs: float,
    surrogate_before: float,
    max_kl: float,
    backtrack_ratio: float,
    max_steps: int,
) -> TRPOInfo:
    """
    Backtracking line search along the step ``sqrt(2 max_kl / shs) * direction`` scaled to the KL bound.

    Candidates ``theta_old + backtrack_ratio**k * full_step`` (``k = 0 .. max_steps - 1``) are written into
    ``parameters`` in place; the first one whose surrogate exceeds ``surrogate_before`` with a KL at most
    ``max_kl`` is kept. If none is, ``parameters`` are restored to ``theta_old``.

    :param evaluate: returns the surrogate and the mean KL at the current ``parameters`` (run with grad enabled)
    :param parameters: the parameters to update in place
    :param direction: the conjugate-gradient direction, shape ``(P,)``
    :param shs: ``direction @ F direction`` (finite and positive)
    :param surrogate_before: the surrogate at ``theta_old``
    :param max_kl: KL bound
    :param backtrack_ratio: shrink factor between candidates
    :param max_steps: maximum number of candidates
    :return: surrogate before/after, KL, step size, backtracks, acceptance
    """
    theta_old = parameters_to_vector(parameters).detach()
    full_step = np.sqrt(2.0 * max_kl / shs) * direction
    for n_backtracks in range(max_steps):
        fraction = backtrack_ratio**n_backtracks
        candidate = theta_old + fraction * full_step
        write_vector(candidate, parameters)
        with th.enable_grad():
            new_surrogate, new_kl = evaluate()
        new_surrogate, new_kl = new_surrogate.detach(), new_kl.detach()
        if float(new_surrogate) > surrogate_before and float(new_kl) <= max_kl:
            return TRPOInfo(
                surrogate_before,
                float(new_surrogate),
                float(new_kl),
                float(fraction * np.sqrt(2.0 * max_kl / shs)),
                n_backtracks,
                True,
            )
    write_vector(theta_old, parameters)
    return TRPOInfo(surrogate_before, surrogate_before, 0.0, 0.0, max_steps, False)
