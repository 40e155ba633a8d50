"""Fine-Tune: the paper's baseline without task inference (docs/references.md, "Baselines").

Meta-training trains one soft actor-critic policy on the mixture of the training tasks (a
uniformly drawn training task per episode). At meta-test the policy is fine-tuned on the new
task's own data: after each trajectory, ``adapt_gradient_steps`` soft actor-critic steps on a
fresh per-task replay buffer, starting from the weights fine-tuned so far (the pretrained ones
after :meth:`FineTune.reset_adaptation`).
"""

from __future__ import annotations

import copy
import io
import math
import pathlib
import pickle
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any, ClassVar, TypeVar

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, TrainFrequencyUnit
from stable_baselines3.common.utils import ConstantSchedule, get_parameters_by_name
from stable_baselines3.sac.policies import SACPolicy

from sb3_pearl.common.adaptation import stored_action
from sb3_pearl.common.checks import check_int, check_real
from sb3_pearl.common.divergence import check_env_step
from sb3_pearl.common.meta_algorithm import (
    MetaAlgorithm,
    check_observed_transition,
    check_task_arguments,
    forwards_arguments_to,
)
from sb3_pearl.common.persistence import (
    IncompleteReplayBufferError,
    check_buffer_tasks,
    expand_buffer,
    refuse_model_zip,
    save_replay_buffer_file,
    saved_arguments,
)
from sb3_pearl.common.tasks import env_time_limit, set_vec_env_task
from sb3_pearl.common.type_aliases import TrainingPlan
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.finetune.discrete_sac import DiscreteSAC, DiscreteSACPolicy, check_sac_arguments

SelfFineTune = TypeVar("SelfFineTune", bound="FineTune")

# Attributes that the adaptation gradient steps swap in, so that the soft actor-critic step of
# training (``train``) runs unchanged on the fine-tuned copy and the new task's buffer.
_ADAPTATION_STATE = ("policy", "log_ent_coef", "ent_coef_optimizer", "replay_buffer", "lr_schedule", "_n_updates", "_logger")


def check_finetune_arguments(arguments: Mapping[str, Any]) -> None:
    """
    Raise a ValueError for the first argument of :class:`FineTune` (its own; SAC's are
    :func:`~sb3_pearl.finetune.discrete_sac.check_sac_arguments`) out of its range (see its docstring).

    Called at the top of ``FineTune.__init__`` with its bound arguments (``locals()``), and by ``load`` on a loaded
    model's settings.

    :param arguments: ``FineTune.__init__``'s arguments by name, defaults included
    """
    args = arguments
    check_task_arguments(args["n_train_tasks"], args["n_test_tasks"], args["train_tasks"], args["test_tasks"])
    check_int("adapt_gradient_steps", args["adapt_gradient_steps"], 0, hint="gradient steps per adapt() call")
    if args["adapt_batch_size"] is not None:
        check_int("adapt_batch_size", args["adapt_batch_size"], 1, hint="or None: batch_size")
    if args["adapt_learning_rate"] is not None:
        check_real("adapt_learning_rate", args["adapt_learning_rate"], 0.0, hint="or None: the meta-training learning rate")
    check_int("adapt_buffer_size", args["adapt_buffer_size"], 1, hint="capacity of the new task's replay buffer")
    if args["max_episode_steps"] is not None:
        check_int("max_episode_steps", args["max_episode_steps"], 1, hint="or None: the env's registered time limit")


@forwards_arguments_to(DiscreteSAC)
class FineTune(MetaAlgorithm, DiscreteSAC):
    """
    Fine-Tune baseline: SAC trained on the mixture of the training tasks, fine-tuned on a new task.

    Meta-training (``learn``) is SB3's SAC (Haarnoja et al. 2018, arXiv:1801.01290; Box actions) or the project's
    soft discrete SAC (Discrete actions, :class:`~sb3_pearl.finetune.discrete_sac.DiscreteSAC`) with one change:
    every episode of every env runs a training task drawn uniformly from :attr:`train_tasks`. The
    policy sees no task information (no task inference).

    Adaptation API (shared with PEARL / PEARL+ / MAML, ``docs/design.md``):

    - :meth:`reset_adaptation`: drop the fine-tuned copy and the new task's buffer; :meth:`predict`
      acts with the pretrained policy again (k = 0);
    - :meth:`observe`: store one transition of the new task in its own (fresh) replay buffer;
    - :meth:`adapt`: ``adapt_gradient_steps`` soft actor-critic steps on that buffer only, on a copy
      of the networks, optimizers and entropy coefficient that starts from the pretrained ones and
      carries over between calls (fine-tuning continues from the weights fine-tuned so far);
    - :meth:`predict`: acts with the fine-tuned copy if there is one, else the pretrained policy.

    The pretrained model itself is never modified by adaptation, so ``save`` / ``learn`` always
    see the meta-trained weights.

    :param policy: ``"MlpPolicy"`` (SAC's MlpPolicy for Box, :class:`DiscreteSACPolicy` for Discrete) or a class
    :param env: an env id or env following the task protocol (``sample_tasks``, ``set_task``, ``get_task``)
    :param n_train_tasks: training tasks: the first ``n_train_tasks`` of ``env.sample_tasks(n_train_tasks +
        n_test_tasks, seed)`` (the same draw as PEARL / PEARL+ / MAML, so a seed gives every algorithm the same tasks)
    :param n_test_tasks: held-out test tasks: the rest of that draw
    :param train_tasks: explicit training tasks (overrides the draw)
    :param test_tasks: explicit test tasks (overrides the draw)
    :param max_episode_steps: the task family's episode length (``None``: the env's registered time limit);
        at adaptation, an episode that ends (``done``) at this length is a time-limit truncation and its last
        transition keeps its bootstrap, every other ``done`` is a terminal state
    :param adapt_gradient_steps: soft actor-critic gradient steps per :meth:`adapt` call (per new-task
        trajectory in the meta-test protocol); default 200 (docs/finetune.md: one gradient step per observed
        transition of a 200-step MuJoCo trajectory, SAC's update-to-data ratio of 1)
    :param adapt_batch_size: minibatch size of the adaptation steps (``None``: ``batch_size``), drawn with
        replacement from the new task's transitions
    :param adapt_learning_rate: learning rate of the adaptation steps (``None``: the initial learning rate of
        meta-training, ``lr_schedule(1)``)
    :param adapt_buffer_size: capacity of the new task's replay buffer (transitions)
    :param _init_setup_model: build the networks at construction
    :param kwargs: every other argument is SAC's, as :class:`~sb3_pearl.finetune.discrete_sac.DiscreteSAC` takes it
        (``learning_rate``, ``buffer_size``, ``batch_size``, ``gamma``, ``ent_coef``, ``policy_kwargs``, ``seed``, ...),
        passed by name, with SAC's defaults; meta-training uses them (``batch_size`` and ``buffer_size`` are
        meta-training's, all training tasks mixed)
    """

    # Read by the meta-test protocol (sb3_pearl.evaluation.meta_test): False keeps its deterministic
    # trajectories, as for PEARL / PEARL+. Fine-tuning learns from them, but after one deterministic
    # trajectory it is worse than k = 0 on the point robot, unlike after one stochastic trajectory
    # (docs/finetune.md, measurements).
    stochastic_adaptation: ClassVar[bool] = False
    # Parameters every Fine-Tune zip holds (load() refuses a zip without them, e.g. a SAC one).
    saved_data_keys: ClassVar[tuple[str, ...]] = ("adapt_gradient_steps", "adapt_buffer_size", "train_tasks")

    def __init__(
        self,
        policy: str | type[SACPolicy] | type[DiscreteSACPolicy],
        env: GymEnv | str,
        *,
        n_train_tasks: int = 100,
        n_test_tasks: int = 30,
        train_tasks: list[Task] | None = None,
        test_tasks: list[Task] | None = None,
        max_episode_steps: int | None = None,
        adapt_gradient_steps: int = 200,
        adapt_batch_size: int | None = None,
        adapt_learning_rate: float | None = None,
        adapt_buffer_size: int = 10_000,
        _init_setup_model: bool = True,
        **kwargs: Any,
    ):
        # Every argument checked before anything is built (docs/reliability.md); SAC's by DiscreteSAC.__init__.
        check_finetune_arguments(locals())
        super().__init__(policy, env, _init_setup_model=False, **kwargs)
        self._init_meta_algorithm(n_train_tasks, n_test_tasks, train_tasks, test_tasks)
        self.max_episode_steps = max_episode_steps
        self.adapt_gradient_steps = adapt_gradient_steps
        self.adapt_batch_size = adapt_batch_size
        self.adapt_learning_rate = adapt_learning_rate
        self.adapt_buffer_size = adapt_buffer_size
        # Adaptation state (meta-test), never saved: see reset_adaptation()
        self._adapted: dict[str, Any] | None = None
        self._adapt_buffer: ReplayBuffer | None = None
        self._adapt_episode_steps = 0
        self.adapt_stats: dict[str, float] = {}
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------------------------------
    # Set-up
    # ------------------------------------------------------------------------------------------
    def _setup_model(self) -> None:
        super()._setup_model()
        self._setup_tasks()
        if self.env is not None and self.max_episode_steps is None:
            self.max_episode_steps = env_time_limit(self.env)
        self.reset_adaptation()

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_adapted", "_adapt_buffer", "_adapt_episode_steps", "adapt_stats"]

    @classmethod
    def _check_saved_arguments(cls, saved: Mapping[str, Any]) -> None:
        """
        The constructor's checks on a loaded model's hyperparameters: SAC's (:func:`check_sac_arguments`) and
        Fine-Tune's own (:func:`check_finetune_arguments`); the oracle's too (a Fine-Tune without fine-tuning).

        :param saved: the attributes by name
        """
        check_sac_arguments(saved_arguments(DiscreteSAC.__init__, saved))
        check_finetune_arguments(saved_arguments(FineTune.__init__, saved))

    def save_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase) -> None:
        """
        SB3's ``save_replay_buffer``, atomic, with the training tasks recorded in the buffer
        (:func:`~sb3_pearl.common.persistence.save_replay_buffer_file`).

        :param path: the pickle (``.pkl`` is appended when the path has no suffix, as in SB3) or an open binary file
        """
        save_replay_buffer_file(self.replay_buffer, self.train_tasks, path, self.verbose)

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """
        SB3's ``load_replay_buffer``, refusing a model zip, a truncated pickle or a buffer collected on other training tasks.

        :param path: the pickle
        :param truncate_last_traj: SB3's option for ``HerReplayBuffer``
        """
        refuse_model_zip(path, type(self).__name__)
        previous = self.replay_buffer
        try:
            super().load_replay_buffer(path, truncate_last_traj)
        except (EOFError, pickle.UnpicklingError) as error:
            raise IncompleteReplayBufferError(path, error) from None
        expand_buffer(self.replay_buffer)
        try:
            check_buffer_tasks(self.replay_buffer, self.train_tasks, path)
        except ValueError:
            self.replay_buffer = previous
            raise

    # ------------------------------------------------------------------------------------------
    # Meta-training on the mixture of the training tasks
    # ------------------------------------------------------------------------------------------
    def _set_random_train_tasks(self, env_indices: Iterable[int]) -> None:
        """Give each env a training task drawn uniformly; it takes effect at that env's next reset."""
        assert self.env is not None
        for index in env_indices:
            task = self.train_tasks[np.random.randint(len(self.train_tasks))]
            set_vec_env_task(self.env, task, [int(index)])

    def _before_env_reset(self) -> None:
        """The tasks of the first episodes of a ``learn()`` (SB3's reset of the envs applies them)."""
        assert self.env is not None
        self._set_random_train_tasks(range(self.env.num_envs))

    def _after_env_reset(self) -> None:
        """``set_task`` is sticky until the next reset: keep one task pending per env."""
        assert self.env is not None
        self._set_random_train_tasks(range(self.env.num_envs))

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """
        Store the transitions (SB3), then draw the task of the episode *after* the one that has
        just started in every env whose episode ended.

        A VecEnv resets a finished env inside ``step`` and ``set_task`` takes effect at the next
        reset, so each env always holds one pending task: the auto-reset that ended an episode
        applied the task drawn at the previous episode end, and no transition ever runs on a task
        other than its episode's.
        """
        # Divergence guard: a non-finite observation or reward is an error naming the env, task and timestep.
        check_env_step(self.env, new_obs, reward, dones, infos, self.num_timesteps - self.n_envs, type(self).__name__)
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        finished = np.flatnonzero(dones)
        if len(finished) > 0:
            self._set_random_train_tasks(finished.tolist())

    def _on_step(self) -> None:
        """After each VecEnv step of SB3's collection: count it (:attr:`num_vec_env_steps`)."""
        super()._on_step()
        self.num_vec_env_steps += 1

    def learn(
        self: SelfFineTune,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "FineTune",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfFineTune:
        """
        Meta-train: SAC (or soft discrete SAC) on the mixture of the training tasks, one task per episode.

        :param total_timesteps: env steps to collect
        :param callback: SB3 callback(s), called once per env step
        :param log_interval: dump the logs every ``log_interval`` episodes
        :param tb_log_name: TensorBoard run name
        :param reset_num_timesteps: restart the step counter
        :param progress_bar: show a progress bar
        """
        self.reset_adaptation()  # learning always continues from the pretrained policy, never from a fine-tuned copy
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def training_plan(self, total_timesteps: int) -> TrainingPlan | None:
        """
        What ``learn(total_timesteps)`` will still collect and train (SB3's off-policy loop: after each rollout of
        ``train_freq`` steps per env, once past ``learning_starts``, ``gradient_steps`` steps); None for a
        ``train_freq`` counted in episodes.
        """
        if self.train_freq.unit != TrainFrequencyUnit.STEP:  # type: ignore[union-attr]
            return None
        remaining = max(total_timesteps - self.num_timesteps, 0)
        chunk = self.train_freq.frequency * self.n_envs  # type: ignore[union-attr]
        rollouts = math.ceil(remaining / chunk)
        first_training = max(self.learning_starts - self.num_timesteps, 0) // chunk  # the first rollout followed by train()
        per_rollout = self.gradient_steps if self.gradient_steps >= 0 else chunk
        updates = max(rollouts - first_training, 0) * per_rollout
        initial = min(max(self.learning_starts - self.num_timesteps, 0), remaining)
        note = f"learning_starts {self.learning_starts:,}" if initial > 0 else ""
        return TrainingPlan(remaining, updates, initial, first_updates=min(1000, updates), note=note)

    # ------------------------------------------------------------------------------------------
    # Adaptation API (shared by every algorithm of the project; SB3's predict never sees rewards)
    # ------------------------------------------------------------------------------------------
    def reset_adaptation(self) -> None:
        """Forget the current task: drop the fine-tuned copy and start a fresh buffer (k = 0: pretrained policy)."""
        self._adapted = None
        self._adapt_buffer = ReplayBuffer(
            self.adapt_buffer_size,
            self.observation_space,
            self.action_space,
            device=self.device,
            n_envs=1,
            handle_timeout_termination=True,
        )
        self._adapt_episode_steps = 0
        self.adapt_stats = {}

    @property
    def n_observed(self) -> int:
        """Transitions of the current task observed since :meth:`reset_adaptation`."""
        return 0 if self._adapt_buffer is None else self._adapt_buffer.size()

    @property
    def adapted_policy(self) -> BasePolicy:
        """The policy :meth:`predict` acts with: the fine-tuned copy, or the pretrained policy before any adaptation."""
        return self.policy if self._adapted is None else self._adapted["policy"]

    def observe(
        self, obs: np.ndarray, action: Any, reward: float, next_obs: np.ndarray, done: bool, truncated: bool | None = None
    ) -> None:
        """
        Record one transition of the new task in its own replay buffer.

        :param obs: observation before the action
        :param action: the action sent to the env (env units for Box, an index for Discrete), as from :meth:`predict`
        :param reward: reward received
        :param next_obs: observation after the action (the terminal observation when ``done``)
        :param done: the episode ended (terminated or truncated)
        :param truncated: whether an ending step was a cut (time limit, step cap: bootstrapped) rather than a terminal
            state; the meta-test passes it. ``None`` (the adaptation API's five arguments): an end at
            ``max_episode_steps`` steps is taken as a time-limit truncation, any other as a terminal state, which
            mistakes a terminal state at the time limit's step (Highway-Merge's failure to merge) for a cut
        """
        obs_arr, next_obs_arr = check_observed_transition(self.observation_space, obs, reward, next_obs)
        if self._adapt_buffer is None:
            self.reset_adaptation()
        assert self._adapt_buffer is not None
        obs_shape = obs_arr.shape
        buffer_action = stored_action(self.action_space, action).reshape(1, -1)
        self._adapt_episode_steps += 1
        done = bool(np.asarray(done).reshape(-1)[0])
        if truncated is None:
            truncated = self.max_episode_steps is not None and self._adapt_episode_steps >= self.max_episode_steps
        truncated = done and bool(truncated)
        self._adapt_buffer.add(
            obs_arr.reshape(1, *obs_shape),
            next_obs_arr.reshape(1, *obs_shape),
            buffer_action,
            np.array([float(np.asarray(reward).reshape(-1)[0])], dtype=np.float32),
            np.array([done]),
            [{"TimeLimit.truncated": truncated}],
        )
        if done:
            self._adapt_episode_steps = 0

    def adapt(self) -> None:
        """
        Fine-tune on the new task: ``adapt_gradient_steps`` soft actor-critic steps on its observed transitions.

        The first call after :meth:`reset_adaptation` copies the pretrained networks, optimizers and entropy
        coefficient; later calls continue from the copy. With nothing observed the policy stays as it is.
        The losses of the last call are in :attr:`adapt_stats` (``critic_loss``, ``actor_loss``, ``ent_coef``, ...).
        """
        if self.n_observed == 0 or self.adapt_gradient_steps == 0:
            return
        if self._adapted is None:
            self._adapted = self._copy_pretrained()
        with self._adaptation_state():
            self.train(gradient_steps=self.adapt_gradient_steps, batch_size=self.adapt_batch_size or self.batch_size)
            assert self._logger is not None
            self.adapt_stats = {key.split("/", 1)[-1]: float(v) for key, v in self._logger.name_to_value.items()}

    def _copy_pretrained(self) -> dict[str, Any]:
        """The adaptation state at k = 0: copies of the pretrained policy (with its optimizers) and entropy coefficient."""
        # One deepcopy, so that the copied optimizers refer to the copied parameters.
        policy, log_ent_coef, ent_coef_optimizer = copy.deepcopy((self.policy, self.log_ent_coef, self.ent_coef_optimizer))
        lr = self.adapt_learning_rate if self.adapt_learning_rate is not None else float(self.lr_schedule(1.0))
        return dict(
            policy=policy,
            log_ent_coef=log_ent_coef,
            ent_coef_optimizer=ent_coef_optimizer,
            replay_buffer=self._adapt_buffer,
            lr_schedule=ConstantSchedule(lr),
            _n_updates=0,
            _logger=Logger(folder=None, output_formats=[]),
        )

    @contextmanager
    def _adaptation_state(self) -> Iterator[None]:
        """Swap the fine-tuned copy and the new task's buffer in, so that ``train`` runs unchanged on them."""
        assert self._adapted is not None
        adapted = self._adapted
        missing = object()  # _logger does not exist before the first learn() / set_logger()
        pretrained = {name: getattr(self, name, missing) for name in _ADAPTATION_STATE}
        adapted["replay_buffer"] = self._adapt_buffer
        adapted["_logger"].name_to_value.clear()
        adapted["_logger"].name_to_count.clear()
        try:
            for name in _ADAPTATION_STATE:
                setattr(self, name, adapted[name])
            self._refresh_aliases()
            yield
        finally:
            for name in _ADAPTATION_STATE:
                adapted[name] = getattr(self, name)
                if pretrained[name] is missing:
                    delattr(self, name)
                else:
                    setattr(self, name, pretrained[name])
            self._refresh_aliases()

    def _refresh_aliases(self) -> None:
        self._create_aliases()
        self.batch_norm_stats = get_parameters_by_name(self.critic, ["running_"])
        self.batch_norm_stats_target = get_parameters_by_name(self.critic_target, ["running_"])
