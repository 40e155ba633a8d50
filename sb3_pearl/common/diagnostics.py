"""Prior-safety diagnostics of a trained PEARL / PEARL+ model (docs/diagnostics.md).

:func:`compute_diagnostics` measures, in seconds on a small model, the quantities behind three
hypotheses for a prior policy ``pi(a | s, z0)``, ``z0 ~ N(0, I)``, that violates constraints:

- ``overlap``: how the posteriors q(z | c) of the training tasks sit against the prior draws:
  per-dimension spread of the posterior means over tasks, mean posterior variance, and the
  cross-validated AUC of two classifiers separating posterior samples from z0 draws (a Gaussian
  classifier with one covariance per class, and leave-one-out k nearest neighbours);
- ``violations``: the violation rate at k = 0 (deterministic actions, the meta-test's setting) on
  held-out tasks, binned by the distance of z0 to the nearest training-task posterior mean
  (terciles), and the rate at z = 0 exactly;
- ``calibration``: the prior critic Q~(s0, a0, z0) at start states against the Monte-Carlo soft
  return of the z0 policy over training tasks (the quantity Q~ is fitted to, see
  :func:`compute_calibration`); PEARL and the ablation ``prior_critic="shared"`` use Q(s, a, z0);
- ``gradient_conflict``: ``||prior_coef * grad prior term|| / ||grad posterior term||`` and the
  cosine of the two actor gradients on meta-batches (:func:`actor_gradient_conflict`, also logged
  during training as ``train/grad_conflict_*`` with ``grad_conflict_log_freq``).

Rollouts with a fixed z (:func:`rollout_with_z`) bypass the adaptation API: the model's
``current_z`` and observed context are left untouched. numpy's and torch's global RNGs are seeded
from ``seed`` for the duration of the call and restored afterwards.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.buffers import MetaReplayBuffer
from sb3_pearl.common.meta_test import _SingleEnv
from sb3_pearl.common.seeding import derived_seed, get_global_rng_state, seed_global_rngs, set_global_rng_state
from sb3_pearl.common.soft_actor_critic import evaluate_policy, q_of_actions, q_of_policy, soft_value
from sb3_pearl.common.type_aliases import PEARLLosses
from sb3_pearl.envs.task_protocol import Task

if TYPE_CHECKING:
    from sb3_pearl.pearl.pearl import PEARL

DEFAULT_N_TASKS = 8
DEFAULT_N_Z0 = 16
DEFAULT_N_POSTERIOR_SAMPLES = 32
DEFAULT_N_GRAD_BATCHES = 4
MAX_CONTEXT_STEPS = 1000
KNN_NEIGHBOURS = 10
CV_FOLDS = 5

# Purposes mixed into the env seeds so that the rollouts of different measurements differ.
_CONTEXT, _VIOLATION, _ZERO, _CALIBRATION = range(4)


# ----------------------------------------------------------------------------------------------
# Gradient conflict on the actor (also called from PEARL.train)
# ----------------------------------------------------------------------------------------------
def _flat_grad(loss: th.Tensor, params: list[th.nn.Parameter]) -> th.Tensor:
    """Gradient of ``loss`` w.r.t. ``params`` flattened to (P,); zeros if the loss does not depend on them."""
    if not loss.requires_grad:
        return th.zeros(sum(p.numel() for p in params), device=params[0].device)
    grads = th.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return th.cat([(th.zeros_like(p) if g is None else g).reshape(-1) for g, p in zip(grads, params)])


def actor_gradient_conflict(model: PEARL, losses: PEARLLosses) -> dict[str, float]:
    """
    Compare the two actor terms of one gradient step on the actor parameters.

    The graph of ``losses`` is kept (``retain_graph``), so the step's own backward pass can follow.

    :param model: the PEARL / PEARL+ model
    :param losses: the losses of the step (``model._compute_losses``)
    :return: ``ratio`` ``||prior_coef * g_prior|| / ||g_post||`` (0 for PEARL, nan if ``g_post`` is 0),
        ``cos`` the cosine of ``g_prior`` and ``g_post`` (nan if either is 0), and both norms
        ``prior_norm`` (weighted by ``prior_coef``) and ``post_norm``
    """
    params = [p for p in model.actor.parameters() if p.requires_grad]
    g_post = _flat_grad(losses.actor_loss, params)  # (P,)
    g_prior = _flat_grad(model.prior_coef * losses.prior_actor_loss, params)  # (P,)
    post_norm, prior_norm = float(g_post.norm()), float(g_prior.norm())
    ratio = prior_norm / post_norm if post_norm > 0 else math.nan
    cos = float(th.dot(g_prior, g_post)) / (prior_norm * post_norm) if prior_norm > 0 and post_norm > 0 else math.nan
    return {"ratio": ratio, "cos": cos, "prior_norm": prior_norm, "post_norm": post_norm}


def record_gradient_conflict(model: PEARL, losses: PEARLLosses, logs: dict[str, list[float]]) -> None:
    """
    Append ``grad_conflict_ratio`` and ``grad_conflict_cos`` of one step to the training logs (finite values only).

    :param model: the model being trained
    :param losses: the losses of the step
    :param logs: the ``train()`` log lists, keyed without the ``train/`` prefix
    """
    conflict = actor_gradient_conflict(model, losses)
    for key in ("ratio", "cos"):
        if math.isfinite(conflict[key]):
            logs.setdefault(f"grad_conflict_{key}", []).append(conflict[key])


# ----------------------------------------------------------------------------------------------
# Classifier AUC (numpy only)
# ----------------------------------------------------------------------------------------------
def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """
    Area under the ROC curve (Mann-Whitney statistic, ties counted half).

    :param scores: classifier scores, shape (n,)
    :param labels: 1 for positives, 0 for negatives, shape (n,)
    :return: the AUC; nan without both classes
    """
    scores = np.asarray(scores, dtype=np.float64)
    labels = np.asarray(labels).astype(bool)
    n_pos, n_neg = int(labels.sum()), int((~labels).sum())
    if n_pos == 0 or n_neg == 0:
        return math.nan
    ranks = np.empty(len(scores))
    ranks[np.argsort(scores, kind="mergesort")] = np.arange(1, len(scores) + 1)
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    ranks = (np.bincount(inverse, weights=ranks) / counts)[inverse]  # average rank of tied scores
    return float((ranks[labels].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def _gaussian_log_density(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """log N(x | mean, cov) per row of ``x`` (n, d)."""
    chol = np.linalg.cholesky(cov)
    white = np.linalg.solve(chol, (x - mean).T)  # (d, n)
    return -0.5 * (white**2).sum(axis=0) - np.log(np.diag(chol)).sum() - 0.5 * x.shape[1] * math.log(2 * math.pi)


def _fit_gaussian(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of ``x`` (n, d), with a small ridge so that collapsed classes stay invertible."""
    mean = x.mean(axis=0)
    cov = np.atleast_2d(np.cov(x, rowvar=False)) if len(x) > 1 else np.zeros((x.shape[1], x.shape[1]))
    ridge = 1e-3 * float(np.trace(cov)) / x.shape[1] + 1e-6
    return mean, cov + ridge * np.eye(x.shape[1])


def gaussian_classifier_auc(positives: np.ndarray, negatives: np.ndarray, n_folds: int = CV_FOLDS, seed: int = 0) -> float:
    """
    Cross-validated AUC of a Gaussian classifier with one mean and covariance per class (QDA).

    Scores are the log-density ratio ``log N(x | positives) - log N(x | negatives)`` of models fitted
    on the other folds (stratified folds).

    :param positives: samples of class 1, shape (n1, d)
    :param negatives: samples of class 0, shape (n0, d)
    :param n_folds: number of folds
    :param seed: seed of the fold assignment
    :return: the out-of-fold AUC (0.5: indistinguishable, 1: separable)
    """
    rng = np.random.default_rng(seed)
    x = np.concatenate([positives, negatives]).astype(np.float64)
    labels = np.concatenate([np.ones(len(positives), bool), np.zeros(len(negatives), bool)])
    folds = np.empty(len(x), dtype=np.int64)
    for cls in (True, False):
        members = np.flatnonzero(labels == cls)
        folds[rng.permutation(members)] = np.arange(len(members)) % n_folds
    scores = np.empty(len(x))
    for fold in range(n_folds):
        test, train = folds == fold, folds != fold
        if not test.any():
            continue
        pos = _fit_gaussian(x[train & labels])
        neg = _fit_gaussian(x[train & ~labels])
        scores[test] = _gaussian_log_density(x[test], *pos) - _gaussian_log_density(x[test], *neg)
    return roc_auc(scores, labels)


def knn_classifier_auc(positives: np.ndarray, negatives: np.ndarray, n_neighbours: int = KNN_NEIGHBOURS) -> float:
    """
    Leave-one-out AUC of a k-nearest-neighbour classifier (score: share of class 1 among the neighbours).

    Unlike the Gaussian classifier it sees clusters: posterior samples bunched around a few task
    means are separated from z0 draws even when both have the same mean and covariance.

    :param positives: samples of class 1, shape (n1, d)
    :param negatives: samples of class 0, shape (n0, d)
    :param n_neighbours: k
    :return: the leave-one-out AUC
    """
    x = np.concatenate([positives, negatives]).astype(np.float64)
    labels = np.concatenate([np.ones(len(positives)), np.zeros(len(negatives))])
    k = max(1, min(n_neighbours, len(x) - 1))
    sq = (x**2).sum(axis=1)
    dist = sq[:, None] + sq[None, :] - 2.0 * x @ x.T  # (n, n) squared distances
    np.fill_diagonal(dist, np.inf)  # leave one out
    neighbours = np.argpartition(dist, k - 1, axis=1)[:, :k]  # (n, k)
    return roc_auc(labels[neighbours].mean(axis=1), labels)


# ----------------------------------------------------------------------------------------------
# Rollouts with a fixed z
# ----------------------------------------------------------------------------------------------
@dataclass
class FixedZRollout:
    """One trajectory of ``pi(a | s, z)`` with z held fixed."""

    observations: np.ndarray  # (T + 1, obs_dim): s_0 .. s_T (s_T: the observation after the last step)
    actions: np.ndarray  # (T, act_dim) network units: scaled Box actions in [-1, 1] or (T, 1) Discrete indices
    rewards: np.ndarray  # (T,) env rewards (not reward-scaled)
    log_probs: np.ndarray  # (T,) log pi(a_t | s_t, z) of the actions taken (nan for deterministic actions)
    cost: float  # sum of info["cost"]
    terminated: bool  # the episode ended in a terminal state (not a time limit or max_steps)

    @property
    def length(self) -> int:
        return len(self.rewards)

    @property
    def episode_return(self) -> float:
        return float(self.rewards.sum())

    @property
    def violated(self) -> bool:
        return self.cost > 0.0


def _act(model: PEARL, obs: np.ndarray, z: th.Tensor, deterministic: bool) -> tuple[np.ndarray, Any, float]:
    """Network action (act_dim,), env action and log-probability of ``pi(. | obs, z)``."""
    policy = model.policy
    x = th.cat([th.as_tensor(obs, dtype=th.float32, device=model.device).reshape(1, -1), z.reshape(1, -1)], dim=-1)
    with th.no_grad():
        if deterministic and not policy.discrete:
            action, log_prob = policy.actor(x, deterministic=True), math.nan
        else:
            pe = evaluate_policy(policy.actor, x)  # Box: a sampled action (1, A); Discrete: probs (1, n_actions)
            if pe.probs is not None:
                index = int(pe.probs.argmax()) if deterministic else int(th.multinomial(pe.probs[0], 1))
                return np.array([index], dtype=np.float32), index, float(pe.log_prob[0, index])
            assert pe.actions is not None
            action, log_prob = pe.actions, float(pe.log_prob)
    scaled = action.cpu().numpy().reshape(-1)
    env_action = policy.unscale_action(scaled).reshape(model.action_space.shape)  # type: ignore[arg-type]
    return scaled.astype(np.float32), env_action, log_prob


def rollout_with_z(
    model: PEARL,
    env: gym.Env | VecEnv,
    task: Task,
    z: th.Tensor | np.ndarray,
    deterministic: bool = True,
    seed: int | None = None,
    max_steps: int | None = None,
) -> FixedZRollout:
    """
    Roll out ``pi(a | s, z)`` on ``task`` with ``z`` held for the whole trajectory.

    The adaptation state of the model (``current_z``, observed context) is not touched.

    :param model: a PEARL / PEARL+ model
    :param env: a task-family env (gymnasium env, possibly wrapped, or a VecEnv of one env)
    :param task: the task, set with ``set_task`` before the reset
    :param z: the latent, shape (latent_dim,)
    :param deterministic: deterministic actions (the meta-test's default) or samples of the policy
    :param seed: seed of the env reset (None: not seeded)
    :param max_steps: stop after this many steps (None: until the episode ends)
    :return: the trajectory
    """
    runner = env if isinstance(env, _SingleEnv) else _SingleEnv(env)
    z_t = th.as_tensor(np.asarray(z.cpu() if isinstance(z, th.Tensor) else z), dtype=th.float32, device=model.device)
    runner.set_task(task)
    runner.seed(seed)
    obs = np.asarray(runner.reset(), dtype=np.float32)
    observations, actions, rewards, log_probs = [obs], [], [], []
    cost, terminated, done = 0.0, False, False
    while not done:
        action, env_action, log_prob = _act(model, obs, z_t, deterministic)
        next_obs, reward, terminated, truncated, info = runner.step(env_action)
        cost += float(info.get("cost", 0.0))
        obs = np.asarray(next_obs, dtype=np.float32)
        observations.append(obs)
        actions.append(action)
        rewards.append(reward)
        log_probs.append(log_prob)
        done = terminated or truncated or (max_steps is not None and len(rewards) >= max_steps)
    return FixedZRollout(
        observations=np.stack(observations),
        actions=np.stack(actions),
        rewards=np.asarray(rewards, dtype=np.float64),
        log_probs=np.asarray(log_probs, dtype=np.float64),
        cost=cost,
        terminated=bool(terminated),
    )


# ----------------------------------------------------------------------------------------------
# The four measurements
# ----------------------------------------------------------------------------------------------
def _collect_context(
    model: PEARL, env: gym.Env | VecEnv, tasks: list[int], n_steps: int, seed: int, max_steps: int | None
) -> MetaReplayBuffer:
    """Fresh data of training tasks: ``n_steps`` per task with z from the prior (one per trajectory), stochastic actions."""
    buffer = MetaReplayBuffer(len(model.train_tasks), n_steps, n_steps, model.observation_space, model.action_space)
    for task in tasks:
        n_trajectory = 0
        while buffer.rl.size[task] < n_steps:
            z = th.randn(model.latent_dim, device=model.device)
            left = n_steps - int(buffer.rl.size[task])
            cap = left if max_steps is None else min(left, max_steps)
            seed_t = derived_seed(seed, _CONTEXT, task, n_trajectory)
            traj = rollout_with_z(model, env, model.train_tasks[task], z, False, seed_t, cap)
            for t in range(traj.length):
                done = traj.terminated and t == traj.length - 1
                row = (traj.observations[t], traj.actions[t], float(traj.rewards[t]), traj.observations[t + 1], done)
                buffer.rl.add(task, *row)
                buffer.context.add(task, *row)
            n_trajectory += 1
    return buffer


def _posteriors(model: PEARL, buffers: list[MetaReplayBuffer], tasks: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Posterior means and variances (n_tasks, L) from ``embedding_batch_size`` context transitions per task."""
    means, variances = [], []
    for buffer, task in zip(buffers, tasks):
        ctx = buffer.context.sample(np.array([task]), model.embedding_batch_size, model.device)
        with th.no_grad():
            context = model.policy.make_context(ctx.observations, ctx.actions, ctx.rewards, ctx.next_observations)
            mean, var = model.encoder.posterior(context)  # (1, L) each
        means.append(mean[0].cpu().numpy())
        variances.append(var[0].cpu().numpy())
    return np.stack(means).astype(np.float64), np.stack(variances).astype(np.float64)


def compute_overlap(means: np.ndarray, variances: np.ndarray, n_samples: int, rng: np.random.Generator) -> dict[str, Any]:
    """
    How the training-task posteriors sit against the prior N(0, I).

    :param means: posterior means, shape (n_tasks, L)
    :param variances: posterior variances, shape (n_tasks, L)
    :param n_samples: posterior samples per task (as many z0 draws in total)
    :param rng: random generator
    :return: spreads, variances and the two classifier AUCs (posterior samples = class 1)
    """
    n_tasks, latent_dim = means.shape
    noise = rng.standard_normal((n_tasks, n_samples, latent_dim))
    samples = (means[:, None] + np.sqrt(variances)[:, None] * noise).reshape(-1, latent_dim)  # (n_tasks * n_samples, L)
    z0 = rng.standard_normal(samples.shape)
    spread = means.std(axis=0) if n_tasks > 1 else np.zeros(latent_dim)
    mean_var = variances.mean(axis=0)
    return {
        "n_tasks": n_tasks,
        "n_per_class": len(samples),
        "posterior_mean_spread": spread.tolist(),
        "posterior_mean_spread_avg": float(spread.mean()),
        "posterior_mean_norm_avg": float(np.linalg.norm(means, axis=1).mean()),
        "posterior_var": mean_var.tolist(),
        "posterior_var_avg": float(mean_var.mean()),
        "auc_gaussian": gaussian_classifier_auc(samples, z0, seed=int(rng.integers(2**31))),
        "auc_knn": knn_classifier_auc(samples, z0),
    }


def compute_violations(
    model: PEARL,
    env: gym.Env | VecEnv,
    tasks: list[Task],
    z0: np.ndarray,
    posterior_means: np.ndarray,
    seed: int,
    max_steps: int | None,
) -> dict[str, Any]:
    """
    Violation rate at k = 0 (deterministic actions) against the distance of z0 to the nearest posterior mean.

    :param model: the model
    :param env: the env
    :param tasks: the tasks rolled out (held-out tasks)
    :param z0: prior draws, shape (n_z0, L)
    :param posterior_means: training-task posterior means, shape (n_tasks, L)
    :param seed: seed of the env resets
    :param max_steps: trajectory cap
    :return: overall rate, the rate per distance tercile, the rate at z = 0
    """
    distance = np.linalg.norm(z0[:, None] - posterior_means[None], axis=-1).min(axis=1)  # (n_z0,)
    violated = np.zeros((len(z0), len(tasks)))
    returns = np.zeros((len(z0), len(tasks)))
    for i, z in enumerate(z0):
        for j, task in enumerate(tasks):
            traj = rollout_with_z(model, env, task, z, True, derived_seed(seed, _VIOLATION, i, j), max_steps)
            violated[i, j], returns[i, j] = traj.violated, traj.episode_return
    zero = [
        rollout_with_z(model, env, task, np.zeros(model.latent_dim), True, derived_seed(seed, _ZERO, j), max_steps)
        for j, task in enumerate(tasks)
    ]
    edges = np.quantile(distance, [0.0, 1 / 3, 2 / 3, 1.0])
    bins = np.clip(np.searchsorted(edges[1:-1], distance, side="right"), 0, 2)  # tercile of each draw
    terciles = []
    for b, name in enumerate(("near", "middle", "far")):
        members = bins == b
        terciles.append(
            {
                "bin": name,
                "distance_low": float(edges[b]),
                "distance_high": float(edges[b + 1]),
                "n_z0": int(members.sum()),
                "violation_rate": float(violated[members].mean()) if members.any() else math.nan,
                "return_mean": float(returns[members].mean()) if members.any() else math.nan,
            }
        )
    per_draw = violated.mean(axis=1)
    corr = float(np.corrcoef(distance, per_draw)[0, 1]) if per_draw.std() > 0 and distance.std() > 0 else math.nan
    return {
        "n_tasks": len(tasks),
        "n_z0": len(z0),
        "violation_rate": float(violated.mean()),
        "return_mean": float(returns.mean()),
        "distance_mean": float(distance.mean()),
        "distance_violation_corr": corr,
        "terciles": terciles,
        "z_zero_violation_rate": float(np.mean([t.violated for t in zero])),
        "z_zero_return_mean": float(np.mean([t.episode_return for t in zero])),
    }


def _critic_for_prior(model: PEARL) -> tuple[Any, str]:
    """The critic that scores the prior term: Q~ (separate) or Q (shared mode, PEARL), with its name."""
    if model.prior_critic is not None:
        return model.prior_critic, "prior critic Q~(s, a, z0)"
    if model.prior_critic_mode == "shared":
        return model.critic, "critic Q(s, a, z0) (prior_critic='shared': the prior term's critic)"
    return model.critic, "critic Q(s, a, z0) (PEARL has no prior critic)"


def compute_calibration(
    model: PEARL,
    env: gym.Env | VecEnv,
    tasks: list[Task],
    z0: np.ndarray,
    seed: int,
    max_steps: int | None,
) -> dict[str, Any]:
    """
    The prior critic at start states against Monte-Carlo returns of the z0 policy.

    Q~ is fitted (reward-scaled soft Bellman target, time limits bootstrapped) to

        Q~(s0, a0, z0) = E[ sum_{t>=0} gamma^t * reward_scale * r_t - ent_coef * sum_{t>=1} gamma^t * log pi(a_t | s_t, z0) ]

    under the *stochastic* policy ``pi(. | ., z0)``, averaged over the training tasks the meta-batches
    mix (the prior critic does not see the task). For each z0 and training task one stochastic
    trajectory from ``s0`` is rolled out; ``a0`` is its first action. ``mc_return`` is that sum over
    the trajectory; ``mc_return_bootstrapped`` adds ``gamma^T * V~(s_T, z0)`` when the trajectory was
    cut by the time limit (as the training target does; 0 after a true termination). A calibrated
    critic has ``bias = q - mc_return_bootstrapped`` near 0.

    :param model: the model
    :param env: the env
    :param tasks: the training tasks rolled out
    :param z0: prior draws, shape (n_z0, L)
    :param seed: seed of the env resets
    :param max_steps: trajectory cap (a cut trajectory is bootstrapped like a time limit)
    :return: means over (z0, task) and the correlation over z0 draws of Q~ with the returns
    """
    critic, critic_name = _critic_for_prior(model)
    ent_coef = model._current_ent_coef()
    discrete = model.policy.discrete
    q = np.zeros((len(z0), len(tasks)))
    mc = np.zeros_like(q)
    boot = np.zeros_like(q)
    env_returns = np.zeros_like(q)
    lengths = np.zeros_like(q)
    for i, z in enumerate(z0):
        z_t = th.as_tensor(z, dtype=th.float32, device=model.device)
        for j, task in enumerate(tasks):
            traj = rollout_with_z(model, env, task, z_t, False, derived_seed(seed, _CALIBRATION, i, j), max_steps)
            discounts = model.gamma ** np.arange(traj.length)  # (T,)
            soft = model.reward_scale * traj.rewards
            soft[1:] -= float(ent_coef) * traj.log_probs[1:]  # the entropy bonus enters from t = 1 on
            mc[i, j] = float((discounts * soft).sum())
            ends = th.as_tensor(traj.observations[[0, -1]], device=model.device)  # (2, obs_dim): s_0 and s_T
            x = th.cat([ends, z_t.expand(2, -1)], dim=-1)  # (2, obs_dim + L)
            with th.no_grad():
                a0 = th.as_tensor(traj.actions[:1], device=model.device)  # (1, act_dim)
                q[i, j] = float(q_of_actions(critic, x[:1], a0, discrete).min(dim=0).values)
                tail = 0.0
                if not traj.terminated:
                    pe = evaluate_policy(model.actor, x[1:])
                    tail = float(soft_value(q_of_policy(critic, x[1:], pe), pe, ent_coef))
            boot[i, j] = mc[i, j] + model.gamma**traj.length * tail
            env_returns[i, j] = traj.episode_return
            lengths[i, j] = traj.length
    q_z, boot_z = q.mean(axis=1), boot.mean(axis=1)  # per z0 draw, averaged over tasks
    corr = float(np.corrcoef(q_z, boot_z)[0, 1]) if q_z.std() > 0 and boot_z.std() > 0 else math.nan
    return {
        "critic": critic_name,
        "n_tasks": len(tasks),
        "n_z0": len(z0),
        "gamma": model.gamma,
        "reward_scale": model.reward_scale,
        "ent_coef": float(ent_coef),
        "q_mean": float(q.mean()),
        "mc_return_mean": float(mc.mean()),
        "mc_return_bootstrapped_mean": float(boot.mean()),
        "bias": float((q - boot).mean()),
        "abs_error_mean": float(np.abs(q - boot).mean()),
        "q_std_over_z0": float(q_z.std()),
        "mc_std_over_z0": float(boot_z.std()),
        "q_mc_corr_over_z0": corr,
        "env_return_mean": float(env_returns.mean()),
        "length_mean": float(lengths.mean()),
    }


def compute_gradient_conflict(model: PEARL, buffer: MetaReplayBuffer, n_batches: int) -> dict[str, Any]:
    """
    :func:`actor_gradient_conflict` on ``n_batches`` meta-batches sampled like ``train()`` does.

    :param model: the model
    :param buffer: the replay and context data to sample from
    :param n_batches: meta-batches
    :return: the mean ratio and cosine, and the values per batch
    """
    candidates = buffer.tasks_with_data()
    per_batch = []
    for _ in range(n_batches):
        tasks = np.random.choice(candidates, size=model.meta_batch, replace=len(candidates) < model.meta_batch)
        replay = buffer.rl.sample(tasks, model.batch_size, model.device)
        ctx = buffer.context.sample(tasks, model.embedding_batch_size, model.device)
        context = model.policy.make_context(ctx.observations, ctx.actions, ctx.rewards, ctx.next_observations)
        z0 = th.randn(len(tasks), model.latent_dim, device=model.device)  # one prior z per task
        per_batch.append(actor_gradient_conflict(model, model._compute_losses(replay, context, z0)))

    def mean_of(key: str) -> float:
        values = [entry[key] for entry in per_batch if math.isfinite(entry[key])]
        return float(np.mean(values)) if values else math.nan

    return {
        "prior_coef": model.prior_coef,
        "n_batches": n_batches,
        "ratio": mean_of("ratio"),
        "cos": mean_of("cos"),
        "prior_norm": mean_of("prior_norm"),
        "post_norm": mean_of("post_norm"),
        "ratio_per_batch": [entry["ratio"] for entry in per_batch],
        "cos_per_batch": [entry["cos"] for entry in per_batch],
    }


def _plain(value: Any) -> Any:
    """JSON value: nan/inf become None, numpy scalars Python numbers."""
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def compute_diagnostics(
    model: PEARL,
    env: gym.Env | VecEnv,
    seed: int = 0,
    n_tasks: int = DEFAULT_N_TASKS,
    n_z0: int = DEFAULT_N_Z0,
    n_posterior_samples: int = DEFAULT_N_POSTERIOR_SAMPLES,
    n_grad_batches: int = DEFAULT_N_GRAD_BATCHES,
    context_steps: int | None = None,
    max_steps: int | None = None,
) -> dict[str, Any]:
    """
    The prior-safety diagnostics of a trained PEARL / PEARL+ model (module docstring, docs/diagnostics.md).

    Posteriors come from each training task's context buffer where it holds data, else from
    ``context_steps`` fresh steps with z from the prior (a loaded model has empty buffers); the
    gradient conflict uses the model's replay buffer if it holds data, else the fresh data.

    :param model: a trained PEARL / PEARL+ model
    :param env: an env of the family the model was trained on (gymnasium env or a VecEnv of one env)
    :param seed: seed of every draw and env reset of the diagnostics
    :param n_tasks: training tasks (posteriors, calibration) and held-out tasks (violations) used
    :param n_z0: prior draws rolled out on every task (violations, calibration)
    :param n_posterior_samples: posterior samples per training task for the classifiers
    :param n_grad_batches: meta-batches of the gradient conflict
    :param context_steps: fresh steps per training task without context data (None: the model's
        ``num_steps_prior + num_steps_posterior``, at most 1000, at least ``embedding_batch_size``)
    :param max_steps: cap on trajectory length (None: the env's horizon)
    :return: a JSON-serialisable dict with ``overlap``, ``violations``, ``calibration``, ``gradient_conflict``
    """
    if not hasattr(model, "encoder") or not hasattr(model, "prior_coef"):
        raise TypeError(f"compute_diagnostics needs a PEARL / PEARL+ model, got {type(model).__name__}")
    if min(n_tasks, n_z0, n_posterior_samples, n_grad_batches) < 1:
        raise ValueError("n_tasks, n_z0, n_posterior_samples and n_grad_batches must be >= 1")
    if not model.train_tasks:
        raise ValueError("the model has no training tasks")
    saved_rng = get_global_rng_state()
    seed_global_rngs(seed)
    rng = np.random.default_rng(seed)
    training = model.policy.training
    model.policy.set_training_mode(False)
    try:
        n_train = min(n_tasks, len(model.train_tasks))
        train_idx = sorted(rng.choice(len(model.train_tasks), size=n_train, replace=False).tolist())
        has_context = model.replay_buffer.context.size > 0
        fresh_tasks = [t for t in train_idx if not has_context[t]]
        if context_steps is None:
            context_steps = min(model.num_steps_prior + model.num_steps_posterior, MAX_CONTEXT_STEPS)
            context_steps = max(context_steps, model.embedding_batch_size)
        fresh = _collect_context(model, env, fresh_tasks, context_steps, seed, max_steps) if fresh_tasks else None
        buffers = [model.replay_buffer if has_context[t] else fresh for t in train_idx]
        means, variances = _posteriors(model, buffers, train_idx)  # type: ignore[arg-type]

        eval_tasks = list(model.test_tasks or model.train_tasks)[:n_tasks]
        z0 = rng.standard_normal((n_z0, model.latent_dim))
        train_tasks = [model.train_tasks[t] for t in train_idx]
        use_model_buffer = len(model.replay_buffer.tasks_with_data()) > 0
        grad_buffer = model.replay_buffer if use_model_buffer or fresh is None else fresh
        result = {
            "algorithm": type(model).__name__,
            "prior_critic": model.prior_critic_mode,
            "prior_coef": model.prior_coef,
            "latent_dim": model.latent_dim,
            "num_timesteps": model.num_timesteps,
            "seed": seed,
            "data": {
                "train_tasks": train_idx,
                "posterior_from_context_buffer": len(train_idx) - len(fresh_tasks),
                "posterior_from_fresh_rollouts": len(fresh_tasks),
                "context_steps": context_steps if fresh_tasks else 0,
                "embedding_batch_size": model.embedding_batch_size,
                "violation_tasks": "test" if model.test_tasks else "train",
                "gradient_batches_from": "replay buffer" if grad_buffer is model.replay_buffer else "fresh rollouts",
            },
            "overlap": compute_overlap(means, variances, n_posterior_samples, rng),
            "violations": compute_violations(model, env, eval_tasks, z0, means, seed, max_steps),
            "calibration": compute_calibration(model, env, train_tasks, z0, seed, max_steps),
            "gradient_conflict": compute_gradient_conflict(model, grad_buffer, n_grad_batches),
        }
    finally:
        model.policy.set_training_mode(training)
        set_global_rng_state(saved_rng)
    return _plain(result)


def format_diagnostics(diagnostics: dict[str, Any]) -> str:
    """
    A readable plain-text report of :func:`compute_diagnostics`'s result.

    :param diagnostics: the result
    :return: the report
    """

    def num(value: Any, fmt: str = ".3f") -> str:
        return "n/a" if value is None else format(value, fmt)

    def f2(value: Any) -> str:
        return num(value, ".2f")

    def vec(values: list[Any]) -> str:
        return "[" + ", ".join(f2(v) for v in values) + "]"

    d, o, v, c, g = (diagnostics[key] for key in ("data", "overlap", "violations", "calibration", "gradient_conflict"))
    lines = [
        f"{diagnostics['algorithm']} (prior_critic={diagnostics['prior_critic']}, prior_coef={diagnostics['prior_coef']}, "
        f"latent_dim={diagnostics['latent_dim']}, {diagnostics['num_timesteps']} steps), seed {diagnostics['seed']}",
        "",
        f"Posterior vs prior z0 ~ N(0, I)  ({o['n_tasks']} training tasks: {d['posterior_from_context_buffer']} from the "
        f"context buffer, {d['posterior_from_fresh_rollouts']} from fresh prior rollouts)",
        f"  spread of posterior means per dim   {vec(o['posterior_mean_spread'])} (avg {num(o['posterior_mean_spread_avg'])})",
        f"  mean posterior variance per dim     {vec(o['posterior_var'])} (avg {num(o['posterior_var_avg'])})",
        f"  mean ||posterior mean||             {num(o['posterior_mean_norm_avg'])}",
        f"  AUC posterior samples vs z0         Gaussian {num(o['auc_gaussian'])}   kNN {num(o['auc_knn'])}"
        f"   (0.5: overlap, 1: separable; {o['n_per_class']} per class)",
        "",
        f"Violations at k = 0 (deterministic, {v['n_z0']} z0 x {v['n_tasks']} {d['violation_tasks']} tasks)",
        f"  {'z0 bin':<8} {'distance to nearest posterior mean':>36} {'n z0':>5} {'viol. rate':>10} {'return':>9}",
    ]
    for b in v["terciles"]:
        dist = f"[{f2(b['distance_low'])}, {f2(b['distance_high'])}]"
        lines.append(f"  {b['bin']:<8} {dist:>36} {b['n_z0']:>5} {f2(b['violation_rate']):>10} {f2(b['return_mean']):>9}")
    mean_dist = "mean " + f2(v["distance_mean"])
    lines += [
        f"  {'all z0':<8} {mean_dist:>36} {v['n_z0']:>5} {f2(v['violation_rate']):>10} {f2(v['return_mean']):>9}",
        f"  {'z = 0':<8} {'':>36} {'':>5} {f2(v['z_zero_violation_rate']):>10} {f2(v['z_zero_return_mean']):>9}",
        f"  correlation(distance, violation rate) over z0: {f2(v['distance_violation_corr'])}",
        "",
        f"Calibration of the {c['critic']}",
        f"  at start states, stochastic z0 policy, {c['n_z0']} z0 x {c['n_tasks']} training tasks; "
        f"reward_scale {c['reward_scale']}, gamma {c['gamma']}, ent_coef {num(c['ent_coef'], '.3g')}",
        f"  Q(s0, a0, z0)                        {f2(c['q_mean'])}",
        f"  MC soft return (horizon only)        {f2(c['mc_return_mean'])}",
        f"  MC soft return + bootstrapped tail   {f2(c['mc_return_bootstrapped_mean'])}",
        f"  bias Q - MC (bootstrapped)           {f2(c['bias'])}   mean |error| {f2(c['abs_error_mean'])}",
        f"  over z0: std Q {f2(c['q_std_over_z0'])}, std MC {f2(c['mc_std_over_z0'])}, "
        f"correlation {f2(c['q_mc_corr_over_z0'])}",
        f"  env return (unscaled, undiscounted)  {f2(c['env_return_mean'])}   mean length {num(c['length_mean'], '.1f')}",
        "",
        f"Gradient conflict on the actor ({g['n_batches']} meta-batches from the {d['gradient_batches_from']})",
        f"  ||prior_coef * g_prior|| / ||g_post||  {num(g['ratio'])}   (prior_coef {g['prior_coef']})",
        f"  cos(g_prior, g_post)                   {num(g['cos'])}",
    ]
    return "\n".join(lines)


__all__ = [
    "FixedZRollout",
    "actor_gradient_conflict",
    "compute_calibration",
    "compute_diagnostics",
    "compute_gradient_conflict",
    "compute_overlap",
    "compute_violations",
    "format_diagnostics",
    "gaussian_classifier_auc",
    "knn_classifier_auc",
    "record_gradient_conflict",
    "roc_auc",
    "rollout_with_z",
]
