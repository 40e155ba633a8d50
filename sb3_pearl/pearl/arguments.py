"""The checks of PEARL's constructor arguments: each error names the argument, its range, what it does and the value."""

from __future__ import annotations

from typing import Any

from stable_baselines3.common.type_aliases import Schedule

from sb3_pearl.common.checks import (
    check_arch,
    check_ent_coef,
    check_gamma,
    check_int,
    check_learning_rate,
    check_real,
    check_tau,
)
from sb3_pearl.common.meta_algorithm import check_task_arguments
from sb3_pearl.envs.task_protocol import Task

PARTIAL_ITERATION_MODES = ("train", "carry")


def check_pearl_arguments(
    learning_rate: float | Schedule,
    buffer_size: int,
    batch_size: int,
    tau: float,
    gamma: float,
    latent_dim: int,
    kl_weight: float,
    encoder_arch: list[int] | None,
    ent_coef: str | float,
    target_entropy: str | float,
    reward_scale: float,
    n_train_tasks: int,
    n_test_tasks: int,
    train_tasks: list[Task] | None,
    test_tasks: list[Task] | None,
    meta_batch: int,
    embedding_batch_size: int,
    num_initial_steps: int,
    num_tasks_sample: int,
    num_steps_prior: int,
    num_steps_posterior: int,
    num_extra_rl_steps_posterior: int,
    num_train_steps_per_itr: int,
    use_bf16: bool | str,
    grad_conflict_log_freq: int,
    partial_iteration: str,
    policy_kwargs: dict[str, Any] | None,
) -> None:
    """
    Raise a ValueError for the first argument of :class:`~sb3_pearl.PEARL` out of its range (see its docstring).

    Called before anything is built, so that a bad argument fails before an env is made.
    """
    check_task_arguments(n_train_tasks, n_test_tasks, train_tasks, test_tasks)
    for name, value, hint in (
        ("meta_batch", meta_batch, "tasks per gradient step"),
        ("batch_size", batch_size, "RL transitions per task in a gradient step"),
        ("embedding_batch_size", embedding_batch_size, "context transitions per task in a gradient step"),
        ("buffer_size", buffer_size, "RL transitions kept per task"),
        ("latent_dim", latent_dim, "size of z"),
        ("num_tasks_sample", num_tasks_sample, "tasks visited per iteration"),
    ):
        check_int(name, value, 1, hint)
    for name, value, hint in (
        ("num_train_steps_per_itr", num_train_steps_per_itr, "gradient steps per iteration; 0 collects only"),
        ("num_initial_steps", num_initial_steps, "prior steps per training task in iteration 0"),
        ("num_steps_prior", num_steps_prior, "prior-z steps per visited task"),
        ("num_steps_posterior", num_steps_posterior, "posterior-z steps per visited task"),
        ("num_extra_rl_steps_posterior", num_extra_rl_steps_posterior, "posterior-z steps for the RL buffer only"),
        ("grad_conflict_log_freq", grad_conflict_log_freq, "0: off"),
    ):
        check_int(name, value, 0, hint)
    if num_steps_prior + num_steps_posterior == 0:
        raise ValueError(
            "num_steps_prior + num_steps_posterior must be > 0: they fill the context buffer the encoder trains on"
        )
    check_learning_rate("learning_rate", learning_rate)
    check_gamma(gamma)
    check_tau(tau)
    check_ent_coef(ent_coef)
    check_real("kl_weight", kl_weight, 0.0, hint="weight of the KL term; 0 turns it off")
    check_real("reward_scale", reward_scale, 0.0, low_open=True, hint="rewards are multiplied by it in the critic targets")
    if target_entropy != "auto":
        check_real("target_entropy", target_entropy, hint="or 'auto'")
    check_arch("encoder_arch", encoder_arch)
    check_arch("policy_kwargs['net_arch']", (policy_kwargs or {}).get("net_arch"))
    if partial_iteration not in PARTIAL_ITERATION_MODES:
        raise ValueError(
            f"partial_iteration must be one of {PARTIAL_ITERATION_MODES} (what learn() does with an iteration its budget "
            f"ends in: train the collected share, or keep it open for the next learn()), got {partial_iteration!r}"
        )
    if use_bf16 not in (True, False, "force"):
        raise ValueError(f"use_bf16 must be True, False or 'force' (bfloat16 even without native support), got {use_bf16!r}")
