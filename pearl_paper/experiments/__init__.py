"""Declarative reproduction experiments (one per paper table, plus the fast family) and their budget presets.

- :mod:`~pearl_paper.experiments.spec`: the dataclasses (families, variants, paper numbers, claims);
- :mod:`~pearl_paper.experiments.families`: the task families with their shifted test distributions
  and competence criteria;
- :mod:`~pearl_paper.experiments.table1`, :mod:`~pearl_paper.experiments.table2`,
  :mod:`~pearl_paper.experiments.table3`, :mod:`~pearl_paper.experiments.safe_point`: the experiments;
- :mod:`~sb3_pearl.budgets`: the ``smoke`` / ``cpu`` / ``paper`` presets (YAML data) and
  :func:`~sb3_pearl.budgets.load_budget`.

``python -m pearl_paper.reproduce`` runs them (docs/reproduce.md).
"""

from __future__ import annotations

from pearl_paper.experiments.families import FAMILIES, get_family
from pearl_paper.experiments.merge_confirm import MERGE_CONFIRM
from pearl_paper.experiments.merge_fixed_entropy import MERGE_TABLE1, MERGE_TABLE2, MERGE_TABLE3
from pearl_paper.experiments.merge_premise import MERGE_PREMISE
from pearl_paper.experiments.oracle import ORACLE, ORACLE_MERGE
from pearl_paper.experiments.pearl_reference import PEARL_REFERENCE
from pearl_paper.experiments.prior_critic import PRIOR_CRITIC, PRIOR_CRITIC_WALKER
from pearl_paper.experiments.safe_point import SAFE_POINT_EXPERIMENT
from pearl_paper.experiments.spec import Claim, Criterion, Experiment, Family, PaperCell, Variant, check_shared
from pearl_paper.experiments.table1 import TABLE1
from pearl_paper.experiments.table1_columns import MERGE_COLUMNS, WALKER_COLUMNS
from pearl_paper.experiments.table1_rules import WALKER_TABLE1
from pearl_paper.experiments.table2 import TABLE2
from pearl_paper.experiments.table3 import TABLE3
from sb3_pearl.budgets import PRESETS, load_budget

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
