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

The package: :mod:`.overlap` (posteriors against the prior, classifier AUCs), :mod:`.rollouts`
(fixed-z rollouts, fresh context, posteriors), :mod:`.violations`, :mod:`.calibration` (prior critic)
and :mod:`.gradients` (actor gradient conflict); this module combines and formats them.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.seeding import get_global_rng_state, seed_global_rngs, set_global_rng_state
from sb3_pearl.pearl.diagnostics.calibration import compute_calibration
from sb3_pearl.pearl.diagnostics.gradients import actor_gradient_conflict, compute_gradient_conflict, record_gradient_conflict
from sb3_pearl.pearl.diagnostics.overlap import CV_FOLDS as CV_FOLDS
from sb3_pearl.pearl.diagnostics.overlap import KNN_NEIGHBOURS as KNN_NEIGHBOURS
from sb3_pearl.pearl.diagnostics.overlap import compute_overlap, gaussian_classifier_auc, knn_classifier_auc, roc_auc
from sb3_pearl.pearl.diagnostics.prior import PriorTerm, prior_term
from sb3_pearl.pearl.diagnostics.rollouts import FixedZRollout, _collect_context, _posteriors, rollout_with_z
from sb3_pearl.pearl.diagnostics.violations import compute_violations
from sb3_pearl.pearl.pearl import PEARL

DEFAULT_N_TASKS = 8
DEFAULT_N_Z0 = 16
DEFAULT_N_POSTERIOR_SAMPLES = 32
DEFAULT_N_GRAD_BATCHES = 4
MAX_CONTEXT_STEPS = 1000


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
    if not isinstance(model, PEARL):
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
            "prior_critic": prior_term(model).critic_mode,
            "prior_coef": prior_term(model).coef,
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
        f"  relative error {f2(c.get('relative_error'))}, rank correlation {f2(c.get('rank_corr'))}; "
        f"task-blind reference {f2(c.get('task_blind_relative_error'))}, "
        f"{f2(c.get('task_blind_rank_corr'))} (bar: under 0.25, over 0.5)",
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
    "PriorTerm",
    "actor_gradient_conflict",
    "compute_calibration",
    "compute_diagnostics",
    "compute_gradient_conflict",
    "compute_overlap",
    "compute_violations",
    "format_diagnostics",
    "gaussian_classifier_auc",
    "knn_classifier_auc",
    "prior_term",
    "record_gradient_conflict",
    "roc_auc",
    "rollout_with_z",
]
