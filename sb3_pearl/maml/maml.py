"""MAML-TRPO (Finn et al. 2017, "Model-Agnostic Meta-Learning for Fast Adaptation of Deep Networks").

One meta-iteration:

1. draw ``meta_batch_size`` training tasks;
2. roll out ``episodes_per_task`` trajectories per task with the meta-parameters ``theta`` (pre-adaptation);
3. per task, ``num_inner_steps`` vanilla policy-gradient steps from ``theta`` on those trajectories
   (advantages: GAE over a linear feature baseline fitted by least squares), giving ``theta'_i``;
4. roll out ``episodes_per_task`` trajectories per task with ``theta'_i`` (post-adaptation);
5. one TRPO step on ``theta`` for the surrogate of the post-adaptation data, where ``theta'_i`` is
   recomputed from ``theta`` (so the meta-gradient flows through the inner step: second order unless
   ``first_order=True``): conjugate gradient on Fisher-vector products of the mean KL, a step scaled
   to the KL bound, and a backtracking line search that re-adapts every candidate and accepts it
   only when the surrogate improves and the KL stays within ``max_kl``.

The adaptation API shared by every algorithm of the project (``reset_adaptation``, ``observe``,
``adapt``, ``predict``) runs step 3 on the trajectories seen on a new task.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping
from functools import partial
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.utils import safe_mean
from torch.nn.utils import parameters_to_vector

from sb3_pearl.common.checks import check_arch, check_gamma, check_int, check_real
from sb3_pearl.common.divergence import check_env_step
from sb3_pearl.common.meta_algorithm import MetaAlgorithm, check_observed_transition, check_task_arguments
from sb3_pearl.common.persistence import saved_arguments
from sb3_pearl.common.tasks import env_time_limit, set_vec_env_task
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.maml.advantages import compute_advantages, split_task_samples
from sb3_pearl.maml.policies import MAMLPolicy, MlpPolicy, Params
from sb3_pearl.maml.sampling import (
    Episode,
    act_store_dim,
    env_actions,
    episodes_to_batch,
    observed_action,
    pick_task,
    reset_one,
)
from sb3_pearl.maml.trpo import conjugate_gradient, fisher_vector_product, line_search
from sb3_pearl.maml.type_aliases import EpisodeBatch, OldPolicy, TaskSamples, TRPOInfo

SelfMAML = TypeVar("SelfMAML", bound="MAML")


def check_maml_arguments(arguments: Mapping[str, Any]) -> None:
    """
    Raise a ValueError for the first argument of :class:`MAML` out of its range (see its docstring).

    Called at the top of ``MAML.__init__`` with its bound arguments (``locals()``), and by ``load`` on a loaded model's
    settings.

    :param arguments: ``MAML.__init__``'s arguments by name, defaults included
    """
    args = arguments
    check_real("inner_lr", args["inner_lr"], 0.0, hint="step size of the inner policy-gradient update, e.g. 0.1")
    check_int("num_inner_steps", args["num_inner_steps"], 1, hint="inner updates per task")
    check_int("meta_batch_size", args["meta_batch_size"], 1, hint="tasks per meta-iteration")
    check_int("episodes_per_task", args["episodes_per_task"], 1, hint="trajectories per task before and after adaptation")
    check_task_arguments(args["n_train_tasks"], args["n_test_tasks"], args["train_tasks"], args["test_tasks"])
    if args["max_episode_steps"] is not None:
        check_int("max_episode_steps", args["max_episode_steps"], 1, hint="or None: the env's registered time limit")
    check_gamma(args["gamma"])
    check_real("gae_lambda", args["gae_lambda"], 0.0, 1.0, hint="GAE lambda; 1: Monte-Carlo returns minus the baseline")
    check_real("baseline_reg", args["baseline_reg"], 0.0, hint="ridge coefficient of the linear baseline")
    check_real("max_kl", args["max_kl"], 0.0, low_open=True, hint="KL bound of the TRPO step, e.g. 0.01")
    check_int("cg_iters", args["cg_iters"], 1, hint="conjugate-gradient iterations")
    check_real("cg_damping", args["cg_damping"], 0.0, hint="damping of the Fisher-vector products")
    check_real("ls_backtrack_ratio", args["ls_backtrack_ratio"], 0.0, 1.0, low_open=True, high_open=True, hint="e.g. 0.8")
    check_int("ls_max_steps", args["ls_max_steps"], 1, hint="line-search candidates")
    check_arch("policy_kwargs['net_arch']", (args["policy_kwargs"] or {}).get("net_arch"))


class MAML(MetaAlgorithm):
    """
    MAML-TRPO: Model-Agnostic Meta-Learning with a TRPO outer loop (Finn et al. 2017).
    Paper: arXiv:1703.03400 (https://arxiv.org/abs/1703.03400)

    The env must follow the task protocol of ``sb3_pearl.envs`` (``sample_tasks``, ``set_task``,
    ``get_task``); each env of the VecEnv runs one task at a time.

    :param policy: the policy, ``"MlpPolicy"`` or a :class:`MAMLPolicy` subclass
    :param env: the task-family env (id, gymnasium env or VecEnv; ``SubprocVecEnv`` works)
    :param inner_lr: step size of the inner vanilla policy-gradient update(s)
    :param num_inner_steps: number of inner updates per task (all on the same pre-adaptation trajectories)
    :param first_order: drop the second-order term (treat the inner gradient as a constant)
    :param meta_batch_size: tasks per meta-iteration
    :param episodes_per_task: trajectories per task, both before and after adaptation
    :param max_episode_steps: episode length; ``None`` uses the env's registered time limit
    :param n_train_tasks: training tasks: the first ``n_train_tasks`` of ``env.sample_tasks(n_train_tasks +
        n_test_tasks, seed)`` (the same draw as PEARL / PEARL+, so a seed gives every algorithm the same tasks)
    :param n_test_tasks: held-out test tasks: the rest of that draw
    :param train_tasks: explicit training tasks (overrides the draw)
    :param test_tasks: explicit test tasks (overrides the draw)
    :param gamma: discount factor
    :param gae_lambda: GAE lambda (1: Monte-Carlo returns minus the baseline)
    :param normalize_advantage: standardise the advantages per task (inner and outer losses)
    :param baseline_reg: ridge coefficient of the linear feature baseline's least-squares fit
    :param max_kl: KL bound of the TRPO step (mean over tasks of the mean per-state KL)
    :param cg_iters: conjugate-gradient iterations
    :param cg_damping: damping added to the Fisher-vector products
    :param ls_backtrack_ratio: shrink factor of the backtracking line search
    :param ls_max_steps: maximum number of line-search candidates
    :param policy_kwargs: keyword arguments for the policy (``net_arch``, ``activation_fn``, ``log_std_init``)
    :param stats_window_size: window (episodes) of the rollout statistics in the logs
    :param tensorboard_log: TensorBoard log directory
    :param seed: random seed (also seeds the train/test task lists)
    :param verbose: 0 silent, 1 info, 2 debug
    :param device: torch device (``"cpu"`` is the sensible choice for these small networks)
    :param _init_setup_model: build the networks at construction
    """

    # The meta-test protocol rolls MAML out with the stochastic policy: its inner policy-gradient
    # step needs on-policy samples (deterministic trajectories would give it no gradient).
    stochastic_adaptation: ClassVar[bool] = True
    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MlpPolicy}
    # Parameters every MAML zip holds (load() refuses a zip without them).
    saved_data_keys: ClassVar[tuple[str, ...]] = ("inner_lr", "meta_batch_size", "num_inner_steps", "train_tasks")
    policy: MAMLPolicy

    def __init__(
        self,
        policy: str | type[MAMLPolicy],
        env: GymEnv | str | None,
        inner_lr: float = 0.1,
        num_inner_steps: int = 1,
        first_order: bool = False,
        meta_batch_size: int = 40,
        episodes_per_task: int = 20,
        max_episode_steps: int | None = None,
        n_train_tasks: int = 100,
        n_test_tasks: int = 30,
        train_tasks: list[Task] | None = None,
        test_tasks: list[Task] | None = None,
        gamma: float = 0.99,
        gae_lambda: float = 1.0,
        normalize_advantage: bool = True,
        baseline_reg: float = 1e-5,
        max_kl: float = 1e-2,
        cg_iters: int = 10,
        cg_damping: float = 1e-5,
        ls_backtrack_ratio: float = 0.8,
        ls_max_steps: int = 15,
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        seed: int | None = None,
        verbose: int = 0,
        device: th.device | str = "cpu",
        _init_setup_model: bool = True,
    ) -> None:
        # Every argument checked before anything is built (docs/reliability.md).
        check_maml_arguments(locals())
        super().__init__(
            policy,
            env,
            learning_rate=inner_lr,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            seed=seed,
        )
        self._init_meta_algorithm(n_train_tasks, n_test_tasks, train_tasks, test_tasks)
        self.inner_lr = inner_lr
        self.num_inner_steps = num_inner_steps
        self.first_order = first_order
        self.meta_batch_size = meta_batch_size
        self.episodes_per_task = episodes_per_task
        self.max_episode_steps = max_episode_steps
        self.gamma = gamma
        self.gae_lambda = gae_lambda
        self.normalize_advantage = normalize_advantage
        self.baseline_reg = baseline_reg
        self.max_kl = max_kl
        self.cg_iters = cg_iters
        self.cg_damping = cg_damping
        self.ls_backtrack_ratio = ls_backtrack_ratio
        self.ls_max_steps = ls_max_steps
        self._task_rng: np.random.Generator | None = None
        # Adaptation state (meta-test): never saved
        self._adapt_episodes: list[Episode] = []
        self._current_episode: Episode = ([], [], [])
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------------------------------
    # set-up
    # ------------------------------------------------------------------------------------------
    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        self.policy = self.policy_class(self.observation_space, self.action_space, **self.policy_kwargs)  # type: ignore[assignment]
        self.policy = self.policy.to(self.device)
        if not isinstance(self.policy, MAMLPolicy):
            raise ValueError(f"MAML needs a MAMLPolicy, got {type(self.policy).__name__}")
        if self._task_rng is None:
            self._task_rng = np.random.default_rng(self.seed)
        if self.env is not None and self.max_episode_steps is None:
            limit = env_time_limit(self.env)
            if limit is None:
                raise ValueError("The env has no registered time limit: pass max_episode_steps to MAML")
            self.max_episode_steps = limit
        self._setup_tasks()
        self.reset_adaptation()

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_adapt_episodes", "_current_episode"]

    @classmethod
    def _check_saved_arguments(cls, saved: Mapping[str, Any]) -> None:
        """
        The constructor's checks (:func:`check_maml_arguments`) on a loaded model's hyperparameters.

        :param saved: the attributes by name
        """
        check_maml_arguments(saved_arguments(MAML.__init__, saved))

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy"], []

    # ------------------------------------------------------------------------------------------
    # sampling and advantages (sampling.py, advantages.py)
    # ------------------------------------------------------------------------------------------
    def _collect_episodes(
        self, tasks: list[Task], params: Params | None, callback: BaseCallback | None = None
    ) -> tuple[EpisodeBatch, bool]:
        """
        Roll out ``episodes_per_task`` trajectories on each task, spreading them over the envs.

        Each env keeps running episodes of its current task (the task sticks across auto-resets) and
        switches (``set_task`` then an explicit reset) only when that task has no episode left
        (see :func:`sb3_pearl.maml.sampling.pick_task`). Adds the env steps taken to ``num_timesteps``.

        :param tasks: the ``T`` tasks
        :param params: per-task parameters (every tensor with leading dimension ``T``), or None for ``theta``
        :param callback: called once per VecEnv step; None during tests
        :return: the padded episodes and whether training should continue (callback result)
        """
        assert self.env is not None and self.max_episode_steps is not None
        env = self.env
        policy = self.policy
        n_envs = env.num_envs
        n_tasks, n_eps, horizon = len(tasks), self.episodes_per_task, self.max_episode_steps
        obs_dim = policy.obs_dim
        observations = np.zeros((n_tasks, n_eps, horizon, obs_dim), dtype=np.float32)
        actions = np.zeros((n_tasks, n_eps, horizon, act_store_dim(policy)), dtype=np.float32)
        rewards = np.zeros((n_tasks, n_eps, horizon), dtype=np.float32)
        lengths = np.zeros((n_tasks, n_eps), dtype=np.int64)

        next_episode = np.zeros(n_tasks, dtype=np.int64)  # next unassigned episode of each task
        env_slot: list[tuple[int, int] | None] = [None] * n_envs  # (task, episode) run by each env
        env_t = np.zeros(n_envs, dtype=np.int64)

        # Initial assignment: one task per env, applied by a reset of all envs.
        for i in range(n_envs):
            task_idx = pick_task(None, next_episode, n_eps, env_slot)
            if task_idx is None:
                break
            env_slot[i] = (task_idx, int(next_episode[task_idx]))
            next_episode[task_idx] += 1
            set_vec_env_task(env, tasks[task_idx], [i])
        obs = np.asarray(env.reset(), dtype=np.float32).reshape(n_envs, obs_dim)

        continue_training = True
        while any(slot is not None for slot in env_slot):
            active = [i for i in range(n_envs) if env_slot[i] is not None]
            with th.no_grad():
                obs_t = th.as_tensor(obs, device=self.device)
                if params is None:
                    raw = policy.sample(obs_t)
                else:
                    task_of_env = th.as_tensor([slot[0] if slot is not None else 0 for slot in env_slot], device=self.device)
                    env_params = {name: value[task_of_env] for name, value in params.items()}
                    raw = policy.batched_distribution(obs_t.unsqueeze(1), env_params).sample().squeeze(1)
            new_obs, step_rewards, dones, infos = env.step(env_actions(policy, raw))
            # Divergence guard: a non-finite observation or reward is an error naming the env, task and timestep.
            check_env_step(env, new_obs, step_rewards, dones, infos, self.num_timesteps, type(self).__name__, active)
            new_obs = np.asarray(new_obs, dtype=np.float32).reshape(n_envs, obs_dim)
            raw_np = raw.cpu().numpy().reshape(n_envs, -1)

            for i in active:
                slot = env_slot[i]
                assert slot is not None
                task_idx, ep_idx = slot
                t = env_t[i]
                observations[task_idx, ep_idx, t] = obs[i]
                actions[task_idx, ep_idx, t] = raw_np[i]
                rewards[task_idx, ep_idx, t] = step_rewards[i]
                env_t[i] += 1
                if not (dones[i] or env_t[i] >= horizon):
                    continue
                lengths[task_idx, ep_idx] = env_t[i]
                env_t[i] = 0
                next_task = pick_task(task_idx, next_episode, n_eps, env_slot)
                if next_task is None:
                    env_slot[i] = None
                    continue
                env_slot[i] = (next_task, int(next_episode[next_task]))
                next_episode[next_task] += 1
                if next_task != task_idx:
                    set_vec_env_task(env, tasks[next_task], [i])
                    new_obs[i] = reset_one(env, i)
                elif not dones[i]:  # cut at max_episode_steps before the env's own limit
                    new_obs[i] = reset_one(env, i)
                # else: the VecEnv auto-reset already started a new episode of the same (sticky) task
            obs = new_obs

            self.num_timesteps += len(active)
            self.num_vec_env_steps += 1
            if callback is not None:
                callback.update_locals(locals())
                if not callback.on_step():
                    continue_training = False
                    break
        return EpisodeBatch(observations, actions, rewards, lengths), continue_training

    def compute_advantages(self, batch: EpisodeBatch) -> th.Tensor:
        """
        GAE advantages over the linear feature baseline with this model's settings
        (see :func:`sb3_pearl.maml.advantages.compute_advantages`).

        :param batch: the episodes
        :return: advantages, shape ``(T, E, H)``, 0 after the end of each episode; standardised per task
            over its valid steps if ``normalize_advantage``
        """
        return compute_advantages(
            batch,
            self.gamma,
            self.gae_lambda,
            self.baseline_reg,
            self.normalize_advantage,
            self.max_episode_steps,
            self.device,
        )

    def _task_samples(self, batch: EpisodeBatch) -> list[TaskSamples]:
        """Advantages for ``batch`` and the valid steps of each task as tensors."""
        return split_task_samples(batch, self.compute_advantages(batch), self.policy, self.device)

    # ------------------------------------------------------------------------------------------
    # inner loop
    # ------------------------------------------------------------------------------------------
    def inner_loss(self, params: Params, samples: TaskSamples) -> th.Tensor:
        """Vanilla policy-gradient loss ``-mean_t log pi(a_t|s_t) A_t`` of one task under ``params``."""
        log_prob = self.policy.log_prob(samples.observations, samples.actions, params)  # (N,)
        return -(log_prob * samples.advantages).mean()

    def adapt_params(self, params: Params, samples: TaskSamples, create_graph: bool | None = None) -> Params:
        """
        ``num_inner_steps`` gradient steps of :meth:`inner_loss` from ``params``.

        :param params: starting parameters (must require grad)
        :param samples: the task's pre-adaptation steps
        :param create_graph: keep the graph of the inner gradient (second-order meta-gradient);
            defaults to ``not first_order``
        :return: the adapted parameters (functions of ``params``)
        """
        if create_graph is None:
            create_graph = not self.first_order
        for _ in range(self.num_inner_steps):
            loss = self.inner_loss(params, samples)
            grads = th.autograd.grad(loss, list(params.values()), create_graph=create_graph)
            params = {name: value - self.inner_lr * grad for (name, value), grad in zip(params.items(), grads, strict=True)}
        return params

    def _adapt_all(self, samples: list[TaskSamples]) -> Params:
        """Adapted parameters of every task (detached), stacked along a leading task dimension."""
        base = {name: p.detach().requires_grad_(True) for name, p in self.policy.meta_parameters().items()}
        with th.enable_grad():
            adapted = [self.adapt_params(base, task, create_graph=False) for task in samples]
        return {name: th.stack([a[name].detach() for a in adapted]) for name in base}

    # ------------------------------------------------------------------------------------------
    # outer loop (TRPO)
    # ------------------------------------------------------------------------------------------
    def _old_policies(self, pre: list[TaskSamples], post: list[TaskSamples]) -> list[OldPolicy]:
        """The sampling policies of the post-adaptation data, detached."""
        adapted = self._adapt_all(pre)
        old = []
        with th.no_grad():
            for j, task in enumerate(post):
                dist = self.policy.distribution(task.observations, {name: value[j] for name, value in adapted.items()})
                actions = task.actions if self.policy.continuous else task.actions.long()
                old.append(OldPolicy(dist.log_prob(actions), dist))
        return old

    def meta_objective(
        self,
        params: Params,
        pre: list[TaskSamples],
        post: list[TaskSamples],
        old: list[OldPolicy],
        create_graph: bool = True,
    ) -> tuple[th.Tensor, th.Tensor]:
        """
        Surrogate and KL of the post-adaptation data, re-adapting from ``params``.

        :param params: meta-parameters (require grad)
        :param pre: pre-adaptation steps per task (inner loop)
        :param post: post-adaptation steps per task (outer loss)
        :param old: the sampling policies of ``post``
        :param create_graph: keep the graph of the inner gradient (only if not ``first_order``)
        :return: mean over tasks of ``mean_t ratio_t A_t`` and of ``mean_t KL(old || new)``
        """
        surrogates, kls = [], []
        for pre_j, post_j, old_j in zip(pre, post, old, strict=True):
            adapted = self.adapt_params(params, pre_j, create_graph=create_graph and not self.first_order)
            dist = self.policy.distribution(post_j.observations, adapted)
            log_prob = dist.log_prob(post_j.actions)
            ratio = th.exp(log_prob - old_j.log_prob)
            surrogates.append((ratio * post_j.advantages).mean())
            kls.append(self.policy.kl(old_j.distribution, dist).mean())
        return th.stack(surrogates).mean(), th.stack(kls).mean()

    def meta_gradient(self, pre: list[TaskSamples], post: list[TaskSamples]) -> th.Tensor:
        """Flat gradient of the surrogate w.r.t. the meta-parameters at the current parameters."""
        params = self.policy.meta_parameters()
        old = self._old_policies(pre, post)
        surrogate, _ = self.meta_objective(params, pre, post, old)
        return parameters_to_vector(th.autograd.grad(surrogate, list(params.values())))

    def trpo_step(self, pre: list[TaskSamples], post: list[TaskSamples]) -> TRPOInfo:
        """
        One TRPO update of the meta-parameters.

        :param pre: pre-adaptation steps per task
        :param post: post-adaptation steps per task (sampled with the adapted parameters)
        :return: surrogate before/after, KL, step size, backtracks, acceptance
        """
        params = self.policy.meta_parameters()
        values = list(params.values())
        old = self._old_policies(pre, post)
        surrogate, kl = self.meta_objective(params, pre, post, old)
        grad = parameters_to_vector(th.autograd.grad(surrogate, values, retain_graph=True))
        grad_kl = parameters_to_vector(th.autograd.grad(kl, values, create_graph=True))

        fvp = partial(fisher_vector_product, grad_kl, values, damping=self.cg_damping)
        direction = conjugate_gradient(fvp, grad.detach(), self.cg_iters)
        shs = float(direction @ fvp(direction))
        surrogate_before = float(surrogate.detach())
        if not np.isfinite(shs) or shs <= 0:
            return TRPOInfo(surrogate_before, surrogate_before, 0.0, 0.0, 0, False)
        return line_search(
            lambda: self.meta_objective(params, pre, post, old, create_graph=False),
            values,
            direction,
            shs,
            surrogate_before,
            self.max_kl,
            self.ls_backtrack_ratio,
            self.ls_max_steps,
        )

    # ------------------------------------------------------------------------------------------
    # training loop
    # ------------------------------------------------------------------------------------------
    @staticmethod
    def _episode_returns(batch: EpisodeBatch) -> np.ndarray:
        return batch.rewards.sum(axis=-1).reshape(-1)  # (T * E,)

    def _train_iteration(self, callback: BaseCallback) -> bool:
        assert self._task_rng is not None
        callback.on_rollout_start()  # before the task draw: a checkpoint saved here resumes exactly
        n_train = len(self.train_tasks)
        task_ids = self._task_rng.choice(n_train, size=self.meta_batch_size, replace=self.meta_batch_size > n_train)
        tasks = [self.train_tasks[j] for j in task_ids]

        pre_batch, continue_training = self._collect_episodes(tasks, None, callback)
        if not continue_training:
            return False
        pre = self._task_samples(pre_batch)
        adapted = self._adapt_all(pre)
        post_batch, continue_training = self._collect_episodes(tasks, adapted, callback)
        if not continue_training:
            return False
        callback.on_rollout_end()
        post = self._task_samples(post_batch)

        info = self.trpo_step(pre, post)
        self._n_updates += 1

        pre_returns, post_returns = self._episode_returns(pre_batch), self._episode_returns(post_batch)
        assert self.ep_info_buffer is not None
        lengths = post_batch.lengths.reshape(-1)
        self.ep_info_buffer.extend({"r": float(r), "l": int(n)} for r, n in zip(post_returns, lengths, strict=True))
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/pre_adaptation_return", float(pre_returns.mean()))
        self.logger.record("train/post_adaptation_return", float(post_returns.mean()))
        self.logger.record("train/surrogate", info.surrogate_after)
        self.logger.record("train/surrogate_improvement", info.surrogate_after - info.surrogate_before)
        self.logger.record("train/kl", info.kl)
        self.logger.record("train/step_size", info.step_size)
        self.logger.record("train/backtracks", info.n_backtracks)
        self.logger.record("train/accepted", float(info.accepted))
        if self.policy.continuous:
            self.logger.record("train/std", float(self.policy.log_std.detach().exp().mean()))
        return True

    def dump_logs(self) -> None:
        """Write the logs (rollout statistics of the post-adaptation episodes and timings)."""
        time_elapsed = max((time.time_ns() - self.start_time) / 1e9, sys.float_info.epsilon)
        fps = int((self.num_timesteps - self._num_timesteps_at_start) / time_elapsed)
        if self.ep_info_buffer:
            self.logger.record("rollout/ep_rew_mean", safe_mean([ep_info["r"] for ep_info in self.ep_info_buffer]))
            self.logger.record("rollout/ep_len_mean", safe_mean([ep_info["l"] for ep_info in self.ep_info_buffer]))
        self.logger.record("time/fps", fps)
        self.logger.record("time/time_elapsed", int(time_elapsed), exclude="tensorboard")
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(step=self.num_timesteps)

    def learn(
        self: SelfMAML,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "MAML",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMAML:
        """
        Meta-train.

        :param total_timesteps: env steps to train on (pre- and post-adaptation steps both count;
            one meta-iteration takes ``2 * meta_batch_size * episodes_per_task * max_episode_steps`` at most)
        :param callback: callback(s) called once per VecEnv step
        :param log_interval: meta-iterations between log dumps
        :param tb_log_name: name of the TensorBoard run
        :param reset_num_timesteps: reset the timestep counter
        :param progress_bar: display a progress bar (tqdm and rich)
        :return: the trained model
        """
        total_steps, callback = self._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        callback.on_training_start(locals(), globals())
        self.reset_adaptation()
        while self.num_timesteps < total_steps:
            self._update_current_progress_remaining(self.num_timesteps, total_steps)
            if not self._train_iteration(callback):
                break
            if log_interval is not None and self._n_updates % log_interval == 0:
                self.dump_logs()
        callback.on_training_end()
        return self

    # ------------------------------------------------------------------------------------------
    # adaptation API (meta-test)
    # ------------------------------------------------------------------------------------------
    def reset_adaptation(self) -> None:
        """Forget the current task: drop the observed trajectories and act with the meta-learned parameters."""
        self._adapt_episodes = []
        self._current_episode = ([], [], [])
        self.policy.adapted_params = None
        self.policy.last_raw_actions = None

    def observe(self, obs: np.ndarray, action: np.ndarray, reward: float, next_obs: np.ndarray, done: bool) -> None:
        """
        Record one transition of the current task.

        :param obs: observation, shape ``obs_shape`` (or ``(1, *obs_shape)``)
        :param action: the action sent to the env (as returned by :meth:`predict`)
        :param reward: the reward
        :param next_obs: next observation (checked, not stored: the baseline needs no bootstrap)
        :param done: end of the trajectory (terminated or truncated)
        """
        obs_arr, _ = check_observed_transition(self.observation_space, obs, reward, next_obs)
        obs_flat = obs_arr.reshape(-1)
        stored = observed_action(self.policy, self.action_space, action)
        observations, actions, rewards = self._current_episode
        observations.append(obs_flat)
        actions.append(stored)
        rewards.append(float(np.asarray(reward).reshape(-1)[0]))
        if bool(np.asarray(done).reshape(-1)[0]):
            self._adapt_episodes.append(self._current_episode)
            self._current_episode = ([], [], [])

    def adapt(self) -> None:
        """
        Inner update(s) from the meta-learned parameters on every trajectory observed since
        :meth:`reset_adaptation` (an unfinished one counts as ending at its last step), as in training.
        With nothing observed, the policy stays the meta-learned one.
        """
        episodes = [*self._adapt_episodes]
        if self._current_episode[0]:
            episodes.append(self._current_episode)
        if not episodes:
            self.policy.adapted_params = None
            return
        batch = episodes_to_batch(episodes, self.policy.obs_dim, act_store_dim(self.policy))
        samples = self._task_samples(batch)
        adapted = self._adapt_all(samples)
        self.policy.adapted_params = {name: value[0] for name, value in adapted.items()}
