"""The checks of PEARL's constructor arguments: each error names the argument, its range, what it does and the value."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

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
from sb3_pearl.pearl.policies import check_latent_dim

PARTIAL_ITERATION_MODES = ("train", "carry")


def check_pearl_arguments(arguments: Mapping[str, Any]) -> None:
    """
    Raise a ValueError for the first argument of :class:`~sb3_pearl.PEARL` out of its range (see its docstring).

    Called before anything is built, so that a bad argument fails before an env is made; it reads the constructor's
    bound arguments (``locals()`` at the top of ``PEARL.__init__``), so the signature is written once, in ``PEARL``.

    :param arguments: ``PEARL.__init__``'s arguments by name, defaults included
    """
    args = arguments
    check_task_arguments(args["n_train_tasks"], args["n_test_tasks"], args["train_tasks"], args["test_tasks"])
    for name, hint in (
        ("meta_batch", "tasks per gradient step"),
        ("batch_size", "RL transitions per task in a gradient step"),
        ("embedding_batch_size", "context transitions per task in a gradient step"),
        ("buffer_size", "RL transitions kept per task"),
        ("num_tasks_sample", "tasks visited per iteration"),
    ):
        check_int(name, args[name], 1, hint)
    for name, hint in (
        ("num_train_steps_per_itr", "gradient steps per iteration; 0 collects only"),
        ("num_initial_steps", "prior steps per training task in iteration 0"),
        ("num_steps_prior", "prior-z steps per visited task"),
        ("num_steps_posterior", "posterior-z steps per visited task"),
        ("num_extra_rl_steps_posterior", "posterior-z steps for the RL buffer only"),
        ("grad_conflict_log_freq", "0: off"),
    ):
        check_int(name, args[name], 0, hint)
    if args["num_steps_prior"] + args["num_steps_posterior"] == 0:
        raise ValueError(
            "num_steps_prior + num_steps_posterior must be > 0: they fill the context buffer the encoder trains on"
        )
    check_latent_dim(args["latent_dim"])  # the policy's check, before anything is built
    check_learning_rate("learning_rate", args["learning_rate"])
    check_gamma(args["gamma"])
    check_tau(args["tau"])
    check_ent_coef(args["ent_coef"])
    check_real("kl_weight", args["kl_weight"], 0.0, hint="weight of the KL term; 0 turns it off")
    check_real(
        "reward_scale", args["reward_scale"], 0.0, low_open=True, hint="rewards are multiplied by it in the critic targets"
    )
    if args["target_entropy"] != "auto":
        check_real("target_entropy", args["target_entropy"], hint="or 'auto'")
    check_arch("encoder_arch", args["encoder_arch"])
    check_arch("policy_kwargs['net_arch']", (args["policy_kwargs"] or {}).get("net_arch"))
    partial_iteration = args["partial_iteration"]
    if partial_iteration not in PARTIAL_ITERATION_MODES:
        raise ValueError(
            f"partial_iteration must be one of {PARTIAL_ITERATION_MODES} (what learn() does with an iteration its budget "
            f"ends in: train the collected share, or keep it open for the next learn()), got {partial_iteration!r}"
        )
    use_bf16 = args["use_bf16"]
    if use_bf16 not in (True, False, "force"):
        raise ValueError(f"use_bf16 must be True, False or 'force' (bfloat16 even without native support), got {use_bf16!r}")
