"""rl_zoo3's ``ExperimentManager`` with the meta-test, and :func:`train` (``train.py``).

:class:`MetaExperimentManager` is rl_zoo3's ``ExperimentManager`` with: the default
hyperparameter file ``zoo_hyperparams/<algo>.yml`` (instead of rl_zoo3's package folder); a
clear error for a YAML / ``-params`` key the algorithm does not take; the meta-test protocol
as the evaluation callback (``--eval-freq``, ``--eval-episodes`` test tasks, logger keys
``meta_test/...``, ``best_model.zip``) and as the Optuna trial score; and, after the model is
saved (also after Ctrl-C), the final meta-test written to ``meta_test.csv``, ``meta_test.json``
and ``adaptation.png`` in the run folder. :func:`train` runs ``rl_zoo3.train.train()`` with it and
the project's algorithms (argument parsing, log layout and the Optuna loop are rl_zoo3's).

The zoo special key ``meta_test`` (a dict, optional) sets the final meta-test:
``n_adapt`` (K, default 5), ``n_repeats`` (1), ``n_tasks`` (None: every saved test task),
``deterministic`` (True); e.g. ``-params meta_test:"dict(n_adapt=3)"``.
"""

from __future__ import annotations

import functools
import glob
import importlib.util
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import rl_zoo3.exp_manager
import rl_zoo3.train
import yaml
from rl_zoo3 import ALGOS
from rl_zoo3.exp_manager import ExperimentManager
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.adaptation import has_adaptation_api
from sb3_pearl.common.callbacks import MetaTestCallback, MetaTestTrialCallback
from sb3_pearl.common.meta_test import MetaTestResult, get_test_tasks, meta_test
from sb3_pearl.zoo.registry import constructor_kwargs, register_algos

# The repository's zoo_hyperparams/ folder (this file is sb3_pearl/zoo/experiment_manager.py).
HYPERPARAMS_DIR = Path(__file__).resolve().parents[2] / "zoo_hyperparams"

# Keys the zoo reads itself (rl_zoo3 ExperimentManager._preprocess_*), never constructor kwargs.
ZOO_SPECIAL_KEYS = frozenset(
    {
        "n_timesteps",
        "n_envs",
        "normalize",
        "env_kwargs",
        "monitor_kwargs",
        "frame_stack",
        "env_wrapper",
        "vec_env_wrapper",
        "callback",
        "noise_type",
        "noise_std",
        "meta_test",
    }
)
META_TEST_DEFAULTS: dict[str, Any] = {"n_adapt": 5, "n_repeats": 1, "n_tasks": None, "deterministic": True}


def default_config(algo: str) -> str:
    """The project's hyperparameter file of ``algo``: ``zoo_hyperparams/<algo>.yml``."""
    return str(HYPERPARAMS_DIR / f"{algo}.yml")


def write_meta_test(result: MetaTestResult, folder: str | os.PathLike[str], title: str = "") -> dict[str, str]:
    """
    Write ``meta_test.csv``, ``meta_test.json`` and ``adaptation.png`` into ``folder``.

    :param result: the meta-test result
    :param folder: the run folder
    :param title: figure title
    :return: the written paths by kind
    """
    from sb3_pearl.plots import plot_adaptation  # matplotlib only when needed

    os.makedirs(folder, exist_ok=True)
    paths = {
        "csv": os.path.join(folder, "meta_test.csv"),
        "json": os.path.join(folder, "meta_test.json"),
        "png": os.path.join(folder, "adaptation.png"),
    }
    result.to_csv(paths["csv"])
    result.to_json(paths["json"])
    plot_adaptation({title or result.config.get("algorithm", "model"): result}, paths["png"], title=title)
    return paths


class MetaExperimentManager(ExperimentManager):
    """
    rl_zoo3's ``ExperimentManager`` for meta-RL (module docstring): same arguments, same log layout.

    The evaluation callback is :class:`~sb3_pearl.common.callbacks.MetaTestCallback` for
    algorithms with the adaptation API (``--eval-episodes`` test tasks per evaluation,
    k = 0..``meta_test.n_adapt``); others keep rl_zoo3's ``EvalCallback``.
    """

    def __init__(self, args: Any, algo: str, env_id: str, log_folder: str, *posargs: Any, **kwargs: Any) -> None:
        if kwargs.get("config") is None and os.path.isfile(default_config(algo)):
            kwargs["config"] = default_config(algo)  # else rl_zoo3's own file (its algorithms)
        super().__init__(args, algo, env_id, log_folder, *posargs, **kwargs)
        self.meta_test_kwargs: dict[str, Any] = dict(META_TEST_DEFAULTS)
        self.adaptive = has_adaptation_api(ALGOS[algo])
        if self.tensorboard_log is not None and importlib.util.find_spec("tensorboard") is None:
            raise ImportError("-tb/--tensorboard-log needs the tensorboard package (not installed): pip install tensorboard")

    # -- hyperparameters ---------------------------------------------------------------------------
    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        if not os.path.isfile(self.config) and self.config.endswith((".yml", ".yaml")):
            raise FileNotFoundError(f"hyperparameter file {self.config} not found (expected zoo_hyperparams/{self.algo}.yml)")
        hyperparams, saved_hyperparams = super().read_hyperparameters()
        self.check_hyperparameters(hyperparams)
        return hyperparams, saved_hyperparams

    def check_hyperparameters(self, hyperparams: dict[str, Any]) -> None:
        """
        Raise a clear error for a key that is neither a constructor kwarg of the algorithm nor a zoo special key.

        :param hyperparams: the entry after ``-params`` overrides
        """
        algo_class = ALGOS[self.algo]
        accepted = constructor_kwargs(algo_class)
        unknown = sorted(set(hyperparams) - accepted - ZOO_SPECIAL_KEYS)
        if unknown:
            overridden = sorted(set(unknown) & set(self.custom_hyperparams or {}))
            where = f"-params ({', '.join(overridden)})" if overridden else f"{self.config} [{self.env_name.gym_id}]"
            raise ValueError(
                f"{algo_class.__name__} does not take the hyperparameter(s) {unknown} given in {where}. "
                f"Accepted constructor kwargs: {sorted(accepted)}; zoo keys: {sorted(ZOO_SPECIAL_KEYS)}"
            )
        meta = hyperparams.get("meta_test") or {}
        if isinstance(meta, str):
            meta = eval(meta)  # the zoo's convention for dict values given as strings
        if not isinstance(meta, dict) or set(meta) - set(META_TEST_DEFAULTS):
            raise ValueError(f"meta_test must be a dict with keys among {sorted(META_TEST_DEFAULTS)}, got {meta!r}")

    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> Any:
        meta = hyperparams.pop("meta_test", None) or {}
        if isinstance(meta, str):
            meta = eval(meta)
        self.meta_test_kwargs.update(meta)
        return super()._preprocess_hyperparams(hyperparams)

    # -- evaluation ------------------------------------------------------------------------------------
    def create_callbacks(self) -> None:
        if not self.adaptive:
            super().create_callbacks()
            return
        eval_freq, self.eval_freq = self.eval_freq, -1  # the zoo's EvalCallback is replaced below
        super().create_callbacks()
        self.eval_freq = eval_freq
        if self.eval_freq > 0 and not self.optimize_hyperparameters:
            self.eval_freq = max(self.eval_freq // self.n_envs, 1)
            if self.verbose > 0:
                print("Creating meta-test environment")
            self.callbacks.append(
                MetaTestCallback(
                    self.create_envs(1, eval_env=True),  # the protocol runs one env
                    eval_freq=self.eval_freq,
                    n_tasks=self.n_eval_episodes,
                    n_adapt=self.meta_test_kwargs["n_adapt"],
                    n_repeats=self.meta_test_kwargs["n_repeats"],
                    deterministic=self.meta_test_kwargs["deterministic"],
                    sample_tasks=self._shifted_eval(),
                    seed=self.seed,
                    best_model_save_path=self.save_path,
                    log_path=self.save_path,
                    verbose=self.verbose,
                )
            )

    def _shifted_eval(self) -> bool:
        """Evaluation tasks are drawn from the eval env when ``--eval-env-kwargs`` differ from the training env's."""
        return self._eval_env_kwargs_args is not None and self.eval_env_kwargs != self.env_kwargs

    def hyperparameters_optimization(self) -> None:
        if not self.adaptive:
            super().hyperparameters_optimization()
            return
        original = rl_zoo3.exp_manager.TrialEvalCallback
        settings = {key: self.meta_test_kwargs[key] for key in ("n_adapt", "n_repeats")}
        rl_zoo3.exp_manager.TrialEvalCallback = functools.partial(MetaTestTrialCallback, **settings)  # type: ignore[misc,assignment]
        try:
            super().hyperparameters_optimization()
        finally:
            rl_zoo3.exp_manager.TrialEvalCallback = original  # type: ignore[misc]

    # -- loading / saving --------------------------------------------------------------------------------
    def _load_pretrained_agent(self, hyperparams: dict[str, Any], env: VecEnv) -> BaseAlgorithm:
        check_model_env(self.trained_agent, self.env_name.gym_id)
        return super()._load_pretrained_agent(hyperparams, env)

    def save_trained_model(self, model: BaseAlgorithm) -> None:
        super().save_trained_model(model)
        if self.adaptive:
            try:
                self.final_meta_test(model)
            except KeyboardInterrupt:
                print("Meta-test interrupted: the model is saved, meta_test.* not written")

    def final_meta_test(self, model: BaseAlgorithm) -> MetaTestResult:
        """
        The meta-test protocol on the model's test tasks after training; writes the meta-test files into the run folder.

        :param model: the trained model
        :return: the result
        """
        settings = self.meta_test_kwargs
        env = self.create_envs(1, eval_env=True)
        try:
            tasks = get_test_tasks(model, env, settings["n_tasks"], self.seed, sample=self._shifted_eval())
            if self.verbose > 0:
                print(f"Meta-test: {len(tasks)} test tasks, k = 0..{settings['n_adapt']}, {settings['n_repeats']} repeat(s)")
            result = meta_test(
                model,
                env,
                tasks,
                n_adapt=settings["n_adapt"],
                n_repeats=settings["n_repeats"],
                deterministic=settings["deterministic"],
                seed=self.seed,
            )
        finally:
            env.close()
        result.config.update(algo=self.algo, env_id=self.env_name.gym_id, timesteps=int(model.num_timesteps))
        paths = write_meta_test(result, self.save_path, title=f"{self.algo} on {self.env_name.gym_id}")
        if self.verbose > 0:
            print(result.format_summary())
            print(f"Meta-test written to {paths['csv']}, {paths['json']}, {paths['png']}")
        return result


def check_model_env(model_path: str, env_id: str) -> None:
    """
    Raise a clear error if the run folder of ``model_path`` says the model was trained on another env.

    :param model_path: path of the model zip (its folder holds ``<EnvId>/args.yml`` in the zoo layout)
    :param env_id: the env id it is about to be used with
    """
    for args_path in glob.glob(os.path.join(os.path.dirname(os.path.abspath(model_path)), "*", "args.yml")):
        with open(args_path) as file:
            saved = yaml.load(file, Loader=yaml.UnsafeLoader) or {}
        trained_env = saved.get("env")
        if trained_env is not None and trained_env != env_id:
            raise ValueError(f"{model_path} was trained on {trained_env}, not on {env_id} (see {args_path})")


def check_model_spaces(model: BaseAlgorithm, env: Any, model_path: str, env_id: str) -> None:
    """
    Raise a clear error if the model's observation / action spaces are not the env's.

    :param model: the loaded model
    :param env: the env (gymnasium env or VecEnv)
    :param model_path: for the message
    :param env_id: for the message
    """
    for kind in ("observation_space", "action_space"):
        model_space, env_space = getattr(model, kind), getattr(env, kind)
        same = type(model_space) is type(env_space) and getattr(model_space, "shape", None) == getattr(
            env_space, "shape", None
        )
        if same and hasattr(model_space, "n"):
            same = int(model_space.n) == int(env_space.n)  # type: ignore[attr-defined]
        if not same:
            raise ValueError(f"{model_path} was saved for another env: its {kind} is {model_space}, {env_id} has {env_space}")


def train(argv: Sequence[str] | None = None) -> None:
    """
    ``rl_zoo3.train.train()`` with the project's algorithms, hyperparameter files and meta-test.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    """
    register_algos()
    if argv is not None:
        sys.argv = [sys.argv[0], *argv]
    rl_zoo3.train.ExperimentManager = MetaExperimentManager  # type: ignore[misc]
    rl_zoo3.train.train()


__all__ = [
    "HYPERPARAMS_DIR",
    "META_TEST_DEFAULTS",
    "ZOO_SPECIAL_KEYS",
    "MetaExperimentManager",
    "check_model_env",
    "check_model_spaces",
    "default_config",
    "train",
    "write_meta_test",
]
