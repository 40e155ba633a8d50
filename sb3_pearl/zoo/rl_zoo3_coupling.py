"""Every point where the project reaches into rl_zoo3's internals, and the contract each relies on.

rl_zoo3 is used as a library only through the names below; every other module of the project imports them from here
(no other module imports ``rl_zoo3``). The names were checked against rl_zoo3's tags v1.7.0 to v2.8.0 and the installed
2.9.2; ``tests/test_zoo_coupling.py`` fails if one is renamed, removed or loses a parameter the project passes.

**Replaced for one call** (``unittest.mock.patch.object``, restored on exit, also on errors), because rl_zoo3 takes no
class for them as an argument and reads its own module globals instead:

- ``sys.argv``, ``rl_zoo3.train.ExperimentManager`` and ``rl_zoo3.train.StoreDict``, by :func:`run_zoo_train`:
  ``rl_zoo3.train.train()`` parses ``sys.argv`` with ``parser.parse_args()`` (the project's own flags are removed
  first), builds the module-global ``ExperimentManager`` (here :class:`~sb3_pearl.zoo.MetaExperimentManager`, with the
  project's ``--budget`` / ``--resume`` settings bound) and gives ``-params`` / ``--env-kwargs`` to the module-global
  ``StoreDict`` action (here :class:`~sb3_pearl.zoo.usage.CheckedStoreDict`: a bad value is a one-line usage error).
  ``train()`` since 1.7.0 (the ``rl_zoo3`` package); ``StoreDict`` in ``rl_zoo3.utils`` since then.
- ``rl_zoo3.exp_manager.TrialEvalCallback``, by :func:`trial_eval_callback_replaced`: ``ExperimentManager.objective``
  builds each Optuna trial's evaluation callback from that name with the arguments ``(eval_env, trial,
  best_model_save_path=, log_path=, n_eval_episodes=, eval_freq=, deterministic=)`` and reads its ``is_pruned`` and
  ``last_mean_reward``; the project puts the meta-test there
  (:class:`~sb3_pearl.evaluation.callbacks.MetaTestTrialCallback`). Since 1.7.0.

**Registered into** (dicts of rl_zoo3, updated in place by :func:`register_algorithms`, idempotent):

- ``rl_zoo3.ALGOS`` (the same dict as ``rl_zoo3.utils.ALGOS``, which ``train()``'s ``--algo`` choices and
  ``ExperimentManager`` read): the zoo names ``pearl``, ``pearlplus``, ``finetune``, ``maml``. Since 1.7.0.
- ``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER`` and ``HYPERPARAMS_CONVERTER`` (``-optimize``; ``--trial-id``
  converts a stored trial's parameters with the converter): the PEARL / PEARL+ samplers. The converter and
  ``ExperimentManager``'s ``trial_id`` argument exist since 2.6.0, hence the floor ``rl_zoo3>=2.6`` in pyproject.toml.

**Subclassed**: ``rl_zoo3.exp_manager.ExperimentManager`` (since 1.7.0), by
:class:`~sb3_pearl.zoo.interruptions.InterruptibleExperimentManager` and
:class:`~sb3_pearl.zoo.meta_testing.MetaTestExperimentManager` (put together in
:class:`~sb3_pearl.zoo.MetaExperimentManager`). The methods overridden are :data:`EXPERIMENT_MANAGER_HOOKS` (each
calls rl_zoo3's, with the parameters listed), the attributes read are :data:`EXPERIMENT_MANAGER_ATTRIBUTES` (set by
rl_zoo3's ``__init__``), and the constructor keywords the project passes or reads are
:data:`EXPERIMENT_MANAGER_KWARGS`. What the overrides rely on beyond names: ``create_callbacks`` fills
``self.callbacks`` with a ``ProgressBarCallback`` (``-P``) and a ``CheckpointCallback`` (``--save-freq``), ``learn``
closes ``self.callbacks[0]`` when training stops and treats ``KeyboardInterrupt`` as a stop, ``trial_id`` is tested
for truth (``--trial-id 0`` needs :class:`~sb3_pearl.zoo.algos.OptunaTrialIndex`), and a ``policy_kwargs``
string is ``eval``-ed with ``torch.nn`` as ``nn`` while a dict is kept (a zoo YAML's ``policy_kwargs`` are strings; a
budget preset's arrive as a dict, converted by the project's ``_preprocess_hyperparams`` first, :mod:`sb3_pearl.zoo.budget`).

**Called**: ``rl_zoo3.create_test_env`` and ``rl_zoo3.utils.get_model_path`` (``enjoy.py`` finds and wraps a model
as rl_zoo3's enjoy does), ``rl_zoo3.utils.get_latest_run_id`` (the run-folder number). Since 1.7.0.
``rl_zoo3.utils.get_saved_hyperparams`` is not called: :mod:`sb3_pearl.zoo.safe_config` re-implements it over a
safe YAML loader.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any
from unittest import mock

import rl_zoo3
import rl_zoo3.exp_manager
import rl_zoo3.hyperparams_opt
import rl_zoo3.train
import rl_zoo3.utils
from rl_zoo3 import ALGOS, create_test_env
from rl_zoo3.exp_manager import ExperimentManager
from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from rl_zoo3.utils import StoreDict, get_latest_run_id, get_model_path
from stable_baselines3.common.base_class import BaseAlgorithm

# ExperimentManager's methods the project overrides (each calls rl_zoo3's), with the parameters rl_zoo3 calls them with.
EXPERIMENT_MANAGER_HOOKS: dict[str, tuple[str, ...]] = {
    "__init__": ("self", "args", "algo", "env_id", "log_folder"),
    "read_hyperparameters": ("self",),
    "_preprocess_hyperparams": ("self", "hyperparams"),
    "setup_experiment": ("self",),
    "create_log_folder": ("self",),
    "create_callbacks": ("self",),
    "_load_pretrained_agent": ("self", "hyperparams", "env"),
    "hyperparameters_optimization": ("self",),
    "learn": ("self", "model"),
    "save_trained_model": ("self", "model"),
    "create_envs": ("self", "n_envs", "eval_env", "no_log"),
}
# ExperimentManager's constructor keywords the project passes (``config``) or reads back as attributes.
EXPERIMENT_MANAGER_KWARGS: tuple[str, ...] = (
    "tensorboard_log",
    "n_timesteps",
    "eval_freq",
    "n_eval_episodes",
    "hyperparams",
    "env_kwargs",
    "eval_env_kwargs",
    "trained_agent",
    "optimize_hyperparameters",
    "seed",
    "log_interval",
    "save_replay_buffer",
    "verbose",
    "config",
    "show_progress",
    "trial_id",
)
# Attributes of an ExperimentManager (set by rl_zoo3's __init__) the project's subclasses read or set.
EXPERIMENT_MANAGER_ATTRIBUTES: tuple[str, ...] = (
    "algo",
    "env_name",
    "config",
    "custom_hyperparams",
    "trial_id",
    "tensorboard_log",
    "env_kwargs",
    "eval_env_kwargs",
    "seed",
    "n_timesteps",
    "n_envs",
    "eval_freq",
    "n_eval_episodes",
    "callbacks",
    "optimize_hyperparameters",
    "verbose",
    "show_progress",
    "trained_agent",
    "continue_training",
    "log_interval",
    "save_replay_buffer",
    "log_path",
    "save_path",
    "params_path",
    "vec_env_class",
)


def register_algorithms(
    algos: Mapping[str, type[BaseAlgorithm]],
    samplers: Mapping[str, Callable[..., dict[str, Any]]],
    converters: Mapping[str, Callable[[dict[str, Any]], dict[str, Any]]],
) -> None:
    """
    Put algorithms and their Optuna samplers into rl_zoo3's registries (updated in place: idempotent).

    :param algos: zoo name -> algorithm class (``rl_zoo3.ALGOS``)
    :param samplers: zoo name -> hyperparameter sampler (``HYPERPARAMS_SAMPLER``)
    :param converters: zoo name -> converter of a stored trial's parameters (``HYPERPARAMS_CONVERTER``)
    """
    ALGOS.update(algos)
    HYPERPARAMS_SAMPLER.update(samplers)
    HYPERPARAMS_CONVERTER.update(converters)


def run_zoo_train(
    argv: Sequence[str],
    experiment_manager: Callable[..., ExperimentManager],
    store_dict: type[StoreDict],
) -> None:
    """
    ``rl_zoo3.train.train()`` on ``argv``, with another experiment manager and ``StoreDict`` action (module docstring):
    ``sys.argv`` and the two module globals of ``rl_zoo3.train`` are replaced for this call only.

    :param argv: rl_zoo3's arguments (without the program name)
    :param experiment_manager: called as rl_zoo3 calls ``ExperimentManager`` (a subclass, or a partial of one)
    :param store_dict: the argparse action of ``-params``, ``--env-kwargs`` and ``--eval-env-kwargs``
    """
    with (
        mock.patch.object(sys, "argv", [sys.argv[0], *argv]),
        mock.patch.object(rl_zoo3.train, "ExperimentManager", experiment_manager),
        mock.patch.object(rl_zoo3.train, "StoreDict", store_dict),
    ):
        rl_zoo3.train.train()


@contextmanager
def trial_eval_callback_replaced(callback: Callable[..., Any]) -> Iterator[None]:
    """
    Within the block, ``ExperimentManager.objective`` builds each Optuna trial's evaluation callback with ``callback``
    (called as rl_zoo3's ``TrialEvalCallback``, module docstring).

    :param callback: a ``TrialEvalCallback``-like class or factory
    """
    with mock.patch.object(rl_zoo3.exp_manager, "TrialEvalCallback", callback):
        yield


__all__ = [
    "ALGOS",
    "EXPERIMENT_MANAGER_ATTRIBUTES",
    "EXPERIMENT_MANAGER_HOOKS",
    "EXPERIMENT_MANAGER_KWARGS",
    "ExperimentManager",
    "StoreDict",
    "create_test_env",
    "get_latest_run_id",
    "get_model_path",
    "register_algorithms",
    "run_zoo_train",
    "trial_eval_callback_replaced",
]
