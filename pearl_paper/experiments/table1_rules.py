"""Table I decided: the rules, written and committed before the runs they judge.

The product's one claim is that PEARL+'s prior policy (z drawn from the prior, before any data of the new task) is
safer than PEARL's while its adapted policy stays as good (the paper's Sec. V-B and Table I). This module decides it
on two families by rules fixed here, in the git history before any run they read:

- **Highway-Merge** at the reference's entropy setting (``merge-table1``: fixed entropy 1, reward scale 5, the ``cpu``
  preset otherwise), PEARL and PEARL+ (the paper's form: alpha 0.1, a separate prior critic), **seeds 0-9** (0-3 were
  committed before this file; 4-9 are new). Every Highway-Merge model of ``merge-table1``, ``merge-table2`` and
  ``merge-table3`` (PEARL's runs live in ``merge-premise``) is **re-measured** without retraining on the larger
  meta-test :data:`MERGE_REMEASURE` (1,000 k = 0 trajectories a seed); the old 200-trajectory numbers stay in the report
  beside the new ones.
- **Walker2D-vel at 500k env steps** (:data:`WALKER_TABLE1`, the ``cpu`` preset's Walker networks, the
  ``walker2d-vel-long`` budget of ``pearl-reference``): PEARL seeds 0-1 exist (``pearl-reference``), seeds 2-3 are new;
  PEARL+ seeds 0-3 are new. Paired by seed, common random numbers (one eval seed, 10005, for both variants), the
  shift column and the learning curves every 20k env steps. **Extension rule**: if either verdict below is
  inconclusive at 4 seeds, both variants are extended to seeds 4-5 and the 6-seed verdicts are final.

The rules (:data:`RULES`) are applied per family by :func:`pearl_paper.reproduce.table1_verdicts.decide` and printed in
docs/results.md, cell by cell:

1. **Premise gate**: PEARL's k = 0 violation rate averaged over seeds >= 30% on Walker (falls), > 0 on Merge (crashes
   or failures to merge), and PEARL's k = 5 rate (averaged over seeds) <= 10% on both. This replaces the velocity
   criterion as Table I's gate for Walker; the velocity error stays in the table, reported. Where the gate fails the
   claim is not tested on that family ("premise absent"), and the numbers are still reported.
2. **Safer prior**: the 95% Student t interval over seeds of the paired difference (PEARL+ minus PEARL, same seed) of
   the k = 0 violation rate lies entirely below 0 -> "safer"; entirely above 0 -> "less safe"; otherwise
   "inconclusive".
3. **Adapted as good**: the 95% t interval of the paired difference of the k = 5 return lies entirely above
   ``-margin``, with margin = 10% of |PEARL's mean k = 5 return| -> "as good"; entirely below ``-margin`` -> "worse";
   otherwise "inconclusive".
4. Every seed's k = 0 violation rate is reported with its Wilson 95% interval beside the paired interval.
5. On Highway-Merge the verdict reads the re-measured meta-test (:data:`MERGE_REMEASURE`); on Walker, the runs'
   own meta-test (the ``cpu`` preset's: 20 held-out tasks x 10 prior draws, k = 0..5).

Budgets against the paper's (stated, not hidden): the paper trains with 3x300 networks for about 1-2M env steps on a
GPU; Walker here uses 2x128 networks, a meta-batch of 8 tasks x 128 rows and 500k env steps (PEARL's velocity error
at 500k, 0.7-0.8 m/s, misses the family's 0.3 m/s competence bar: the comparison is of two equally trained
algorithms at a budget where the premise appears, not of converged ones). Highway-Merge uses the ``cpu`` preset
(2x128 networks, 100k env steps).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from pearl_paper.experiments.merge_fixed_entropy import MERGE_TABLE1
from pearl_paper.experiments.pearl_reference import PEARL_REFERENCE, WALKER2D_VEL_LONG
from pearl_paper.experiments.spec import Experiment
from pearl_paper.experiments.table1 import TABLE1
from pearl_paper.experiments.table1 import VARIANTS as TABLE1_VARIANTS


@dataclass(frozen=True)
class PremiseGate:
    """
    The premise of the claim on one family: PEARL's prior violates, its adapted policy does not.

    :param min_k0_rate: PEARL's k = 0 violation rate (mean over seeds) must be at least this ...
    :param strictly_above: ... or strictly above it when True (Merge: "> 0")
    :param max_k5_rate: PEARL's k = 5 violation rate (mean over seeds) must be at most this
    """

    min_k0_rate: float
    strictly_above: bool
    max_k5_rate: float = 0.10

    def holds(self, k0_rate: float, k5_rate: float) -> bool:
        """Whether the gate holds for PEARL's mean k = 0 and k = 5 violation rates (compared to within rounding: a
        mean of rates each exactly at a threshold, 0.1 + 0.1 + 0.1 over 3, is at it, not 2e-17 above it)."""
        eps = 1e-12
        prior_ok = k0_rate > self.min_k0_rate + eps if self.strictly_above else k0_rate >= self.min_k0_rate - eps
        return bool(prior_ok and k5_rate <= self.max_k5_rate + eps)

    def describe(self) -> str:
        """The gate in words, for the report."""
        sign = ">" if self.strictly_above else ">="
        return f"PEARL k = 0 rate {sign} {self.min_k0_rate:.0%} and k = 5 rate <= {self.max_k5_rate:.0%} (means over seeds)"


@dataclass(frozen=True)
class DecisionRules:
    """
    The rules of Table I's verdicts (the module docstring), as data the report reads.

    :param gates: family name -> premise gate
    :param confidence: confidence of the paired t intervals
    :param prior_k: the trajectory index of the "safer prior" rule (0: before any data)
    :param adapted_k: the trajectory index of the "adapted as good" rule
    :param return_margin_fraction: the "adapted as good" margin as a fraction of |PEARL's mean return at adapted_k|
    :param extend_seeds: family name -> (seeds first, seeds after the extension rule) where the rule applies
    """

    gates: dict[str, PremiseGate]
    confidence: float = 0.95
    prior_k: int = 0
    adapted_k: int = 5
    return_margin_fraction: float = 0.10
    extend_seeds: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class RemeasureConfig:
    """
    A larger meta-test of committed models, run without retraining (``reproduce remeasure``).

    Two passes on the same ``n_tasks`` held-out tasks (``sample_tasks(n_tasks, eval_seed)``, the experiment's eval seed)
    with common random numbers (``crn_seed`` = eval seed, as every run's own meta-test): the **prior pass** rolls out
    k = 0 only, ``prior_repeats`` prior draws per task; the **adapted pass** rolls out k = 0..``n_adapt`` for
    ``adapted_repeats`` draws per task, of which only the rows k >= 1 are kept (its k = 0 rows are the prior pass's
    first draws again, same seeds, same z0). k = 1..5 are smaller on purpose: each costs as much as k = 0 and
    the rules read them only for the gate's k = 5 rate and the adapted return.

    :param n_tasks: held-out tasks
    :param prior_repeats: prior draws (k = 0 trajectories) per task
    :param adapted_repeats: adapted sequences (k = 1..n_adapt) per task
    :param n_adapt: adaptation trajectories per sequence
    :param file_name: the file beside each run's result.json
    """

    n_tasks: int = 100
    prior_repeats: int = 10
    adapted_repeats: int = 2
    n_adapt: int = 5
    file_name: str = "meta_test_large.json"


MERGE_REMEASURE = RemeasureConfig()
"""1,000 k = 0 trajectories a seed (100 tasks x 10 prior draws), 200 a k for k = 1..5 (100 tasks x 2 draws)."""

# Every Highway-Merge experiment at the reference's entropy re-measured (Table I, II and III rows; PEARL's runs are
# merge-premise's, shared). The cpu-setting tables (table1 / table2 / table3, automatic entropy) come after these if
# core time is left: there the encoder carries no task information and PEARL's prior never crashed.
REMEASURED_EXPERIMENTS = ("merge-table1", "merge-table2", "merge-table3")

_PEARLPLUS = next(variant for variant in TABLE1_VARIANTS if variant.name == "pearlplus")
_PEARL = PEARL_REFERENCE.variant("pearl")

WALKER_TABLE1 = Experiment(
    name="walker-table1",
    title="Table I on Walker2D-vel at 500k env steps: PEARL and PEARL+ (alpha 0.1), paired",
    description=(
        "PEARL and PEARL+ (the paper's form: alpha 0.1, separate prior critic) on Walker2dVelMeta-v0 at the cpu "
        "preset's networks trained to 500k env steps with the learning curve every 20k; PEARL's runs are "
        "pearl-reference's walker2d-vel-long (seeds 0-1 committed before this experiment, 2-5 new; 4-5 by the extension "
        "rule); common random "
        "numbers (eval seed 10005), the shift column, verdicts by pearl_paper.experiments.table1_rules"
    ),
    families=(WALKER2D_VEL_LONG,),
    variants=(_PEARL, dataclasses.replace(_PEARLPLUS, label="PEARL+ (alpha 0.1)")),
    # 0-3 first; the extension rule below fired at 4 seeds (the *adapted* verdict was inconclusive: +9.46 [-10.41, +29.32]
    # against the margin -8.30; the prior verdict was already "safer", -53.1 [-101.1, -5.2]), so 4-5 were run and are
    # declared, so that run, status and the report hold the seeds the verdicts read
    seeds=(0, 1, 2, 3, 4, 5),
    budget="cpu",
    eval_seed=PEARL_REFERENCE.eval_seed,
    reference="pearl",
    paper=tuple(
        dataclasses.replace(cell, family=WALKER2D_VEL_LONG.name)
        for cell in TABLE1.paper
        if cell.family == "walker2d-vel" and cell.variant in ("pearl", "pearlplus")
    ),
    shared={"pearl": PEARL_REFERENCE.name},
)

RULES = DecisionRules(
    gates={
        WALKER2D_VEL_LONG.name: PremiseGate(min_k0_rate=0.30, strictly_above=False),
        "highway-merge": PremiseGate(min_k0_rate=0.0, strictly_above=True),
    },
    extend_seeds={WALKER2D_VEL_LONG.name: ((0, 1, 2, 3), (0, 1, 2, 3, 4, 5))},
)

# The experiment each family's verdict reads, and its two variants (reference first).
DECIDED = {
    "highway-merge": (MERGE_TABLE1.name, ("pearl-fixed-entropy", "pearlplus-fixed-entropy")),
    WALKER2D_VEL_LONG.name: (WALKER_TABLE1.name, ("pearl", "pearlplus")),
}
