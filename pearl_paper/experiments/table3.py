"""Table III of the paper: the weight alpha of the prior term on Highway-Merge.

Variants: PEARL+ with ``prior_coef`` alpha in {5, 1, 0.1, 0.01, 0}. alpha = 0 is ``PEARLPlus`` with
``prior_coef=0`` (the prior critic is still built and trained, the actor's prior term is off), not
the ``PEARL`` class: the sweep changes one number of one algorithm, as in the paper's table.

Claims: the crash rates against alpha = 0 from the numbers (5 points or more: a difference), and the
text on returns: "an alpha that is too large can impair learning during adaptation (e.g. alpha = 1),
and even fail to adapt (alpha = 5)", read as a lower return after adaptation than alpha = 0.1.
"""

from __future__ import annotations

from pearl_paper.experiments.families import HIGHWAY_MERGE
from pearl_paper.experiments.spec import Claim, Experiment, Variant, claims_from_paper, paper_cells

KS = (0, -1)
SOURCE = "Table III"
ALPHAS = (5.0, 1.0, 0.1, 0.01, 0.0)


def alpha_variant(alpha: float) -> Variant:
    """PEARL+ with ``prior_coef=alpha`` (named ``alpha-<alpha>``)."""
    return Variant(
        f"alpha-{alpha:g}", f"PEARL+ (alpha {alpha:g})", "pearlplus", {"prior_coef": alpha, "prior_critic": "separate"}
    )


VARIANTS = tuple(alpha_variant(alpha) for alpha in ALPHAS)

PAPER = paper_cells(
    HIGHWAY_MERGE.name,
    "violation",
    {
        "alpha-5": [0.0, 11.8],
        "alpha-1": [0.5, 0.0],
        "alpha-0.1": [2.5, 0.0],
        "alpha-0.01": [35.0, 0.0],
        "alpha-0": [37.5, 0.0],
    },
    KS,
    scale=0.01,
    source=f"{SOURCE} (Highway-Merge)",
)

RETURN_CLAIMS = (
    Claim(HIGHWAY_MERGE.name, "alpha-5", "alpha-0.1", "return", -1, "lower", source="Sec. V-E: alpha 5 fails to adapt"),
    Claim(HIGHWAY_MERGE.name, "alpha-1", "alpha-0.1", "return", -1, "lower", source="Sec. V-E: alpha 1 impairs adaptation"),
)

TABLE3 = Experiment(
    name="table3",
    title="Table III: the weight alpha of the prior term",
    description="PEARL+ with alpha in {5, 1, 0.1, 0.01, 0} on Highway-Merge; crash rate and return before (k = 0) "
    "and after adaptation",
    families=(HIGHWAY_MERGE,),
    variants=VARIANTS,
    seeds=(0, 1, 2, 3),
    budget="cpu",
    eval_seed=10_003,
    reference="alpha-0",
    paper=PAPER,
    claims=(*claims_from_paper(PAPER, "alpha-0", "violation", source=SOURCE), *RETURN_CLAIMS),
)
