"""Table II of the paper: the ablation of the prior critic on Ant-3D-Vel and Highway-Merge.

Variants: PEARL; PEARL+ (w/o), the prior term scored by the critic itself (``prior_critic="shared"``);
PEARL+ (300-Node) and PEARL+ (100-Node), a separate prior critic of 3 x 300 / 3 x 100 units. Every
PEARL+ variant uses alpha = 0.1. "Before adaptation" is k = 0, "after adaptation" the last trajectory
of the meta-test (k = -1).

Claims: the violation rates against PEARL from the numbers (5 points or more: a difference); the
returns against PEARL from the numbers, a difference being at least ``RETURN_MARGIN_PAPER`` in the
paper's units (about the paper's own standard deviations over 4 runs); and the ablation's point,
"PEARL+ gives better performance before adaptation and better adaptation ability" than PEARL+ (w/o).
"""

from __future__ import annotations

from pearl_paper.experiments.families import ANT3D_VEL, HIGHWAY_MERGE
from pearl_paper.experiments.spec import Claim, Experiment, Variant, claims_from_paper, paper_cells

KS = (0, -1)
SOURCE = "Table II"
# Paper-unit differences of the returns read as claimed differences: about the paper's standard deviations.
RETURN_MARGIN_PAPER = {ANT3D_VEL.name: 20.0, HIGHWAY_MERGE.name: 10.0}

VARIANTS = (
    Variant("pearl", "PEARL", "pearl"),
    Variant("pearlplus-wo", "PEARL+ (w/o)", "pearlplus", {"prior_coef": 0.1, "prior_critic": "shared"}),
    Variant(
        "pearlplus-300",
        "PEARL+ (300-Node)",
        "pearlplus",
        {"prior_coef": 0.1, "prior_critic": "separate", "prior_critic_arch": [300, 300, 300]},
    ),
    Variant(
        "pearlplus-100",
        "PEARL+ (100-Node)",
        "pearlplus",
        {"prior_coef": 0.1, "prior_critic": "separate", "prior_critic_arch": [100, 100, 100]},
    ),
)

ANT_RETURNS = paper_cells(
    ANT3D_VEL.name,
    "return",
    {
        "pearl": [45.48, 106.36],
        "pearlplus-wo": [92.47, 151.32],
        "pearlplus-300": [109.34, 166.10],
        "pearlplus-100": [104.26, 163.79],
    },
    KS,
    source=f"{SOURCE}a (Ant3D-vel)",
)
MERGE_RETURNS = paper_cells(
    HIGHWAY_MERGE.name,
    "return",
    {
        "pearl": [-33.44, 67.28],
        "pearlplus-wo": [42.47, 54.19],
        "pearlplus-300": [58.12, 69.52],
        "pearlplus-100": [56.47, 70.14],
    },
    KS,
    source=f"{SOURCE}b (Highway-Merge)",
)
PAPER = (
    *ANT_RETURNS,
    *MERGE_RETURNS,
    *paper_cells(
        ANT3D_VEL.name,
        "violation",
        {"pearl": [33.33, 0.0], "pearlplus-wo": [0.0, 0.0], "pearlplus-300": [0.0, 0.0], "pearlplus-100": [0.0, 0.0]},
        KS,
        scale=0.01,
        source=f"{SOURCE}a (Ant3D-vel)",
    ),
    *paper_cells(
        HIGHWAY_MERGE.name,
        "violation",
        {"pearl": [27.84, 0.0], "pearlplus-wo": [0.74, 0.0], "pearlplus-300": [0.86, 0.0], "pearlplus-100": [0.86, 0.0]},
        KS,
        scale=0.01,
        source=f"{SOURCE}b (Highway-Merge)",
    ),
)

ABLATION_CLAIMS = tuple(
    Claim(
        family, variant, "pearlplus-wo", "return", k, "higher", source=f"{SOURCE}, Sec. V-D: better than PEARL+ (w/o) {when}"
    )
    for family in (ANT3D_VEL.name, HIGHWAY_MERGE.name)
    for variant in ("pearlplus-300", "pearlplus-100")
    for k, when in ((0, "before adaptation"), (-1, "after adaptation"))
)

TABLE2 = Experiment(
    name="table2",
    title="Table II: ablation of the prior critic",
    description="PEARL, PEARL+ (w/o) (prior term on the shared critic), PEARL+ with a 3x300 and a 3x100 prior critic "
    "(alpha 0.1) on Ant-3D-Vel and Highway-Merge; return and violation rate before (k = 0) and after adaptation",
    families=(ANT3D_VEL, HIGHWAY_MERGE),
    variants=VARIANTS,
    seeds=(0, 1, 2, 3),
    budget="cpu",
    eval_seed=10_002,
    reference="pearl",
    paper=PAPER,
    claims=(
        *claims_from_paper(PAPER, "pearl", "violation", source=SOURCE),
        *claims_from_paper(ANT_RETURNS, "pearl", "return", margin=RETURN_MARGIN_PAPER[ANT3D_VEL.name], source=SOURCE),
        *claims_from_paper(MERGE_RETURNS, "pearl", "return", margin=RETURN_MARGIN_PAPER[HIGHWAY_MERGE.name], source=SOURCE),
        *ABLATION_CLAIMS,
    ),
)
