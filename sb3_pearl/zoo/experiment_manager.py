"""rl_zoo3's ``ExperimentManager`` for meta-RL, and :func:`train` (``train.py``).

:class:`MetaExperimentManager` puts together, on rl_zoo3's ``ExperimentManager``:

- here: the default hyperparameter file ``zoo_hyperparams/<algo>.yml`` (instead of rl_zoo3's package folder), the
  budget presets (``--budget PRESET``, :mod:`sb3_pearl.zoo.budget`), a clear error for a YAML / ``-params`` key the
  algorithm does not take, the ``meta_test`` key, and ``--resume``'s replay buffer;
- :mod:`sb3_pearl.zoo.meta_testing`: the meta-test as the evaluation callback, the Optuna score and the final
  meta-test (``meta_test.csv``, ``meta_test.json``, ``adaptation.png`` in the run folder);
- :mod:`sb3_pearl.zoo.interruptions`: SIGTERM and Ctrl-C stop training where it resumes exactly (the run marked cut),
  and exceptions save the model.

:func:`train` runs ``rl_zoo3.train.train()`` with it and the project's algorithms (argument parsing, log layout and the
Optuna loop are rl_zoo3's), after the project's own flags (:mod:`sb3_pearl.zoo.flags`); user errors are one line with
exit status 2 (:mod:`sb3_pearl.zoo.usage`).

The zoo special key ``meta_test`` (a dict, optional) sets the meta-tests: ``n_adapt`` (K, default 5), ``n_repeats``
(1), ``n_tasks`` (None: as many as the model's ``n_test_tasks``), ``deterministic`` (True) and ``eval_seed`` (10000,
the seed of the held-out tasks drawn from the eval env and of the common random numbers:
:mod:`sb3_pearl.evaluation.held_out`, the same meta-test as the harness's); e.g.
``-params meta_test:"dict(n_adapt=3)"``, which sets those keys over the YAML entry's (or budget preset's) ``meta_test``
and keeps its others. A string value is parsed with :func:`~sb3_pearl.zoo.safe_config.parse_dict_string` (literals
only, never ``eval``). Every value is checked before anything is built
(:func:`~sb3_pearl.evaluation.held_out.check_meta_test_settings`): one out of range is a one-line error.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import importlib.util
import inspect
import os
import re
import shutil
import sys
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pprint import pprint
from typing import Any
from unittest import mock

import gymnasium as gym
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.budgets import model_kwargs
from sb3_pearl.common.adaptation import has_adaptation_api
from sb3_pearl.common.checks import check_learning_rate
from sb3_pearl.common.persistence import IncompleteReplayBufferError, read_model_data
from sb3_pearl.common.threads import mark_num_threads_explicit, num_threads_flag
from sb3_pearl.config import HYPERPARAMS_DIR
from sb3_pearl.evaluation.callbacks import checkpoint_replay_buffer_path
from sb3_pearl.evaluation.held_out import check_meta_test_settings, model_test_tasks, write_meta_test
from sb3_pearl.registry import constructor_parameters
from sb3_pearl.zoo import usage
from sb3_pearl.zoo.algos import OptunaTrialIndex, constructor_kwargs, register_algos
from sb3_pearl.zoo.budget import budget_hyperparams
from sb3_pearl.zoo.flags import DEFAULT_CHECKPOINT_MINUTES, PROJECT_FLAGS_HELP, parse_project_flags, resume_buffer_path
from sb3_pearl.zoo.interruptions import InterruptibleExperimentManager, SetupInterrupted
from sb3_pearl.zoo.meta_testing import (
    SHORT_RUN_FRACTION,
    ZOO_META_TEST_DEFAULTS,
    MetaTestExperimentManager,
    meta_test_dict,
)
from sb3_pearl.zoo.model_checks import check_model_env, check_model_spaces, check_saved_model_family
from sb3_pearl.zoo.rl_zoo3_coupling import ALGOS, get_latest_run_id, run_zoo_train
from sb3_pearl.zoo.safe_config import load_run_yaml
from sb3_pearl.zoo.usage import CheckedStoreDict, UsageError, exit_on_usage_error

# What a --resume may set otherwise than the run did: the env steps to run up to, the evaluation settings.
RESUME_MAY_CHANGE = frozenset({"n_timesteps", "meta_test"})

# Constructor arguments a model saves resolved, not as given ("auto" -> -dim(A), None -> the env's step limit): a resume
# compares one set on one side only with the constructor's default, not with the saved value.
SAVED_RESOLVED = frozenset({"target_entropy", "max_episode_steps"})

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


def default_config(algo: str) -> str:
    """The project's hyperparameter file of ``algo``: ``zoo_hyperparams/<algo>.yml``."""
    return str(HYPERPARAMS_DIR / f"{algo}.yml")


class MetaExperimentManager(InterruptibleExperimentManager, MetaTestExperimentManager):
    """
    rl_zoo3's ``ExperimentManager`` for meta-RL (module docstring): same arguments, same log layout.

    The evaluation callback is :class:`~sb3_pearl.evaluation.callbacks.MetaTestCallback` for
    algorithms with the adaptation API (``--eval-episodes`` test tasks per evaluation,
    k = 0..``meta_test.n_adapt``); others keep rl_zoo3's ``EvalCallback``. ``--save-freq`` writes
    resumable checkpoints (:class:`~sb3_pearl.evaluation.callbacks.ResumableCheckpointCallback`), which
    ``train.py --resume <checkpoint>`` continues up to ``n_timesteps``.

    :param args: rl_zoo3's arguments (its ``ExperimentManager``'s, as are ``algo``, ``env_id``, ``log_folder`` and the rest)
    :param resume: ``--resume``: continue the checkpoint given as ``-i`` with its counters, up to ``n_timesteps`` in all
    :param budget: ``--budget PRESET``: the family's entry of that budget preset replaces the YAML entry
    :param command: ``train.py``'s command line (the resume command of a run cut by a signal is made from it)
    :param checkpoint_minutes: ``--checkpoint-minutes M``: a resumable checkpoint every M minutes of training (0: off)
    :param resume_without_buffer: ``--resume-without-buffer``: a replay buffer that is empty, truncated or corrupt is
        skipped with a warning naming it (the run goes on from an empty buffer) instead of refused
    """

    _reserved_folder: str | None = None  # the run folder this manager created (removed if the set-up fails)

    def __init__(
        self,
        args: Any,
        algo: str,
        env_id: str,
        log_folder: str,
        *posargs: Any,
        resume: bool = False,
        budget: str | None = None,
        command: Sequence[str] = (),
        checkpoint_minutes: float = DEFAULT_CHECKPOINT_MINUTES,
        resume_without_buffer: bool = False,
        **kwargs: Any,
    ) -> None:
        if kwargs.get("config") is None and os.path.isfile(default_config(algo)):
            kwargs["config"] = default_config(algo)  # else rl_zoo3's own file (its algorithms)
        self.resume, self.budget, self.command = resume, budget, list(command)
        self.checkpoint_minutes, self.resume_without_buffer = checkpoint_minutes, resume_without_buffer
        self.run_hyperparams: dict[str, Any] = {}
        super().__init__(args, algo, env_id, log_folder, *posargs, **kwargs)
        self.meta_test_kwargs = dict(ZOO_META_TEST_DEFAULTS)
        self.adaptive = has_adaptation_api(ALGOS[algo])
        if self.tensorboard_log is not None and importlib.util.find_spec("tensorboard") is None:
            raise ImportError("-tb/--tensorboard-log needs the tensorboard package (not installed): pip install tensorboard")

    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        # -params' meta_test sets its keys over the entry's meta_test (rl_zoo3 would replace the whole dict): it is kept
        # out of rl_zoo3's update and merged here.
        custom = self.custom_hyperparams
        custom_meta = (custom or {}).get("meta_test")
        if custom is not None and custom_meta is not None:
            self.custom_hyperparams = {key: value for key, value in custom.items() if key != "meta_test"}
        try:
            hyperparams, saved_hyperparams = self._read_entry()
        finally:
            self.custom_hyperparams = custom
        if custom_meta is not None:
            entry_meta = meta_test_dict(hyperparams.get("meta_test"), f"{self.config} [{self.env_name.gym_id}]")
            hyperparams["meta_test"] = {**entry_meta, **meta_test_dict(custom_meta, "-params")}
            saved_hyperparams = OrderedDict((key, hyperparams[key]) for key in sorted(hyperparams))
            print(f"meta_test (the entry's, with -params' keys over it): {hyperparams['meta_test']}")
        self.check_hyperparameters(hyperparams)
        self.run_hyperparams = dict(saved_hyperparams)  # what config.yml records (a --resume compares them)
        return hyperparams, saved_hyperparams

    def _read_entry(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """rl_zoo3's ``read_hyperparameters`` (the YAML entry, or a budget preset's), with ``-params`` over it."""
        if self.budget is not None:
            return self._read_budget(self.budget)
        if not os.path.isfile(self.config) and self.config.endswith((".yml", ".yaml")):
            raise UsageError(f"hyperparameter file {self.config} not found (expected zoo_hyperparams/{self.algo}.yml)")
        if self.config.endswith((".yml", ".yaml")):
            usage.check_conf_file(self.config, self.env_name.gym_id)
        if self.trial_id is not None:  # --trial-id 0 must load trial 0, not the YAML defaults
            self.trial_id = OptunaTrialIndex(self.trial_id)
        try:
            return super().read_hyperparameters()
        except ValueError as error:  # e.g. no entry for the env in the file
            raise UsageError(str(error)) from error

    def _read_budget(self, preset: str) -> tuple[dict[str, Any], dict[str, Any]]:
        """rl_zoo3's ``read_hyperparameters`` with the entry of a budget preset instead of the YAML file's."""
        hyperparams = budget_hyperparams(preset, self.env_name.gym_id, self.algo)
        print(f"Loading hyperparameters from: the {preset} budget preset (sb3_pearl/config/presets/{preset}.yml)")
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
        usage.check_n_envs(
            hyperparams,
            "-params" if "n_envs" in (self.custom_hyperparams or {}) else f"{self.config} [{self.env_name.gym_id}]",
        )
        algo_class = ALGOS[self.algo]
        accepted = constructor_kwargs(algo_class)
        unknown = sorted(set(hyperparams) - accepted - ZOO_SPECIAL_KEYS)
        if unknown:
            overridden = sorted(set(unknown) & set(self.custom_hyperparams or {}))
            where = f"-params ({', '.join(overridden)})" if overridden else f"{self.config} [{self.env_name.gym_id}]"
            known = sorted(accepted | ZOO_SPECIAL_KEYS)
            named = []
            for key in unknown:
                match = difflib.get_close_matches(key, known, n=1)
                named.append(f"{key!r} (did you mean {match[0]}?)" if match else repr(key))
            raise UsageError(
                f"{algo_class.__name__} does not take the hyperparameter(s) {', '.join(named)} given in {where} "
                f"(the accepted ones: help({algo_class.__name__}) and the zoo keys of docs/cli.md)"
            )
        self._check_learning_rate(hyperparams.get("learning_rate"))
        where = "-params" if "meta_test" in (self.custom_hyperparams or {}) else f"{self.config} [{self.env_name.gym_id}]"
        try:
            check_meta_test_settings(meta_test_dict(hyperparams.get("meta_test"), where))
        except ValueError as error:
            raise UsageError(f"{error} (in {where})") from None

    def _check_learning_rate(self, learning_rate: Any) -> None:
        """
        The constructors' learning-rate check, made here: rl_zoo3 wraps a number (and ``lin_<x>``) into a schedule,
        which the constructors take without looking inside (a nan reached torch).

        :param learning_rate: the entry's value (a number, ``"lin_<x>"``, or None)
        """
        where = "-params" if "learning_rate" in (self.custom_hyperparams or {}) else f"{self.config} [{self.env_name.gym_id}]"
        value = learning_rate
        if isinstance(learning_rate, str) and "_" in learning_rate:
            try:
                value = float(learning_rate.split("_", 1)[1])
            except ValueError:
                raise UsageError(f"learning_rate in {where}: {learning_rate!r} is not a number or lin_<number>") from None
        if value is not None and not callable(value):
            try:
                check_learning_rate("learning_rate", value)
            except ValueError as error:
                raise UsageError(f"{error} (in {where})") from None

    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> Any:
        self.meta_test_kwargs.update(meta_test_dict(hyperparams.pop("meta_test", None), "meta_test"))
        # A short run (-n under a tenth of the entry's n_timesteps: a smoke run of the pipeline) meta-tests on a few
        # tasks and one draw (meta_test_settings), so that it costs what it trains, unless -params sets them. With -i
        # (not --resume), -n counts the steps added to a trained model: never a short run.
        entry_steps = float(hyperparams.get("n_timesteps") or 0)
        added_to_a_trained_model = self.continue_training and not self.resume
        self.short_run = not added_to_a_trained_model and 0 < self.n_timesteps * SHORT_RUN_FRACTION < entry_steps
        self.meta_test_chosen = set(meta_test_dict((self.custom_hyperparams or {}).get("meta_test"), "-params"))
        # A budget preset's policy_kwargs arrive as the preset's plain dict (activation by name, as config.yml saves
        # them); the harness's own conversion makes them constructor kwargs. A zoo YAML's string form is rl_zoo3's.
        return super()._preprocess_hyperparams(model_kwargs(hyperparams))

    def setup_experiment(self) -> tuple[BaseAlgorithm, dict[str, Any]] | None:
        """
        rl_zoo3's set-up; a ValueError on the way (a value the env or the algorithm refuses) is a user error. For an
        algorithm with the adaptation API, the held-out tasks of the meta-tests are drawn once here, so that a draw
        that hits training tasks (``--seed`` equal to the eval seed, a family with few distinct tasks) is refused
        before training, not after it. A set-up that fails, or that SIGTERM / Ctrl-C stops, removes the run folder it
        reserved: nothing is left behind.
        """
        try:
            with self.stop_signals_abort_setup():  # SIGTERM / Ctrl-C here: SetupInterrupted, the folder removed below
                setup = super().setup_experiment()
                if setup is not None and self.adaptive:
                    self._check_held_out_tasks(setup[0])
            return setup
        except UsageError:
            self._remove_reserved_folder()
            raise
        except ValueError as error:
            self._remove_reserved_folder()
            raise UsageError(str(error)) from error
        except TypeError as error:
            self._remove_reserved_folder()
            if "unexpected keyword argument" in str(error) and (self.env_kwargs or self.eval_env_kwargs):
                raise UsageError(env_kwargs_error(self.env_name.gym_id, error)) from None
            raise
        except BaseException:
            self._remove_reserved_folder()
            raise

    def create_log_folder(self) -> None:
        """
        Reserve the run folder ``<log folder>/<algo>/<EnvId>_<n>``: created exclusively, the next free number taken on a
        collision (rl_zoo3 picks ``n`` when the manager is made and creates the folder later with ``exist_ok``, so two
        runs started together shared one folder: one's model, args.yml and monitor file over the other's).
        """
        self.save_path = reserve_run_folder(self.log_path, str(self.env_name), self.save_path)
        self._reserved_folder = self.save_path
        self.params_path = f"{self.save_path}/{self.env_name}"
        os.makedirs(self.params_path, exist_ok=True)

    def _remove_reserved_folder(self) -> None:
        folder = getattr(self, "_reserved_folder", None)
        if folder is not None and os.path.isdir(folder):
            shutil.rmtree(folder, ignore_errors=True)  # created by this process, empty of results
        self._reserved_folder = None

    def _check_held_out_tasks(self, model: BaseAlgorithm) -> None:
        settings = self.meta_test_settings(model)
        env = self.create_envs(1, eval_env=True)
        try:
            model_test_tasks(
                model, env, settings["n_tasks"], settings["eval_seed"], f"{self.env_name.gym_id} (--seed {self.seed})"
            )
        except ValueError as error:
            raise UsageError(f"{error} (meta_test eval_seed {settings['eval_seed']}, or another --seed)") from error
        finally:
            env.close()

    def _check_resume_hyperparams(self) -> None:
        """
        ``--resume`` continues a run as it was: refuse hyperparameters (YAML entry, ``--budget``, ``-params``) that
        differ from those in the run's ``<EnvId>/config.yml``, except :data:`RESUME_MAY_CHANGE` (the budget to run up
        to, the evaluation settings). A model zip without its run's config is resumed with the settings given.
        """
        config = os.path.join(os.path.dirname(self.trained_agent), str(self.env_name), "config.yml")  # the run's params path
        if not os.path.isfile(config):
            print(f"Note: no {config} beside the checkpoint: its run's hyperparameters cannot be checked against these")
            return
        saved, current = dict(load_run_yaml(config) or {}), self.run_hyperparams
        missing = object()
        # A constructor argument not set on one side is what the run used: the checkpoint's own value where its zip
        # holds it as a plain number or string, else the constructor's default. So a key added to the YAML entry since
        # the run, at the value the run used, is no change, and one at a default changed since is refused.
        try:
            held = read_model_data(self.trained_agent)
        except (OSError, ValueError):
            held = {}  # a damaged zip: load() says so next
        used: dict[str, Any] = {}
        for name, parameter in constructor_parameters(ALGOS[self.algo]).items():
            if (name not in held or name in SAVED_RESOLVED) and parameter.default is not inspect.Parameter.empty:
                used[name] = parameter.default
            elif isinstance(held.get(name), (bool, int, float, str)):
                used[name] = held[name]  # (a serialised object is not compared: a key of it set on one side differs)

        def value(settings: dict[str, Any], key: str) -> Any:
            return settings.get(key, used.get(key, missing))

        def shown(settings: dict[str, Any], key: str) -> str:
            if key in settings:
                return repr(settings[key])
            return "not set" if key not in used else f"not set (the model's {used[key]!r})"

        changed = [
            f"{key}: {shown(saved, key)} in the run, {shown(current, key)} now"
            for key in sorted(saved.keys() | current.keys())
            if key not in RESUME_MAY_CHANGE and value(saved, key) != value(current, key)
        ]
        if changed:
            raise UsageError(
                f"--resume {self.trained_agent}: the hyperparameters differ from the run's ({config}): "
                f"{'; '.join(changed)}. A resume continues the run as it was: give the run's settings (its YAML entry, "
                "--budget and -params; a key not set in the run is removed from the entry or given the model's value), "
                "or train a new run with -i to continue from the model with new ones"
            )

    def _load_pretrained_agent(self, hyperparams: dict[str, Any], env: VecEnv) -> BaseAlgorithm:
        check_model_env(self.trained_agent, self.env_name.gym_id)
        if self.resume:
            self._check_resume_hyperparams()
        flag = "--resume" if self.resume else "-i"  # another family: the fix is --env, not the constructor's advice
        check_saved_model_family(self.trained_agent, env, self.env_name.gym_id, model_label=f"{flag} {self.trained_agent}")
        algo_class = ALGOS[self.algo]
        load_buffer = getattr(algo_class, "load_replay_buffer", None)
        if load_buffer is None:  # on-policy (MAML): no buffer to load
            return super()._load_pretrained_agent(hyperparams, env)

        own_buffer = resume_buffer_path(self.trained_agent, self.env_name.gym_id)

        def checked_load(model: BaseAlgorithm, path: str, *args: Any, **kwargs: Any) -> None:
            if self.resume and (own_buffer is None or os.path.abspath(path) != os.path.abspath(own_buffer)):
                return  # the folder's replay_buffer.pkl belongs to its <EnvId>.zip, not to this checkpoint
            self._load_replay_buffer(load_buffer, model, path, *args, **kwargs)

        with mock.patch.object(algo_class, "load_replay_buffer", checked_load):  # rl_zoo3's <folder>/replay_buffer.pkl
            model = super()._load_pretrained_agent(hyperparams, env)
        buffer_path = checkpoint_replay_buffer_path(self.trained_agent)
        if buffer_path is not None and os.path.isfile(buffer_path):
            print(f"Loading the checkpoint's replay buffer {buffer_path}")
            self._load_replay_buffer(load_buffer, model, buffer_path)
        return model

    def _load_replay_buffer(
        self, load: Callable[..., Any], model: BaseAlgorithm, path: str, *args: Any, **kwargs: Any
    ) -> None:
        """
        ``load(model, path)`` (the class's ``load_replay_buffer``); an empty, truncated or corrupt pickle is a one-line
        error naming the file and the flag that goes on without it, or with ``--resume-without-buffer`` a warning (the
        model keeps its empty buffer).
        """
        try:
            load(model, path, *args, **kwargs)
        except IncompleteReplayBufferError as error:
            problem = f"{path} is not a complete replay buffer pickle ({error.reason})"
            if not self.resume_without_buffer:
                fix = (
                    "add --resume-without-buffer to resume from an empty buffer (the run then differs from the "
                    "uninterrupted one)"
                    if self.resume
                    else "move it away to continue training from an empty buffer"
                )
                raise UsageError(f"{problem}: {fix}") from None
            print(f"Warning: {problem}: going on from an empty replay buffer (--resume-without-buffer)", flush=True)

    def after_save(self, model: BaseAlgorithm) -> None:
        """After the save: the final meta-test of an algorithm with the adaptation API (Ctrl-C / SIGTERM skip it)."""
        if self.adaptive:
            self.final_meta_test(model)


def env_kwargs_error(env_id: str, error: TypeError) -> str:
    """
    The one-line message for an ``--env-kwargs`` (or YAML ``env_kwargs``) key the env's constructor does not take.

    :param env_id: the env id
    :param error: the constructor's ``TypeError``
    :return: the message, with the constructor's parameters
    """
    match = re.search(r"unexpected keyword argument '([^']+)'", str(error))
    key = match.group(1) if match else str(error)
    spec = gym.spec(env_id)
    accepted = ""
    if isinstance(spec.entry_point, str):
        module, _, name = spec.entry_point.partition(":")
        parameters = inspect.signature(getattr(importlib.import_module(module), name)).parameters
        accepted = (
            " (its parameters: " + ", ".join(p for p, v in parameters.items() if v.kind == v.POSITIONAL_OR_KEYWORD) + ")"
        )
    return f"--env-kwargs / env_kwargs: {env_id} does not take {key!r}{accepted}"


def reserve_run_folder(log_path: str, env_name: str, planned: str) -> str:
    """
    Create a run folder exclusively: ``planned`` (``<log_path>/<env_name>_<n><suffix>``, rl_zoo3's choice), or the
    next free number when another process took it first.

    :param log_path: the algorithm's log folder
    :param env_name: the env id as rl_zoo3 writes it
    :param planned: the folder rl_zoo3 chose
    :return: the folder created, which this process owns
    """
    match = re.fullmatch(re.escape(env_name) + r"_(\d+)(.*)", os.path.basename(planned))
    number, suffix = (int(match.group(1)), match.group(2)) if match else (get_latest_run_id(log_path, env_name) + 1, "")
    os.makedirs(log_path, exist_ok=True)
    while True:
        folder = os.path.join(log_path, f"{env_name}_{number}{suffix}")
        try:
            os.mkdir(folder)
            return folder
        except FileExistsError:
            number = max(number, get_latest_run_id(log_path, env_name)) + 1


def train(argv: Sequence[str] | None = None) -> None:
    """
    ``rl_zoo3.train.train()`` with the project's algorithms, hyperparameter files and meta-test.

    The project's own flags (:mod:`sb3_pearl.zoo.flags`): ``--budget PRESET`` and ``--resume CHECKPOINT`` (a
    ``rl_model_<steps>_steps.zip`` written by ``--save-freq``, or a run's final model: load it with its replay buffer
    and RNG states and train up to ``n_timesteps`` in all, instead of ``-i``'s ``n_timesteps`` more from a reset
    counter).

    rl_zoo3's ``train()`` takes no experiment manager or argument-parsing class: it reads the module names
    ``ExperimentManager`` and ``StoreDict``, replaced for this call only by
    :func:`~sb3_pearl.zoo.rl_zoo3_coupling.run_zoo_train` (the contract: :mod:`sb3_pearl.zoo.rl_zoo3_coupling`).

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    """
    register_algos()
    with exit_on_usage_error():
        flags = parse_project_flags(list(sys.argv[1:] if argv is None else argv))
        if num_threads_flag(flags.zoo_args) > 0:  # rl_zoo3 sets it; learn() must not replace it with the default
            mark_num_threads_explicit()
        manager = functools.partial(
            MetaExperimentManager,
            resume=flags.resume,
            budget=flags.budget,
            command=flags.command,
            checkpoint_minutes=flags.checkpoint_minutes,
            resume_without_buffer=flags.resume_without_buffer,
        )
        try:
            run_zoo_train(flags.zoo_args, manager, CheckedStoreDict)  # CheckedStoreDict: a bad -params value is one line
        except SetupInterrupted as stop:
            print(f"Stopped by {stop.signal_name} before training: nothing trained or saved, no run folder kept", flush=True)
            raise SystemExit(stop.exit_status) from None
        except SystemExit:
            if {"-h", "--help"} & set(flags.zoo_args):
                print(PROJECT_FLAGS_HELP)
            raise


__all__ = [
    "HYPERPARAMS_DIR",
    "ZOO_META_TEST_DEFAULTS",
    "ZOO_SPECIAL_KEYS",
    "MetaExperimentManager",
    "check_model_env",
    "check_model_spaces",
    "default_config",
    "train",
    "write_meta_test",
]
