"""Networks shared by the algorithms of the project: z-conditioned (or plain) actors and critics.

Every network takes one input ``x`` (for PEARL: the observation concatenated with z). Box actions
use a tanh-squashed Gaussian actor and critics on ``cat(x, a)``; Discrete actions use a categorical
actor and critics that output one Q value per action (soft discrete SAC). Output layers run in
float32 even when the hidden layers run under ``torch.autocast`` (``use_bf16``).
"""

from __future__ import annotations

from typing import Any

import torch as th
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn
from torch.distributions import Normal
from torch.func import functional_call
from torch.nn import functional as F
from torch.optim import Adam

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


class InplaceReLU(nn.ReLU):
    """ReLU that overwrites its input: the Linear output it follows is not needed by autograd (its speed: docs/speed.md)."""

    def __init__(self) -> None:
        super().__init__(inplace=True)


def frozen_layer(layer: nn.Module, x: th.Tensor) -> th.Tensor:
    """
    ``layer(x)`` with the layer's parameters detached: gradients reach ``x`` only.

    A ``Linear`` runs as one ``F.linear`` on detached views of its weight and bias (what ``layer(x)`` computes, without
    ``torch.func.functional_call``'s per-call cost of swapping every parameter of the module); a layer without
    parameters (an activation) runs as it is; any other layer through ``functional_call``.
    """
    if isinstance(layer, nn.Linear):
        return F.linear(x, layer.weight.detach(), None if layer.bias is None else layer.bias.detach())
    params = {name: p.detach() for name, p in layer.named_parameters()}
    return functional_call(layer, params, (x,)) if params else layer(x)


def mlp_with_fp32_head(mlp: nn.Module, x: th.Tensor, frozen: bool = False) -> th.Tensor:
    """
    Run an MLP whose hidden layers may run under autocast (``use_bf16``) while its output layer runs in
    float32: Q values, log-stds and posterior parameters keep full precision for the losses.

    :param mlp: an ``nn.Sequential``
    :param x: its input
    :param frozen: run it on detached parameters (:func:`frozen_layer`): gradients reach ``x`` only
    """
    assert isinstance(mlp, nn.Sequential)
    *hidden, head = mlp
    for layer in hidden:
        x = frozen_layer(layer, x) if frozen else layer(x)
    with th.autocast(device_type=x.device.type, enabled=False):
        x = x.float()
        return frozen_layer(head, x) if frozen else head(x)


def fast_optimizer_kwargs(
    optimizer_class: type[th.optim.Optimizer], optimizer_kwargs: dict[str, Any], device: th.device
) -> dict[str, Any]:
    """
    The optimizer arguments with torch's fused implementation switched on where it is the same algorithm and faster.

    ``torch.optim.Adam`` runs its single-tensor loop on a CPU unless told otherwise; ``fused=True`` (one kernel for
    all parameters, CPU and CUDA) runs the same update up to float rounding in fewer kernels (its speed: docs/speed.md,
    "What changed in the step"). Arguments the user gave (``fused``, ``foreach``) are kept as they are.

    :param optimizer_class: the optimizer class
    :param optimizer_kwargs: the user's arguments (not modified)
    :param device: the device of the parameters
    :return: the arguments to build the optimizer with
    """
    kwargs = dict(optimizer_kwargs)
    if optimizer_class is Adam and device.type in ("cpu", "cuda") and not {"fused", "foreach"} & kwargs.keys():
        kwargs["fused"] = True
    return kwargs


def use_fused_optimizer(optimizer: th.optim.Optimizer, fused: bool | None) -> None:
    """
    Set ``fused`` in every parameter group of ``optimizer`` (after ``load_state_dict``, which restores the saved groups'
    flags: a model saved before :func:`fast_optimizer_kwargs` existed would otherwise step in the slow loop).

    :param optimizer: the optimizer
    :param fused: the flag it was built with (``None``: leave the groups as they are)
    """
    if fused is None:
        return
    for group in optimizer.param_groups:
        group["fused"] = fused
        if fused:  # the fused kernels take the step counts as float32 tensors on the parameters' device
            for param in group["params"]:
                state = optimizer.state.get(param, {})
                if "step" in state:
                    state["step"] = th.as_tensor(state["step"], dtype=th.float32, device=param.device)


class UncheckedSquashedDiagGaussian(SquashedDiagGaussianDistribution):
    """
    SB3's tanh-squashed diagonal Gaussian without torch's argument validation (the same numbers).

    torch checks every Normal's parameters and samples (one device sync each) and raises a cryptic
    "Expected parameter loc ... invalid values" once weights diverge; here non-finite values flow
    into the losses, where PEARL's divergence guard (``PEARL.train``) skips the update and names the
    cause.
    """

    def proba_distribution(  # type: ignore[override]
        self, mean_actions: th.Tensor, log_std: th.Tensor
    ) -> UncheckedSquashedDiagGaussian:
        self.distribution = Normal(mean_actions, th.ones_like(mean_actions) * log_std.exp(), validate_args=False)
        return self


class SquashedGaussianActor(nn.Module):
    """
    pi(a | s, z) for Box actions: tanh-squashed diagonal Gaussian, log std clamped to [-20, 2].

    :param input_dim: obs_dim + latent_dim
    :param action_dim: action size
    :param net_arch: hidden layer sizes
    :param activation_fn: activation between hidden layers
    """

    def __init__(self, input_dim: int, action_dim: int, net_arch: list[int], activation_fn: type[nn.Module] = nn.ReLU):
        super().__init__()
        self.latent_pi = nn.Sequential(*create_mlp(input_dim, -1, net_arch, activation_fn))
        last = net_arch[-1] if net_arch else input_dim
        self.mu = nn.Linear(last, action_dim)
        self.log_std = nn.Linear(last, action_dim)
        self.action_dist = UncheckedSquashedDiagGaussian(action_dim)

    def _params(self, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        h = self.latent_pi(x)
        with th.autocast(device_type=h.device.type, enabled=False):
            h = h.float()
            # Both heads in one matrix product (each output is the same dot product as ``self.mu(h)`` /
            # ``self.log_std(h)``; one kernel instead of two, forward and backward)
            weight = th.cat([self.mu.weight, self.log_std.weight])
            bias = th.cat([self.mu.bias, self.log_std.bias])
            mean, log_std = F.linear(h, weight, bias).split(self.mu.out_features, dim=-1)
            return mean, th.clamp(log_std, LOG_STD_MIN, LOG_STD_MAX)

    def action_log_prob(self, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Reparameterised actions in [-1, 1] (N, A) and their log-probabilities (N,)."""
        mean, log_std = self._params(x)
        return self.action_dist.log_prob_from_params(mean, log_std)

    def forward(self, x: th.Tensor, deterministic: bool = False) -> th.Tensor:
        mean, log_std = self._params(x)
        return self.action_dist.actions_from_params(mean, log_std, deterministic=deterministic)


class CategoricalActor(nn.Module):
    """
    pi(a | s, z) for Discrete actions.

    :param input_dim: obs_dim + latent_dim
    :param n_actions: number of actions
    :param net_arch: hidden layer sizes
    :param activation_fn: activation between hidden layers
    """

    def __init__(self, input_dim: int, n_actions: int, net_arch: list[int], activation_fn: type[nn.Module] = nn.ReLU):
        super().__init__()
        self.logits = nn.Sequential(*create_mlp(input_dim, n_actions, net_arch, activation_fn))

    def probs(self, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Action probabilities and log-probabilities, each (N, n_actions)."""
        log_probs = F.log_softmax(mlp_with_fp32_head(self.logits, x), dim=-1)
        return log_probs.exp(), log_probs

    def action_log_prob(self, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Sampled action indices (N,) and their log-probabilities (N,), from the same draws as ``forward``."""
        distribution = th.distributions.Categorical(logits=mlp_with_fp32_head(self.logits, x), validate_args=False)
        actions = distribution.sample()
        return actions, distribution.log_prob(actions)

    def forward(self, x: th.Tensor, deterministic: bool = False) -> th.Tensor:
        logits = mlp_with_fp32_head(self.logits, x)
        if deterministic:
            return logits.argmax(dim=-1)
        return th.distributions.Categorical(logits=logits, validate_args=False).sample()


class LatentCritic(nn.Module):
    """
    ``n_critics`` independent Q networks (independent initialisations) on the same input.

    Box: input (s, z, a), output 1. Discrete: input (s, z), output one value per action.

    :param input_dim: input size
    :param output_dim: 1 (Box) or the number of actions (Discrete)
    :param net_arch: hidden layer sizes
    :param n_critics: number of Q networks
    :param activation_fn: activation between hidden layers
    """

    def __init__(
        self,
        input_dim: int,
        output_dim: int,
        net_arch: list[int],
        n_critics: int = 2,
        activation_fn: type[nn.Module] = nn.ReLU,
    ):
        super().__init__()
        self.q_networks = nn.ModuleList(
            nn.Sequential(*create_mlp(input_dim, output_dim, net_arch, activation_fn)) for _ in range(n_critics)
        )

    def forward(self, x: th.Tensor) -> th.Tensor:
        """Q values of every network, shape ``(n_critics, N, output_dim)``."""
        return th.stack([mlp_with_fp32_head(q, x) for q in self.q_networks])

    def forward_frozen(self, x: th.Tensor) -> th.Tensor:
        """Like :meth:`forward` but with detached parameters: gradients reach ``x`` only (actor losses)."""
        return th.stack([mlp_with_fp32_head(q, x, frozen=True) for q in self.q_networks])


def polyak_update_foreach(params: list[th.Tensor], target_params: list[th.Tensor], tau: float) -> None:
    """
    SB3's ``polyak_update`` (``target = (1 - tau) * target + tau * param``, the same two roundings) in two foreach
    kernels instead of two per tensor.

    :param params: the parameters
    :param target_params: their target copies, in the same order
    :param tau: the Polyak coefficient
    """
    if len(params) != len(target_params):
        raise ValueError(f"{len(params)} parameters but {len(target_params)} target parameters")
    with th.no_grad():
        targets = [p.data for p in target_params]
        th._foreach_mul_(targets, 1 - tau)
        th._foreach_add_(targets, [p.data for p in params], alpha=tau)


__all__ = [
    "LOG_STD_MAX",
    "LOG_STD_MIN",
    "CategoricalActor",
    "InplaceReLU",
    "LatentCritic",
    "SquashedGaussianActor",
    "fast_optimizer_kwargs",
    "frozen_layer",
    "mlp_with_fp32_head",
    "polyak_update_foreach",
    "use_fused_optimizer",
]
