"""One reproduction run: build, learn, save, meta-test (held-out, shifted, training tasks), diagnose, write result.json.

:func:`run_one` is what each child process of ``python -m pearl_paper.reproduce run`` executes (through
the internal ``run-one`` subcommand), with one torch thread.

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
from sb3_pearl.evaluation.held_out import held_out_meta_test, meta_test_record, model_test_tasks, run_meta_test
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


def held_out_record(
    model: Any,
    env: gym.Env,
    settings: dict[str, Any],
    eval_seed: int,
    env_kwargs: dict[str, Any],
    what: str = "",
    on_trajectory_start: Callable[[int, int, int], None] | None = None,
) -> dict[str, Any]:
    """
    A run's held-out meta-test as result.json stores it (``meta_test`` / ``shift``): the meta-test of every trained
    model (:func:`~sb3_pearl.evaluation.held_out.held_out_meta_test`, train.py's too) with its wall time and env kwargs.

    :param model: the trained model
    :param env: the evaluation env (built with ``env_kwargs``)
    :param settings: the budget's meta-test settings
    :param eval_seed: the experiment's eval seed
    :param env_kwargs: the env's kwargs, recorded
    :param what: the run, for messages
    :param on_trajectory_start: called before every trajectory (the resume tests' interruption hook)
    :return: the record
    """
    start = time.time()
    # no per-step traces in result.json (the merge family's would add megabytes per run): trace_keys=()
    result = held_out_meta_test(model, env, settings, eval_seed, what, trace_keys=(), on_trajectory_start=on_trajectory_start)
    return meta_test_record(result, wall_time_s=time.time() - start, env_kwargs=env_kwargs)


class RunStopped(KeyboardInterrupt):
    """Training stopped on request (a signal to the run's process) where it resumes exactly, its checkpoint saved."""


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
    env_kwargs = dict(family.env_kwargs)
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
    phases: dict[str, Any] = dict(state["phases"]) if state is not None else {}
    segment_cpu, segment_wall = time.process_time(), time.time()

    files: dict[str, str] = dict(state["files"]) if state is not None else {}

    # The CPU seconds and env steps at the last state written: the steps since then give the current rate, which
    # `reproduce status` prefers to the run's average (PEARL's initial pool makes its first steps far cheaper).
    resumed_steps = int(state["num_timesteps"]) if state is not None else 0  # the checkpoint in force
    last = {"cpu_s": spent["cpu_s"], "steps": resumed_steps}
    recent: dict[str, float] = dict(state.get("recent") or {}) if state is not None else {}

    def save_state(phase: str, model: Any, written: dict[str, str] | None = None) -> None:
        if written is not None:
            files.clear()
            files.update(written)
        if phase == "train":  # the training time of every segment so far (a resumed run adds its own)
            phases["train_s"] = train_s_before + time.time() - train_start
        cpu_s = spent["cpu_s"] + time.process_time() - segment_cpu
        if phase == "train" and model.num_timesteps > last["steps"]:
            recent.update(cpu_s=cpu_s - last["cpu_s"], steps=int(model.num_timesteps) - last["steps"])
        last.update(cpu_s=cpu_s, steps=int(model.num_timesteps))
        checkpoint.write_state(
            {
                "identity": identity,
                "phase": phase,
                "files": files,
                "num_timesteps": int(model.num_timesteps),
                "spent": {"cpu_s": cpu_s, "wall_s": spent["wall_s"] + time.time() - segment_wall},
                "recent": recent,  # the training's CPU seconds and env steps between its last two checkpoints
                "phases": phases,
            }
        )

    env = make_vec_env(family.env_id, n_envs=budget["n_envs"], seed=seed, env_kwargs=env_kwargs)
    algo = algorithm_class(variant.algo)
    progress = folder / PROGRESS_FILE
    if state is None:
        model = algo(budget["policy"], env, seed=seed, verbose=0, device="auto", **model_kwargs(kwargs))
        model.set_logger(csv_logger_continuing(folder, None))
    else:
        model = checkpoint.load_model(state, algo, env)
        model.set_logger(csv_logger_continuing(folder, checkpoint.progress_snapshot(state)))
        log(f"[{key.label()}] resumed at {model.num_timesteps} steps ({state['phase']}), {sorted(phases)} done", flush=True)
    if state is None or state["phase"] == "train":
        remaining = budget["n_timesteps"] - model.num_timesteps
        log(f"[{key.label()}] learn {remaining} of {budget['n_timesteps']} steps", flush=True)
        train_start, train_s_before = time.time(), float(phases.get("train_s", 0.0))
        on_save = lambda written: save_state("train", model, written)  # noqa: E731
        callbacks: list[BaseCallback] = [
            PeriodicCheckpoint(checkpoint, progress, checkpoint_interval_s, on_save, interrupt, in_force_steps=resumed_steps)
        ]
        curve_env = None
        if "curve" in budget:  # the learning curve on the held-out tasks (docs/reproduce.md, "Learning curves")
            curve_env = gym.make(family.env_id, **env_kwargs)
            curve_tasks = model_test_tasks(model, curve_env, budget["curve"]["n_tasks"], experiment.eval_seed, key.label())
            resume_at = int(state["num_timesteps"]) if state is not None else 0
            callbacks.append(
                LearningCurve(
                    folder / CURVE_FILE,
                    curve_env,
                    curve_tasks,
                    budget["curve"],
                    experiment.eval_seed,
                    resume_at,
                    (family.competence, budget["competence_meta_test"], family.trace_keys()) if family.competence else None,
                )
            )
        at_resume = (int(model.num_timesteps), int(getattr(model, "_n_updates", 0)))
        pending = int(getattr(model, "_pending_gradient_steps", 0))  # a stop's gradient steps, trained first
        try:
            if remaining > 0 or pending > 0:
                callback = CallbackList([*callbacks, *([stop] if stop is not None else [])])
                model.learn(max(remaining, 0), callback=callback, reset_num_timesteps=state is None)
        except StopRequested:
            pass  # at an iteration start: saved below
        if curve_env is not None:
            curve_env.close()
        if stop is not None and stop.stopped:
            trained = (int(model.num_timesteps), int(getattr(model, "_n_updates", 0)))
            if trained != at_resume:  # else the checkpoint in force is this state
                save_state("train", model, checkpoint.save_model(model, progress, "{}_u{}".format(*trained)))
            raise RunStopped(f"at {trained[0]:,} env steps and {trained[1]:,} gradient steps")
        phases["train_s"] = train_s_before + time.time() - train_start
        model.save(folder / MODEL_FILE)
        save_state("evaluate", model, checkpoint.save_model(model, progress))  # with the buffers the diagnostics read
    model.logger.close()
    env.close()
    train_tasks = list(getattr(model, "train_tasks", []) or [])

    def phase(name: str, compute: Callable[[], Any]) -> Any:
        """An evaluation phase: done once, its JSON record kept in the checkpoint until result.json is written."""
        if name not in phases:
            start = time.time()
            phases[name] = json_value(compute())
            phases[f"{name}_s"] = time.time() - start
            save_state("evaluate", model)
        return phases[name]

    settings = budget["meta_test"]
    eval_env = gym.make(family.env_id, **env_kwargs)
    trajectories = iter(range(1, 1 << 62))
    on_trajectory = None if interrupt is None else (lambda *_: interrupt("meta_test", next(trajectories)))

    def held_out_phase() -> dict[str, Any]:
        log(f"[{key.label()}] meta-test {settings}", flush=True)
        return held_out_record(model, eval_env, settings, experiment.eval_seed, env_kwargs, key.label(), on_trajectory)

    held_out = phase("meta_test", held_out_phase)

    def shifted_meta_test() -> dict[str, Any] | None:
        if family.shift_env_kwargs is None:
            return None
        shift_settings = budget["shift_meta_test"]
        shift_kwargs = {**env_kwargs, **dict(family.shift_env_kwargs)}
        shift_env = gym.make(family.env_id, **shift_kwargs)
        log(f"[{key.label()}] shifted meta-test {shift_settings}", flush=True)
        record = held_out_record(model, shift_env, shift_settings, experiment.eval_seed, shift_kwargs, key.label())
        shift_env.close()
        return record

    shift = phase("shift", shifted_meta_test)

    def competence_check() -> dict[str, Any]:
        if not train_tasks:
            return {"skipped": "the model has no training tasks"}
        comp_settings = budget["competence_meta_test"]
        on_train = run_meta_test(
            model, eval_env, train_tasks[: comp_settings["n_tasks"]], comp_settings, experiment.eval_seed, family.trace_keys()
        )
        return {**evaluate_competence(on_train, family.competence), "settings": comp_settings, "summary": on_train.summary}

    competence = phase("competence", competence_check)

    def prior_measures() -> dict[str, Any]:
        tasks = model_test_tasks(model, eval_env, settings["n_tasks"], experiment.eval_seed, key.label())
        try:
            return compute_prior_measures(
                model, variant.algo, family, env_kwargs, settings, tasks, held_out["summary"][0], experiment.eval_seed, seed
            )
        except Exception:  # like the diagnostics: a bug here must not throw away a trained run (`reproduce measure`)
            log(f"[{key.label()}] prior-critic measures failed:\n{traceback.format_exc()}", flush=True)
            return {"error": traceback.format_exc()}

    prior_critic = phase("prior_measures", prior_measures)

    def diagnose() -> dict[str, Any]:
        if variant.algo not in DIAGNOSED_ALGOS:
            return {"skipped": f"diagnostics apply to PEARL / PEARL+, not {variant.algo}"}
        try:
            return compute_diagnostics(model, eval_env, seed=seed)
        except Exception:  # a diagnostics bug must not throw away a trained and meta-tested run
            log(f"[{key.label()}] diagnostics failed:\n{traceback.format_exc()}", flush=True)
            return {"error": traceback.format_exc()}

    diagnostics = phase("diagnostics", diagnose)
    eval_env.close()
    timings = {"train": phases["train_s"]}
    for name in ("meta_test", "shift", "competence", "prior_measures", "diagnostics"):
        if name != "shift" or shift is not None:
            timings[name] = phases[f"{name}_s"]
    total_cpu = spent["cpu_s"] + time.process_time() - segment_cpu
    timings["total"] = spent["wall_s"] + time.time() - segment_wall

    result = json_value(
        {
            "experiment": experiment.name,
            "family": family.name,
            "variant": variant.name,
            "seed": seed,
            "budget_preset": budget_preset,
            "spec": spec_record(experiment, family, variant),
            "budget": budget,
            "model_kwargs": kwargs,
            "eval_seed": experiment.eval_seed,
            "versions": package_versions(),
            "cpu": {**cpu_start, "load_average_end": cpu_info()["load_average"], "cpu_time_s": total_cpu},
            "wall_time_s": timings,
            "num_timesteps": int(model.num_timesteps),
            "device": str(model.device),
            "meta_test": held_out,
            "shift": shift,
            "competence": competence,
            "prior_critic": prior_critic,
            "diagnostics": diagnostics,
            "curve": read_curve(folder / CURVE_FILE) or None,  # the learning curve, when the budget asks for one
        }
    )
    write_json_atomic(folder / RESULT_FILE, result)
    checkpoint.remove()
    log(f"[{key.label()}] done in {timings['total']:.0f} s: {folder / RESULT_FILE}", flush=True)
    return result
