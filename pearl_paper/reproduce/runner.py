"""One reproduction run: build, learn, save, meta-test (held-out, shifted, training tasks), diagnose, write result.json.

:func:`run_one` is what each child process of ``python -m pearl_paper.reproduce run`` executes (through
the internal ``run-one`` subcommand), with one torch thread. Its steps are the methods of :class:`RunState`, which holds
the run's settings and checkpoint bookkeeping: open (settings, identity check, checkpoint state), model (new or resumed),
train, evaluate (each phase once, resumable) and write the result.

Test tasks and common random numbers: the held-out test tasks are ``sample_tasks(n_tasks, eval_seed)``
of the family env, with the experiment's fixed ``eval_seed``, so every variant and every model seed
is meta-tested on the same tasks; the meta-test runs with ``seed=eval_seed`` and
``crn_seed=eval_seed`` (the same env reset seeds and prior draws for every model). Nothing is chosen
on test tasks. The shifted meta-test draws its tasks the same way from the shifted env. The
competence check runs on the model's first ``n_tasks`` *training* tasks. The prior-critic measures
(calibration and prior-optimality gap, :mod:`pearl_paper.reproduce.prior_measures`) come next.
"""

from __future__ import annotations

import copy
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.env_util import make_vec_env

import sb3_pearl  # noqa: F401  (registers the task families)
from pearl_paper.experiments import get_experiment
from pearl_paper.experiments.spec import Experiment, Family, Variant
from pearl_paper.reproduce.checkpoint import (
    DEFAULT_INTERVAL_S,
    Interrupt,
    PeriodicCheckpoint,
    RunCheckpoint,
    csv_logger_continuing,
)
from pearl_paper.reproduce.competence import evaluate_competence
from pearl_paper.reproduce.curve import CURVE_FILE, LearningCurve, read_curve
from pearl_paper.reproduce.layout import (
    MODEL_FILE,
    PROGRESS_FILE,
    RESULT_FILE,
    RunKey,
    cpu_info,
    package_versions,
    read_result,
    run_dir,
    write_json_atomic,
)
from pearl_paper.reproduce.prior_measures import compute_prior_measures
from sb3_pearl.budgets import check_constructor_kwargs, load_budget, model_kwargs
from sb3_pearl.common.callbacks import StopOnSignalCallback, StopRequested
from sb3_pearl.common.threads import mark_num_threads_explicit
from sb3_pearl.evaluation.held_out import held_out_record, model_test_tasks, run_meta_test
from sb3_pearl.evaluation.meta_test import json_value
from sb3_pearl.pearl.diagnostics import compute_diagnostics
from sb3_pearl.registry import algorithm_class

DIAGNOSED_ALGOS = ("pearl", "pearlplus")


def run_kwargs(budget: dict[str, Any], variant: Variant, where: str) -> dict[str, Any]:
    """
    The constructor kwargs of a run: the budget's, with the variant's overrides on top (both checked).

    :param budget: the loaded budget
    :param variant: the variant
    :param where: for the messages
    :return: the kwargs as written (see :func:`~sb3_pearl.budgets.model_kwargs`)
    """
    overrides = dict(variant.overrides)
    check_constructor_kwargs(variant.algo, overrides, f"{where} variant {variant.name} overrides")
    return {**copy.deepcopy(budget["kwargs"]), **copy.deepcopy(overrides)}


def spec_record(experiment: Experiment, family: Family, variant: Variant) -> dict[str, Any]:
    """What result.json stores of the spec."""
    return json_value(
        {
            "experiment": {"name": experiment.name, "title": experiment.title, "eval_seed": experiment.eval_seed},
            "family": {
                "name": family.name,
                "env_id": family.env_id,
                "env_kwargs": dict(family.env_kwargs),
                "shift_env_kwargs": dict(family.shift_env_kwargs) if family.shift_env_kwargs is not None else None,
                "budget_family": family.budget_name,
            },
            "variant": {
                "name": variant.name,
                "label": variant.label,
                "algo": variant.algo,
                "overrides": dict(variant.overrides),
            },
        }
    )


def existing_result(path: Path, budget_preset: str) -> dict[str, Any] | None:
    """
    The complete result of a run folder, if any; an error if it was run with another budget preset.

    :param path: the run folder
    :param budget_preset: the preset of the requested run
    :return: the result or None
    """
    result_path = path / RESULT_FILE
    if not result_path.is_file():
        return None
    result = read_result(result_path)
    if result.get("budget_preset") != budget_preset:
        raise ValueError(
            f"{result_path} was run with budget preset {result.get('budget_preset')!r}, not {budget_preset!r}: "
            "use another --results-dir, or --force to replace it"
        )
    return result


class RunStopped(KeyboardInterrupt):
    """Training stopped on request (a signal to the run's process) where it resumes exactly, its checkpoint saved."""


@dataclass
class RunState:
    """
    One run's settings and checkpoint bookkeeping: the time spent by earlier segments, the phases done (their records and
    wall times), the files of the checkpoint in force and the training's recent rate; written by :meth:`save_state`.

    Made by :meth:`open`; :func:`run_one` then calls :meth:`model`, :meth:`train` (when :attr:`needs_training`),
    :meth:`evaluate` and :meth:`write_result`.
    """

    experiment: Experiment
    family: Family
    variant: Variant
    seed: int
    budget_preset: str
    key: RunKey
    folder: Path
    budget: dict[str, Any]
    kwargs: dict[str, Any]
    env_kwargs: dict[str, Any]
    log: Callable[..., None]
    cpu_start: dict[str, Any]
    checkpoint: RunCheckpoint
    state: dict[str, Any] | None
    identity: Any
    spent: dict[str, float]
    phases: dict[str, Any]
    segment_cpu: float
    segment_wall: float
    files: dict[str, str]
    resumed_steps: int
    # The CPU seconds and env steps at the last state written: the steps since then give the current rate, which
    # `reproduce status` prefers to the run's average (PEARL's initial pool makes its first steps far cheaper).
    last: dict[str, float]
    recent: dict[str, float]
    train_start: float = 0.0
    train_s_before: float = 0.0

    @classmethod
    def open(
        cls,
        experiment_name: str,
        family_name: str,
        variant_name: str,
        seed: int,
        budget_preset: str,
        results_dir: str | Path,
        verbose: int,
    ) -> RunState:
        """
        The run's settings (checked), its folder (made) and its checkpoint state, with the timers of this segment started.

        :param experiment_name: the experiment
        :param family_name: a family of the experiment
        :param variant_name: a variant of the experiment
        :param seed: the model seed
        :param budget_preset: the budget preset
        :param results_dir: root of the results layout
        :param verbose: print progress
        :return: the run
        """
        th.set_num_threads(1)  # one thread per run: the harness runs share the cores
        mark_num_threads_explicit()
        experiment = get_experiment(experiment_name)
        family, variant = experiment.family(family_name), experiment.variant(variant_name)
        if seed == experiment.eval_seed:
            raise ValueError(f"seed {seed} is the experiment's eval_seed: choose another model seed")
        key = RunKey(experiment.name, family.name, variant.name, seed)
        folder = run_dir(results_dir, key)
        folder.mkdir(parents=True, exist_ok=True)
        budget = load_budget(budget_preset, family.budget_name, variant.algo)
        kwargs = run_kwargs(budget, variant, f"{key.label()} (preset {budget_preset})")
        log = print if verbose else (lambda *args, **kw: None)
        cpu_start = cpu_info()
        checkpoint = RunCheckpoint(folder)
        state = checkpoint.read_state()
        identity = json_value({"budget_preset": budget_preset, "budget": budget, "model_kwargs": kwargs})
        if state is not None and state.get("identity") != identity:
            raise ValueError(
                f"{checkpoint.folder} was written by a run with other settings ({state.get('identity')}): "
                "delete it, or rerun with --force, to restart the run from zero"
            )
        spent = dict(state["spent"]) if state is not None else {"cpu_s": 0.0, "wall_s": 0.0}
        resumed_steps = int(state["num_timesteps"]) if state is not None else 0  # the checkpoint in force
        return cls(
            experiment=experiment,
            family=family,
            variant=variant,
            seed=seed,
            budget_preset=budget_preset,
            key=key,
            folder=folder,
            budget=budget,
            kwargs=kwargs,
            env_kwargs=dict(family.env_kwargs),
            log=log,
            cpu_start=cpu_start,
            checkpoint=checkpoint,
            state=state,
            identity=identity,
            spent=spent,
            phases=dict(state["phases"]) if state is not None else {},
            segment_cpu=time.process_time(),
            segment_wall=time.time(),
            files=dict(state["files"]) if state is not None else {},
            resumed_steps=resumed_steps,
            last={"cpu_s": spent["cpu_s"], "steps": resumed_steps},
            recent=dict(state.get("recent") or {}) if state is not None else {},
        )

    @property
    def needs_training(self) -> bool:
        """Whether the run trains: a new run, or one resumed from a checkpoint written during training."""
        return self.state is None or self.state["phase"] == "train"

    def save_state(self, phase: str, model: Any, written: dict[str, str] | None = None) -> None:
        """
        Write the checkpoint state: the time spent so far, the phases done, the files of the checkpoint in force.

        :param phase: ``train`` or ``evaluate``, where a resumed run goes on
        :param model: the model
        :param written: the files of a checkpoint just saved (now the one in force)
        """
        if written is not None:
            self.files.clear()
            self.files.update(written)
        if phase == "train":  # the training time of every segment so far (a resumed run adds its own)
            self.phases["train_s"] = self.train_s_before + time.time() - self.train_start
        cpu_s = self.spent["cpu_s"] + time.process_time() - self.segment_cpu
        if phase == "train" and model.num_timesteps > self.last["steps"]:
            self.recent.update(cpu_s=cpu_s - self.last["cpu_s"], steps=int(model.num_timesteps) - self.last["steps"])
        self.last.update(cpu_s=cpu_s, steps=int(model.num_timesteps))
        self.checkpoint.write_state(
            {
                "identity": self.identity,
                "phase": phase,
                "files": self.files,
                "num_timesteps": int(model.num_timesteps),
                "spent": {"cpu_s": cpu_s, "wall_s": self.spent["wall_s"] + time.time() - self.segment_wall},
                "recent": self.recent,  # the training's CPU seconds and env steps between its last two checkpoints
                "phases": self.phases,
            }
        )

    def make_env(self) -> Any:
        """The training env: the family's, ``n_envs`` of them, seeded with the model seed."""
        return make_vec_env(self.family.env_id, n_envs=self.budget["n_envs"], seed=self.seed, env_kwargs=self.env_kwargs)

    def model(self, env: Any) -> Any:
        """
        The model: a new one, or the one of the checkpoint in force; logging to the run's progress file.

        :param env: the training env
        :return: the model
        """
        algo = algorithm_class(self.variant.algo)
        if self.state is None:
            model = algo(self.budget["policy"], env, seed=self.seed, verbose=0, device="auto", **model_kwargs(self.kwargs))
            model.set_logger(csv_logger_continuing(self.folder, None))
        else:
            model = self.checkpoint.load_model(self.state, algo, env)
            model.set_logger(csv_logger_continuing(self.folder, self.checkpoint.progress_snapshot(self.state)))
            done = sorted(self.phases)
            self.log(
                f"[{self.key.label()}] resumed at {model.num_timesteps} steps ({self.state['phase']}), {done} done", flush=True
            )
        return model

    def learning_curve(self, model: Any, stop: StopOnSignalCallback | None) -> tuple[LearningCurve, gym.Env]:
        """
        The learning curve on the held-out tasks (docs/reproduce.md, "Learning curves"), with its env.

        :param model: the model
        :param stop: the run's stop callback (training it stops ends without the curve's end point)
        :return: the callback and its env (to close)
        """
        curve = self.budget["curve"]
        curve_env = gym.make(self.family.env_id, **self.env_kwargs)
        curve_tasks = model_test_tasks(model, curve_env, curve["n_tasks"], self.experiment.eval_seed, self.key.label())
        family, budget = self.family, self.budget
        competence = (family.competence, budget["competence_meta_test"], family.trace_keys()) if family.competence else None
        callback = LearningCurve(
            self.folder / CURVE_FILE,
            curve_env,
            curve_tasks,
            curve,
            self.experiment.eval_seed,
            self.resumed_steps,
            competence,
            stop,
        )
        return callback, curve_env

    def train(
        self, model: Any, checkpoint_interval_s: float, interrupt: Interrupt | None, stop: StopOnSignalCallback | None
    ) -> None:
        """
        Train the model to the budget's steps, with a checkpoint every ``checkpoint_interval_s`` seconds; save it.

        :param model: the model
        :param checkpoint_interval_s: seconds of training between checkpoints
        :param interrupt: the test hook simulating a kill
        :param stop: a stop asked for during training: its checkpoint is saved and :class:`RunStopped` raised
        """
        remaining = self.budget["n_timesteps"] - model.num_timesteps
        self.log(f"[{self.key.label()}] learn {remaining} of {self.budget['n_timesteps']} steps", flush=True)
        self.train_start, self.train_s_before = time.time(), float(self.phases.get("train_s", 0.0))
        progress = self.folder / PROGRESS_FILE
        on_save = lambda written: self.save_state("train", model, written)  # noqa: E731
        callbacks: list[BaseCallback] = [
            PeriodicCheckpoint(
                self.checkpoint, progress, checkpoint_interval_s, on_save, interrupt, in_force_steps=self.resumed_steps
            )
        ]
        curve_env = None
        if "curve" in self.budget:
            curve, curve_env = self.learning_curve(model, stop)
            callbacks.append(curve)
        at_resume = (int(model.num_timesteps), int(getattr(model, "_n_updates", 0)))
        pending = int(getattr(model, "_pending_gradient_steps", 0))  # a stop's gradient steps, trained first
        try:
            if remaining > 0 or pending > 0:
                callback = CallbackList([*callbacks, *([stop] if stop is not None else [])])
                model.learn(max(remaining, 0), callback=callback, reset_num_timesteps=self.state is None)
        except StopRequested:
            pass  # at an iteration start: saved below
        if curve_env is not None:
            curve_env.close()
        if stop is not None and stop.stopped:
            trained = (int(model.num_timesteps), int(getattr(model, "_n_updates", 0)))
            if trained != at_resume:  # else the checkpoint in force is this state
                self.save_state("train", model, self.checkpoint.save_model(model, progress, "{}_u{}".format(*trained)))
            raise RunStopped(f"at {trained[0]:,} env steps and {trained[1]:,} gradient steps")
        self.phases["train_s"] = self.train_s_before + time.time() - self.train_start
        model.save(self.folder / MODEL_FILE)
        written = self.checkpoint.save_model(model, progress)  # with the buffers the diagnostics read
        self.save_state("evaluate", model, written)
        if stop is not None and stop.requested:  # asked after the last stop point (e.g. during the curve's end point)
            raise RunStopped(f"at the end of training ({int(model.num_timesteps):,} env steps), before the evaluations")

    def phase(self, name: str, model: Any, compute: Callable[[], Any]) -> Any:
        """
        An evaluation phase: done once, its JSON record kept in the checkpoint until result.json is written.

        :param name: the phase
        :param model: the model
        :param compute: computes its record
        :return: the record
        """
        if name not in self.phases:
            start = time.time()
            self.phases[name] = json_value(compute())
            self.phases[f"{name}_s"] = time.time() - start
            self.save_state("evaluate", model)
        return self.phases[name]

    def evaluate(self, model: Any, interrupt: Interrupt | None) -> dict[str, Any]:
        """
        The evaluation phases, each done once (a resumed run skips those done): the held-out meta-test, the shifted
        meta-test, the competence check, the prior-critic measures and the diagnostics.

        :param model: the trained model
        :param interrupt: the test hook simulating a kill, called before every trajectory of the held-out meta-test
        :return: their records, by their result.json keys
        """
        eval_env = gym.make(self.family.env_id, **self.env_kwargs)
        trajectories = iter(range(1, 1 << 62))
        on_trajectory = None if interrupt is None else (lambda *_: interrupt("meta_test", next(trajectories)))
        held_out = self.phase("meta_test", model, lambda: self.held_out_meta_test(model, eval_env, on_trajectory))
        shift = self.phase("shift", model, lambda: self.shifted_meta_test(model))
        competence = self.phase("competence", model, lambda: self.competence_check(model, eval_env))
        prior_critic = self.phase("prior_measures", model, lambda: self.prior_measures(model, eval_env, held_out))
        diagnostics = self.phase("diagnostics", model, lambda: self.diagnose(model, eval_env))
        eval_env.close()
        return {
            "meta_test": held_out,
            "shift": shift,
            "competence": competence,
            "prior_critic": prior_critic,
            "diagnostics": diagnostics,
        }

    def held_out_meta_test(
        self, model: Any, eval_env: gym.Env, on_trajectory: Callable[[int, int, int], None] | None
    ) -> dict[str, Any]:
        """The meta-test on the held-out tasks (:func:`held_out_record`)."""
        settings = self.budget["meta_test"]
        self.log(f"[{self.key.label()}] meta-test {settings}", flush=True)
        return held_out_record(
            model, eval_env, settings, self.experiment.eval_seed, self.env_kwargs, self.key.label(), on_trajectory
        )

    def shifted_meta_test(self, model: Any) -> dict[str, Any] | None:
        """The meta-test on the shifted env's held-out tasks; None for a family without a shift."""
        if self.family.shift_env_kwargs is None:
            return None
        shift_settings = self.budget["shift_meta_test"]
        shift_kwargs = {**self.env_kwargs, **dict(self.family.shift_env_kwargs)}
        shift_env = gym.make(self.family.env_id, **shift_kwargs)
        self.log(f"[{self.key.label()}] shifted meta-test {shift_settings}", flush=True)
        record = held_out_record(model, shift_env, shift_settings, self.experiment.eval_seed, shift_kwargs, self.key.label())
        shift_env.close()
        return record

    def competence_check(self, model: Any, eval_env: gym.Env) -> dict[str, Any]:
        """The competence check on the model's first training tasks."""
        train_tasks = list(getattr(model, "train_tasks", []) or [])
        if not train_tasks:
            return {"skipped": "the model has no training tasks"}
        comp_settings = self.budget["competence_meta_test"]
        on_train = run_meta_test(
            model,
            eval_env,
            train_tasks[: comp_settings["n_tasks"]],
            comp_settings,
            self.experiment.eval_seed,
            self.family.trace_keys(),
        )
        competence = evaluate_competence(on_train, self.family.competence)
        return {**competence, "settings": comp_settings, "summary": on_train.summary}

    def prior_measures(self, model: Any, eval_env: gym.Env, held_out: dict[str, Any]) -> dict[str, Any]:
        """The prior-critic measures on the held-out tasks; the traceback if they fail."""
        settings = self.budget["meta_test"]
        tasks = model_test_tasks(model, eval_env, settings["n_tasks"], self.experiment.eval_seed, self.key.label())
        try:
            return compute_prior_measures(
                model,
                self.variant.algo,
                self.family,
                self.env_kwargs,
                settings,
                tasks,
                held_out["summary"][0],
                self.experiment.eval_seed,
                self.seed,
            )
        except Exception:  # like the diagnostics: a bug here must not throw away a trained run (`reproduce measure`)
            self.log(f"[{self.key.label()}] prior-critic measures failed:\n{traceback.format_exc()}", flush=True)
            return {"error": traceback.format_exc()}

    def diagnose(self, model: Any, eval_env: gym.Env) -> dict[str, Any]:
        """The diagnostics (PEARL and PEARL+ only); the traceback if they fail."""
        if self.variant.algo not in DIAGNOSED_ALGOS:
            return {"skipped": f"diagnostics apply to PEARL / PEARL+, not {self.variant.algo}"}
        try:
            return compute_diagnostics(model, eval_env, seed=self.seed)
        except Exception:  # a diagnostics bug must not throw away a trained and meta-tested run
            self.log(f"[{self.key.label()}] diagnostics failed:\n{traceback.format_exc()}", flush=True)
            return {"error": traceback.format_exc()}

    def write_result(self, model: Any, evaluations: dict[str, Any]) -> dict[str, Any]:
        """
        Write result.json (atomically) and remove the checkpoint.

        :param model: the trained model
        :param evaluations: the records of :meth:`evaluate`
        :return: the result written
        """
        timings = {"train": self.phases["train_s"]}
        for name in ("meta_test", "shift", "competence", "prior_measures", "diagnostics"):
            if name != "shift" or evaluations["shift"] is not None:
                timings[name] = self.phases[f"{name}_s"]
        total_cpu = self.spent["cpu_s"] + time.process_time() - self.segment_cpu
        timings["total"] = self.spent["wall_s"] + time.time() - self.segment_wall
        experiment, family, variant = self.experiment, self.family, self.variant
        result = json_value(
            {
                "experiment": experiment.name,
                "family": family.name,
                "variant": variant.name,
                "seed": self.seed,
                "budget_preset": self.budget_preset,
                "spec": spec_record(experiment, family, variant),
                "budget": self.budget,
                "model_kwargs": self.kwargs,
                "eval_seed": experiment.eval_seed,
                "versions": package_versions(),
                "cpu": {**self.cpu_start, "load_average_end": cpu_info()["load_average"], "cpu_time_s": total_cpu},
                "wall_time_s": timings,
                "num_timesteps": int(model.num_timesteps),
                "device": str(model.device),
                **evaluations,  # meta_test, shift, competence, prior_critic, diagnostics
                "curve": read_curve(self.folder / CURVE_FILE) or None,  # the learning curve, when the budget asks for one
            }
        )
        write_json_atomic(self.folder / RESULT_FILE, result)
        self.checkpoint.remove()
        self.log(f"[{self.key.label()}] done in {timings['total']:.0f} s: {self.folder / RESULT_FILE}", flush=True)
        return result


def run_one(
    experiment_name: str,
    family_name: str,
    variant_name: str,
    seed: int,
    budget_preset: str,
    results_dir: str | Path,
    verbose: int = 1,
    checkpoint_interval_s: float = DEFAULT_INTERVAL_S,
    interrupt: Interrupt | None = None,
    stop: StopOnSignalCallback | None = None,
) -> dict[str, Any]:
    """
    Train, save and evaluate one (variant, seed) of an experiment; write its result.json last and atomically.

    An interrupted run resumes from its checkpoint (:mod:`pearl_paper.reproduce.checkpoint`): training from the last
    iteration start saved (every ``checkpoint_interval_s`` seconds), evaluation from the first phase not done.

    :param experiment_name: ``table1``, ``table2``, ``table3``, ``safe-point``, ...
    :param family_name: a family of the experiment
    :param variant_name: a variant of the experiment
    :param seed: the model seed
    :param budget_preset: ``smoke``, ``cpu`` or ``paper``
    :param results_dir: root of the results layout
    :param verbose: print progress
    :param checkpoint_interval_s: seconds of training between checkpoints (0: at every iteration start)
    :param interrupt: test hook simulating a kill (:class:`~pearl_paper.reproduce.checkpoint.PeriodicCheckpoint`;
        also called as ``interrupt("meta_test", n)`` before every trajectory of the held-out meta-test)
    :param stop: a stop asked for during training (``stop.requested``, set by the child's signal handler) stops it where
        it resumes exactly, saves a checkpoint there and raises :class:`RunStopped`
    :return: the result written
    """
    run = RunState.open(experiment_name, family_name, variant_name, seed, budget_preset, results_dir, verbose)
    env = run.make_env()
    model = run.model(env)  # new, or resumed from the checkpoint
    if run.needs_training:
        run.train(model, checkpoint_interval_s, interrupt, stop)  # raises RunStopped on a stop
    model.logger.close()
    env.close()
    evaluations = run.evaluate(model, interrupt)  # each phase once, resumable
    return run.write_result(model, evaluations)
