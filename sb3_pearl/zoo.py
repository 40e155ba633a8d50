"""rl-zoo integration: the project's algorithms in ``rl_zoo3`` and an ExperimentManager with the meta-test.

``train.py`` and ``enjoy.py`` at the repository root are thin wrappers over this module:

- :func:`register_algos` puts ``pearl`` / ``pearlplus`` (and ``finetune`` / ``maml`` when
  :mod:`sb3_pearl` exports ``FineTune`` / ``MAML``) in ``rl_zoo3.ALGOS`` and the PEARL / PEARL+
  hyperparameter samplers in ``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER`` (``-optimize``).
- :class:`MetaExperimentManager` is rl_zoo3's ``ExperimentManager`` with: the default
  hyperparameter file ``zoo_hyperparams/<algo>.yml`` (instead of rl_zoo3's package folder); a
  clear error for a YAML / ``-params`` key the algorithm does not take; the meta-test protocol
  as the evaluation callback (``--eval-freq``, ``--eval-episodes`` test tasks, logger keys
  ``meta_test/...``, ``best_model.zip``) and as the Optuna trial score; and, after the model is
  saved (also after Ctrl-C), the final meta-test written to ``meta_test.csv``, ``meta_test.json``
  and ``adaptation.png`` in the run folder.
- :func:`train` runs ``rl_zoo3.train.train()`` with both in place (argument parsing, log layout and
  the Optuna loop are rl_zoo3's).

The zoo special key ``meta_test`` (a dict, optional) sets the final meta-test:
``n_adapt`` (K, default 5), ``n_repeats`` (1), ``n_tasks`` (None: every saved test task),
``deterministic`` (True); e.g. ``-params meta_test:"dict(n_adapt=3)"``.
"""

from __future__ import annotations

import argparse
import difflib
import functools
import importlib
import importlib.util
import inspect
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import optuna
import rl_zoo3.exp_manager
import rl_zoo3.hyperparams_opt
import rl_zoo3.train
import torch as th
import yaml
from gymnasium.envs.registration import load_env_creator
from gymnasium.wrappers import HumanRendering, RecordVideo
from huggingface_sb3 import EnvironmentName
from rl_zoo3 import ALGOS, create_test_env, get_saved_hyperparams
from rl_zoo3.exp_manager import ExperimentManager
from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from rl_zoo3.utils import StoreDict, get_model_path
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

import sb3_pearl
from sb3_pearl.common.callbacks import MetaTestCallback, MetaTestTrialCallback
from sb3_pearl.common.evaluation import ROW_COLUMNS, MetaTestResult, get_test_tasks, meta_test
from sb3_pearl.pearl import PEARL, PEARLPlus

HYPERPARAMS_DIR = Path(__file__).resolve().parent.parent / "zoo_hyperparams"

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
# Set by the zoo itself when it builds the model: not allowed in a YAML entry.
ZOO_SET_KWARGS = frozenset({"env", "tensorboard_log", "seed", "verbose", "device", "_init_setup_model"})
# Constructor kwargs a class refuses although its parent takes them (PEARL is PEARL+ without the prior term).
REFUSED_KWARGS: dict[type, frozenset[str]] = {
    PEARL: frozenset({"prior_coef", "prior_critic", "prior_critic_arch", "prior_n_critics"}),
}
META_TEST_DEFAULTS: dict[str, Any] = {"n_adapt": 5, "n_repeats": 1, "n_tasks": None, "deterministic": True}

# Optuna categorical choices (names are stored in the study, converted by convert_pearl_params)
NET_ARCHS: dict[str, list[int]] = {"small": [64, 64], "medium": [256, 256], "big": [300, 300, 300]}
ENCODER_ARCHS: dict[str, list[int]] = {"small": [64, 64], "medium": [200, 200], "big": [200, 200, 200]}


# ----------------------------------------------------------------------------------------------
# Algorithms and hyperparameter samplers
# ----------------------------------------------------------------------------------------------
def constructor_kwargs(algo_class: type) -> set[str]:
    """
    Keyword arguments ``algo_class(...)`` takes, following ``**kwargs`` up the MRO.

    :param algo_class: an algorithm class
    :return: the accepted names (without the ones the zoo sets itself)
    """
    accepted: set[str] = set()
    for cls in algo_class.__mro__:
        if "__init__" not in vars(cls):
            continue
        params = inspect.signature(vars(cls)["__init__"]).parameters.values()
        accepted |= {p.name for p in params if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL) and p.name != "self"}
        if not any(p.kind == p.VAR_KEYWORD for p in params):
            break
    return accepted - ZOO_SET_KWARGS - REFUSED_KWARGS.get(algo_class, frozenset())


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


def register_algos() -> dict[str, type[BaseAlgorithm]]:
    """
    Register the project's algorithms (and samplers) with rl_zoo3; idempotent.

    ``pearl`` and ``pearlplus`` always; ``finetune`` and ``maml`` when :mod:`sb3_pearl` exports
    ``FineTune`` / ``MAML`` (the baselines' issue). A sampler is registered for the algorithms
    that have one here.

    :return: the registered algorithms by zoo name
    """
    algos: dict[str, type[BaseAlgorithm]] = {"pearl": PEARL, "pearlplus": PEARLPlus}
    for name, attribute in (("finetune", "FineTune"), ("maml", "MAML")):
        algo = getattr(sb3_pearl, attribute, None)
        if algo is not None:
            algos[name] = algo
    ALGOS.update(algos)
    HYPERPARAMS_SAMPLER.update({"pearl": sample_pearl_params, "pearlplus": sample_pearlplus_params})
    HYPERPARAMS_CONVERTER.update({"pearl": convert_pearl_params, "pearlplus": convert_pearl_params})
    return algos


def has_adaptation_api(algo_class: type) -> bool:
    """Whether instances of ``algo_class`` implement reset_adaptation / observe / adapt / predict."""
    return all(callable(getattr(algo_class, name, None)) for name in ("reset_adaptation", "observe", "adapt", "predict"))


# ----------------------------------------------------------------------------------------------
# Experiment manager
# ----------------------------------------------------------------------------------------------
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
    import glob

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


# ----------------------------------------------------------------------------------------------
# enjoy.py: prior and posterior rollouts of a trained model
# ----------------------------------------------------------------------------------------------
def enjoy_parser() -> argparse.ArgumentParser:
    """The command line of ``enjoy.py`` (rl_zoo3's model-finding flags plus the meta-test ones)."""
    parser = argparse.ArgumentParser(
        description="Roll out a trained meta-RL model on test tasks: the prior trajectory (k = 0), then posterior "
        "trajectories after adapting on the earlier ones (k = 1..--n-adapt).",
    )
    parser.add_argument("--env", help="environment ID", type=EnvironmentName, default="SafePointGoalMeta-v0")
    parser.add_argument("-f", "--folder", help="Log folder", type=str, default="logs")
    parser.add_argument("--algo", help="RL Algorithm", default="pearlplus", type=str, choices=list(ALGOS.keys()))
    parser.add_argument("--exp-id", help="Experiment ID (default: 0: latest, -1: no exp folder)", default=0, type=int)
    parser.add_argument("--load-best", action="store_true", default=False, help="Load the best model (best_model.zip)")
    parser.add_argument("--load-checkpoint", type=int, help="Load the checkpoint of this many timesteps")
    parser.add_argument("--load-last-checkpoint", action="store_true", default=False, help="Load the last checkpoint")
    parser.add_argument("--n-tasks", help="number of test tasks", default=3, type=int)
    parser.add_argument("--n-adapt", help="last trajectory index K (k = 0 prior, 1..K posterior)", default=5, type=int)
    parser.add_argument("--n-repeats", help="repeats of the sequence per task", default=1, type=int)
    parser.add_argument(
        "--sample-tasks",
        action="store_true",
        default=False,
        help="draw --n-tasks tasks from the env (with --seed) instead of the model's saved test tasks "
        "(implied by --env-kwargs: a shifted task distribution)",
    )
    parser.add_argument("--stochastic", action="store_true", default=False, help="Use stochastic actions")
    parser.add_argument("--no-render", action="store_true", default=False, help="Do not render the environment")
    parser.add_argument("--video-folder", type=str, default=None, help="Record one video per trajectory here")
    parser.add_argument(
        "--plot",
        nargs="?",
        const="",
        default=None,
        help="Save the adaptation curve (and, for the merge family, speed profiles and the b_min scatter); "
        "optional PNG path (default: <run folder>/enjoy_adaptation.png)",
    )
    parser.add_argument("--seed", help="Random generator seed", type=int, default=0)
    parser.add_argument("--device", help="PyTorch device to be use (ex: cpu, cuda...)", default="auto", type=str)
    parser.add_argument("--num-threads", help="Number of threads for PyTorch (-1 to use default)", default=-1, type=int)
    parser.add_argument("--verbose", help="Verbose mode (0: no output, 1: INFO)", default=1, type=int)
    parser.add_argument(
        "--gym-packages", type=str, nargs="+", default=[], help="Additional external Gym environment package modules to import"
    )
    parser.add_argument(
        "--env-kwargs", type=str, nargs="+", action=StoreDict, help="Optional keyword argument to pass to the env constructor"
    )
    return parser


def _render_modes(env_id: str) -> list[str]:
    spec = gym.spec(env_id)
    creator = load_env_creator(spec.entry_point) if isinstance(spec.entry_point, str) else spec.entry_point
    return list(getattr(creator, "metadata", {}).get("render_modes", []))


def _saved_env_kwargs(log_path: str, env_name: str, hyperparams: dict[str, Any]) -> dict[str, Any]:
    """env kwargs of the training run: the config's, overridden by the command line's (rl_zoo3's enjoy rule)."""
    env_kwargs: dict[str, Any] = dict(hyperparams.pop("env_kwargs", None) or {})
    args_path = os.path.join(log_path, env_name, "args.yml")
    if os.path.isfile(args_path):
        with open(args_path) as file:
            loaded = yaml.load(file, Loader=yaml.UnsafeLoader) or {}
        if loaded.get("env_kwargs") is not None:
            env_kwargs = dict(loaded["env_kwargs"])
    return env_kwargs


def format_task_table(result: MetaTestResult, task: int, repeat: int = 0) -> str:
    """The rows of one task and repeat: k, prior / posterior, return, cost, length (and the family extras)."""
    extras = [key for key in result.columns[len(ROW_COLUMNS) :]]
    header = f"{'k':>3}  {'policy':<9} {'return':>10} {'cost':>6} {'length':>6}" + "".join(f" {key:>10}" for key in extras)
    lines = [header]
    for row in result.rows:
        if row["task"] != task or row["repeat"] != repeat:
            continue
        policy = "prior" if row["k"] == 0 else "posterior"
        line = f"{row['k']:>3}  {policy:<9} {row['return']:>10.2f} {row['cost']:>6.1f} {row['length']:>6d}"
        line += "".join(f" {float(row.get(key, float('nan'))):>10.3g}" for key in extras)
        lines.append(line)
    return "\n".join(lines)


def enjoy(argv: Sequence[str] | None = None) -> MetaTestResult:
    """
    ``enjoy.py``: load a model like rl-zoo and roll out prior then posterior trajectories on test tasks.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the meta-test of the rollouts
    """
    register_algos()
    args = enjoy_parser().parse_args(argv)
    for module in args.gym_packages:
        importlib.import_module(module)
    env_name: EnvironmentName = args.env
    env_id = env_name.gym_id
    if env_id not in gym.registry:
        close = difflib.get_close_matches(env_id, list(gym.registry), n=1)
        raise SystemExit(f"enjoy.py: {env_id} not found in gym registry" + (f", you maybe meant {close[0]}?" if close else ""))
    try:
        _, model_path, log_path = get_model_path(
            args.exp_id, args.folder, args.algo, env_name, args.load_best, args.load_checkpoint, args.load_last_checkpoint
        )
    except (AssertionError, ValueError) as error:
        raise SystemExit(f"enjoy.py: {error}") from None
    if args.num_threads > 0:
        th.set_num_threads(args.num_threads)
    set_random_seed(args.seed)
    try:
        check_model_env(model_path, env_id)
    except ValueError as error:
        raise SystemExit(f"enjoy.py: {error}") from None
    print(f"Loading {model_path}")

    hyperparams, maybe_stats_path = get_saved_hyperparams(os.path.join(log_path, env_name), test_mode=True)
    env_kwargs = _saved_env_kwargs(log_path, env_name, hyperparams)
    shifted = bool(args.env_kwargs)
    if args.env_kwargs:
        env_kwargs.update(args.env_kwargs)
    render = not args.no_render
    if args.video_folder is not None:
        env_kwargs["render_mode"] = "rgb_array"
    elif render and "render_mode" not in env_kwargs:
        env_kwargs["render_mode"] = "human" if "human" in _render_modes(env_id) else "rgb_array"
    vec_env = create_test_env(
        env_id,
        n_envs=1,
        stats_path=maybe_stats_path,
        seed=args.seed,
        should_render=False,
        hyperparams=hyperparams,
        env_kwargs=env_kwargs,
    )
    env: gym.Env = vec_env.envs[0]  # type: ignore[attr-defined]
    if args.video_folder is not None:
        env = RecordVideo(env, args.video_folder, episode_trigger=lambda _: True, disable_logger=True)
    elif render and env_kwargs.get("render_mode") == "rgb_array":
        env = HumanRendering(env)

    model = ALGOS[args.algo].load(model_path, device=args.device)
    try:
        check_model_spaces(model, env, model_path, env_id)
    except ValueError as error:
        raise SystemExit(f"enjoy.py: {error}") from None
    tasks = get_test_tasks(model, env, args.n_tasks, args.seed, sample=args.sample_tasks or shifted)
    source = "sampled from the env" if (args.sample_tasks or shifted or not getattr(model, "test_tasks", None)) else "saved"
    print(f"{len(tasks)} test tasks ({source}), trajectories k = 0 (prior) .. {args.n_adapt} (posterior)")

    def name_video(task: int, repeat: int, k: int) -> None:
        if isinstance(env, RecordVideo):
            phase = "prior" if k == 0 else "posterior"
            env.name_prefix = f"{args.algo}-{env_id}-task{task}-rep{repeat}-k{k}-{phase}"

    try:
        result = meta_test(
            model,
            env,
            tasks,
            n_adapt=args.n_adapt,
            n_repeats=args.n_repeats,
            deterministic=not args.stochastic,
            seed=args.seed,
            on_trajectory_start=name_video,
        )
    finally:
        env.close()
    result.config.update(algo=args.algo, env_id=env_id, model_path=model_path)
    for task_index, task in enumerate(result.tasks):
        for repeat in range(args.n_repeats):
            print(f"\nTask {task_index} (repeat {repeat}): {json.dumps(task)}")
            print(format_task_table(result, task_index, repeat))
    print("\nSummary over tasks")
    print(result.format_summary())
    if args.video_folder is not None:
        print(f"Videos in {args.video_folder}")
    if args.plot is not None:
        from sb3_pearl.plots import plot_all

        output = args.plot or os.path.join(log_path, "enjoy_adaptation.png")
        for path in plot_all({args.algo: result}, output, title=f"{args.algo} on {env_id}"):
            print(f"Saved {path}")
    return result


__all__ = [
    "HYPERPARAMS_DIR",
    "MetaExperimentManager",
    "check_model_env",
    "check_model_spaces",
    "constructor_kwargs",
    "enjoy",
    "convert_pearl_params",
    "default_config",
    "register_algos",
    "sample_pearl_params",
    "sample_pearlplus_params",
    "train",
    "write_meta_test",
]
