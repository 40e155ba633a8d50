"""Policies for MAML: a stochastic MLP whose parameters can be swapped for adapted ones.

MAML evaluates the same network under many parameter sets (the meta-learned ``theta`` and one
adapted ``theta'_i`` per task). The policy is therefore written so that every computation takes an
optional ``params`` dict (name -> tensor, as in :meth:`torch.nn.Module.named_parameters`) and runs
through :func:`torch.func.functional_call`; with ``params=None`` the module's own parameters are used.

Box actions: a diagonal Gaussian with a state-independent log-std, in *normalised* units (the action
box is mapped to [-1, 1]); the sample is clipped to [-1, 1] and rescaled to the env's box only when it
is sent to the env, while log-probabilities use the unclipped sample (as SB3's PPO does).
Discrete actions: a categorical distribution over logits.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn
from torch.distributions import Categorical, Distribution, Independent, Normal, kl_divergence
from torch.func import functional_call, vmap

Params = dict[str, th.Tensor]


class MAMLPolicy(BasePolicy):
    """
    Stochastic MLP policy for MAML (Gaussian for Box actions, categorical for Discrete).

    :param observation_space: observation space (a Box; it is flattened)
    :param action_space: Box or Discrete action space
    :param lr_schedule: unused (SB3 signature compatibility; MAML has no optimizer)
    :param net_arch: hidden layer sizes; ``[]`` gives a linear policy. Default ``[64, 64]``.
    :param activation_fn: activation between hidden layers. Default ``nn.Tanh``.
    :param log_std_init: initial value of the state-independent log standard deviation (Box only)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Any = None,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.Tanh,
        log_std_init: float = 0.0,
    ) -> None:
        if not isinstance(observation_space, spaces.Box):
            raise ValueError(f"MAML supports Box observation spaces only, got {observation_space}")
        if not isinstance(action_space, (spaces.Box, spaces.Discrete)):
            raise ValueError(
                f"MAML supports Box (Gaussian policy) and Discrete (categorical policy) action spaces, got {action_space}"
            )
        if isinstance(action_space, spaces.Box) and len(action_space.shape) != 1:
            raise ValueError(f"MAML needs a 1-D Box action space, got shape {action_space.shape}")
        super().__init__(observation_space, action_space, squash_output=isinstance(action_space, spaces.Box))
        self.net_arch = [64, 64] if net_arch is None else list(net_arch)
        self.activation_fn = activation_fn
        self.log_std_init = log_std_init
        self.obs_dim = int(th.tensor(observation_space.shape).prod().item())
        self.continuous = isinstance(action_space, spaces.Box)
        self.action_dim = int(action_space.shape[0]) if isinstance(action_space, spaces.Box) else int(action_space.n)

        self.mlp = nn.Sequential(*create_mlp(self.obs_dim, self.action_dim, self.net_arch, activation_fn))
        for module in self.mlp:
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)
        if self.continuous:
            self.log_std = nn.Parameter(th.full((self.action_dim,), float(log_std_init)))
        # Parameters used by ``_predict`` (set by MAML.adapt(); None: the module's own parameters).
        # Not an nn.Parameter, so never part of the state dict.
        self.adapted_params: Params | None = None
        # Unclipped actions of the last ``_predict`` call (normalised units), so that MAML.observe()
        # can recover the sample behind a clipped env action.
        self.last_raw_actions: th.Tensor | None = None

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(net_arch=self.net_arch, activation_fn=self.activation_fn, log_std_init=self.log_std_init)
        data.pop("normalize_images", None)
        data.pop("features_extractor_class", None)
        data.pop("features_extractor_kwargs", None)
        data.pop("squash_output", None)
        return data

    def meta_parameters(self) -> Params:
        """The meta-learned parameters as a name -> parameter dict (live ``nn.Parameter`` objects)."""
        return dict(self.named_parameters())

    def forward(self, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:  # type: ignore[override]
        """
        Distribution parameters.

        :param obs: flat observations, shape ``(B, obs_dim)``
        :return: ``(mean, log_std)`` of shapes ``(B, act_dim)`` and ``(act_dim,)`` for Box actions;
            ``(logits, empty)`` with logits of shape ``(B, n_actions)`` for Discrete actions
        """
        out = self.mlp(obs)
        if self.continuous:
            return out, self.log_std
        return out, out.new_zeros(0)

    def distribution(self, obs: th.Tensor, params: Params | None = None) -> Distribution:
        """
        The action distribution under ``params`` (the module's own parameters if None).

        :param obs: observations, shape ``(B, *obs_shape)``
        :param params: name -> tensor dict replacing the module's parameters
        :return: a distribution with batch shape ``(B,)`` (event dims folded in for Box)
        """
        obs = obs.reshape(obs.shape[0], -1).float()
        out, log_std = self(obs) if params is None else functional_call(self, params, (obs,))
        return self.make_distribution(out, log_std)

    def make_distribution(self, out: th.Tensor, log_std: th.Tensor) -> Distribution:
        """
        Build the action distribution from the outputs of :meth:`forward`.

        :param out: means or logits, shape ``(..., act_dim)``
        :param log_std: log standard deviations broadcastable to ``out`` (ignored for Discrete)
        :return: a distribution with batch shape ``out.shape[:-1]``
        """
        if self.continuous:
            return Independent(Normal(out, log_std.exp().expand_as(out)), 1)
        return Categorical(logits=out)

    def batched_distribution(self, obs: th.Tensor, params: Params) -> Distribution:
        """
        The action distributions of ``K`` parameter sets at once (:func:`torch.func.vmap`).

        :param obs: flat observations, shape ``(K, B, obs_dim)``
        :param params: name -> tensor dict, every tensor with a leading dimension ``K``
        :return: a distribution with batch shape ``(K, B)``
        """
        obs = obs.float()
        if type(self).forward is MAMLPolicy.forward and all(
            isinstance(m, nn.Linear) or not any(True for _ in m.parameters()) for m in self.mlp
        ):
            # fast path for the Linear/activation stack built here: one batched matmul per layer
            out = obs
            for idx, module in enumerate(self.mlp):
                if isinstance(module, nn.Linear):
                    weight, bias = params[f"mlp.{idx}.weight"], params[f"mlp.{idx}.bias"]  # (K, out, in), (K, out)
                    out = th.baddbmm(bias.unsqueeze(1), out, weight.transpose(1, 2))  # (K, B, out)
                else:
                    out = module(out)
            log_std = params["log_std"] if self.continuous else out.new_zeros(0)
        else:
            out, log_std = vmap(lambda p, o: functional_call(self, p, (o,)))(params, obs)
        if self.continuous:
            log_std = log_std.unsqueeze(1)  # (K, 1, act_dim)
        return self.make_distribution(out, log_std)

    def log_prob(self, obs: th.Tensor, actions: th.Tensor, params: Params | None = None) -> th.Tensor:
        """
        Log-probability of ``actions`` (normalised Box actions or Discrete indices), shape ``(B,)``.
        """
        dist = self.distribution(obs, params)
        if not self.continuous:
            actions = actions.reshape(-1).long()
        return dist.log_prob(actions)

    @staticmethod
    def kl(old: Distribution, new: Distribution) -> th.Tensor:
        """KL(old || new) per row, shape ``(B,)``."""
        return kl_divergence(old, new)

    def sample(self, obs: th.Tensor, params: Params | None = None, deterministic: bool = False) -> th.Tensor:
        """
        Raw actions: unclipped normalised Box actions ``(B, act_dim)`` or Discrete indices ``(B,)``.
        """
        dist = self.distribution(obs, params)
        if deterministic:
            return dist.mean if self.continuous else dist.probs.argmax(dim=-1)  # type: ignore[attr-defined]
        return dist.sample()

    def _predict(self, observation: th.Tensor, deterministic: bool = False) -> th.Tensor:  # type: ignore[override]
        raw = self.sample(observation, self.adapted_params, deterministic)
        self.last_raw_actions = raw
        # Box: BasePolicy.predict rescales [-1, 1] to the env's box (squash_output=True), so clip first.
        return raw.clamp(-1.0, 1.0) if self.continuous else raw


MlpPolicy = MAMLPolicy
