"""Callbacks: the meta-test protocol during training (SB3's ``EvalCallback`` for meta-RL)."""

from __future__ import annotations

import csv
import os
import re
import shutil
import time
from typing import Any

import gymnasium as gym
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_pearl.common.adaptation import check_adaptive
from sb3_pearl.common.atomic import atomic_write
from sb3_pearl.common.persistence import read_model_data
from sb3_pearl.common.seeding import get_global_rng_state, set_global_rng_state
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.evaluation.held_out import DEFAULT_EVAL_SEED, model_test_tasks, run_meta_test
from sb3_pearl.evaluation.meta_test import MetaTestResult
from sb3_pearl.evaluation.statistics import SUMMARY_COLUMNS


class MetaTestCallback(BaseCallback):
    """
    Run the meta-test protocol every ``eval_freq`` calls, on the tasks and with the seeding of every meta-test of a
    trained model (:mod:`sb3_pearl.evaluation.held_out`: ``eval_env.sample_tasks(n_tasks, eval_seed)``, common random
    numbers from ``eval_seed``), so consecutive evaluations differ only by the model.

    The numbers go to the model's logger under ``meta_test/``: ``return_k<k>``,
    ``violation_rate_k<k>``, ``cvar10_k<k>`` for every k, plus ``return_prior`` (k = 0) and
    ``return_adapted`` (k = ``n_adapt``). ``last_mean_reward`` is the adapted return (k = ``n_adapt``),
    the score of the best model (``best_model.zip`` in ``best_model_save_path``) and of Optuna trials.
    Each evaluation is appended to ``<log_path>/meta_test_history.csv``.

    :param eval_env: a task-family env (gymnasium env or a VecEnv of one env)
    :param eval_freq: evaluate every ``eval_freq`` calls (one call per VecEnv step); <= 0 disables
    :param n_tasks: test tasks per evaluation (None: as many as the model's ``n_test_tasks``)
    :param n_adapt: last trajectory index K (k = 0..K)
    :param n_repeats: repeats per task
    :param deterministic: deterministic actions
    :param tasks: explicit test tasks (default: the held-out tasks drawn from ``eval_env`` with ``eval_seed``; an
        ``eval_env`` built with other ranges gives a shifted distribution)
    :param eval_seed: seed of the task draw, of the resets and of the common random numbers
    :param best_model_save_path: folder of ``best_model.zip`` (None: not saved)
    :param log_path: folder of ``meta_test_history.csv`` (None: not written)
    :param resumes: the folder of the run this training resumes (``train.py --resume``): its evaluations up to the
        model's env steps start this run's history, and its ``best_model.zip`` and score this run's best when that
        evaluation is among them (:meth:`continue_history`); None: a run of its own
    :param verbose: 0 silent, 1 a progress bar and one line per evaluation
    """

    def __init__(
        self,
        eval_env: gym.Env | VecEnv,
        eval_freq: int = 10_000,
        n_tasks: int | None = None,
        n_adapt: int = 5,
        n_repeats: int = 1,
        deterministic: bool = True,
        tasks: list[Task] | None = None,
        eval_seed: int = DEFAULT_EVAL_SEED,
        best_model_save_path: str | None = None,
        log_path: str | None = None,
        resumes: str | None = None,
        verbose: int = 1,
    ) -> None:
        super().__init__(verbose)
        self.eval_env = eval_env
        self.eval_freq = eval_freq
        self.n_tasks = n_tasks
        self.n_adapt = n_adapt
        self.n_repeats = n_repeats
        self.deterministic = deterministic
        self.tasks = tasks
        self.eval_seed = eval_seed
        self.best_model_save_path = best_model_save_path
        self.log_path = log_path
        self.resumes = resumes
        self.best_mean_reward = -float("inf")
        self.last_mean_reward = -float("inf")
        self.last_result: MetaTestResult | None = None
        self.n_evaluations = 0

    def _init_callback(self) -> None:
        check_adaptive(self.model)
        self.n_calls = continued_calls(self.model)
        if self.tasks is None:
            self.tasks = model_test_tasks(self.model, self.eval_env, self.n_tasks, self.eval_seed, "MetaTestCallback")
        for folder in (self.best_model_save_path, self.log_path):
            if folder is not None:
                os.makedirs(folder, exist_ok=True)
        if self.resumes is not None:
            self.continue_history(self.resumes)
            self.resumes = None  # once: a later learn() with this callback keeps its own best

    def continue_history(self, folder: str) -> None:
        """
        Continue the evaluations of the run in ``folder`` that this training resumes: its ``meta_test_history.csv``
        rows up to the model's env steps (the resume point: a cut run may have evaluated past the checkpoint it
        resumes from) start this run's history, and when its ``best_model.zip`` is the model of its best evaluation
        (the first highest adapted return) and that evaluation is among them, the zip and its score are this run's
        best so far, so ``best_model.zip`` is the best of the whole run. Nothing is carried from a history of other
        settings (other k or trajectories per k; train.py passes ``folder`` only when the cut run's meta-test
        settings, evaluation episodes and env kwargs are this run's) or one that cannot be read; the best is this
        run's own when the cut run's best came after the resume point.

        :param folder: the resumed run's folder
        """
        assert self.tasks is not None
        path = os.path.join(folder, "meta_test_history.csv")
        if self.log_path is None or not os.path.isfile(path):
            return
        try:
            with open(path, newline="") as file:
                rows = list(csv.DictReader(file))
            evaluations: dict[int, set[tuple[str, str]]] = {}
            for row in rows:
                evaluations.setdefault(int(row["timesteps"]), set()).add((row["k"], row["n"]))
            adapted = [(float(row["return_mean"]), int(row["timesteps"])) for row in rows if row["k"] == str(self.n_adapt)]
        except (KeyError, ValueError) as error:
            print(f"Note: {path} cannot be read ({error!r}): this run's history starts anew")
            return
        expected = {(str(k), str(len(self.tasks) * self.n_repeats)) for k in range(self.n_adapt + 1)}
        if any(group != expected for group in evaluations.values()):
            print(f"Note: {path} was written with other meta-test settings: this run's history starts anew")
            return
        resumed_at = int(self.model.num_timesteps)  # the callback's own num_timesteps is set at the training start
        kept = [row for row in rows if int(row["timesteps"]) <= resumed_at]
        own = os.path.join(self.log_path, "meta_test_history.csv")
        if kept and not os.path.exists(own):
            with atomic_write(own, "w", newline="") as file:
                writer = csv.DictWriter(file, fieldnames=list(rows[0]))
                writer.writeheader()
                writer.writerows(kept)
        if not adapted or self.best_model_save_path is None:
            return
        best_return, best_at = max(adapted, key=lambda entry: (entry[0], -entry[1]))  # the first of the highest
        best_model = os.path.join(folder, "best_model.zip")
        if best_at > resumed_at or saved_num_timesteps(best_model) != best_at:  # not the model of that evaluation
            return
        if os.path.abspath(folder) != os.path.abspath(self.best_model_save_path):
            with (
                open(best_model, "rb") as source,
                atomic_write(os.path.join(self.best_model_save_path, "best_model.zip"), "wb") as target,
            ):
                shutil.copyfileobj(source, target)
        self.best_mean_reward = best_return

    def _on_step(self) -> bool:
        if self.eval_freq > 0 and self.n_calls % self.eval_freq == 0:
            self.evaluate()
        return True

    def evaluate(self) -> MetaTestResult:
        """Run the protocol now, log it and keep the best model."""
        assert self.tasks is not None
        settings = {"n_adapt": self.n_adapt, "n_repeats": self.n_repeats, "deterministic": self.deterministic}
        result = run_meta_test(
            self.model,
            self.eval_env,
            self.tasks,
            settings,
            self.eval_seed,
            progress_bar=self.verbose >= 1,
            description="Meta-test (Ctrl-C stops training after it)",
        )
        # the meta-test restored the global RNGs; leaving the adaptation state (PEARL draws a prior z) must not move
        # them either, or a run with evaluations would train on other random numbers than one without
        rng_state = get_global_rng_state()
        self.model.reset_adaptation()  # type: ignore[attr-defined]
        set_global_rng_state(rng_state)
        self.last_result = result
        self.n_evaluations += 1
        for entry in result.summary:
            k = entry["k"]
            self.logger.record(f"meta_test/return_k{k}", entry["return_mean"])
            self.logger.record(f"meta_test/violation_rate_k{k}", entry["violation_rate"])
            self.logger.record(f"meta_test/cvar10_k{k}", entry["return_cvar10"])
        prior, adapted = result.summary_at(0), result.summary_at(self.n_adapt)
        self.logger.record("meta_test/return_prior", prior["return_mean"])
        self.logger.record("meta_test/return_adapted", adapted["return_mean"])
        self.logger.record("meta_test/violation_rate_prior", prior["violation_rate"])
        self.logger.record("meta_test/cum_violations", adapted["cum_violations"])
        self.last_mean_reward = float(adapted["return_mean"])
        if self.verbose >= 1:
            untrained = " (no gradient step yet: the initial collection)" if getattr(self.model, "_n_updates", 1) == 0 else ""
            print(
                f"Meta-test num_timesteps={self.num_timesteps} over {len(self.tasks)} test tasks x {self.n_repeats} "
                f"repeat(s): return k=0 {prior['return_mean']:.2f}, k={self.n_adapt} {adapted['return_mean']:.2f}; "
                f"violation rate k=0 {prior['violation_rate']:.2f}{untrained}"
            )
        if self.log_path is not None:
            self._append_history(result)
        if self.last_mean_reward > self.best_mean_reward:
            self.best_mean_reward = self.last_mean_reward
            if self.best_model_save_path is not None:
                self.model.save(os.path.join(self.best_model_save_path, "best_model"))
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(self.num_timesteps)
        return result

    def _append_history(self, result: MetaTestResult) -> None:
        """Append this evaluation to ``meta_test_history.csv``: the file is rewritten atomically (a kill keeps it whole)."""
        assert self.log_path is not None
        path = os.path.join(self.log_path, "meta_test_history.csv")
        previous = ""
        if os.path.exists(path):
            with open(path, newline="") as file:
                previous = file.read()
        with atomic_write(path, "w", newline="") as file:
            file.write(previous)
            writer = csv.DictWriter(file, fieldnames=["timesteps", *SUMMARY_COLUMNS], extrasaction="ignore")
            if not previous:
                writer.writeheader()
            for entry in result.summary:
                writer.writerow({"timesteps": self.num_timesteps, **entry})


class MetaTestTrialCallback(MetaTestCallback):
    """
    :class:`MetaTestCallback` reporting the adapted return to an Optuna trial (rl_zoo3's ``TrialEvalCallback`` interface).

    :param eval_env: a task-family env
    :param trial: the Optuna trial
    :param n_eval_episodes: test tasks per evaluation
    :param eval_freq: evaluate every ``eval_freq`` calls
    :param deterministic: deterministic actions
    :param verbose: verbosity
    :param best_model_save_path: folder of ``best_model.zip`` (None: not saved)
    :param log_path: folder of the evaluation history (None: not written)
    :param meta_test_kwargs: other :class:`MetaTestCallback` arguments (n_adapt, n_repeats, ...)
    """

    def __init__(
        self,
        eval_env: VecEnv,
        trial: Any,
        n_eval_episodes: int = 5,
        eval_freq: int = 10_000,
        deterministic: bool = True,
        verbose: int = 0,
        best_model_save_path: str | None = None,
        log_path: str | None = None,
        **meta_test_kwargs: Any,
    ) -> None:
        super().__init__(
            eval_env,
            eval_freq=eval_freq,
            n_tasks=n_eval_episodes,
            deterministic=deterministic,
            best_model_save_path=best_model_save_path,
            log_path=log_path,
            verbose=verbose,
            **meta_test_kwargs,
        )
        self.trial = trial
        self.eval_idx = 0
        self.is_pruned = False

    def _on_step(self) -> bool:
        if self.eval_freq > 0 and self.n_calls % self.eval_freq == 0:
            self.evaluate()
            self.eval_idx += 1
            self.trial.report(self.last_mean_reward, self.eval_idx)
            if self.trial.should_prune():
                self.is_pruned = True
                return False
        return True


class ResumableCheckpointCallback(CheckpointCallback):
    """
    SB3's ``CheckpointCallback`` writing *resumable* checkpoints: the model zip (with every RNG state, see
    :mod:`sb3_pearl.common.persistence`) and, for off-policy models, the replay buffer
    (``<prefix>_replay_buffer_<steps>_steps.pkl``), both written atomically, saved once due at the next point where
    a resume is exact instead of in the middle of a rollout: the next rollout start, or, for a checkpoint due by time
    with PEARL / PEARL+, the next gradient step (:func:`~sb3_pearl.common.callbacks.gradient_step_event`; the
    iteration's steps still to train are saved with the model, the file named ``..._steps_u<gradient steps>``), so a
    periodic checkpoint is never more than a gradient step late even inside a 25-minute iteration.

    A checkpoint is due after ``save_freq`` calls (``on_step``, one per VecEnv step; rl_zoo3's ``--save-freq``) and/or
    ``every_s`` seconds of wall-clock time since the last one (``train.py --checkpoint-minutes``); ``keep_last``
    deletes the previous checkpoint's files once the new one is written, so a periodic checkpoint costs the disk of
    one.

    PEARL / PEARL+ and MAML call ``on_rollout_start`` at the start of an iteration, before they draw its tasks,
    so ``train.py --resume`` of such a checkpoint continues bit for bit as the uninterrupted run
    (docs/reliability.md). Fine-Tune's rollouts are single env steps, so its checkpoints fall inside episodes:
    the zip holds the envs' mid-episode state (:mod:`sb3_pearl.common.env_state`, a DummyVecEnv's) and resumes
    bit for bit too.

    :param save_freq: save after this many calls (``on_step``, one per VecEnv step); 0: by time only
    :param save_path: the folder
    :param name_prefix: file name prefix
    :param verbose: 1 prints each checkpoint's path
    :param every_s: also save after this many seconds since the last checkpoint (None: by calls only)
    :param keep_last: delete the previous checkpoint's files after each save
    """

    def __init__(
        self,
        save_freq: int,
        save_path: str,
        name_prefix: str = "rl_model",
        verbose: int = 0,
        every_s: float | None = None,
        keep_last: bool = False,
    ) -> None:
        if every_s is not None and not every_s > 0:
            raise ValueError(f"every_s must be > 0 seconds or None, got {every_s}")
        super().__init__(max(save_freq, 1), save_path, name_prefix=name_prefix, save_replay_buffer=True, verbose=verbose)
        self.by_calls = save_freq > 0
        self.every_s = every_s
        self.keep_last = keep_last
        self._due = False
        self._last_save = time.monotonic()
        self._previous: list[str] = []
        self.saved: list[list[str]] = []  # the files of every checkpoint written

    def _init_callback(self) -> None:
        super()._init_callback()
        self.n_calls = continued_calls(self.model)

    def _on_step(self) -> bool:
        if self.by_calls and self.n_calls % self.save_freq == 0:
            self._due = True
        return True

    def _is_due(self) -> bool:
        timed = self.every_s is not None and time.monotonic() - self._last_save >= self.every_s
        return self._due or timed

    def _on_rollout_start(self) -> None:
        if self._is_due():
            self._save()

    def on_gradient_step(self) -> bool:
        """Between two of PEARL's gradient steps: save there when due by time (never asks to stop); a checkpoint due
        by calls (``--save-freq``) waits for the next iteration start, where rl_zoo3's users expect it."""
        if self.every_s is not None and time.monotonic() - self._last_save >= self.every_s:
            self._save()
        return True

    def _save(self) -> None:
        self._due = False
        model_path = self._checkpoint_path(extension="zip")
        if self._previous and model_path in self._previous:
            self._last_save = time.monotonic()
            return  # nothing new since the last checkpoint (same step count, same gradient steps): keep it
        buffer_paths: list[str] = []
        if getattr(self.model, "replay_buffer", None) is not None and hasattr(self.model, "save_replay_buffer"):
            buffer_paths.append(self._checkpoint_path("replay_buffer_", extension="pkl"))
            self.model.save_replay_buffer(buffer_paths[0])  # type: ignore[attr-defined]
        self.model.save(model_path)  # last: a checkpoint's zip on disk means its buffer is too (a kill between them)
        paths = [model_path, *buffer_paths]
        if self.keep_last:
            for old in self._previous:
                if old not in paths and os.path.exists(old):
                    os.remove(old)
        self._previous = paths
        self.saved.append(paths)
        self._last_save = time.monotonic()
        if self.verbose >= 1:
            print(f"Saving resumable checkpoint to {', '.join(paths)}", flush=True)

    def _checkpoint_path(self, checkpoint_type: str = "", extension: str = "") -> str:
        """SB3's ``<prefix>_<steps>_steps``; inside an iteration's gradient steps ``<prefix>_<steps>_steps_u<updates>``."""
        pending = int(getattr(self.model, "_pending_gradient_steps", 0))
        steps = f"{self.num_timesteps}_steps" + (f"_u{int(getattr(self.model, '_n_updates', 0))}" if pending else "")
        return os.path.join(self.save_path, f"{self.name_prefix}_{checkpoint_type}{steps}.{extension}")


def continued_calls(model: BaseAlgorithm) -> int:
    """
    The ``on_step`` calls the model's training has made (one per VecEnv step): where a callback counting calls starts,
    so that a resumed run evaluates and checkpoints on the uninterrupted run's grid (every ``eval_freq`` /
    ``save_freq`` calls from the start, not from the resume).

    :param model: the model training starts or resumes
    :return: the project's algorithms: their ``num_vec_env_steps``; another SB3 algorithm, or a model saved before it
        was recorded: ``num_timesteps // n_envs`` (exact for SB3's collection, where every env steps each call);
        0 for a new run
    """
    counted = int(getattr(model, "num_vec_env_steps", 0))
    return counted if counted > 0 else int(model.num_timesteps) // max(int(model.n_envs), 1)


def saved_num_timesteps(model_path: str) -> int | None:
    """
    The env steps an SB3 model zip was saved at, read from its ``data`` entry without loading the model.

    :param model_path: the zip
    :return: its ``num_timesteps``; None when the file is missing or is not such a zip
    """
    try:
        return int(read_model_data(model_path)["num_timesteps"])
    except (OSError, KeyError, ValueError, TypeError):  # DamagedModelError is a ValueError
        return None


def checkpoint_replay_buffer_path(model_path: str) -> str | None:
    """
    The replay buffer saved with a checkpoint: ``<prefix>_replay_buffer_<steps>_steps[_u<updates>].pkl`` for
    ``<prefix>_<steps>_steps[_u<updates>].zip`` (None for a path of another form).

    :param model_path: the checkpoint's model zip
    :return: the buffer's path (which may not exist)
    """
    folder, name = os.path.split(model_path)
    match = re.fullmatch(r"(?P<prefix>.+)_(?P<steps>\d+)_steps(?P<updates>_u\d+)?\.zip", name)
    if match is None:
        return None
    return os.path.join(folder, f"{match['prefix']}_replay_buffer_{match['steps']}_steps{match['updates'] or ''}.pkl")


__all__ = [
    "MetaTestCallback",
    "MetaTestTrialCallback",
    "ResumableCheckpointCallback",
    "checkpoint_replay_buffer_path",
    "continued_calls",
]
