"""PEARL (Rakelly et al. 2019, arXiv:1903.08254): off-policy meta-RL with probabilistic context variables.

``train()`` follows Algorithm 1 of the paper, vectorised over the ``meta_batch`` tasks: every
network runs once per gradient step on the rows of all tasks, shaped ``(T * B, ...)``.
"""

from __future__ import annotations

import io
import math
import pathlib
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.adaptation import stored_action
from sb3_pearl.common.buffers import MetaReplayBuffer
from sb3_pearl.common.callbacks import gradient_step_event
from sb3_pearl.common.divergence import NonFiniteUpdateGuard, check_env_step, check_finite_actions
from sb3_pearl.common.meta_algorithm import MetaAlgorithm, check_observed_transition
from sb3_pearl.common.networks import CategoricalActor, LatentCritic, SquashedGaussianActor, polyak_update_foreach
from sb3_pearl.common.persistence import check_buffer_tasks, read_replay_buffer, save_replay_buffer_file, saved_arguments
from sb3_pearl.common.precision import resolve_bf16
from sb3_pearl.common.tasks import set_vec_env_task
from sb3_pearl.common.type_aliases import MetaReplaySamples, PEARLLosses, PosteriorSample, TrainingPlan
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.pearl.arguments import check_pearl_arguments
from sb3_pearl.pearl.collection import OpenIteration, Segment, requeue_open_segments, start_piece
from sb3_pearl.pearl.gradient_conflict import record_gradient_conflict
from sb3_pearl.pearl.losses import LossSettings, compute_losses
from sb3_pearl.pearl.policies import ContextEncoder, PEARLPolicy
from sb3_pearl.pearl.returns import PendingPiece, piece_returns

SelfPEARL = TypeVar("SelfPEARL", bound="PEARL")


class PEARL(MetaAlgorithm, OffPolicyAlgorithm):
    """
    PEARL (Rakelly et al. 2019, arXiv:1903.08254): off-policy meta-RL with probabilistic context variables.

    A context encoder infers q(z | c) from a task's transitions (product of Gaussians with a KL
    bottleneck to N(0, I)); a soft actor-critic conditioned on z acts and learns. The encoder is
    trained by the critic loss and the KL only. ``train()`` follows the paper's Algorithm 1.
    :class:`PEARLPlus` adds the paper's prior-regularisation term through hooks this class calls without
    knowing what they add: the loss settings handed to the one loss step (:meth:`_loss_settings`), the
    sum of the losses (:meth:`_total_loss`), the target networks (:meth:`_target_pairs`), the networks
    (:attr:`networks`) and what is saved (:meth:`_get_torch_save_params`).

    All losses touch disjoint parameter sets, so one backward pass serves every optimizer; the actor
    terms see the critics through frozen parameters (gradients reach the actor only) and, unlike the
    reference implementation and SB3's SAC (which compute the actor loss after the critic step), the
    critics as they were before this step's update (docs/pearl.md states the effect).

    Data collection (``learn``, :meth:`collect_iteration`) follows the reference schedule (:mod:`sb3_pearl.pearl.collection`):
    prior-z and posterior-z trajectories per visited task, then ``num_train_steps_per_itr`` gradient
    steps. A ``learn`` budget ending inside an iteration trains the collected share of it, or, with
    ``partial_iteration="carry"``, keeps it open for the next ``learn``.

    :param policy: ``"MlpPolicy"`` or a :class:`PEARLPolicy` subclass
    :param env: an env id or env following the task protocol (``sample_tasks``, ``set_task``,
        ``get_task``); with ``n_envs > 1`` every env runs its own task
    :param learning_rate: learning rate of every optimizer (constant or schedule)
    :param buffer_size: RL transitions kept per training task
    :param batch_size: RL transitions per task in a gradient step (reference: 256)
    :param tau: Polyak coefficient of the target critics
    :param gamma: discount factor
    :param latent_dim: size of z
    :param kl_weight: weight ``beta`` of KL(q(z|c) || N(0, I)), summed over the meta-batch tasks
    :param use_next_obs_in_context: context transitions are (s, a, r, s') instead of (s, a, r)
    :param encoder_arch: hidden sizes of the context encoder
    :param ent_coef: a fixed entropy coefficient (default 1.0, the reference's, with ``reward_scale=5``)
        or ``"auto"`` / ``"auto_<init>"`` (learned, SB3's rule). The default is the setting measured to
        make the encoder learn: with ``"auto"`` and ``reward_scale=1`` the posterior collapses to the
        prior (docs/pearl.md)
    :param target_entropy: target of the learned entropy coefficient; ``"auto"`` is ``-dim(A)`` for
        Box and ``0.6 * log(n_actions)`` for Discrete
    :param reward_scale: rewards are multiplied by this in the critic targets (not in the context);
        default 5 (the reference's; it sets the critic loss's weight against ``kl_weight``)
    :param n_train_tasks: training tasks drawn from ``env.sample_tasks`` with the model seed
    :param n_test_tasks: held-out test tasks drawn in the same call
    :param train_tasks: explicit training tasks (overrides the draw)
    :param test_tasks: explicit test tasks (overrides the draw)
    :param meta_batch: tasks per gradient step
    :param embedding_batch_size: context transitions per task in a gradient step
    :param num_initial_steps: prior steps per training task in iteration 0
    :param num_tasks_sample: tasks visited per iteration
    :param num_steps_prior: prior-z steps per visited task
    :param num_steps_posterior: posterior-z steps per visited task (also stored as context)
    :param num_extra_rl_steps_posterior: posterior-z steps per visited task for the RL buffer only
    :param num_train_steps_per_itr: gradient steps per iteration
    :param use_bf16: run the hidden layers of every network in bfloat16 (``torch.autocast``) during
        gradient steps; weights, optimizers, output layers and losses stay float32. It pays only where
        bfloat16 is native (e.g. a CPU with AVX512-BF16); on a device without it torch emulates bfloat16,
        slower than float32, so ``True`` warns and trains in float32, ``"force"`` uses bfloat16 anyway
        (:mod:`sb3_pearl.common.precision`; the speed and learning figures: docs/pearl.md, docs/speed.md)
    :param grad_conflict_log_freq: every this many gradient steps, log ``train/grad_conflict_ratio``
        (the weighted gradient of the actor's second term against its first on the actor parameters: 0 for PEARL,
        whose actor has one term; PEARL+'s prior term) and ``train/grad_conflict_cos`` (their cosine) from that
        step's losses (docs/diagnostics.md); 0: off
    :param partial_iteration: when a ``learn`` budget ends inside an iteration: ``"train"`` (default, the protocol of
        the committed results) trains the collected share, so that short runs train; ``"carry"`` keeps the iteration
        open (saved with the model) for the next ``learn``, so a run split anywhere is bit-identical to the unsplit
        one (docs/reliability.md). An iteration interrupted by a callback is kept open in both modes.
    :param policy_kwargs: extra policy arguments (``net_arch``, ``activation_fn``, ``n_critics``, ...)
    :param stats_window_size: episodes averaged in the rollout logs
    :param tensorboard_log: TensorBoard log folder
    :param verbose: 0 silent, 1 info, 2 debug
    :param seed: seed of the networks, the task draw and the sampling
    :param device: torch device
    :param _init_setup_model: build the networks at construction
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": PEARLPolicy}
    requires_flat_observations: ClassVar[bool] = True  # the networks take z concatenated to a flat observation
    # Parameters every PEARL / PEARL+ zip holds (load() refuses a zip without them, e.g. a SAC one).
    saved_data_keys: ClassVar[tuple[str, ...]] = ("kl_weight", "meta_batch", "num_train_steps_per_itr", "train_tasks")
    # Gradient steps in a row with a non-finite loss or gradient (each skipped) that stop training (DivergenceError).
    max_consecutive_nonfinite_updates: ClassVar[int] = 10
    policy: PEARLPolicy
    replay_buffer: MetaReplayBuffer  # type: ignore[assignment]
    # The policy's networks the model names as attributes (SB3's aliases; never saved apart from the policy).
    networks: ClassVar[tuple[str, ...]] = ("encoder", "actor", "critic", "critic_target")
    encoder: ContextEncoder
    actor: SquashedGaussianActor | CategoricalActor
    critic: LatentCritic
    critic_target: LatentCritic
    # Called after every gradient step of train() while set (the progress callback sets it during learn()); never saved.
    gradient_step_callback: Callable[[], None] | None = None
    # The callbacks of the running learn(): told of every gradient step (gradient_step_event), never saved.
    _learn_callback: BaseCallback | None = None
    # Gradient steps of the current iteration still to train: a stop between two gradient steps leaves them here, saved
    # with the model, and the resumed learn() trains them first (0: none pending; older zips have none).
    _pending_gradient_steps: int = 0

    def __init__(
        self,
        policy: str | type[PEARLPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 100_000,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        latent_dim: int = 5,
        kl_weight: float = 0.1,
        use_next_obs_in_context: bool = False,
        encoder_arch: list[int] | None = None,
        ent_coef: str | float = 1.0,
        target_entropy: str | float = "auto",
        reward_scale: float = 5.0,
        n_train_tasks: int = 100,
        n_test_tasks: int = 30,
        train_tasks: list[Task] | None = None,
        test_tasks: list[Task] | None = None,
        meta_batch: int = 16,
        embedding_batch_size: int = 100,
        num_initial_steps: int = 2000,
        num_tasks_sample: int = 5,
        num_steps_prior: int = 400,
        num_steps_posterior: int = 0,
        num_extra_rl_steps_posterior: int = 600,
        num_train_steps_per_itr: int = 2000,
        use_bf16: bool | str = False,
        grad_conflict_log_freq: int = 0,
        partial_iteration: str = "train",
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        # Every argument checked before anything is built (docs/reliability.md).
        check_pearl_arguments(locals())
        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=0,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            gradient_steps=num_train_steps_per_itr,
            policy_kwargs=dict(policy_kwargs) if policy_kwargs is not None else None,  # a copy: entries are added below
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            support_multi_env=True,
            sde_support=False,
            supported_action_spaces=None,  # checked by _init_meta_algorithm with a ValueError
        )
        self._init_meta_algorithm(n_train_tasks, n_test_tasks, train_tasks, test_tasks)
        self.kl_weight = kl_weight
        self.ent_coef = ent_coef
        self.target_entropy = target_entropy
        self.reward_scale = reward_scale
        self.meta_batch = meta_batch
        self.embedding_batch_size = embedding_batch_size
        self.num_initial_steps = num_initial_steps
        self.num_tasks_sample = num_tasks_sample
        self.num_steps_prior = num_steps_prior
        self.num_steps_posterior = num_steps_posterior
        self.num_extra_rl_steps_posterior = num_extra_rl_steps_posterior
        self.num_train_steps_per_itr = num_train_steps_per_itr
        self.use_bf16 = use_bf16
        self.grad_conflict_log_freq = grad_conflict_log_freq
        self.partial_iteration = partial_iteration
        self._open_iteration: OpenIteration | None = None  # saved: a "carry" run resumes inside its iteration
        self.n_iterations = 0
        self.log_ent_coef: th.Tensor | None = None
        self.ent_coef_optimizer: th.optim.Adam | None = None
        self.policy_kwargs.update(latent_dim=latent_dim, use_next_obs_in_context=use_next_obs_in_context)
        if encoder_arch is not None:
            self.policy_kwargs["encoder_arch"] = encoder_arch
        self._adapt_context: list[tuple[np.ndarray, np.ndarray, float, np.ndarray]] = []
        if _init_setup_model:
            self._setup_model()

    @property
    def latent_dim(self) -> int:
        """Size of z."""
        return self.policy.latent_dim

    # ------------------------------------------------------------------------------------------
    # Set-up
    # ------------------------------------------------------------------------------------------
    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        self._setup_tasks()
        context_size = max(self.num_initial_steps, self.num_steps_prior + self.num_steps_posterior, 1)
        self.replay_buffer = MetaReplayBuffer(
            len(self.train_tasks) or self.n_train_tasks,
            self.buffer_size,
            context_size,
            self.observation_space,
            self.action_space,
        )
        self.policy = self.policy_class(  # type: ignore[assignment]
            self.observation_space, self.action_space, self.lr_schedule, **self.policy_kwargs
        )
        self.policy = self.policy.to(self.device)
        self._create_aliases()
        self._setup_entropy()
        self._convert_train_freq()
        self._update_guard = NonFiniteUpdateGuard(type(self).__name__, self.max_consecutive_nonfinite_updates)
        self._bf16_enabled = resolve_bf16(self.use_bf16, self.device, type(self).__name__)
        self.reset_adaptation()

    def _create_aliases(self) -> None:
        for name in self.networks:
            setattr(self, name, getattr(self.policy, name))

    def _setup_entropy(self) -> None:
        if self.target_entropy == "auto":
            if isinstance(self.action_space, spaces.Discrete):
                self.target_entropy = 0.6 * math.log(int(self.action_space.n))
            else:
                self.target_entropy = -float(np.prod(self.action_space.shape))  # type: ignore[arg-type]
        self.target_entropy = float(self.target_entropy)
        if isinstance(self.ent_coef, str):
            if not self.ent_coef.startswith("auto"):
                raise ValueError(f"ent_coef must be a float, 'auto' or 'auto_<init>', got {self.ent_coef!r}")
            init_value = float(self.ent_coef.split("_")[1]) if "_" in self.ent_coef else 1.0
            if init_value <= 0.0:
                raise ValueError(f"the initial entropy coefficient must be > 0, got {init_value}")
            self.log_ent_coef = th.log(th.ones(1, device=self.device) * init_value).requires_grad_(True)
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=self.lr_schedule(1))
        else:
            self.ent_coef_tensor = th.tensor(float(self.ent_coef), device=self.device)

    def _current_ent_coef(self) -> th.Tensor:
        if self.log_ent_coef is not None:
            return self.log_ent_coef.detach().exp()
        return self.ent_coef_tensor

    # ------------------------------------------------------------------------------------------
    # Algorithm 1: the losses of one gradient step
    # ------------------------------------------------------------------------------------------
    def _loss_settings(self) -> LossSettings:
        """The coefficients and switches of a gradient step, read at each step (they may change between ``learn`` calls)."""
        assert isinstance(self.target_entropy, float), "target_entropy is resolved by _setup_model"
        return LossSettings(gamma=self.gamma, reward_scale=self.reward_scale, target_entropy=self.target_entropy)

    def sample_posterior(self, context: th.Tensor, sample: bool = True) -> PosteriorSample:
        """
        Task inference, the one place where a context becomes a posterior and a z (losses, collection, adaptation).

        :param context: context transitions (T, N, context_dim)
        :param sample: draw z from q(z | c) with the reparameterisation trick, or take its mean
        :return: posterior mean and variance and z, each (T, latent_dim)
        """
        mean, var = self.policy.encoder.posterior(context)
        z = mean + var.sqrt() * th.randn_like(mean) if sample else mean
        return PosteriorSample(mean, var, z)

    def _compute_losses(self, replay: MetaReplaySamples, context: th.Tensor, z0: th.Tensor) -> PEARLLosses:
        """
        The losses of one gradient step for T tasks (:func:`sb3_pearl.pearl.losses.compute_losses`): task inference
        q(z | c) on each task's context, then the critic, actor and entropy losses (and the terms the settings of
        :meth:`_loss_settings` switch on: PEARL+'s prior terms, in the same pass, from the same random draws).

        :param replay: RL batch, tensors of leading shape (T, B)
        :param context: context transitions (T, N, context_dim)
        :param z0: prior latents (T, latent_dim), one per task
        :return: the losses
        """
        return compute_losses(
            self.policy,
            replay,
            posterior=self.sample_posterior(context),  # z carries the encoder's gradients
            z0=z0,
            ent_coef=self._current_ent_coef(),
            log_ent_coef=self.log_ent_coef,
            settings=self._loss_settings(),
        )

    def _named_losses(self, losses: PEARLLosses) -> dict[str, th.Tensor]:
        """The losses of a step by name, in the order of the total loss (the divergence guard's message)."""
        names = ("critic_loss", "kl_loss", "actor_loss", "ent_coef_loss", "ent_coef")
        return {name: getattr(losses, name) for name in names}

    def _logged_losses(self, losses: PEARLLosses) -> dict[str, th.Tensor]:
        """The values of a step logged as ``train/<name>`` (their means over the steps of a ``train()`` call)."""
        return {
            "critic_loss": losses.critic_loss,
            "kl": losses.kl_loss,
            "actor_loss": losses.actor_loss,
            "ent_coef": losses.ent_coef,
            "ent_coef_loss": losses.ent_coef_loss,
            "z_mean_abs": losses.z_mean.abs().mean(),
            "z_var": losses.z_var.mean(),
        }

    def _divergence_settings(self) -> dict[str, Any]:
        """The settings the divergence guard names as likely fixes."""
        return {
            "learning_rate": self.lr_schedule(self._current_progress_remaining),
            "reward_scale": self.reward_scale,
            "kl_weight": self.kl_weight,
        }

    def _total_loss(self, losses: PEARLLosses) -> th.Tensor:
        """The sum of the step's losses, back-propagated once (each reaches only its own networks)."""
        return losses.critic_loss + self.kl_weight * losses.kl_loss + losses.actor_loss + losses.ent_coef_loss

    def _returns_horizon(self) -> int | None:
        """
        Whether collection records the Monte-Carlo returns of the rows collected with z from the prior
        (:mod:`sb3_pearl.pearl.returns`), and their horizon: None (PEARL): none; ``n`` > 0: n-step returns; 0: each
        to the end of its trajectory (PEARL+'s ``prior_target="mc"``).
        """
        return None

    def _actor_second_term_weight(self) -> float:
        """The weight of the actor's second loss term in the total loss, for the gradient conflict's log: 0, PEARL's
        actor has one term (PEARL+: its prior term's ``prior_coef``)."""
        return 0.0

    def _sample_context(self, tasks: np.ndarray) -> th.Tensor:
        """``embedding_batch_size`` context transitions of each task, (len(tasks), N, context_dim)."""
        ctx = self.replay_buffer.context.sample(tasks, self.embedding_batch_size, self.device)
        return self.policy.make_context(ctx.observations, ctx.actions, ctx.rewards, ctx.next_observations)

    def _sample_meta_batch(self, batch_size: int | None = None) -> tuple[MetaReplaySamples, th.Tensor, th.Tensor]:
        """RL batch (``batch_size`` rows per task, default ``self.batch_size``), context and z0 for ``meta_batch`` tasks."""
        candidates = self.replay_buffer.tasks_with_data()
        if len(candidates) == 0:
            raise RuntimeError("no training task holds data yet: collect before training")
        tasks = np.random.choice(candidates, size=self.meta_batch, replace=len(candidates) < self.meta_batch)
        replay = self.replay_buffer.rl.sample(
            tasks, batch_size or self.batch_size, self.device, returns=self._returns_horizon() is not None
        )
        context = self._sample_context(tasks)
        # One z ~ N(0, I) per task: the prior terms' z0 where the loss settings switch them on; drawn in every model, so
        # that PEARL and PEARL+ share one random stream.
        z0 = th.randn(len(tasks), self.latent_dim, device=self.device)
        return replay, context, z0

    def _target_pairs(self) -> tuple[list[th.Tensor], list[th.Tensor]]:
        """The critics' parameters and, in the same order, their target networks' (Polyak-averaged after every step)."""
        return [*self.critic.parameters()], [*self.critic_target.parameters()]

    def _count_gradient_step(self) -> None:
        """One gradient step done: ``_n_updates``, and, inside ``learn()``, the iteration's steps still to train."""
        self._n_updates += 1
        if self._learn_callback is not None:  # a direct train() call leaves learn()'s bookkeeping alone
            self._pending_gradient_steps = max(self._pending_gradient_steps - 1, 0)

    def train(self, gradient_steps: int, batch_size: int = 256) -> int:  # type: ignore[override]
        """
        ``gradient_steps`` steps of Algorithm 1's inner loop, each over ``meta_batch`` tasks.

        During ``learn()`` the callbacks are told of every gradient step (:func:`gradient_step_event`); one that asks
        to stop (a signal, a checkpoint) stops it between two steps, where the model's state (weights, optimizers,
        RNG streams, ``_n_updates`` and the iteration's steps still to train) is one a saved model resumes exactly. Two
        things are not carried across such a resume: the non-finite-update guard's count of skipped steps in a row
        (it restarts at 0) and the logged ``train/*`` means of the interrupted iteration, which cover only the steps
        after the resume; the weights are the uninterrupted run's, bit for bit.

        :param gradient_steps: number of gradient steps
        :param batch_size: RL transitions per task in each step (``learn`` passes ``self.batch_size``)
        :return: the gradient steps taken (``gradient_steps`` unless a stop was asked for)
        """
        self.policy.set_training_mode(True)
        optimizers = self.policy.optimizers()
        if self.ent_coef_optimizer is not None:
            optimizers = [*optimizers, self.ent_coef_optimizer]
        self._update_learning_rate(optimizers)
        parameters = [p for optimizer in optimizers for group in optimizer.param_groups for p in group["params"]]
        critic_params, critic_target_params = self._target_pairs()
        logs: dict[str, list[float]] = {}
        steps_done = 0
        for _ in range(gradient_steps):
            if steps_done > 0 and self._learn_callback is not None and not gradient_step_event(self._learn_callback):
                break  # a stop was asked for: the state here is one a saved model resumes exactly
            steps_done += 1
            # Sample meta_batch training tasks: each task's RL batch b, context c and one prior latent z0.
            replay, context, z0 = self._sample_meta_batch(batch_size)
            # Infer z ~ q(z | c) from each context, then the losses: critic, KL, actor and entropy (and what the loss
            # settings switch on).
            with th.autocast(device_type=self.device.type, dtype=th.bfloat16, enabled=self._bf16_enabled):
                losses = self._compute_losses(replay, context, z0)
            if self.grad_conflict_log_freq > 0 and self._n_updates % self.grad_conflict_log_freq == 0:
                # two extra actor-only backward passes
                record_gradient_conflict(self.actor, self._actor_second_term_weight(), losses, logs)
            # The updates: one backward pass serves every optimizer (the losses touch disjoint parameters).
            for optimizer in optimizers:
                optimizer.zero_grad(set_to_none=True)
            total_loss = self._total_loss(losses)
            total_loss.backward()
            # Divergence guard: a non-finite loss or gradient skips the step (one sync); too many in a row stop.
            if not self._update_guard.is_finite(total_loss, parameters):
                self._update_guard.skip(self._named_losses(losses), self._divergence_settings())
                self._count_gradient_step()
                continue
            self._update_guard.ok()
            for optimizer in optimizers:
                optimizer.step()
            polyak_update_foreach(critic_params, critic_target_params, self.tau)  # the target critics follow
            self._count_gradient_step()  # counted once the step's work is done: a save between steps sees it whole
            if self.gradient_step_callback is not None:
                self.gradient_step_callback()
            for key, value in self._logged_losses(losses).items():
                logs.setdefault(key, []).append(float(value.item()))
        self.policy.set_training_mode(False)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        if self._update_guard.skipped:
            self.logger.record("train/skipped_updates", self._update_guard.skipped)
        for key, values in logs.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))
        return steps_done

    # ------------------------------------------------------------------------------------------
    # The meta-training loop
    # ------------------------------------------------------------------------------------------
    def learn(
        self: SelfPEARL,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "PEARL",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfPEARL:
        """
        Meta-train for ``total_timesteps`` env steps (Algorithm 1).

        :param total_timesteps: env steps to collect
        :param callback: SB3 callback(s), called once per env step
        :param log_interval: dump the logs every ``log_interval`` iterations
        :param tb_log_name: TensorBoard run name
        :param reset_num_timesteps: restart the step counter
        :param progress_bar: show a progress bar
        """
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        callback.on_training_start(locals(), globals())
        assert self.env is not None
        self._learn_callback = callback
        try:
            self._learn_iterations(total_timesteps, callback, log_interval)
        finally:
            self._learn_callback = None
        callback.on_training_end()
        return self

    def _learn_iterations(self, total_timesteps: int, callback: BaseCallback, log_interval: int) -> None:
        """Algorithm 1's outer loop: collect an iteration's data, then train its gradient steps (see :meth:`learn`)."""
        assert self.env is not None
        while self.num_timesteps < total_timesteps or self._pending_gradient_steps > 0:
            if self._pending_gradient_steps == 0:  # else: an iteration whose gradient steps a stop interrupted
                state = self._open_iteration  # an iteration a previous learn() left open ("carry"), or a new one
                if state is None:
                    callback.on_rollout_start()  # before _plan_iteration's draws: a checkpoint saved here resumes exactly
                    state = self._start_iteration(self._plan_iteration())
                continue_training = self.collect_iteration(self.env, callback, state)
                if not state.finished and (self.partial_iteration == "carry" or not continue_training):
                    self._open_iteration = state  # finished by the next learn(); nothing trained on it yet
                    return
                self._finish_open_pieces(state)  # trained now: a trajectory the budget ended inside is cut here
                self._open_iteration = None
                if not continue_training:
                    return
                if state.collected > 0:  # "train": a budget ending inside the iteration trains the collected share
                    steps = math.ceil(self.num_train_steps_per_itr * state.collected / max(state.planned, 1))
                    self._pending_gradient_steps = steps
            if self._pending_gradient_steps > 0:
                self.train(gradient_steps=self._pending_gradient_steps, batch_size=self.batch_size)
                if self._pending_gradient_steps > 0:
                    return  # stopped between two gradient steps: the rest trains first when learn() resumes
            self.n_iterations += 1
            self.logger.record("time/iterations", self.n_iterations)
            if log_interval and self.n_iterations % log_interval == 0:
                self.dump_logs()

    def _before_env_reset(self) -> None:
        """``learn()`` resets the envs: an iteration left open has its trajectories cut and its segments requeued."""
        if self._open_iteration is not None:
            self._finish_open_pieces(self._open_iteration)  # the envs are reset: their trajectories are cut
            requeue_open_segments(self._open_iteration, self.n_envs)  # the envs are reset: their segments start anew

    def training_plan(self, total_timesteps: int) -> TrainingPlan:
        """
        What ``learn(total_timesteps)`` will still do: iteration 0's initial data (if some training task has none yet),
        then full iterations and maybe a partial last one, whose gradient steps are scaled as ``learn`` scales them.

        :param total_timesteps: the ``learn`` budget, counted from 0 (a resumed run plans what is left)
        :return: the plan
        """
        remaining = max(total_timesteps - self.num_timesteps, 0)
        steps = self.num_train_steps_per_itr
        chunks: list[tuple[int, int]] = []  # (collected, planned) per iteration
        open_iteration = self._open_iteration
        if open_iteration is not None and remaining > 0:  # first, the iteration a previous learn() left open
            rest = min(open_iteration.planned - open_iteration.collected, remaining)
            chunks.append((open_iteration.collected + rest, open_iteration.planned))
            remaining -= rest
        without_data = int(np.count_nonzero(self.replay_buffer.rl.size == 0)) if self.num_initial_steps > 0 else 0
        if open_iteration is None and without_data > 0 and remaining > 0:
            planned = self.num_initial_steps * without_data
            chunks.append((min(planned, remaining), planned))
            remaining -= chunks[-1][0]
        per_iteration = self.num_tasks_sample * (
            self.num_steps_prior + self.num_steps_posterior + self.num_extra_rl_steps_posterior
        )
        full, rest = divmod(remaining, per_iteration) if per_iteration > 0 else (0, 0)
        chunks += [(per_iteration, per_iteration)] * full + ([(rest, per_iteration)] if rest > 0 else [])
        carry = self.partial_iteration == "carry"  # an unfinished last iteration is trained by a later learn()
        updates = [0 if carry and done < planned else math.ceil(steps * done / planned) for done, planned in chunks]
        pending = int(self._pending_gradient_steps)  # an iteration whose gradient steps a stop interrupted: trained first
        if pending > 0:
            updates.insert(0, pending)
        initial = chunks[0][0] if chunks and open_iteration is None and without_data > 0 and pending == 0 else 0
        note = ""
        if initial:
            per_task, planned = self.num_initial_steps, self.num_initial_steps * without_data
            note = f"iteration 0: {per_task:,} steps with z from the prior per training task, {without_data} tasks"
            if initial < planned:  # the budget ends inside iteration 0: say how much of it runs
                note += f"; this run's {initial:,} steps reach {math.ceil(initial / per_task)} of them"
            else:
                note += f" ({planned:,} in all)"
        return TrainingPlan(
            env_steps=max(total_timesteps - self.num_timesteps, 0),
            gradient_steps=sum(updates),
            initial_steps=initial,
            first_updates=updates[0] if updates else 0,
            note=note,
        )

    # ------------------------------------------------------------------------------------------
    # Data collection: Algorithm 1's inner loop over tasks (the iteration's state: sb3_pearl.pearl.collection)
    # ------------------------------------------------------------------------------------------
    def _plan_iteration(self) -> list[list[Segment]]:
        """The segments of the next iteration, one program (list of segments) per visited task."""
        without_data = np.flatnonzero(self.replay_buffer.rl.size == 0)
        if len(without_data) > 0 and self.num_initial_steps > 0:  # iteration 0 (or an interrupted one): initial prior data
            initial = self.num_initial_steps
            return [
                [Segment(task=int(t), n_steps=initial, z_source="prior", add_to_context=True, clear_context=True)]
                for t in without_data
            ]
        programs = []
        for task in np.random.randint(len(self.train_tasks), size=self.num_tasks_sample):
            t = int(task)
            program = [
                Segment(task=t, n_steps=self.num_steps_prior, z_source="prior", add_to_context=True, clear_context=True),
                Segment(t, n_steps=self.num_steps_posterior, z_source="posterior", add_to_context=True, clear_context=False),
                Segment(
                    t,
                    n_steps=self.num_extra_rl_steps_posterior,
                    z_source="posterior",
                    add_to_context=False,
                    clear_context=False,
                ),
            ]
            if self.num_steps_prior == 0:  # the context buffer is still cleared when the task is visited
                program.insert(0, Segment(t, n_steps=0, z_source="prior", add_to_context=False, clear_context=True))
            programs.append(program)
        return programs

    def _start_iteration(self, programs: list[list[Segment]]) -> OpenIteration:
        """The collection state of a new iteration made of ``programs`` (:meth:`_plan_iteration`)."""
        n_envs = self.n_envs
        return OpenIteration(
            queue=deque(deque(program) for program in programs),
            running=[deque() for _ in range(n_envs)],
            segments=[None] * n_envs,
            remaining=np.zeros(n_envs, dtype=np.int64),
            z=np.zeros((n_envs, self.latent_dim), dtype=np.float32),
            planned=sum(seg.n_steps for program in programs for seg in program),
        )

    def _start_segment(self, env: VecEnv, slot: int, segment: Segment, obs: np.ndarray) -> None:
        """Switch env ``slot`` to the segment's task and reset it explicitly (no auto-reset leak)."""
        set_vec_env_task(env, self.train_tasks[segment.task], [slot])
        obs[slot] = env.env_method("reset", indices=[slot])[0][0]

    def _draw_z(self, segment: Segment) -> th.Tensor:
        """z for a new trajectory: from the prior, or from the posterior of the task's context buffer."""
        if segment.z_source == "posterior" and self.replay_buffer.context.size[segment.task] > 0:
            with th.no_grad():
                return self.sample_posterior(self._sample_context(np.array([segment.task]))).z[0]
        return th.randn(self.latent_dim, device=self.device)

    def collect_iteration(self, env: VecEnv, callback: BaseCallback, state: OpenIteration) -> bool:
        """
        Run the iteration's programs on the envs, each env one task at a time, until the iteration or the budget ends.

        The caller calls ``callback.on_rollout_start()`` before planning a new iteration (:meth:`_plan_iteration` draws
        from the global RNG), so that a checkpoint saved there resumes exactly; this ends with ``on_rollout_end()``.

        :param env: the model's envs
        :param callback: the callbacks of the running ``learn()``, called once per env step
        :param state: the iteration (updated in place: what is left of it, the steps collected)
        :return: whether training should go on (False: a callback asked to stop)
        """
        n_envs = env.num_envs
        obs = np.array(self._last_obs, dtype=np.float32)  # type: ignore[arg-type]
        z = th.as_tensor(state.z, device=self.device)
        returns = self._returns_horizon() is not None  # the prior-z rows get Monte-Carlo returns (sb3_pearl.pearl.returns)
        continue_training = True
        while True:
            for slot in range(n_envs):
                while state.remaining[slot] == 0 and (state.running[slot] or state.queue):
                    if not state.running[slot]:
                        state.running[slot] = state.queue.popleft()
                    segment = state.running[slot].popleft()
                    if segment.clear_context:
                        self.replay_buffer.context.clear(segment.task)
                    if segment.n_steps > 0:
                        self._start_segment(env, slot, segment, obs)
                        state.segments[slot] = segment
                        state.remaining[slot] = segment.n_steps
                        z[slot] = self._draw_z(segment)
                        if returns and segment.z_source == "prior":
                            start_piece(state, slot, segment.task)
            active = np.flatnonzero(state.remaining > 0)
            if len(active) == 0 or self.num_timesteps >= self._total_timesteps:
                break

            with th.no_grad():
                if returns:  # the same draws as act(), with the log-probabilities the returns need
                    actions_t, log_probs_t = self.policy.act_with_log_prob(th.as_tensor(obs, device=self.device), z)
                    log_probs = log_probs_t.cpu().numpy().astype(np.float64)  # (n_envs,)
                else:
                    actions_t = self.policy.act(th.as_tensor(obs, device=self.device), z)
                actions = actions_t.cpu().numpy()
            check_finite_actions(actions, self.num_timesteps, type(self).__name__)
            env_actions = actions if self.policy.discrete else self.policy.unscale_action(actions)
            new_obs, rewards, dones, infos = env.step(env_actions)
            # Divergence guard: a non-finite observation or reward is an error naming the env, task and timestep.
            check_env_step(env, new_obs, rewards, dones, infos, self.num_timesteps, type(self).__name__, active.tolist())

            for slot in active.tolist():
                current = state.segments[slot]
                assert current is not None
                next_obs = infos[slot]["terminal_observation"] if dones[slot] else new_obs[slot]  # type: ignore[call-overload,index]
                terminated = bool(dones[slot]) and not infos[slot].get("TimeLimit.truncated", False)
                transition = (current.task, obs[slot], actions[slot].reshape(-1), rewards[slot], next_obs, terminated)
                row = int(self.replay_buffer.rl.pos[current.task])
                if returns:
                    self._cut_before_overwrite(state, current.task, row)
                self.replay_buffer.rl.add(*transition, prior_z=current.z_source == "prior")
                if current.add_to_context:
                    self.replay_buffer.context.add(*transition)
                state.remaining[slot] -= 1
                if returns:
                    self._record_row(state, slot, row, float(log_probs[slot]), bool(dones[slot]), terminated)
                    if state.remaining[slot] == 0:  # the segment ends inside the trajectory: the next one resets the env
                        self._finish_open_pieces(state, [slot])
                if dones[slot]:
                    self._episode_num += 1
                    if state.remaining[slot] > 0:
                        z[slot] = self._draw_z(current)  # z is drawn once per trajectory
                        if returns and current.z_source == "prior":
                            start_piece(state, slot, current.task)
            state.collected += len(active)
            self.num_timesteps += len(active)
            self.num_vec_env_steps += 1
            self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)  # a learning-rate schedule's
            obs = np.array(new_obs, dtype=np.float32)
            self._update_info_buffer([infos[i] for i in active], dones[active])
            callback.update_locals(locals())
            if not callback.on_step():
                continue_training = False
                break
        self._last_obs = obs
        state.z = z.cpu().numpy()
        callback.on_rollout_end()
        return continue_training

    def _record_row(self, state: OpenIteration, slot: int, row: int, log_prob: float, done: bool, terminated: bool) -> None:
        """Env ``slot`` stored buffer ``row`` (its action's log-probability ``log_prob``) in its piece, which ends with its
        trajectory (``done``)."""
        piece = state.pieces[slot] if state.pieces is not None else None
        if piece is None:
            return
        piece.rows.append(row)
        piece.log_probs.append(log_prob)
        if done:
            self._finish_piece(piece, terminated)
            state.pieces[slot] = None  # type: ignore[index]

    def _cut_before_overwrite(self, state: OpenIteration, task: int, row: int) -> None:
        """
        The RL buffer is about to write ``row`` of ``task``: an open piece that holds it (as its oldest row, since the ring
        overwrites oldest first) is cut before it and goes on as a new piece. Its returns are written, then the overwritten
        row loses its own (:meth:`TaskReplayBuffer.add`).
        """
        for slot, piece in enumerate(state.pieces or ()):
            if piece is not None and piece.task == task and piece.rows and piece.rows[0] == row:
                self._finish_piece(piece, terminated=False)
                state.pieces[slot] = PendingPiece(piece.task)  # type: ignore[index]

    def _finish_open_pieces(self, state: OpenIteration, slots: list[int] | None = None) -> None:
        """
        Cut the pieces still open on ``slots`` (None: every env): a segment or the collection ended inside a trajectory,
        so their tails are bootstrapped.
        """
        for slot, piece in enumerate(state.pieces or ()):
            if piece is not None and (slots is None or slot in slots):
                self._finish_piece(piece, terminated=False)
                state.pieces[slot] = None  # type: ignore[index]

    def _finish_piece(self, piece: PendingPiece, terminated: bool) -> None:
        """The returns of the piece's rows, into the RL buffer (:meth:`TaskReplayBuffer.write_returns`)."""
        if not piece.rows:
            return
        buffer = self.replay_buffer.rl
        rows = np.asarray(piece.rows, dtype=np.int64)
        horizon = self._returns_horizon()
        assert horizon is not None, "pieces are opened only when returns are recorded"
        rewards, log_probs = buffer.rewards[piece.task, rows, 0], np.asarray(piece.log_probs)
        returns = piece_returns(rewards, log_probs, self.gamma, terminated, horizon)
        buffer.write_returns(piece.task, rows, returns.reward_sum, returns.log_prob_sum, returns.discount, rows[returns.tail])

    # ------------------------------------------------------------------------------------------
    # Adaptation API (meta-test): task inference from the transitions observed on a new task
    # ------------------------------------------------------------------------------------------
    def reset_adaptation(self) -> None:
        """Forget the observed context and draw z from the prior, held until :meth:`adapt` (k = 0)."""
        self._adapt_context = []
        self.policy.current_z = th.randn(self.latent_dim, device=self.device)

    def resample_prior(self) -> None:
        """A fresh z from the prior, the context kept (the reference's exploration trajectories, each with its own z)."""
        self.policy.current_z = th.randn(self.latent_dim, device=self.device)

    def observe(self, obs: np.ndarray, action: Any, reward: float, next_obs: np.ndarray, done: bool) -> None:
        """
        Record one transition of the new task (env-space action, as returned by :meth:`predict`).

        :param obs: observation before the action, shape (obs_dim,)
        :param action: the action taken (env units for Box, an index for Discrete)
        :param reward: reward received
        :param next_obs: observation after the action
        :param done: whether the episode ended (not used by the encoder)
        """
        obs, next_obs = check_observed_transition(self.observation_space, obs, reward, next_obs)  # (obs_dim,) each
        self._adapt_context.append(
            (obs, stored_action(self.action_space, action), float(np.asarray(reward).reshape(-1)[0]), next_obs)
        )

    def _adaptation_context(self) -> th.Tensor:
        """Everything observed since the last reset as one task's context, (1, N, context_dim)."""
        obs, actions, rewards, next_obs = (np.stack(column) for column in zip(*self._adapt_context))
        tensors = [
            th.as_tensor(a, device=self.device, dtype=th.float32)[None] for a in (obs, actions, rewards[:, None], next_obs)
        ]
        return self.policy.make_context(*tensors)

    def infer_posterior(self) -> tuple[th.Tensor, th.Tensor]:
        """Posterior mean and variance (each (latent_dim,)) from everything observed since the last reset."""
        if not self._adapt_context:
            return th.zeros(self.latent_dim, device=self.device), th.ones(self.latent_dim, device=self.device)
        with th.no_grad():
            posterior = self.sample_posterior(self._adaptation_context(), sample=False)
        return posterior.mean[0], posterior.var[0]

    def adapt(self, sample_z: bool = True) -> None:
        """
        Infer the posterior from all observed transitions and act with a new z from it.

        :param sample_z: draw z from the posterior (the reference's meta-test) or use its mean
        """
        if not self._adapt_context:  # nothing observed: a new draw from the prior
            self.policy.current_z = (
                th.randn(self.latent_dim, device=self.device) if sample_z else th.zeros(self.latent_dim, device=self.device)
            )
            return
        with th.no_grad():
            self.policy.current_z = self.sample_posterior(self._adaptation_context(), sample=sample_z).z[0]

    # ------------------------------------------------------------------------------------------
    # Save / load
    # ------------------------------------------------------------------------------------------
    def _excluded_save_params(self) -> list[str]:
        unsaved = ["_adapt_context", "_update_guard", "_bf16_enabled", "gradient_step_callback", "_learn_callback"]
        return [*super()._excluded_save_params(), *self.networks, *unsaved]

    def set_parameters(
        self,
        load_path_or_dict: str | dict[str, th.Tensor],
        exact_match: bool = True,
        device: th.device | str = "auto",
    ) -> None:
        """
        SB3's ``set_parameters``; the optimizers then step in the form they were built with (fused Adam), whatever
        the saved states say (a model saved before the optimizers were fused restores ``fused=None``).

        :param load_path_or_dict: a saved zip or a dict of state dicts
        :param exact_match: every network must be in the dict
        :param device: the device to load the parameters on
        """
        super().set_parameters(load_path_or_dict, exact_match, device)
        self.policy.restore_fused_optimizers()

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", *(f"{name}.optimizer" for name in self._optimized_networks())]
        if self.ent_coef_optimizer is not None:
            return [*state_dicts, "ent_coef_optimizer"], ["log_ent_coef"]
        return state_dicts, ["ent_coef_tensor"]

    def _optimized_networks(self) -> list[str]:
        """The networks with an optimizer of their own (saved with the model), in the policy's order."""
        return ["encoder", "actor", "critic"]

    @classmethod
    def _check_saved_arguments(cls, saved: Mapping[str, Any]) -> None:
        """
        The constructor's checks (:func:`~sb3_pearl.pearl.arguments.check_pearl_arguments`) on a loaded model's
        hyperparameters (``latent_dim`` and ``encoder_arch`` are kept in ``policy_kwargs``).

        :param saved: the attributes by name
        """
        policy_kwargs = saved.get("policy_kwargs")
        policy_kwargs = policy_kwargs if isinstance(policy_kwargs, dict) else {}
        derived = {key: policy_kwargs[key] for key in ("latent_dim", "encoder_arch") if key in policy_kwargs}
        check_pearl_arguments(saved_arguments(PEARL.__init__, saved, **derived))

    def save_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase) -> None:
        """
        Save the per-task RL and context buffers, atomically, with the training tasks recorded in them
        (:func:`~sb3_pearl.common.persistence.save_replay_buffer_file`).

        :param path: the pickle (``.pkl`` is appended when the path has no suffix, as in SB3) or an open binary file
        """
        save_replay_buffer_file(self.replay_buffer, self.train_tasks, path, self.verbose)

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """
        Load the per-task RL and context buffers saved by ``save_replay_buffer``.

        :param path: the pickle
        :param truncate_last_traj: unused (SB3's option for ``HerReplayBuffer``)
        """
        buffer = read_replay_buffer(path, self.verbose, type(self).__name__)
        if isinstance(buffer, ReplayBuffer) or not isinstance(buffer, MetaReplayBuffer):
            raise ValueError(
                f"{path} does not hold a MetaReplayBuffer (per-task buffers saved by PEARL / PEARL+ save_replay_buffer)"
            )
        if buffer.n_tasks != len(self.train_tasks):
            raise ValueError(
                f"{path} holds the per-task buffers of {buffer.n_tasks} training tasks but this model has "
                f"{len(self.train_tasks)}: load the replay buffer saved with this model, or construct the model with "
                f"n_train_tasks={buffer.n_tasks} and the buffer's tasks (train_tasks=...)"
            )
        check_buffer_tasks(buffer, self.train_tasks, path)
        self.replay_buffer = buffer
