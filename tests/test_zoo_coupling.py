"""The rl_zoo3 contract of :mod:`sb3_pearl.zoo.rl_zoo3_coupling`: fails if rl_zoo3 renames, removes or reshapes a name
the project subclasses, patches, registers into or calls, and if a module other than the coupling one imports rl_zoo3."""

from __future__ import annotations

import argparse
import ast
import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import rl_zoo3
import rl_zoo3.callbacks
import rl_zoo3.exp_manager
import rl_zoo3.hyperparams_opt
import rl_zoo3.train
import rl_zoo3.utils

from sb3_pearl.zoo import MetaExperimentManager, rl_zoo3_coupling
from sb3_pearl.zoo.algos import register_algos
from sb3_pearl.zoo.interruptions import InterruptibleExperimentManager
from sb3_pearl.zoo.meta_testing import MetaTestExperimentManager

ROOT = Path(__file__).resolve().parent.parent
ExperimentManager = rl_zoo3.exp_manager.ExperimentManager


def parameter_names(function: Callable[..., Any]) -> list[str]:
    return list(inspect.signature(function).parameters)


def test_train_reads_the_patched_module_globals() -> None:
    """``train()`` builds ``rl_zoo3.train.ExperimentManager`` and the ``StoreDict`` action by their module names."""
    assert callable(rl_zoo3.train.train) and parameter_names(rl_zoo3.train.train) == []
    names = rl_zoo3.train.train.__code__.co_names
    assert "ExperimentManager" in names and "StoreDict" in names
    assert rl_zoo3.train.ExperimentManager is ExperimentManager
    assert rl_zoo3.train.StoreDict is rl_zoo3.utils.StoreDict
    assert "parse_args()" in inspect.getsource(rl_zoo3.train.train)  # reads sys.argv


def test_experiment_manager_call_matches_train() -> None:
    """The constructor keywords ``train()`` passes, and the ones the project reads back, are still there."""
    init = inspect.signature(ExperimentManager.__init__).parameters
    assert list(init)[:5] == list(rl_zoo3_coupling.EXPERIMENT_MANAGER_HOOKS["__init__"])
    missing = [name for name in rl_zoo3_coupling.EXPERIMENT_MANAGER_KWARGS if name not in init]
    assert not missing, f"ExperimentManager.__init__ lost {missing}"
    source = inspect.getsource(rl_zoo3.train.train)
    assert "config=args.conf_file" in source and "trial_id=args.trial_id" in source


def test_experiment_manager_hooks_and_attributes() -> None:
    """Every method the project overrides exists with the parameters it is called with; the attributes read are set."""
    for name, parameters in rl_zoo3_coupling.EXPERIMENT_MANAGER_HOOKS.items():
        method = getattr(ExperimentManager, name, None)
        assert callable(method), f"ExperimentManager.{name} is gone"
        assert parameter_names(method)[: len(parameters)] == list(parameters), name
    source = inspect.getsource(ExperimentManager)
    for attribute in rl_zoo3_coupling.EXPERIMENT_MANAGER_ATTRIBUTES:
        assert f"self.{attribute} =" in source or f"self.{attribute}:" in source, f"ExperimentManager.{attribute} not set"


def test_the_hook_list_is_complete() -> None:
    """Each ExperimentManager method the project's managers override is listed in the contract."""
    overridden = {
        name
        for cls in (InterruptibleExperimentManager, MetaTestExperimentManager, MetaExperimentManager)
        for name in vars(cls)
        if callable(getattr(ExperimentManager, name, None)) and callable(vars(cls)[name])
    }
    assert overridden <= set(rl_zoo3_coupling.EXPERIMENT_MANAGER_HOOKS), overridden - set(
        rl_zoo3_coupling.EXPERIMENT_MANAGER_HOOKS
    )


def test_trial_eval_callback_name() -> None:
    """``objective`` builds the trial callback from ``rl_zoo3.exp_manager.TrialEvalCallback`` with these arguments."""
    assert "TrialEvalCallback" in ExperimentManager.objective.__code__.co_names
    assert rl_zoo3.exp_manager.TrialEvalCallback is rl_zoo3.callbacks.TrialEvalCallback
    parameters = parameter_names(rl_zoo3.callbacks.TrialEvalCallback.__init__)
    for name in ("eval_env", "trial", "n_eval_episodes", "eval_freq", "deterministic", "best_model_save_path", "log_path"):
        assert name in parameters


def test_trial_eval_callback_replaced_restores() -> None:
    original = rl_zoo3.exp_manager.TrialEvalCallback
    marker = object()
    with rl_zoo3_coupling.trial_eval_callback_replaced(marker):  # type: ignore[arg-type]
        assert rl_zoo3.exp_manager.TrialEvalCallback is marker
    assert rl_zoo3.exp_manager.TrialEvalCallback is original


def test_store_dict_is_an_argparse_action() -> None:
    store_dict = rl_zoo3.utils.StoreDict
    assert issubclass(store_dict, argparse.Action)
    assert parameter_names(store_dict.__call__) == ["self", "parser", "namespace", "values", "option_string"]


def test_registries_are_shared_dicts() -> None:
    """The dicts the project registers into are the ones ``train()``, ``ExperimentManager`` and the samplers read."""
    assert rl_zoo3.ALGOS is rl_zoo3.utils.ALGOS is rl_zoo3.train.ALGOS
    assert rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER is rl_zoo3.exp_manager.HYPERPARAMS_SAMPLER
    assert rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER is rl_zoo3.exp_manager.HYPERPARAMS_CONVERTER
    algos = register_algos()
    assert all(rl_zoo3.ALGOS[name] is algo for name, algo in algos.items())
    assert {"pearl", "pearlplus"} <= set(rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER)
    assert {"pearl", "pearlplus"} <= set(rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER)


@pytest.mark.parametrize(
    ("function", "parameters"),
    [
        (rl_zoo3.create_test_env, ("env_id", "n_envs", "stats_path", "seed", "should_render", "hyperparams", "env_kwargs")),
        (rl_zoo3.utils.get_model_path, ("exp_id", "folder", "algo", "env_name", "load_best", "load_checkpoint")),
        (rl_zoo3.utils.get_latest_run_id, ("log_path", "env_name")),
    ],
)
def test_called_functions(function: Callable[..., Any], parameters: tuple[str, ...]) -> None:
    assert set(parameters) <= set(parameter_names(function)), function.__name__


def test_only_the_coupling_module_imports_rl_zoo3() -> None:
    """rl_zoo3 is reached through :mod:`sb3_pearl.zoo.rl_zoo3_coupling` only (its docstring is the contract)."""
    offenders = []
    for path in [*sorted((ROOT / "sb3_pearl").rglob("*.py")), ROOT / "train.py", ROOT / "enjoy.py"]:
        if path.name == "rl_zoo3_coupling.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            if any(name == "rl_zoo3" or name.startswith("rl_zoo3.") for name in names):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, offenders
