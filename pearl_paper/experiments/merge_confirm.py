"""Highway-Merge's Table I verdict confirmed on fresh seeds: the rules, written and committed before the runs they judge.

The "safer prior" verdict on Highway-Merge (``merge-table1``, seeds 0-9) rests mostly on seeds 0-3, which were seen
before its rules were written; seeds 4-9 alone give an interval that holds 0. This experiment repeats the comparison
on ten seeds that no one has seen, and its verdict is decided on those ten seeds alone.

**What runs.** ``merge-confirm`` declares the two variants of ``merge-table1`` unchanged (the same :class:`Variant`
objects: PEARL and PEARL+ with alpha 0.1 and a separate prior critic, both at the reference's entropy setting, fixed
entropy 1 and reward scale 5), the same family (``highway-merge``, default task ranges), the same ``cpu`` budget
preset, the same eval seed (10001: the same held-out tasks, env seeds and prior draws as ``merge-table1``), the same
code path (``reproduce run``, one process and one torch thread per run), and model **seeds 10-19** for both variants.
Both variants' runs live in this experiment's own folder (``results/merge-confirm/``).

**What is measured.** Every run is re-measured without retraining by ``reproduce remeasure`` on Table I's larger
meta-test (:data:`~pearl_paper.experiments.table1_rules.MERGE_REMEASURE`: 100 held-out tasks x 10 prior draws =
1,000 k = 0 trajectories a seed, 200 a k for k = 1..5).

**The rules** are Table I's (:data:`CONFIRM_RULES` is :data:`~pearl_paper.experiments.table1_rules.RULES`, unchanged):

1. premise gate: PEARL's k = 0 violation rate (crash or failure to merge, mean over seeds) > 0 and its k = 5 rate
   <= 10%;
2. **safer prior**: the 95% Student t interval of the paired k = 0 violation-rate difference (PEARL+ minus PEARL, same
   seed) over seeds 10-19 lies entirely below 0 -> "safer"; entirely above -> "less safe"; otherwise "inconclusive";
3. **adapted as good**: the 95% t interval of the paired k = 5 return difference lies entirely above -10% of |PEARL's
   mean k = 5 return| -> "as good"; entirely below -> "worse"; otherwise "inconclusive".

The confirmation's verdict is the verdict of these rules on seeds 10-19 **only**, whatever it is, and it goes into the
README's headline beside the original one (seeds 0-9). The pooled 20-seed verdict is reported as secondary. No seed is
added, dropped or rerun for its result: a run that fails for a technical reason (a crash, a kill) is resumed or
rerun from its checkpoint with the same seed, and said so. If fewer than 10 paired seeds are finished when the report
is written, the report says "pending" with the number of finished pairs, not a verdict.

Beside every t interval the report gives a second interval that needs no normality (the paired sign-flip
permutation interval, :mod:`pearl_paper.reproduce.stats`); it is reported, it does not decide.
"""

from __future__ import annotations

from pearl_paper.experiments.merge_fixed_entropy import MERGE_TABLE1
from pearl_paper.experiments.spec import Experiment
from pearl_paper.experiments.table1_rules import RULES, DecisionRules

PROJECTED_CORE_HOURS = {"per run (merge-table1's 13-21 min + the re-measure, ~4 min)": 0.3, "20 runs": 6.0}
"""The cost, stated before the runs (merge-table1's measured run times on this project's machines)."""

CONFIRM_SEEDS = tuple(range(10, 20))
"""The fresh seeds: no model of any experiment was trained with them before this file was committed."""

MERGE_CONFIRM = Experiment(
    name="merge-confirm",
    title="Table I on Highway-Merge confirmed on fresh seeds 10-19 (reference's entropy setting)",
    description=(
        "merge-table1's PEARL and PEARL+ (alpha 0.1) unchanged: cpu preset, fixed entropy 1, reward scale 5, eval seed "
        "10001; model seeds 10-19, decided on those seeds alone by Table I's rules (pearl_paper.experiments.merge_confirm)"
    ),
    families=MERGE_TABLE1.families,
    variants=MERGE_TABLE1.variants,
    seeds=CONFIRM_SEEDS,
    budget=MERGE_TABLE1.budget,
    eval_seed=MERGE_TABLE1.eval_seed,
    reference=MERGE_TABLE1.reference,
    paper=MERGE_TABLE1.paper,
    claims=MERGE_TABLE1.claims,
)

CONFIRM_RULES: DecisionRules = RULES
"""Table I's rules, unchanged (the module docstring)."""

CONFIRMED_FAMILY = "highway-merge"
CONFIRMED_VARIANTS = ("pearl-fixed-entropy", "pearlplus-fixed-entropy")
