"""The meta-test in ``train.py``: the evaluation callback, the Optuna trial score and the final meta-test.

:class:`MetaTestExperimentManager` is rl_zoo3's ``ExperimentManager`` where, for algorithms with the adaptation API:

- the evaluation callback is :class:`~sb3_pearl.evaluation.callbacks.MetaTestCallback` (``--eval-episodes`` test tasks
  per evaluation, k = 0..``meta_test.n_adapt``, logger keys ``meta_test/...``, ``best_model.zip``), and the callbacks
  add the cost of the run (:class:`~sb3_pearl.evaluation.progress.TrainingProgressCallback`, also ``-P``'s bar) and
  resumable ``--save-freq`` checkpoints;
- the ``--eval-freq`` evaluations (and ``best_model.zip``) and the Optuna trials use validation tasks (drawn with
  ``eval_seed + 1``), never the final meta-test's tasks;
- :meth:`final_meta_test` runs the meta-test of every trained model (:mod:`sb3_pearl.evaluation.held_out`) and writes
  ``meta_test.csv``, ``meta_test.json`` and ``adaptation.png`` into the run folder.

Other algorithms keep rl_zoo3's ``EvalCallback``.
"""

from __future__ import annotations

import functools
import os
from typing import Any

import yaml
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import CheckpointCallback, ProgressBarCallback

from sb3_pearl.evaluation.callbacks import MetaTestCallback, MetaTestTrialCallback, ResumableCheckpointCallback
from sb3_pearl.evaluation.held_out import (
    DEFAULT_EVAL_SEED,
    META_TEST_DEFAULTS,
    default_n_tasks,
    held_out_meta_test,
    write_meta_test,
)
from sb3_pearl.evaluation.meta_test import MetaTestResult
from sb3_pearl.evaluation.progress import TrainingProgressCallback
from sb3_pearl.zoo.budget import faster_option
from sb3_pearl.zoo.rl_zoo3_coupling import ExperimentManager, trial_eval_callback_replaced
from sb3_pearl.zoo.safe_config import load_run_yaml, parse_dict_string
from sb3_pearl.zoo.usage import UsageError, program_name

# The zoo key `meta_test`: the settings of every meta-test plus the eval seed of its tasks (evaluation/held_out.py).
ZOO_META_TEST_DEFAULTS: dict[str, Any] = {**META_TEST_DEFAULTS, "eval_seed": DEFAULT_EVAL_SEED}
SHORT_RUN_FRACTION = 10  # -n below 1 / SHORT_RUN_FRACTION of the entry's n_timesteps is a short (smoke) run ...
SHORT_RUN_META_TEST_TASKS = 5  # ... whose final meta-test draws at most this many held-out tasks, unless meta_test says


def meta_test_dict(value: Any, where: str) -> dict[str, Any]:
    """
    The zoo key ``meta_test`` as a dict: None is empty, a string is parsed without ``eval``
    (:func:`~sb3_pearl.zoo.safe_config.parse_dict_string`); anything else than a dict of the known keys is a
    :class:`~sb3_pearl.zoo.usage.UsageError`.

    :param value: the key's value (YAML entry, budget preset or ``-params``)
    :param where: where it was given, for the message
    :return: the dict (a copy)
    """
    if value is None:
        return {}
    if isinstance(value, str):  # the zoo's convention for dict values given as strings, parsed without eval()
        try:
            value = parse_dict_string(value, "meta_test")
        except ValueError as error:
            raise UsageError(f"{error} (in {where})") from None
    if not isinstance(value, dict) or set(value) - set(ZOO_META_TEST_DEFAULTS):
        raise UsageError(
            f"meta_test must be a dict with keys among {sorted(ZOO_META_TEST_DEFAULTS)}, got {value!r} (in {where})"
        )
    return dict(value)


class MetaTestExperimentManager(ExperimentManager):
    """rl_zoo3's ``ExperimentManager`` with the meta-test as its evaluation (module docstring)."""

    adaptive: bool = False  # the algorithm has the adaptation API
    budget: str | None = None  # --budget PRESET (the faster-option hint of the progress callback)
    short_run: bool = False  # a short run: its final meta-test on SHORT_RUN_META_TEST_TASKS tasks, one draw each
    meta_test_chosen: set[str] = set()  # the meta_test keys given with -params (a short run keeps them)
    meta_test_kwargs: dict[str, Any]  # the `meta_test` key over ZOO_META_TEST_DEFAULTS

    @property
    def validation_seed(self) -> int:
        """The seed of the validation tasks (``eval_seed + 1``): the ``--eval-freq`` evaluations and Optuna trials."""
        return int(self.meta_test_kwargs["eval_seed"]) + 1

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
        if self.verbose >= 1 and not self.optimize_hyperparameters:
            settings = self.meta_test_settings(None)
            tasks = settings.get("n_tasks") or "the model's test"
            short = self.short_run
            if short and self.meta_test_kwargs.get("n_tasks") is None:  # the cap also depends on the model's test tasks
                tasks = f"at most {SHORT_RUN_META_TEST_TASKS}"
            print(
                f"After training, the final meta-test: {tasks} tasks x {settings['n_repeats']} prior draw(s) x "
                f"{int(settings['n_adapt']) + 1} trajectories ("
                + (
                    "a short run, -n under a tenth of the entry's n_timesteps: its numbers check the pipeline; "
                    if short
                    else ""
                )
                + 'Ctrl-C skips it; -params "meta_test:dict(n_tasks=N)" sizes it)',
                flush=True,
            )
        self.callbacks.insert(0, TrainingProgressCallback(self.show_progress, slow_hint, verbose=self.verbose))
        # --save-freq: resumable checkpoints (model with its RNG states + replay buffer, at an iteration start).
        self.callbacks = [
            ResumableCheckpointCallback(cb.save_freq, cb.save_path, cb.name_prefix, cb.verbose)
            if type(cb) is CheckpointCallback
            else cb
            for cb in self.callbacks
        ]
        minutes = float(getattr(self, "checkpoint_minutes", 0.0))
        if minutes > 0 and not self.optimize_hyperparameters:  # --checkpoint-minutes: a kill loses at most that much
            self.callbacks.append(
                ResumableCheckpointCallback(
                    0, self.save_path, "checkpoint", self.verbose, every_s=60 * minutes, keep_last=True
                )
            )
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
                    eval_seed=self.validation_seed,  # best_model.zip is never chosen on the final meta-test's tasks
                    best_model_save_path=self.save_path,
                    log_path=self.save_path,
                    resumes=self._evaluations_to_continue(),
                    verbose=self.verbose,
                )
            )

    def _evaluations_to_continue(self) -> str | None:
        """
        ``--resume``: the cut run's folder, whose evaluations (``meta_test_history.csv``, ``best_model.zip``) this run
        continues (:meth:`~sb3_pearl.evaluation.callbacks.MetaTestCallback.continue_history`) when they were made as
        this run's are: the same ``meta_test`` settings of those evaluations (``n_adapt``, ``n_repeats``,
        ``deterministic``, ``eval_seed``; defaults resolved), ``--eval-episodes`` and env kwargs of the evaluation
        env. A resume may change those; its evaluations then start anew. None: not a resume, or other evaluations.
        """
        if not getattr(self, "resume", False):
            return None
        folder = os.path.dirname(self.trained_agent)
        params = os.path.join(folder, str(self.env_name))
        try:
            args = dict(load_run_yaml(os.path.join(params, "args.yml")) or {})
            config = dict(load_run_yaml(os.path.join(params, "config.yml")) or {})
            settings = {**ZOO_META_TEST_DEFAULTS, **meta_test_dict(config.get("meta_test"), "config.yml")}
        except (OSError, ValueError, UsageError, yaml.YAMLError):
            return None  # no run folder beside the checkpoint (a zip of its own), or one that cannot be read
        evaluated_in = args.get("eval_env_kwargs") or args.get("env_kwargs") or {}  # rl_zoo3's eval env kwargs
        evaluation = ("n_adapt", "n_repeats", "deterministic", "eval_seed")  # what the --eval-freq meta-tests use
        same = (
            all(settings[key] == self.meta_test_kwargs[key] for key in evaluation)
            and args.get("eval_episodes") == self.n_eval_episodes
            and dict(evaluated_in) == dict(self.eval_env_kwargs or {})
        )
        if not same:
            print(
                f"Note: {folder} evaluated with other meta-test settings, --eval-episodes or env kwargs: this run's "
                "meta_test_history.csv and best_model.zip start anew"
            )
            return None
        return folder

    def hyperparameters_optimization(self) -> None:
        if not self.adaptive:
            super().hyperparameters_optimization()
            return
        settings = {key: self.meta_test_kwargs[key] for key in ("n_adapt", "n_repeats")}
        settings["eval_seed"] = self.validation_seed  # trials are never scored on the final meta-test's tasks
        # rl_zoo3's objective() builds its TrialEvalCallback from the module's name and takes no callback class: the
        # name is replaced for this call only (sb3_pearl.zoo.rl_zoo3_coupling).
        with trial_eval_callback_replaced(functools.partial(MetaTestTrialCallback, **settings)):
            super().hyperparameters_optimization()

    def meta_test_settings(self, model: BaseAlgorithm | None) -> dict[str, Any]:
        """
        The final meta-test's settings for ``model``: the ``meta_test`` key's (the YAML entry's or the budget
        preset's, with ``-params``'s on top). A short run (``-n`` under 1 / :data:`SHORT_RUN_FRACTION` of the entry's
        ``n_timesteps``) draws at most :data:`SHORT_RUN_META_TEST_TASKS` tasks and one prior draw of each, unless
        ``-params`` sets ``n_tasks`` / ``n_repeats``.

        :param model: the trained model (None: the task count is not capped by the model's test tasks yet)
        :return: the settings
        """
        settings = dict(self.meta_test_kwargs)
        if self.short_run:
            if "n_tasks" not in self.meta_test_chosen:
                n_tasks = settings.get("n_tasks") or (default_n_tasks(model) if model is not None else None)
                settings["n_tasks"] = min(SHORT_RUN_META_TEST_TASKS, n_tasks or SHORT_RUN_META_TEST_TASKS)
            if "n_repeats" not in self.meta_test_chosen:
                settings["n_repeats"] = 1
        return settings

    def final_meta_test(self, model: BaseAlgorithm) -> MetaTestResult:
        """
        The meta-test of every trained model (:mod:`sb3_pearl.evaluation.held_out`: held-out tasks drawn from the eval
        env with the ``meta_test`` key's ``eval_seed``, common random numbers) after training; writes the meta-test
        files into the run folder.

        :param model: the trained model
        :return: the result
        """
        settings = self.meta_test_settings(model)
        env = self.create_envs(1, eval_env=True)
        try:
            if self.verbose > 0:
                print(
                    f"Meta-test: held-out tasks drawn with eval seed {settings['eval_seed']}, k = 0..{settings['n_adapt']}, "
                    f"{settings['n_repeats']} repeat(s)"
                )
            result = held_out_meta_test(
                model,
                env,
                settings,
                settings["eval_seed"],
                what=self.env_name.gym_id,
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


__all__ = ["ZOO_META_TEST_DEFAULTS", "MetaTestExperimentManager"]
