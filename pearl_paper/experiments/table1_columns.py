"""Table I's other two columns, Fine-Tune and MAML, on the two decided families: declared, with their costs, before
their runs.

The paper's Table I has four columns (Fine-Tune, MAML, PEARL, PEARL+). The decided rows (``table1_rules``) have two.
This module declares the other two on the same rows, at stated budgets, so that Table I in the report has the
paper's four columns, each cell with its interval, beside the paper's numbers:

- **Fine-Tune** (one SAC on the mixture of the training tasks, fine-tuned on the new task's data after each
  trajectory; the ``cpu`` preset's settings, 50 fine-tuning steps per trajectory) at **PEARL's env-step budget** of the
  row: Walker2D-vel 500k (``walker-table1``), Highway-Merge 100k (``merge-table1``);
- **MAML** (MAML-TRPO, the ``cpu`` preset's settings: 10 tasks x 10 episodes a meta-iteration, 64-64 tanh policy) at
  **10 times PEARL's env-step budget**, the low end of the paper's "10-100x more sample efficient": Walker2D-vel 5M,
  Highway-Merge 1M. Its measured cost allowed it (below); the higher end (100x) did not fit;
- **seeds 0-3** for both (the first seeds of the PEARL rows: the same task draw per seed, ``n_train_tasks`` 40 /
  ``n_test_tasks`` 10 as PEARL's), the rows' **eval seeds** (Walker 10005, Merge 10001: the same held-out tasks, env
  seeds and common random numbers as PEARL's and PEARL+'s runs), the rows' meta-test (20 held-out tasks x 10 prior
  draws, k = 0..5).

No verdict rule is attached to these columns (the paper's claims are about PEARL+ against PEARL); each cell is reported
with its interval over the 4 seeds (t and sign-flip), beside the paper's number, and the differences to PEARL at
k = 0 and k = 5 are reported, not decided.
"""

from __future__ import annotations

import dataclasses

from pearl_paper.experiments.families import HIGHWAY_MERGE
from pearl_paper.experiments.merge_fixed_entropy import MERGE_TABLE1
from pearl_paper.experiments.pearl_reference import WALKER2D_VEL_LONG
from pearl_paper.experiments.spec import Experiment
from pearl_paper.experiments.table1 import TABLE1
from pearl_paper.experiments.table1_rules import WALKER_TABLE1

PROJECTED_CORE_HOURS = {
    "Fine-Tune, Walker2D-vel 500k (10.9 ms per env step with its gradient step, 29 min of fine-tuning meta-test)": 2.0,
    "Fine-Tune, Highway-Merge 100k (9.0 ms per env step, 7.5 min of meta-test)": 0.4,
    "MAML, Walker2D-vel 5M (0.60 ms per env step, whole iterations, 9 min of meta-test)": 1.0,
    "MAML, Highway-Merge 1M (0.81 ms per env step, 3.5 min of meta-test)": 0.3,
    "all 16 runs (4 seeds each)": 14.8,
}
"""The costs, measured before the runs with ``python benchmarks/budget_timing.py --preset cpu --families walker2d-vel
highway-merge --algos finetune maml`` on the project's Intel Xeon, one torch thread, the machine loaded (load average
5 on 2 cores: two training runs beside it), so an idle core takes about half."""

COLUMNS = tuple(variant for variant in TABLE1.variants if variant.name in ("finetune", "maml"))
SEEDS = (0, 1, 2, 3)


def _paper(family_name: str, source: str) -> tuple:
    return tuple(
        dataclasses.replace(cell, family=family_name)
        for cell in TABLE1.paper
        if cell.family == source and cell.variant in ("finetune", "maml")
    )


WALKER_COLUMNS_FAMILY = dataclasses.replace(WALKER2D_VEL_LONG, budget_family="walker2d-vel-columns")
MERGE_COLUMNS_FAMILY = dataclasses.replace(HIGHWAY_MERGE, budget_family="highway-merge-columns")

WALKER_COLUMNS = Experiment(
    name="walker-columns",
    title="Table I's Fine-Tune and MAML columns on Walker2D-vel (500k / 5M env steps)",
    description=(
        "Fine-Tune at PEARL's 500k env steps and MAML at 10x (5M) on Walker2D-vel, walker-table1's tasks and eval seed "
        "(10005), seeds 0-3 (pearl_paper.experiments.table1_columns)"
    ),
    families=(WALKER_COLUMNS_FAMILY,),
    variants=COLUMNS,
    seeds=SEEDS,
    budget="cpu",
    eval_seed=WALKER_TABLE1.eval_seed,
    reference="finetune",
    paper=_paper(WALKER2D_VEL_LONG.name, "walker2d-vel"),
)

MERGE_COLUMNS = Experiment(
    name="merge-columns",
    title="Table I's Fine-Tune and MAML columns on Highway-Merge (100k / 1M env steps)",
    description=(
        "Fine-Tune at PEARL's 100k env steps and MAML at 10x (1M) on Highway-Merge, merge-table1's tasks and eval seed "
        "(10001), seeds 0-3 (pearl_paper.experiments.table1_columns)"
    ),
    families=(MERGE_COLUMNS_FAMILY,),
    variants=COLUMNS,
    seeds=SEEDS,
    budget="cpu",
    eval_seed=MERGE_TABLE1.eval_seed,
    reference="finetune",
    paper=_paper(HIGHWAY_MERGE.name, HIGHWAY_MERGE.name),
)
