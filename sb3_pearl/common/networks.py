"""Networks shared by the algorithms of the project: z-conditioned (or plain) actors and critics.

Every network takes one input ``x`` (for PEARL: the observation concatenated with z). Box actions
use a tanh-squashed Gaussian actor and critics on ``cat(x, a)``; Discrete actions use a categorical
actor and critics that output one Q value per action (soft discrete SAC). Output layers run in
float32 even when the hidden layers run under ``torch.autocast`` (``use_bf16``).
"""

from __future__ import annotations

import torch as th
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn
from torch.distributions import Normal
from torch.func import functional_call
from torch.nn import functional as F

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


class InplaceReLU(nn.ReLU):
    """ReLU that overwrites its input: the Linear output it follows is not needed by autograd (6-7% faster steps)."""

    def __init__(self) -> None:
        super().__init__(inplace=True)


def mlp_with_fp32_head(mlp: nn.Module, x: th.Tensor) -> th.Tensor:
    """
    Run an MLP whose hidden layers may run under autocast (``use_bf16``) while its output layer runs in
    float32: Q values, log-stds and posterior parameters keep full precision for the losses.
    """
    assert isinstance(mlp, nn.Sequential)
    *hidden, head = mlp
    for layer in hidden:
        x = layer(x)
    with th.autocast(device_type=x.device.type, enabled=False):
        return head(x.float())


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
            return self.mu(h), th.clamp(self.log_std(h), LOG_STD_MIN, LOG_STD_MAX)

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
        params = {name: p.detach() for name, p in self.named_parameters()}
        return functional_call(self, params, (x,))


__all__ = [
    "LOG_STD_MAX",
    "LOG_STD_MIN",
    "CategoricalActor",
    "InplaceReLU",
    "LatentCritic",
    "SquashedGaussianActor",
    "mlp_with_fp32_head",
]
