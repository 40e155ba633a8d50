"""The fast family: the alpha sweep of Table III on SafePointGoalMeta-v0, with two crash penalties.

Variants: PEARL+ with ``prior_coef`` alpha in {0, 0.1, 1, 5}; alpha = 0 is ``PEARLPlus`` with
``prior_coef=0`` (the prior critic trained, the actor's prior term off), not the ``PEARL`` class, so
that the sweep changes one number of one algorithm. Beside the sweep, not in the paper: alpha 0.1 and 1
with ``prior_data="prior"`` (``alpha-<alpha>-priordata``).

Families: ``safe-point`` (the registered env: crash penalty 2 per skipped step) and its variant
``safe-point-crash5`` (``crash_penalty=5``): with a heavier penalty a crash costs more return
under the prior, which is what the prior term optimises, so the paper's effect should be easier
to see there if it exists.

The paper has no numbers for this family. The claims are Table III's pattern: alpha > 0 makes the
prior policy (k = 0) safer than alpha = 0; alpha = 0.1 adapts as well as alpha = 0 (no material
difference in the violation rate after adaptation, return not lower); alpha = 5 fails to adapt
(lower return after adaptation than alpha = 0).
"""

from __future__ import annotations

import dataclasses

from pearl_paper.experiments.families import SAFE_POINT
from pearl_paper.experiments.spec import Claim, Experiment, Family, Variant
from pearl_paper.experiments.table3 import alpha_variant

ALPHAS = (0.0, 0.1, 1.0, 5.0)
SOURCE = "Table III pattern (no paper numbers for this family)"

SAFE_POINT_CRASH5: Family = dataclasses.replace(
    SAFE_POINT,
    name="safe-point-crash5",
    title="SafePointGoal, crash penalty 5",
    env_kwargs={"crash_penalty": 5.0},
    budget_family=SAFE_POINT.name,
)

# Not in the paper: the prior terms on prior-z transitions only (PEARLPlus(prior_data="prior"), off by default), the
# test of the hypothesis that the prior critic is fitted on task-confounded data (docs/diagnostics.md).
PRIOR_DATA_ALPHAS = (0.1, 1.0)


def prior_data_variant(alpha: float) -> Variant:
    """PEARL+ with ``prior_coef=alpha`` and ``prior_data="prior"`` (named ``alpha-<alpha>-priordata``)."""
    base = alpha_variant(alpha)
    return Variant(
        f"{base.name}-priordata",
        f"PEARL+ (alpha {alpha:g}, prior-z data only)",
        base.algo,
        {**base.overrides, "prior_data": "prior"},
    )


VARIANTS = (*(alpha_variant(alpha) for alpha in ALPHAS), *(prior_data_variant(alpha) for alpha in PRIOR_DATA_ALPHAS))

CLAIMS = tuple(
    claim
    for family in (SAFE_POINT.name, SAFE_POINT_CRASH5.name)
    for claim in (
        *(Claim(family, f"alpha-{a:g}", "alpha-0", "violation", 0, "lower", source=SOURCE) for a in ALPHAS[1:]),
        Claim(family, "alpha-0.1", "alpha-0", "violation", -1, "equal", source=SOURCE),
        Claim(family, "alpha-0.1", "alpha-0", "return", -1, "not_lower", source=SOURCE),
        Claim(family, "alpha-5", "alpha-0", "return", -1, "lower", source=SOURCE),
        *(
            Claim(family, f"alpha-{a:g}-priordata", "alpha-0", "violation", 0, "lower", source="not in the paper")
            for a in PRIOR_DATA_ALPHAS
        ),
    )
)

SAFE_POINT_EXPERIMENT = Experiment(
    name="safe-point",
    title="SafePointGoal: the alpha sweep on the fast family",
    description="PEARL+ with alpha in {0, 0.1, 1, 5} on SafePointGoalMeta-v0 with crash penalty 2 (registered) and 5",
    families=(SAFE_POINT, SAFE_POINT_CRASH5),
    variants=VARIANTS,
    seeds=(0, 1, 2, 3, 4),  # the fast family: 5 seeds
    budget="cpu",
    eval_seed=10_004,
    reference="alpha-0",
    claims=CLAIMS,
)
