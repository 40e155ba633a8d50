"""Declarative reproduction experiments (one per paper table, plus the fast family) and their budget presets.

- :mod:`~sb3_pearl.experiments.spec`: the dataclasses (families, variants, paper numbers, claims);
- :mod:`~sb3_pearl.experiments.families`: the task families with their shifted test distributions
  and competence criteria;
- :mod:`~sb3_pearl.experiments.table1`, :mod:`~sb3_pearl.experiments.table2`,
  :mod:`~sb3_pearl.experiments.table3`, :mod:`~sb3_pearl.experiments.safe_point`: the experiments;
- :mod:`~sb3_pearl.experiments.budgets`: the ``smoke`` / ``cpu`` / ``paper`` presets (YAML data) and
  :func:`~sb3_pearl.experiments.budgets.load_budget`.

``python -m sb3_pearl.reproduce`` runs them (docs/reproduce.md).
"""

from __future__ import annotations

from sb3_pearl.experiments.budgets import PRESETS, load_budget
from sb3_pearl.experiments.families import FAMILIES, get_family
from sb3_pearl.experiments.merge_confirm import MERGE_CONFIRM
from sb3_pearl.experiments.merge_fixed_entropy import MERGE_TABLE1, MERGE_TABLE2, MERGE_TABLE3
from sb3_pearl.experiments.merge_premise import MERGE_PREMISE
from sb3_pearl.experiments.oracle import ORACLE, ORACLE_MERGE
from sb3_pearl.experiments.pearl_reference import PEARL_REFERENCE
from sb3_pearl.experiments.prior_critic import PRIOR_CRITIC, PRIOR_CRITIC_WALKER
from sb3_pearl.experiments.safe_point import SAFE_POINT_EXPERIMENT
from sb3_pearl.experiments.spec import Claim, Criterion, Experiment, Family, PaperCell, Variant, check_shared
from sb3_pearl.experiments.table1 import TABLE1
from sb3_pearl.experiments.table1_columns import MERGE_COLUMNS, WALKER_COLUMNS
from sb3_pearl.experiments.table1_rules import WALKER_TABLE1
from sb3_pearl.experiments.table2 import TABLE2
from sb3_pearl.experiments.table3 import TABLE3

EXPERIMENTS: dict[str, Experiment] = {
    e.name: e
    for e in (
        TABLE1,
        TABLE2,
        TABLE3,
        SAFE_POINT_EXPERIMENT,
        PRIOR_CRITIC,
        PRIOR_CRITIC_WALKER,
        PEARL_REFERENCE,
        MERGE_PREMISE,
        MERGE_TABLE1,
        MERGE_TABLE2,
        MERGE_TABLE3,
        WALKER_TABLE1,
        MERGE_CONFIRM,
        ORACLE,
        ORACLE_MERGE,
        WALKER_COLUMNS,
        MERGE_COLUMNS,
    )
}
for _experiment in EXPERIMENTS.values():
    check_shared(_experiment, EXPERIMENTS)


def get_experiment(name: str) -> Experiment:
    """
    The experiment called ``name``.

    :param name: ``table1``, ``table2``, ``table3`` or ``safe-point``
    :return: the experiment
    """
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}: choose among {sorted(EXPERIMENTS)}")
    return EXPERIMENTS[name]


__all__ = [
    "EXPERIMENTS",
    "FAMILIES",
    "PRESETS",
    "Claim",
    "Criterion",
    "Experiment",
    "Family",
    "PaperCell",
    "Variant",
    "get_experiment",
    "get_family",
    "load_budget",
]
