"""rl_zoo3's ``ExperimentManager`` with the meta-test, and :func:`train` (``train.py``).

:class:`MetaExperimentManager` is rl_zoo3's ``ExperimentManager`` with: the default
hyperparameter file ``zoo_hyperparams/<algo>.yml`` (instead of rl_zoo3's package folder); a
clear error for a YAML / ``-params`` key the algorithm does not take; the meta-test protocol
as the evaluation callback (``--eval-freq``, ``--eval-episodes`` test tasks, logger keys
``meta_test/...``, ``best_model.zip``) and as the Optuna trial score; and, after the model is
saved (also after Ctrl-C), the final meta-test written to ``meta_test.csv``, ``meta_test.json``
and ``adaptation.png`` in the run folder. :func:`train` runs ``rl_zoo3.train.train()`` with it and
the project's algorithms (argument parsing, log layout and the Optuna loop are rl_zoo3's), plus the flag
``--budget PRESET`` (a family's entry of a budget preset, :mod:`sb3_pearl.zoo.budget`), the cost of the run
announced and measured (:class:`~sb3_pearl.common.progress.TrainingProgressCallback`, also ``-P``'s progress bar)
and user errors as one line with exit status 2 (:mod:`sb3_pearl.zoo.usage`).

The zoo special key ``meta_test`` (a dict, optional) sets the final meta-test:
``n_adapt`` (K, default 5), ``n_repeats`` (1), ``n_tasks`` (None: every saved test task),
``deterministic`` (True); e.g. ``-params meta_test:"dict(n_adapt=3)"``. A string value is parsed with
:func:`~sb3_pearl.zoo.safe_config.parse_dict_string` (literals only, never ``eval``).
"""

from __future__ import annotations

import argparse
import functools
import glob
import importlib
import importlib.util
import os
import signal
import sys
import threading
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from pprint import pprint
from types import FrameType
from typing import Any, ClassVar

import rl_zoo3.exp_manager
import rl_zoo3.train
from rl_zoo3 import ALGOS
from rl_zoo3.exp_manager import ExperimentManager
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import CheckpointCallback, ProgressBarCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.adaptation import has_adaptation_api
from sb3_pearl.common.callbacks import (
    MetaTestCallback,
    MetaTestTrialCallback,
    ResumableCheckpointCallback,
    checkpoint_replay_buffer_path,
)
from sb3_pearl.common.meta_test import MetaTestResult, get_test_tasks, meta_test
from sb3_pearl.common.progress import TrainingProgressCallback
from sb3_pearl.zoo import usage
from sb3_pearl.zoo.budget import budget_hyperparams, faster_option
from sb3_pearl.zoo.registry import OptunaTrialIndex, constructor_kwargs, register_algos
from sb3_pearl.zoo.safe_config import load_run_yaml, parse_dict_string
from sb3_pearl.zoo.usage import CheckedStoreDict, UsageError, check_env_id, exit_on_usage_error, program_name


def _hyperparams_dir() -> Path:
    """
    ``zoo_hyperparams/``: the repository's folder in a checkout (the source), else the copy packaged with an installed
    sb3_pearl (``sb3_pearl/zoo/hyperparams/``, copied by setup.py's build step).
    """
    checkout = Path(__file__).resolve().parents[2] / "zoo_hyperparams"  # this file is sb3_pearl/zoo/experiment_manager.py
    return checkout if checkout.is_dir() else Path(__file__).resolve().parent / "hyperparams"


HYPERPARAMS_DIR = _hyperparams_dir()

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
    k = 0..``meta_test.n_adapt``); others keep rl_zoo3's ``EvalCallback``. ``--save-freq`` writes
    resumable checkpoints (:class:`~sb3_pearl.common.callbacks.ResumableCheckpointCallback`), which
    ``train.py --resume <checkpoint>`` continues up to ``n_timesteps`` (:attr:`resume`).
    """

    # Set by train() for --resume: -i continues the checkpoint's run (counters kept) up to n_timesteps in all.
    resume: ClassVar[bool] = False
    # Set by train() for --budget PRESET: the family's entry of that budget preset replaces the YAML entry.
    budget: ClassVar[str | None] = None

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
        if self.budget is not None:
            hyperparams, saved_hyperparams = self._read_budget(self.budget)
        else:
            if not os.path.isfile(self.config) and self.config.endswith((".yml", ".yaml")):
                raise UsageError(f"hyperparameter file {self.config} not found (expected zoo_hyperparams/{self.algo}.yml)")
            if self.trial_id is not None:  # --trial-id 0 must load trial 0, not the YAML defaults
                self.trial_id = OptunaTrialIndex(self.trial_id)
            try:
                hyperparams, saved_hyperparams = super().read_hyperparameters()
            except ValueError as error:  # e.g. no entry for the env in the file
                raise UsageError(str(error)) from error
        self.check_hyperparameters(hyperparams)
        return hyperparams, saved_hyperparams

    def _read_budget(self, preset: str) -> tuple[dict[str, Any], dict[str, Any]]:
        """rl_zoo3's ``read_hyperparameters`` with the entry of a budget preset instead of the YAML file's."""
        hyperparams = budget_hyperparams(preset, self.env_name.gym_id, self.algo)
        print(f"Loading hyperparameters from: the {preset} budget preset (sb3_pearl/experiments/presets/{preset}.yml)")
        if self.custom_hyperparams is not None:
            hyperparams.update(self.custom_hyperparams)
        saved_hyperparams = OrderedDict((key, hyperparams[key]) for key in sorted(hyperparams))
        print("Default hyperparameters for environment (ones being tuned will be overridden):")
        pprint(saved_hyperparams)
        return hyperparams, saved_hyperparams

    def check_hyperparameters(self, hyperparams: dict[str, Any]) -> None:
        """
        Raise a clear error for a key that is neither a constructor kwarg of the algorithm nor a zoo special key.

        :param hyperparams: the entry after ``-params`` overrides
        """
        usage.check_yaml_n_timesteps(hyperparams, f"{self.config} [{self.env_name.gym_id}]")
        algo_class = ALGOS[self.algo]
        accepted = constructor_kwargs(algo_class)
        unknown = sorted(set(hyperparams) - accepted - ZOO_SPECIAL_KEYS)
        if unknown:
            overridden = sorted(set(unknown) & set(self.custom_hyperparams or {}))
            where = f"-params ({', '.join(overridden)})" if overridden else f"{self.config} [{self.env_name.gym_id}]"
            raise UsageError(
                f"{algo_class.__name__} does not take the hyperparameter(s) {unknown} given in {where}. "
                f"Accepted constructor kwargs: {sorted(accepted)}; zoo keys: {sorted(ZOO_SPECIAL_KEYS)}"
            )
        meta = hyperparams.get("meta_test") or {}
        if isinstance(meta, str):  # the zoo's convention for dict values given as strings, parsed without eval()
            meta = parse_dict_string(meta, "meta_test")
        if not isinstance(meta, dict) or set(meta) - set(META_TEST_DEFAULTS):
            raise UsageError(f"meta_test must be a dict with keys among {sorted(META_TEST_DEFAULTS)}, got {meta!r}")

    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> Any:
        meta = hyperparams.pop("meta_test", None) or {}
        if isinstance(meta, str):
            meta = parse_dict_string(meta, "meta_test")
        self.meta_test_kwargs.update(meta)
        return super()._preprocess_hyperparams(hyperparams)

    def setup_experiment(self) -> tuple[BaseAlgorithm, dict[str, Any]] | None:
        """rl_zoo3's set-up; a ValueError on the way (a value the env or the algorithm refuses) is a user error."""
        try:
            return super().setup_experiment()
        except UsageError:
            raise
        except ValueError as error:
            raise UsageError(str(error)) from error

    # -- evaluation ------------------------------------------------------------------------------------
    def create_callbacks(self) -> None:
        if not self.adaptive:
            super().create_callbacks()
            return
        eval_freq, self.eval_freq = self.eval_freq, -1  # the zoo's EvalCallback is replaced below
        super().create_callbacks()
        self.eval_freq = eval_freq
        # The cost of the run (plan, measured costs, ETA) and -P's bar, counting gradient steps: callback 0, which
        # rl_zoo3's learn() closes when training stops.
        self.callbacks = [cb for cb in self.callbacks if not isinstance(cb, ProgressBarCallback)]
        slow_hint = faster_option(self.env_name.gym_id, self.algo, self.budget, program_name())
        self.callbacks.insert(0, TrainingProgressCallback(self.show_progress, slow_hint, verbose=self.verbose))
        # --save-freq: resumable checkpoints (model with its RNG states + replay buffer, at an iteration start).
        self.callbacks = [
            ResumableCheckpointCallback(cb.save_freq, cb.save_path, cb.name_prefix, cb.verbose)
            if type(cb) is CheckpointCallback
            else cb
            for cb in self.callbacks
        ]
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
        model = super()._load_pretrained_agent(hyperparams, env)  # with <folder>/replay_buffer.pkl if there is one
        buffer_path = checkpoint_replay_buffer_path(self.trained_agent)
        if buffer_path is not None and os.path.isfile(buffer_path) and hasattr(model, "load_replay_buffer"):
            print(f"Loading the checkpoint's replay buffer {buffer_path}")
            model.load_replay_buffer(buffer_path)
        return model

    # -- interruptions: SIGTERM and exceptions save the model, as Ctrl-C does -----------------------------
    def learn(self, model: BaseAlgorithm) -> None:
        """
        rl_zoo3's ``learn`` (Ctrl-C stops training and the model is saved), plus:

        - SIGTERM (``kill``, a batch scheduler's time limit) stops training the same way; the model is saved,
          the final meta-test is skipped and ``train.py`` exits with status 143 (128 + SIGTERM);
        - an exception during training saves the model reached so far into the run folder, says where, and is
          re-raised.

        :param model: the model to train
        """
        self._stop_signal: str | None = None
        self._sigterm_raises = True
        self._previous_sigterm_handler = self._install_sigterm_handler()
        try:
            if self.resume and self.continue_training:
                self._learn_resumed(model)
            else:
                super().learn(model)
        except Exception as error:
            self._restore_sigterm_handler()
            self._save_after_failure(model, error)
            raise
        self._sigterm_raises = False  # from here on, a SIGTERM no longer interrupts the save

    def _learn_resumed(self, model: BaseAlgorithm) -> None:
        """
        ``train.py --resume``: continue the checkpoint's run up to ``n_timesteps`` in all (its counters kept,
        ``reset_num_timesteps=False``), as rl_zoo3's ``learn`` otherwise (Ctrl-C stops and saves).
        """
        remaining = self.n_timesteps - model.num_timesteps
        print(f"Resuming at {model.num_timesteps} timesteps: {max(remaining, 0)} to go (n_timesteps {self.n_timesteps})")
        kwargs: dict[str, Any] = {}
        if self.log_interval > -1:
            kwargs["log_interval"] = self.log_interval
        elif self.log_interval < -1:
            kwargs["log_interval"] = None
        if self.callbacks:
            kwargs["callback"] = self.callbacks
        try:
            if remaining > 0:
                model.learn(remaining, reset_num_timesteps=False, **kwargs)
        except KeyboardInterrupt:
            pass  # as rl_zoo3: the model is saved by save_trained_model
        finally:
            if self.callbacks:
                self.callbacks[0].on_training_end()
            try:
                assert model.env is not None
                model.env.close()
            except EOFError:
                pass

    def _install_sigterm_handler(self) -> Any:
        if threading.current_thread() is not threading.main_thread():
            return None  # signal handlers can only be installed by the main thread
        return signal.signal(signal.SIGTERM, self._on_sigterm)

    def _restore_sigterm_handler(self) -> None:
        previous = getattr(self, "_previous_sigterm_handler", None)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
            self._previous_sigterm_handler = None

    def _on_sigterm(self, signum: int, frame: FrameType | None) -> None:
        first = self._stop_signal is None
        self._stop_signal = "SIGTERM"
        if first and self._sigterm_raises:
            print("Received SIGTERM: stopping training and saving the model (SIGKILL stops without saving)", flush=True)
            raise KeyboardInterrupt  # rl_zoo3's learn() / the meta-test stop as after Ctrl-C
        print("Received SIGTERM: finishing the save first", flush=True)

    def _model_path(self) -> str:
        return os.path.join(self.save_path, f"{self.env_name}.zip")

    def _save_after_failure(self, model: BaseAlgorithm, error: BaseException) -> None:
        """Save the model reached when training raised ``error`` (and its replay buffer if asked), and say where."""
        try:
            model.save(self._model_path())
            if self.save_replay_buffer and hasattr(model, "save_replay_buffer"):
                model.save_replay_buffer(os.path.join(self.save_path, "replay_buffer.pkl"))
        except Exception as save_error:  # report both; the training error is re-raised by the caller
            print(f"Training failed ({type(error).__name__}) and saving the model failed too: {save_error}", file=sys.stderr)
            return
        print(
            f"Training stopped by {type(error).__name__} at {model.num_timesteps} timesteps: the model reached so far is "
            f"saved to {self._model_path()} (continue with train.py -i {self._model_path()}); the error follows",
            file=sys.stderr,
            flush=True,
        )

    def save_trained_model(self, model: BaseAlgorithm) -> None:
        """rl_zoo3's save (model, replay buffer), then the final meta-test unless training was stopped by SIGTERM."""
        self._sigterm_raises = False
        if getattr(self, "_previous_sigterm_handler", None) is None:
            self._stop_signal = getattr(self, "_stop_signal", None)
            self._previous_sigterm_handler = self._install_sigterm_handler()
        try:
            super().save_trained_model(model)
            if self._stop_signal is None and self.adaptive:
                self._sigterm_raises = True
                try:
                    self.final_meta_test(model)
                except KeyboardInterrupt:
                    print("Meta-test interrupted: the model is saved, meta_test.* not written")
        finally:
            self._restore_sigterm_handler()
        if self._stop_signal is not None:
            print(
                f"Stopped by {self._stop_signal} at {model.num_timesteps} timesteps: the model is saved to "
                f"{self._model_path()} (final meta-test skipped; continue with train.py -i {self._model_path()})",
                flush=True,
            )
            raise SystemExit(128 + signal.SIGTERM)

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
                progress_bar=self.verbose > 0 or self.show_progress,
                description="Meta-test (Ctrl-C skips it)",
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
    Raise a clear error (:class:`~sb3_pearl.zoo.usage.UsageError`) if the run folder of ``model_path`` says the model
    was trained on another env.

    :param model_path: path of the model zip (its folder holds ``<EnvId>/args.yml`` in the zoo layout)
    :param env_id: the env id it is about to be used with
    """
    for args_path in glob.glob(os.path.join(os.path.dirname(os.path.abspath(model_path)), "*", "args.yml")):
        saved = load_run_yaml(args_path) or {}
        trained_env = saved.get("env")
        if trained_env is not None and trained_env != env_id:
            raise UsageError(f"{model_path} was trained on {trained_env}, not on {env_id} (see {args_path})")


def check_model_spaces(model: BaseAlgorithm, env: Any, model_path: str, env_id: str) -> None:
    """
    Raise a clear error (:class:`~sb3_pearl.zoo.usage.UsageError`) if the model's observation / action spaces are not
    the env's.

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
            raise UsageError(f"{model_path} was saved for another env: its {kind} is {model_space}, {env_id} has {env_space}")


def train(argv: Sequence[str] | None = None) -> None:
    """
    ``rl_zoo3.train.train()`` with the project's algorithms, hyperparameter files and meta-test.

    One flag of its own: ``--resume CHECKPOINT`` (a ``rl_model_<steps>_steps.zip`` written by ``--save-freq``,
    or a run's final model): load it with its replay buffer and RNG states and train up to ``n_timesteps`` in
    all, instead of ``-i``'s ``n_timesteps`` more from a reset counter.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    """
    register_algos()
    with exit_on_usage_error():
        args = _project_flags(list(sys.argv[1:] if argv is None else argv))
        sys.argv = [sys.argv[0], *args]
        rl_zoo3.train.ExperimentManager = MetaExperimentManager  # type: ignore[misc]
        rl_zoo3.train.StoreDict = CheckedStoreDict  # type: ignore[misc]  # a bad -params value: one line, not a traceback
        try:
            rl_zoo3.train.train()
        except SystemExit:
            if {"-h", "--help"} & set(args):
                print(PROJECT_FLAGS_HELP)
            raise


PROJECT_FLAGS_HELP = """
sb3-pearl flags (docs/cli.md):
  --budget PRESET       train with the env's entry of a budget preset instead of zoo_hyperparams/<algo>.yml:
                        cpu (one run <= 45 min on one core), smoke (seconds) or paper
                        (sb3_pearl/experiments/presets/; -n and -params still override it)
  --resume CHECKPOINT   continue a --save-freq checkpoint (or a run's model) up to n_timesteps in all, with its
                        replay buffer and RNG states"""


def _project_flags(args: list[str]) -> list[str]:
    """
    Handle the project's own flags (``--resume``, ``--budget``) and check ``--env``; return rl_zoo3's arguments.

    :param args: the command line
    :return: the arguments for rl_zoo3's parser
    """
    MetaExperimentManager.resume = False
    MetaExperimentManager.budget = None
    usage.check_n_timesteps(args)
    if "--resume" in args:
        index = args.index("--resume")
        if index + 1 >= len(args) or not os.path.isfile(args[index + 1]) or not args[index + 1].endswith(".zip"):
            raise UsageError(
                "--resume takes the checkpoint's model zip, e.g. --resume logs/pearl/Env_1/rl_model_5000_steps.zip"
            )
        if "-i" in args or "--trained-agent" in args:
            raise UsageError("--resume and -i/--trained-agent exclude each other (--resume is -i that keeps the counters)")
        args[index] = "--trained-agent"
        MetaExperimentManager.resume = True
    peek = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    peek.add_argument("--env", default=None)
    peek.add_argument("--algo", default=None)
    peek.add_argument("--gym-packages", nargs="+", default=[])
    peek.add_argument("--budget", default=None)
    known, _ = peek.parse_known_args(args)
    for module in known.gym_packages:
        importlib.import_module(module)
    if known.env is not None:
        check_env_id(known.env)
    if "--budget" in args:
        index = args.index("--budget")
        if known.budget is None or known.budget.startswith("-"):
            raise UsageError("--budget takes a budget preset name: smoke, cpu or paper")
        del args[index : index + 2]
        if known.algo is not None and known.env is not None:
            budget_hyperparams(known.budget, known.env, known.algo)  # an unknown preset or entry: the error now
        MetaExperimentManager.budget = known.budget
    return args


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
