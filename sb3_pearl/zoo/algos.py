"""The project's algorithms in ``rl_zoo3`` (not a registry of its own: it puts :mod:`sb3_pearl.registry`'s algorithms in
``rl_zoo3.ALGOS``), the constructor kwargs of each and the Optuna samplers.

:func:`register_algos` puts ``pearl`` / ``pearlplus`` (and ``finetune`` / ``maml`` / ``oracle`` when
:mod:`sb3_pearl` exports ``FineTune`` / ``MAML`` / ``Oracle``) in ``rl_zoo3.ALGOS`` and the PEARL / PEARL+
hyperparameter samplers in ``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER`` (``-optimize``), through
:func:`sb3_pearl.zoo.rl_zoo3_coupling.register_algorithms`.
"""

from __future__ import annotations

from typing import Any

import optuna
from stable_baselines3.common.base_class import BaseAlgorithm
from torch import nn

import sb3_pearl
from sb3_pearl.pearl import PEARL, PEARLPlus
from sb3_pearl.registry import ZOO_SET_KWARGS, constructor_kwargs
from sb3_pearl.zoo.rl_zoo3_coupling import register_algorithms

# Optuna categorical choices (names are stored in the study, converted by convert_pearl_params)
NET_ARCHS: dict[str, list[int]] = {"small": [64, 64], "medium": [256, 256], "big": [300, 300, 300]}
ENCODER_ARCHS: dict[str, list[int]] = {"small": [64, 64], "medium": [200, 200], "big": [200, 200, 200]}


def convert_pearl_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """
    Constructor kwargs from the Optuna parameters of :func:`sample_pearl_params` / :func:`sample_pearlplus_params`.

    :param sampled_params: the trial's parameters
    :return: PEARL / PEARL+ kwargs
    """
    params = dict(sampled_params)
    hyperparams: dict[str, Any] = {}
    hyperparams["gamma"] = 1.0 - params.pop("one_minus_gamma")
    hyperparams["batch_size"] = 2 ** params.pop("batch_size_pow")
    hyperparams["policy_kwargs"] = {"net_arch": NET_ARCHS[params.pop("net_arch")], "activation_fn": nn.ReLU}
    hyperparams["encoder_arch"] = ENCODER_ARCHS[params.pop("encoder_arch")]
    if "prior_critic_arch" in params:
        hyperparams["prior_critic_arch"] = NET_ARCHS[params.pop("prior_critic_arch")]
    hyperparams.update(params)
    return hyperparams


def _suggest_pearl(trial: optuna.Trial) -> None:
    trial.suggest_float("learning_rate", 1e-4, 1e-3, log=True)
    trial.suggest_float("kl_weight", 0.01, 1.0, log=True)
    trial.suggest_categorical("latent_dim", [3, 5, 8])
    trial.suggest_float("one_minus_gamma", 0.001, 0.05, log=True)
    trial.suggest_int("batch_size_pow", 6, 8)  # 64 .. 256 rows per task
    trial.suggest_categorical("net_arch", list(NET_ARCHS))
    trial.suggest_categorical("encoder_arch", list(ENCODER_ARCHS))
    trial.suggest_categorical("reward_scale", [1.0, 3.0, 5.0, 10.0])


def sample_pearl_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """
    Optuna sampler for PEARL: learning rate, KL weight, latent size, discount, batch size, net sizes, reward scale.

    :param trial: the Optuna trial
    :param n_actions: action dimension (unused)
    :param n_envs: number of envs (unused)
    :param additional_args: rl_zoo3's extra arguments (unused)
    :return: constructor kwargs
    """
    _suggest_pearl(trial)
    return convert_pearl_params(trial.params)


def sample_pearlplus_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """
    Optuna sampler for PEARL+: the PEARL parameters plus ``prior_coef`` (alpha) and the prior critic's size.

    :param trial: the Optuna trial
    :param n_actions: action dimension (unused)
    :param n_envs: number of envs (unused)
    :param additional_args: rl_zoo3's extra arguments (unused)
    :return: constructor kwargs
    """
    _suggest_pearl(trial)
    trial.suggest_float("prior_coef", 0.01, 1.0, log=True)  # the paper: 0.1 works, 1 and 5 hurt adaptation
    trial.suggest_categorical("prior_critic_arch", list(NET_ARCHS))
    return convert_pearl_params(trial.params)


class OptunaTrialIndex(int):
    """A trial index that is true even when 0: rl_zoo3 tests ``trial_id`` for truth and would skip ``--trial-id 0``."""

    def __bool__(self) -> bool:
        return True


def register_algos() -> dict[str, type[BaseAlgorithm]]:
    """
    Register the project's algorithms (and samplers) with rl_zoo3; idempotent.

    ``pearl`` and ``pearlplus`` always; ``finetune`` and ``maml`` when :mod:`sb3_pearl` exports
    ``FineTune`` / ``MAML``. A sampler is registered for the algorithms that have one here.

    :return: the registered algorithms by zoo name
    """
    algos: dict[str, type[BaseAlgorithm]] = {"pearl": PEARL, "pearlplus": PEARLPlus}
    for name, attribute in (("finetune", "FineTune"), ("maml", "MAML"), ("oracle", "Oracle")):
        algo = getattr(sb3_pearl, attribute, None)
        if algo is not None:
            algos[name] = algo
    register_algorithms(
        algos,
        samplers={"pearl": sample_pearl_params, "pearlplus": sample_pearlplus_params},
        converters={"pearl": convert_pearl_params, "pearlplus": convert_pearl_params},
    )
    return algos


__all__ = [
    "ENCODER_ARCHS",
    "NET_ARCHS",
    "ZOO_SET_KWARGS",
    "constructor_kwargs",
    "convert_pearl_params",
    "register_algos",
    "sample_pearl_params",
    "sample_pearlplus_params",
]
