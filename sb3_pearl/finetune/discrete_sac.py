"""SB3's SAC (Haarnoja et al. 2018, arXiv:1801.01290) extended to Discrete action spaces, for the Fine-Tune baseline.

Box action spaces run :class:`stable_baselines3.SAC` unchanged (its policy, its gradient step).
Discrete action spaces use a categorical actor and critics with one Q value per action, so that
the soft state value and the actor loss are exact expectations over actions (Christodoulou 2019,
"Soft Actor-Critic for Discrete Action Settings", arXiv:1910.07207). The math is the project's
(:mod:`sb3_pearl.common.soft_actor_critic`) and the networks are PEARL's
(:class:`~sb3_pearl.common.networks.CategoricalActor`, :class:`~sb3_pearl.common.networks.LatentCritic`)
used without a latent input.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, PyTorchObs, Schedule
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.sac.policies import SACPolicy
from torch import nn

from sb3_pearl.common.checks import (
    check_arch,
    check_ent_coef,
    check_gamma,
    check_int,
    check_learning_rate,
    check_real,
    check_tau,
    is_integer,
)
from sb3_pearl.common.networks import CategoricalActor, LatentCritic, fast_optimizer_kwargs
from sb3_pearl.common.soft_actor_critic import (
    critic_regression_loss,
    entropy_log_prob,
    evaluate_policy,
    q_of_actions,
    q_of_policy,
    soft_value,
)

SelfDiscreteSAC = TypeVar("SelfDiscreteSAC", bound="DiscreteSAC")

# Target entropy of the learned entropy coefficient for Discrete actions: a share of the maximum
# entropy log(n_actions), the value PEARLPlus uses (Christodoulou 2019 used 0.98, which keeps the
# policy close to uniform).
DISCRETE_TARGET_ENTROPY_SHARE = 0.6


class DiscreteSACPolicy(BasePolicy):
    """
    Actor and twin critics of soft discrete SAC: pi(a | s) categorical, Q(s) -> R^|A| per critic.

    The actor and the critic hold their own optimizers (``actor.optimizer``, ``critic.optimizer``)
    as in SB3's :class:`~stable_baselines3.sac.policies.SACPolicy`.

    :param observation_space: flat Box observation space
    :param action_space: Discrete action space
    :param lr_schedule: learning rate schedule (both optimizers)
    :param net_arch: hidden sizes of the actor and of each critic (SB3 SAC default: [256, 256])
    :param activation_fn: activation between hidden layers
    :param n_critics: number of Q networks (twin Q: 2), independently initialised
    :param optimizer_class: optimizer
    :param optimizer_kwargs: extra optimizer arguments
    """

    actor: CategoricalActor
    critic: LatentCritic
    critic_target: LatentCritic

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        n_critics: int = 2,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ):
        if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) != 1:
            raise ValueError(f"DiscreteSACPolicy needs a flat Box observation space (obs_dim,), got {observation_space}")
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"DiscreteSACPolicy needs a Discrete action space, got {action_space}")
        if n_critics < 1:
            raise ValueError(f"n_critics must be >= 1, got {n_critics}")
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=False,
        )
        self.net_arch = list(net_arch) if net_arch is not None else [256, 256]
        self.activation_fn = activation_fn
        self.n_critics = n_critics
        self.obs_dim = int(observation_space.shape[0])
        self.n_actions = int(action_space.n)
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        self.actor = CategoricalActor(self.obs_dim, self.n_actions, self.net_arch, self.activation_fn)
        self.critic = LatentCritic(self.obs_dim, self.n_actions, self.net_arch, self.n_critics, self.activation_fn)
        self.critic_target = LatentCritic(self.obs_dim, self.n_actions, self.net_arch, self.n_critics, self.activation_fn)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic_target.requires_grad_(False)
        lr = lr_schedule(1)
        self.actor.optimizer = self.optimizer_class(self.actor.parameters(), lr=lr, **self.optimizer_kwargs)  # type: ignore[call-arg,assignment]
        self.critic.optimizer = self.optimizer_class(self.critic.parameters(), lr=lr, **self.optimizer_kwargs)  # type: ignore[call-arg,assignment]
        self.set_training_mode(False)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            n_critics=self.n_critics,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic=deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        assert isinstance(observation, th.Tensor)
        return self.actor(observation.float().reshape(observation.shape[0], -1), deterministic=deterministic)

    def set_training_mode(self, mode: bool) -> None:
        self.actor.train(mode)
        self.critic.train(mode)
        self.training = mode


def check_sac_arguments(arguments: Mapping[str, Any]) -> None:
    """
    Raise a ValueError for the first SAC argument of :class:`DiscreteSAC` out of its range (see its docstring).

    Called at the top of ``DiscreteSAC.__init__`` with its bound arguments (``locals()``), and by ``load`` on a loaded
    model's settings (:class:`~sb3_pearl.finetune.FineTune`).

    :param arguments: ``DiscreteSAC.__init__``'s arguments by name, defaults included
    """
    args = arguments
    check_int("batch_size", args["batch_size"], 1, hint="minibatch size of meta-training")
    check_int("buffer_size", args["buffer_size"], 1, hint="replay buffer size of meta-training")
    check_int("learning_starts", args["learning_starts"], 0, hint="random-action steps before the first gradient step")
    check_int("target_update_interval", args["target_update_interval"], 1, hint="gradient steps between target updates")
    check_int("n_steps", args["n_steps"], 1, hint="n-step returns; 1 for one-step")
    gradient_steps = args["gradient_steps"]
    if not (is_integer(gradient_steps) and (gradient_steps >= 0 or gradient_steps == -1)):
        raise ValueError(f"gradient_steps must be an integer >= 0, or -1 (as many as env steps), got {gradient_steps!r}")
    check_learning_rate("learning_rate", args["learning_rate"])
    check_gamma(args["gamma"])
    check_tau(args["tau"])
    check_ent_coef(args["ent_coef"])
    if args["target_entropy"] != "auto":
        check_real("target_entropy", args["target_entropy"], hint="or 'auto'")
    check_arch("policy_kwargs['net_arch']", (args["policy_kwargs"] or {}).get("net_arch"))


class DiscreteSAC(SAC):
    """
    Soft Actor-Critic for Box *and* Discrete action spaces.

    Box: SB3's :class:`~stable_baselines3.SAC`, unchanged. Discrete: soft discrete SAC with a
    :class:`DiscreteSACPolicy` (``"MlpPolicy"`` selects it), per gradient step

    - critics: ``0.5 * sum_i MSE(Q_i(s)[a], r + gamma * (1 - d) * V'(s'))`` with
      ``V'(s') = sum_a pi(a|s') (min_i Q'_i(s')[a] - alpha log pi(a|s'))`` from the target critics;
    - actor: ``-mean_s sum_a pi(a|s) (min_i Q_i(s)[a] - alpha log pi(a|s))`` (critics frozen);
    - entropy coefficient (``ent_coef="auto"``): ``-log(alpha) * (E_pi[log pi] + target_entropy)``,
      ``target_entropy="auto"`` = ``0.6 * log(n_actions)``.

    The order of the updates, the Polyak update of the target critics, the logger keys
    (``train/critic_loss``, ``train/actor_loss``, ``train/ent_coef``, ``train/ent_coef_loss``) and
    save / load are SAC's. Takes every argument of :class:`~stable_baselines3.SAC` with SAC's defaults (gSDE is Box
    only), stated here once for the project: ``SAC.__init__`` refuses Discrete action spaces, so this constructor calls
    ``OffPolicyAlgorithm.__init__`` itself. Each argument is checked before anything is built (docs/reliability.md).

    :param policy: ``"MlpPolicy"`` (SAC's MlpPolicy for Box, :class:`DiscreteSACPolicy` for Discrete) or a class
    :param env: the environment (Box or Discrete actions)
    :param learning_rate: learning rate (constant or schedule)
    :param buffer_size: replay buffer size
    :param learning_starts: random-action steps before the first gradient step
    :param batch_size: minibatch size
    :param tau: Polyak coefficient of the target critics
    :param gamma: discount factor
    :param train_freq: update the model every ``train_freq`` steps (int or ``(n, "step" | "episode")``)
    :param gradient_steps: gradient steps after each rollout (-1: as many as env steps collected)
    :param action_noise: extra exploration noise (Box)
    :param replay_buffer_class: replay buffer class
    :param replay_buffer_kwargs: its extra arguments
    :param optimize_memory_usage: SB3's memory-efficient replay buffer
    :param n_steps: n-step returns
    :param ent_coef: ``"auto"`` / ``"auto_<init>"`` (learned) or a float
    :param target_update_interval: Polyak update of the target critics every this many gradient steps
    :param target_entropy: target of the learned entropy coefficient (``"auto"``: ``-dim(A)`` for Box,
        ``0.6 * log(n_actions)`` for Discrete)
    :param use_sde: generalised state-dependent exploration (Box only)
    :param sde_sample_freq: gSDE noise resampling frequency
    :param use_sde_at_warmup: gSDE instead of uniform random actions before ``learning_starts``
    :param stats_window_size: episodes averaged in the rollout logs
    :param tensorboard_log: TensorBoard log folder
    :param policy_kwargs: extra policy arguments (``net_arch``, ``activation_fn``, ``n_critics``, ...)
    :param verbose: 0 silent, 1 info, 2 debug
    :param seed: seed of the networks and the sampling
    :param device: torch device
    :param _init_setup_model: build the networks at construction
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = dict(SAC.policy_aliases)

    def __init__(
        self,
        policy: str | type[SACPolicy] | type[DiscreteSACPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        ent_coef: str | float = "auto",
        target_update_interval: int = 1,
        target_entropy: str | float = "auto",
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        use_sde_at_warmup: bool = False,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        # Every argument checked before anything is built (docs/reliability.md).
        check_sac_arguments(locals())
        # SAC.__init__ admits Box action spaces only (an assertion): run its parent with both
        # spaces admitted, then set SAC's own attributes exactly as SAC.__init__ does.
        OffPolicyAlgorithm.__init__(
            self,
            policy,  # type: ignore[arg-type]
            env,
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            use_sde=use_sde,
            sde_sample_freq=sde_sample_freq,
            use_sde_at_warmup=use_sde_at_warmup,
            supported_action_spaces=None,  # checked below with a ValueError
            support_multi_env=True,
        )
        if self.env is not None and not isinstance(self.action_space, (spaces.Box, spaces.Discrete)):
            raise ValueError(
                f"{type(self).__name__} supports Box (SAC) and Discrete (soft discrete SAC) action spaces, "
                f"got {type(self.action_space).__name__}: {self.action_space}"
            )
        self.target_entropy = target_entropy
        self.log_ent_coef: th.Tensor | None = None
        self.ent_coef = ent_coef
        self.target_update_interval = target_update_interval
        self.ent_coef_optimizer: th.optim.Adam | None = None

        if _init_setup_model:
            self._setup_model()

    @property
    def discrete(self) -> bool:
        """Whether the action space is Discrete (soft discrete SAC) rather than Box (SAC)."""
        return isinstance(self.action_space, spaces.Discrete)

    def _setup_model(self) -> None:
        if self.discrete:
            if self.policy_class is self.policy_aliases["MlpPolicy"]:
                self.policy_class = DiscreteSACPolicy
            if not issubclass(self.policy_class, DiscreteSACPolicy):
                raise ValueError(
                    f"Discrete action spaces need 'MlpPolicy' or a DiscreteSACPolicy, got {self.policy_class.__name__}"
                )
            # OffPolicyAlgorithm adds use_sde to the policy kwargs (gSDE is Box only, BaseAlgorithm rejects it here).
            self.policy_kwargs.pop("use_sde", None)
            if self.target_entropy == "auto":
                self.target_entropy = DISCRETE_TARGET_ENTROPY_SHARE * math.log(int(self.action_space.n))  # type: ignore[attr-defined]
        elif issubclass(self.policy_class, DiscreteSACPolicy):
            raise ValueError(f"DiscreteSACPolicy needs a Discrete action space, got {self.action_space}")
        # Adam in torch's fused form unless the user chose, as PEARL's policy does (the same update in one kernel), for
        # building the policy only: policy_kwargs keep what the user gave (they are saved, and `load` compares them).
        # A model saved before this keeps its saved optimizer groups (load_state_dict restores their flags).
        given = self.policy_kwargs
        optimizer_class = given.get("optimizer_class", th.optim.Adam)
        fast = fast_optimizer_kwargs(optimizer_class, given.get("optimizer_kwargs") or {}, self.device)
        self.policy_kwargs = {**given, "optimizer_kwargs": fast}
        try:
            super()._setup_model()
        finally:
            self.policy_kwargs = given

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """``gradient_steps`` soft actor-critic steps: SAC's for Box, soft discrete SAC's for Discrete."""
        if not self.discrete:
            super().train(gradient_steps, batch_size)
            return
        policy = self.policy
        assert isinstance(policy, DiscreteSACPolicy)
        actor, critic, critic_target = policy.actor, policy.critic, policy.critic_target
        policy.set_training_mode(True)
        optimizers: list[th.optim.Optimizer] = [actor.optimizer, critic.optimizer]  # type: ignore[list-item]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)

        ent_coef_losses, ent_coefs, actor_losses, critic_losses = [], [], [], []
        for gradient_step in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
            obs = replay_data.observations.float()  # type: ignore[union-attr]
            next_obs = replay_data.next_observations.float()  # type: ignore[union-attr]

            pe = evaluate_policy(actor, obs)  # probabilities and log-probabilities of every action
            if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
                ent_coef = th.exp(self.log_ent_coef.detach())
                assert isinstance(self.target_entropy, float)
                ent_coef_loss = -(self.log_ent_coef * (entropy_log_prob(pe) + self.target_entropy).detach()).mean()
                ent_coef_losses.append(ent_coef_loss.item())
                self.ent_coef_optimizer.zero_grad()
                ent_coef_loss.backward()
                self.ent_coef_optimizer.step()
            else:
                ent_coef = self.ent_coef_tensor
            ent_coefs.append(ent_coef.item())

            with th.no_grad():
                next_pe = evaluate_policy(actor, next_obs)
                next_v = soft_value(q_of_policy(critic_target, next_obs, next_pe), next_pe, ent_coef)
                target_q = replay_data.rewards + (1 - replay_data.dones) * discounts * next_v

            critic_loss = critic_regression_loss(
                q_of_actions(critic, obs, replay_data.actions, discrete=True), target_q, coef=0.5
            )
            critic_losses.append(critic_loss.item())
            critic.optimizer.zero_grad()
            critic_loss.backward()
            critic.optimizer.step()

            actor_loss = -soft_value(q_of_policy(critic.forward_frozen, obs, pe), pe, ent_coef).mean()
            actor_losses.append(actor_loss.item())
            actor.optimizer.zero_grad()
            actor_loss.backward()
            actor.optimizer.step()

            if gradient_step % self.target_update_interval == 0:
                polyak_update(critic.parameters(), critic_target.parameters(), self.tau)

        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/ent_coef", np.mean(ent_coefs))
        self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))
        if len(ent_coef_losses) > 0:
            self.logger.record("train/ent_coef_loss", np.mean(ent_coef_losses))

    def learn(
        self: SelfDiscreteSAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DiscreteSAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDiscreteSAC:
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
