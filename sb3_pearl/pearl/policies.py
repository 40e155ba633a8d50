"""Networks of PEARL and PEARL+: context encoder, z-conditioned actor, twin critics, prior critic.

Every network takes the latent task variable z concatenated to the observation. Box actions use a
tanh-squashed Gaussian actor and critics Q(s, z, a) -> R; Discrete actions use a categorical actor
and critics Q(s, z) -> R^|A| (soft discrete SAC, exact expectations over actions).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.nn import functional as F

from sb3_pearl.common.checks import check_int
from sb3_pearl.common.context import product_of_gaussians
from sb3_pearl.common.networks import (
    CategoricalActor,
    InplaceReLU,
    LatentCritic,
    SquashedGaussianActor,
    fast_optimizer_kwargs,
    mlp_with_fp32_head,
    use_fused_optimizer,
)

PRIOR_CRITIC_MODES = ("separate", "shared", "none")
PRIOR_CRITIC_INPUTS = ("state_z0", "state")


def check_latent_dim(latent_dim: int) -> None:
    """
    Raise a ValueError unless ``latent_dim`` (the size of z) is an integer >= 1: the policy's check, which
    :func:`~sb3_pearl.pearl.arguments.check_pearl_arguments` runs before anything is built.

    :param latent_dim: size of z
    """
    check_int("latent_dim", latent_dim, 1, "size of z")


def check_prior_critic(prior_critic: str, prior_critic_input: str, modes: tuple[str, ...] = PRIOR_CRITIC_MODES) -> None:
    """
    Raise a ValueError for an unknown prior-critic mode or input: the policy's check, which PEARL+'s argument checks run
    before anything is built, with its own modes (a PEARL+ model has a prior term: not ``"none"``).

    :param prior_critic: the prior-critic mode
    :param prior_critic_input: ``"state_z0"`` or ``"state"``
    :param modes: the modes allowed
    """
    if prior_critic not in modes:
        raise ValueError(f"unknown prior_critic mode {prior_critic!r}: expected one of {modes}")
    if prior_critic_input not in PRIOR_CRITIC_INPUTS:
        raise ValueError(
            f"unknown prior_critic_input {prior_critic_input!r}: expected one of {PRIOR_CRITIC_INPUTS} "
            "(the paper's Q~(s, a, z0), or a z-free Q~(s, a))"
        )


class ContextEncoder(nn.Module):
    """
    q(z | c): one Gaussian factor per context transition, combined by product of Gaussians.

    :param context_dim: size of one context transition (s, a, r[, s'])
    :param latent_dim: size of z
    :param net_arch: hidden layer sizes
    :param activation_fn: activation between hidden layers
    """

    def __init__(self, context_dim: int, latent_dim: int, net_arch: list[int], activation_fn: type[nn.Module] = nn.ReLU):
        super().__init__()
        self.latent_dim = latent_dim
        self.net = nn.Sequential(*create_mlp(context_dim, 2 * latent_dim, net_arch, activation_fn))

    def forward(self, context: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Per-transition factors: ``context`` (T, N, D) -> means and variances, each (T, N, L)."""
        out = mlp_with_fp32_head(self.net, context)
        mu, pre_var = out[..., : self.latent_dim], out[..., self.latent_dim :]
        return mu, F.softplus(pre_var)

    def posterior(self, context: th.Tensor, mask: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        """q(z | c) per task: ``context`` (T, N, D) -> means and variances, each (T, L)."""
        mu, var = self(context)
        return product_of_gaussians(mu, var, mask=mask)


class PEARLPolicy(BasePolicy):
    """
    Policy holding every network of PEARL / PEARL+ and their optimizers.

    ``predict`` acts with :attr:`current_z` (set by the algorithm's adaptation API): SB3's
    ``predict`` never sees rewards, so task inference happens outside it.

    :param observation_space: flat Box observation space
    :param action_space: Box or Discrete
    :param lr_schedule: learning rate schedule (all optimizers)
    :param net_arch: hidden sizes of the actor and the critics (reference: [300, 300, 300])
    :param activation_fn: activation function
    :param latent_dim: size of z (reference: 5)
    :param encoder_arch: hidden sizes of the context encoder (reference: [200, 200, 200])
    :param use_next_obs_in_context: context transitions are (s, a, r, s') instead of (s, a, r)
    :param prior_critic: ``"none"`` (PEARL, the default), ``"separate"`` (PEARL+: extra critic Q~(s, a, z0)) or
        ``"shared"`` (ablation PEARL+ (w/o): the prior term uses Q(s, a, z0)); PEARLPlus sets it
    :param prior_critic_arch: hidden sizes of the prior critic (paper: [300]*3, ablation [100]*3)
    :param n_critics: number of Q networks of the critic (twin Q: 2)
    :param prior_n_critics: number of Q networks of the prior critic; the paper adds "a new Q-network"
        Q~ (one network, Section IV), which is the default; 2 gives it a twin-Q minimum as well, more a
        pessimistic ensemble (the minimum over all of them, in its target and in the actor's prior term)
    :param prior_critic_input: ``"state_z0"`` (the paper: Q~(s, a, z0)) or ``"state"`` (a z-free prior critic
        Q~(s, a): z0 ~ N(0, I) carries no task information, so it is an input the critic can only overfit)
    :param optimizer_class: optimizer
    :param optimizer_kwargs: extra optimizer arguments
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        latent_dim: int = 5,
        encoder_arch: list[int] | None = None,
        use_next_obs_in_context: bool = False,
        prior_critic: str = "none",
        prior_critic_arch: list[int] | None = None,
        n_critics: int = 2,
        prior_n_critics: int = 1,
        prior_critic_input: str = "state_z0",
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ):
        if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) != 1:
            raise ValueError(f"PEARL needs a flat Box observation space of shape (obs_dim,), got {observation_space}")
        if not isinstance(action_space, (spaces.Box, spaces.Discrete)):
            raise ValueError(f"PEARL supports Box and Discrete action spaces, got {type(action_space).__name__}")
        check_prior_critic(prior_critic, prior_critic_input)
        check_latent_dim(latent_dim)
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=isinstance(action_space, spaces.Box),
        )
        self.net_arch = list(net_arch) if net_arch is not None else [300, 300, 300]
        self.activation_fn = activation_fn
        # nn.ReLU is built in-place (same values, less memory traffic); other activations as given
        self.layer_activation: type[nn.Module] = InplaceReLU if activation_fn is nn.ReLU else activation_fn
        self.latent_dim = latent_dim
        self.encoder_arch = list(encoder_arch) if encoder_arch is not None else [200, 200, 200]
        self.use_next_obs_in_context = use_next_obs_in_context
        self.prior_critic_mode = prior_critic
        self.prior_critic_arch = list(prior_critic_arch) if prior_critic_arch is not None else [300, 300, 300]
        self.n_critics = n_critics
        self.prior_n_critics = prior_n_critics
        self.prior_critic_input = prior_critic_input
        self.discrete = isinstance(action_space, spaces.Discrete)
        self.obs_dim = int(observation_space.shape[0])
        self.action_dim = (
            int(action_space.n) if isinstance(action_space, spaces.Discrete) else int(np.prod(action_space.shape))
        )
        # z used by predict(); set by the adaptation API, never saved (it is not a parameter or buffer).
        self.current_z = th.zeros(latent_dim)
        self._build(lr_schedule)

    @property
    def context_dim(self) -> int:
        """Size of one context transition: s, a (one-hot if Discrete), r[, s']."""
        return self.obs_dim * (2 if self.use_next_obs_in_context else 1) + self.action_dim + 1

    def _make_critic(self, net_arch: list[int], n_critics: int, with_latent: bool = True) -> LatentCritic:
        obs_z = self.obs_dim + (self.latent_dim if with_latent else 0)
        if self.discrete:
            return LatentCritic(obs_z, self.action_dim, net_arch, n_critics, self.layer_activation)
        return LatentCritic(obs_z + self.action_dim, 1, net_arch, n_critics, self.layer_activation)

    def _build(self, lr_schedule: Schedule) -> None:
        obs_z = self.obs_dim + self.latent_dim
        self.encoder = ContextEncoder(self.context_dim, self.latent_dim, self.encoder_arch, self.layer_activation)
        self.actor: SquashedGaussianActor | CategoricalActor
        if self.discrete:
            self.actor = CategoricalActor(obs_z, self.action_dim, self.net_arch, self.layer_activation)
        else:
            self.actor = SquashedGaussianActor(obs_z, self.action_dim, self.net_arch, self.layer_activation)
        self.critic = self._make_critic(self.net_arch, self.n_critics)
        self.critic_target = self._make_critic(self.net_arch, self.n_critics)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic_target.requires_grad_(False)
        self.prior_critic: LatentCritic | None = None
        self.prior_critic_target: LatentCritic | None = None
        if self.prior_critic_mode == "separate":
            with_z0 = self.prior_critic_input == "state_z0"
            self.prior_critic = self._make_critic(self.prior_critic_arch, self.prior_n_critics, with_z0)
            self.prior_critic_target = self._make_critic(self.prior_critic_arch, self.prior_n_critics, with_z0)
            self.prior_critic_target.load_state_dict(self.prior_critic.state_dict())
            self.prior_critic_target.requires_grad_(False)

        # Adam in torch's fused form unless the user chose (the same update in one kernel; its speed: docs/speed.md)
        kwargs = fast_optimizer_kwargs(self.optimizer_class, self.optimizer_kwargs, self.device)
        self.fused_optimizers: bool | None = kwargs.get("fused")  # restored after loading saved optimizer states

        def make_optimizer(module: nn.Module) -> th.optim.Optimizer:
            return self.optimizer_class(module.parameters(), lr=lr_schedule(1), **kwargs)  # type: ignore[call-arg]

        self.encoder.optimizer = make_optimizer(self.encoder)  # type: ignore[assignment]
        self.actor.optimizer = make_optimizer(self.actor)  # type: ignore[assignment]
        self.critic.optimizer = make_optimizer(self.critic)  # type: ignore[assignment]
        if self.prior_critic is not None:
            self.prior_critic.optimizer = make_optimizer(self.prior_critic)  # type: ignore[assignment]
        self.set_training_mode(False)

    def optimizers(self) -> list[th.optim.Optimizer]:
        """The network optimizers (not the entropy coefficient's), for learning-rate updates."""
        modules: list[nn.Module] = [self.encoder, self.actor, self.critic]
        if self.prior_critic is not None:
            modules.append(self.prior_critic)
        return [m.optimizer for m in modules]  # type: ignore[misc]

    def restore_fused_optimizers(self) -> None:
        """Give the optimizers back the ``fused`` flag they were built with (``load_state_dict`` sets the saved one)."""
        for optimizer in self.optimizers():
            use_fused_optimizer(optimizer, self.fused_optimizers)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            latent_dim=self.latent_dim,
            encoder_arch=self.encoder_arch,
            use_next_obs_in_context=self.use_next_obs_in_context,
            prior_critic=self.prior_critic_mode,
            prior_critic_arch=self.prior_critic_arch,
            n_critics=self.n_critics,
            prior_n_critics=self.prior_n_critics,
            prior_critic_input=self.prior_critic_input,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data

    # -- context -----------------------------------------------------------------------------
    def actions_for_networks(self, actions: th.Tensor) -> th.Tensor:
        """Stored actions -> network input: scaled Box vectors as they are, Discrete indices one-hot."""
        if self.discrete:
            return F.one_hot(actions[..., 0].long(), self.action_dim).to(th.float32)
        return actions

    def make_context(
        self, observations: th.Tensor, actions: th.Tensor, rewards: th.Tensor, next_observations: th.Tensor
    ) -> th.Tensor:
        """Context transitions from stored tensors of leading shape (T, N): -> (T, N, context_dim)."""
        parts = [observations, self.actions_for_networks(actions), rewards]
        if self.use_next_obs_in_context:
            parts.append(next_observations)
        return th.cat(parts, dim=-1)

    def prior_critic_features(self, observations: th.Tensor, z0: th.Tensor) -> th.Tensor:
        """The prior critic's input (without the action) for observations (N, obs_dim) and latents z0 (N, L)."""
        if self.prior_critic_input == "state":
            return observations
        return th.cat([observations, z0], dim=-1)

    # -- acting ------------------------------------------------------------------------------
    def act(self, observations: th.Tensor, z: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """Actions for observations (N, obs_dim) under latents z (N, L) or (L,): scaled Box actions or indices."""
        if z.dim() == 1:
            z = z.expand(observations.shape[0], -1)
        return self.actor(th.cat([observations, z], dim=-1), deterministic=deterministic)

    def act_with_log_prob(self, observations: th.Tensor, z: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        Sampled actions as :meth:`act` draws them (the same random draws) and their log-probabilities (N,), computed
        from the draw itself: exact for a saturated Box action, whose tanh cannot be inverted.
        """
        if z.dim() == 1:
            z = z.expand(observations.shape[0], -1)
        return self.actor.action_log_prob(th.cat([observations, z], dim=-1))

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        assert isinstance(observation, th.Tensor)
        return self.act(observation.float(), self.current_z.to(observation.device), deterministic)

    def set_training_mode(self, mode: bool) -> None:
        for module in (self.encoder, self.actor, self.critic, self.prior_critic):
            if module is not None:
                module.train(mode)
        self.training = mode


MlpPolicy = PEARLPolicy
