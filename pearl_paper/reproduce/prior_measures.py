"""The two prior-critic measures of a run (result.json ``prior_critic``; docs/pearl.md, "Measures").

- **Calibration** (PEARL / PEARL+): the critic that scores the actor's prior term, Q~(s0, a0, z0) (Q(s0, a0, z0)
  for PEARL and the shared ablation), against the Monte-Carlo soft return of the same z0 rollouts
  (:func:`~sb3_pearl.pearl.diagnostics.compute_calibration`): ``bias``, ``relative_error`` and ``rank_corr``,
  on the model's first :data:`N_CALIBRATION_TASKS` *training* tasks with :data:`N_CALIBRATION_Z0` prior draws.
- **Prior-optimality gap** (every algorithm): the k = 0 return and violation rate of the prior policy against the
  family's task-independent bar (:class:`~pearl_paper.experiments.spec.PriorBar`), on the model's first
  ``n_tasks`` training tasks (the meta-test's ``n_tasks`` x ``n_repeats``) and on the held-out test tasks of the
  meta-test, with the same env seeds and prior draws (common random numbers: the experiment's eval seed).
  A scripted bar is rolled out here; a variant bar (Walker2D-vel: Fine-Tune) is another run's ``model`` entry
  and the report pairs them by seed.

Everything here is seeded from the eval seed and the model seed alone, so that the measures of a model loaded
from its ``model.zip`` are those of the model in memory at the end of its run (``reproduce measure`` fills them in
for runs written before they existed). Selection rules read the ``train`` entries only.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from pearl_paper.experiments.spec import Family
from sb3_pearl.common.seeding import derived_seed, get_global_rng_state, seed_global_rngs, set_global_rng_state
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.evaluation.held_out import run_meta_test
from sb3_pearl.evaluation.meta_test import json_value
from sb3_pearl.evaluation.scripted import ScriptedPolicy
from sb3_pearl.pearl.diagnostics import compute_calibration

N_CALIBRATION_TASKS = 8
N_CALIBRATION_Z0 = 16
_CALIBRATION_STREAM = 18  # the derived-seed stream of the calibration draws: apart from every other stream
MEASURES_VERSION = 2  # 2: the calibration's task-blind reference; records of version 1 are measured again


def scripted_prior(env_id: str, name: str) -> ScriptedPolicy:
    """
    The scripted policy ``name`` that the env module of ``env_id`` declares in ``SCRIPTED_PRIORS``.

    :param env_id: the registered env id
    :param name: the policy's name
    :return: the policy with the adaptation API
    """
    entry_point = gym.spec(env_id).entry_point
    module_name = entry_point.split(":")[0] if isinstance(entry_point, str) else entry_point.__module__
    module = __import__(module_name, fromlist=["SCRIPTED_PRIORS"])
    policies = getattr(module, "SCRIPTED_PRIORS", {})
    if name not in policies:
        raise ValueError(f"{env_id} declares no scripted policy {name!r} (its module {module_name} has {sorted(policies)})")
    return ScriptedPolicy(policies[name], name)


def _k0(model: Any, env: gym.Env, tasks: list[Task], n_repeats: int, eval_seed: int) -> dict[str, float]:
    """k = 0 return and violation rate of ``model`` on ``tasks`` (deterministic actions, common random numbers)."""
    result = run_meta_test(model, env, tasks, {"n_adapt": 0, "n_repeats": n_repeats, "deterministic": True}, eval_seed)
    k0 = result.summary[0]
    return {"n": int(k0["n"]), "return": float(k0["return_mean"]), "violation": float(k0["violation_rate"])}


def _gap(model: dict[str, float], bar: dict[str, float]) -> dict[str, float]:
    """Model minus bar: ``return`` > 0 is better than the bar, ``violation`` > 0 violates more often."""
    return {"return": model["return"] - bar["return"], "violation": model["violation"] - bar["violation"]}


def prior_calibration(model: Any, env: gym.Env, seed: int) -> dict[str, Any]:
    """
    Calibration of the prior term's critic on the model's first training tasks, seeded by ``seed`` only.

    :param model: a PEARL / PEARL+ model
    :param env: an env of its family
    :param seed: seed of the z0 draws, the env resets and the stochastic actions
    :return: :func:`compute_calibration`'s dict
    """
    tasks = list(model.train_tasks)[:N_CALIBRATION_TASKS]
    z0 = np.random.default_rng(derived_seed(seed, _CALIBRATION_STREAM)).standard_normal((N_CALIBRATION_Z0, model.latent_dim))
    saved = get_global_rng_state()
    seed_global_rngs(derived_seed(seed, _CALIBRATION_STREAM, 1))
    training = model.policy.training
    model.policy.set_training_mode(False)
    try:
        return compute_calibration(model, env, tasks, z0, seed, None)
    finally:
        model.policy.set_training_mode(training)
        set_global_rng_state(saved)


def compute_prior_measures(
    model: Any,
    algo: str,
    family: Family,
    env_kwargs: dict[str, Any],
    settings: dict[str, Any],
    test_tasks: list[Task],
    test_k0: dict[str, Any],
    eval_seed: int,
    model_seed: int,
) -> dict[str, Any]:
    """
    result.json's ``prior_critic`` section of one run.

    :param model: the trained model
    :param algo: its algorithm name (``pearl``, ``pearlplus``, ``finetune``, ``maml``)
    :param family: the family (its prior bar)
    :param env_kwargs: the family's env kwargs
    :param settings: the meta-test settings (``n_tasks``, ``n_repeats``)
    :param test_tasks: the held-out test tasks of the meta-test
    :param test_k0: the meta-test's k = 0 summary on them
    :param eval_seed: the experiment's eval seed
    :param model_seed: the run's model seed
    :return: ``{"version", "calibration", "prior_optimality"}``
    """
    env = gym.make(family.env_id, **env_kwargs)
    try:
        calibration: dict[str, Any] | None = None
        if algo in ("pearl", "pearlplus") and getattr(model, "train_tasks", None):
            calibration = prior_calibration(model, env, derived_seed(eval_seed, model_seed))
        train_tasks = list(getattr(model, "train_tasks", []) or [])[: settings["n_tasks"]]
        optimality: dict[str, Any] = {
            "bar": None if family.prior_bar is None else {"kind": family.prior_bar.kind, "name": family.prior_bar.name},
            "settings": {"n_train_tasks": len(train_tasks), "n_repeats": settings["n_repeats"], "eval_seed": eval_seed},
            "train": None,
            "test": {
                "model": {"n": int(test_k0["n"]), "return": test_k0["return_mean"], "violation": test_k0["violation_rate"]}
            },
        }
        if train_tasks:
            optimality["train"] = {"model": _k0(model, env, train_tasks, settings["n_repeats"], eval_seed)}
        if family.prior_bar is not None and family.prior_bar.kind == "scripted":
            bar = scripted_prior(family.env_id, family.prior_bar.name)
            for part, tasks in (("train", train_tasks), ("test", list(test_tasks))):
                if tasks and optimality[part] is not None:
                    optimality[part]["bar"] = _k0(bar, env, tasks, settings["n_repeats"], eval_seed)
                    optimality[part]["gap"] = _gap(optimality[part]["model"], optimality[part]["bar"])
    finally:
        env.close()
    return json_value({"version": MEASURES_VERSION, "calibration": calibration, "prior_optimality": optimality})


def measure_results(
    results_dir: str | Path, experiments: Sequence[str] | None = None, force: bool = False, echo: Any = print
) -> list[Path]:
    """
    Fill in the ``prior_critic`` section of complete runs written before it existed, or by an earlier
    :data:`MEASURES_VERSION`, and measure the oracle's shifted meta-test again where it was standardised over the shifted
    tasks (:mod:`~pearl_paper.reproduce.oracle_shift`) (``reproduce measure``).

    The model is loaded from the run's ``model.zip`` and measured exactly as :func:`run_one` measures it (the
    measures are seeded by the eval seed and the model seed only); result.json is rewritten atomically with the
    section added, everything else untouched.

    :param results_dir: root of the results layout
    :param experiments: only these experiments (None: all)
    :param force: measure runs that already have the section again
    :param echo: progress output
    :return: the result files rewritten
    """
    from pearl_paper.reproduce.layout import RESULT_FILE
    from pearl_paper.reproduce.ownership import RunLockedError, run_lock

    root = Path(results_dir)
    if not root.is_dir():
        raise ValueError(f"results dir {root} does not exist or is not a folder")
    written: list[Path] = []
    for path in sorted(root.rglob(RESULT_FILE)):
        try:
            with run_lock(path.parent, wait_s=0.0):  # a run being (re)trained is left to its owner
                if _measure_one(path, experiments, force):
                    written.append(path)
                    echo(f"measured {path}")
        except RunLockedError as error:
            echo(f"skip {path}: {error}")
        except (ValueError, OSError) as error:  # a copy, a moved or missing model.zip: named, the other runs measured
            echo(f"skip {path}: {error}")
    return written


def _measure_one(path: Path, experiments: Sequence[str] | None, force: bool) -> bool:
    """Measure one run, under its lock; its result.json is read here, so nothing written before is overwritten."""
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.layout import read_run_result, write_json_atomic
    from pearl_paper.reproduce.oracle_shift import remeasure_oracle_shift, stale_oracle_shift
    from sb3_pearl.registry import algorithm_class

    if experiments is not None and path.parent.parent.parent.parent.name not in experiments:
        return False  # <experiment>/<family>/<variant>/seed<N>/result.json: filtered before anything is read
    result = read_run_result(path)  # refused if it is not the result of its folder's run
    algo = get_experiment(result["experiment"]).variant(result["variant"]).algo
    measured = _measure_prior(path, result, algo, force)
    if stale_oracle_shift(result, algorithm_class(algo)):
        result["shift"] = remeasure_oracle_shift(path.parent, result)
        measured = True
    if measured:
        write_json_atomic(path, result)
    return measured


def _measure_prior(path: Path, result: dict[str, Any], algo: str, force: bool) -> bool:
    """Fill in (or update) ``result``'s prior-critic measures from the run's model; whether anything changed."""
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.layout import MODEL_FILE, cpu_info
    from sb3_pearl.registry import algorithm_class

    section = result.get("prior_critic")
    current = isinstance(section, dict) and "error" not in section and section.get("version", 0) >= MEASURES_VERSION
    if current and not force:
        return False
    family = get_experiment(result["experiment"]).family(result["family"])
    if not force and isinstance(section, dict) and "error" not in section and section.get("version") == 1:
        # version 2 added the task-blind reference to the calibration only: the prior-optimality rollouts (the costly
        # part on MuJoCo and highway families) are kept, the calibration is redone (seeded as compute_prior_measures
        # seeds it, so the result equals a full measurement)
        if section.get("calibration") is not None:
            model = algorithm_class(algo).load(path.parent / MODEL_FILE, device=result.get("device", "cpu"))  # type: ignore[attr-defined]
            env = gym.make(family.env_id, **dict(family.env_kwargs))
            try:
                calibration = prior_calibration(model, env, derived_seed(result["eval_seed"], result["seed"]))
            finally:
                env.close()
            section["calibration"] = json_value(calibration)
            # rollouts of chaotic dynamics (MuJoCo) diverge across CPUs: say where the calibration was redone
            section["calibration_remeasured"] = {"from_version": 1, "cpu": cpu_info()["model"]}
        section["version"] = MEASURES_VERSION
        return True
    model = algorithm_class(algo).load(path.parent / MODEL_FILE, device=result.get("device", "cpu"))  # type: ignore[attr-defined]
    meta = result["meta_test"]
    result["prior_critic"] = compute_prior_measures(
        model,
        algo,
        family,
        dict(family.env_kwargs),
        result["budget"]["meta_test"],
        list(meta["tasks"]),
        meta["summary"][0],
        result["eval_seed"],
        result["seed"],
    )
    return True
