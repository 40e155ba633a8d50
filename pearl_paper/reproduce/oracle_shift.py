"""The oracle's shifted meta-test, measured again where its task vector was standardised over the shifted tasks.

The oracle is told the task as a standardised vector (:class:`~sb3_pearl.envs.task_observation.TaskObservation`). Its
runs made before the standardisation was saved with the model standardised the shifted meta-test's task vector over
the *shifted* env's own distribution: a 2.5 m/s Walker target (training U[0, 2], shift U[2, 3]) read as an average
training task, about 1 m/s, so those shifted numbers measure an oracle told the wrong task. The held-out meta-test,
the competence check and the velocity records act in the training distribution and were right.

``reproduce measure`` finds such records (a task-aware run's ``shift`` whose config records no
``task_standardisation``), loads the run's ``model.zip`` (an older one is given its training env's standardisation,
as in its training; loading it with that env would refuse the zips saved with float64 observation spaces), meta-tests
it again on the shifted env of the run's own record (its env kwargs, not the family's current definition) with the
same settings, eval seed and tasks as the run did, and replaces the ``shift`` section, marked ``remeasured`` with the
reason and the CPU. The old numbers stay in git.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym

from sb3_pearl.envs.task_observation import training_standardisation
from sb3_pearl.evaluation.held_out import held_out_record

REMEASURED_REASON = (
    "the task vector had been standardised over the shifted env's tasks instead of the training distribution's; "
    "measured again from model.zip with the training standardisation"
)


def stale_oracle_shift(result: dict[str, Any], algo_class: type) -> bool:
    """Whether ``result`` is a task-aware run's whose shifted meta-test did not record the standardisation it used."""
    from sb3_pearl.oracle import Oracle

    shift = result.get("shift")
    if not issubclass(algo_class, Oracle) or not isinstance(shift, dict):
        return False
    return "task_standardisation" not in shift.get("config", {})


def remeasure_oracle_shift(folder: Path, result: dict[str, Any]) -> dict[str, Any]:
    """
    The run's shifted meta-test again, told the task on the training distribution's scale.

    :param folder: the run folder (holds ``model.zip``)
    :param result: the run's ``result.json``
    :return: the new ``shift`` section (the record :func:`~sb3_pearl.evaluation.held_out.held_out_record` writes, plus
        ``remeasured``)
    """
    from pearl_paper.experiments import get_experiment
    from pearl_paper.reproduce.layout import MODEL_FILE, cpu_info
    from sb3_pearl.registry import algorithm_class

    experiment = get_experiment(result["experiment"])
    family = experiment.family(result["family"])
    # the run's own recorded kwargs, training and shifted, not the family's current definition
    env_kwargs = dict(result.get("spec", {}).get("family", {}).get("env_kwargs") or {})
    shift_kwargs = dict(shift["env_kwargs"]) if isinstance((shift := result["shift"]).get("env_kwargs"), dict) else None
    if shift_kwargs is None:
        raise ValueError(f"{folder}: the run's shift record holds no env_kwargs to measure it again with")
    algo = experiment.variant(result["variant"]).algo
    model = algorithm_class(algo).load(folder / MODEL_FILE, device="cpu")  # type: ignore[attr-defined]
    if model.task_standardisation is None:  # saved before it was recorded: the training env's, as in its training
        model.task_standardisation = training_standardisation(family.env_id, env_kwargs)
    shift_env = gym.make(family.env_id, **shift_kwargs)
    try:
        label = f"{result['experiment']} {result['family']} {result['variant']} seed{result['seed']}"
        settings = result["budget"]["shift_meta_test"]
        record = held_out_record(model, shift_env, settings, result["eval_seed"], shift_kwargs, label)
    finally:
        shift_env.close()
    return {**record, "remeasured": {"reason": REMEASURED_REASON, "cpu": cpu_info()["model"]}}
