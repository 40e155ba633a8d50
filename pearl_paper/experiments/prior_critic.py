"""The prior-critic experiments: which design of PEARL+'s prior critic values the prior policy right.

Not in the paper. The paper's PEARL+ scores the actor's prior term with one new Q-network Q~(s, a, z0) trained by
its own soft Bellman loss; on every family we trained, that critic does not value the z0 policy (docs/results.md),
so the actor climbs its errors. :data:`DESIGNS` are the alternatives, each one or two constructor arguments of
:class:`~sb3_pearl.pearl.pearl_plus.PEARLPlus` (docs/pearl.md, "Prior-critic designs", says why each):

- ``twin``: ``prior_n_critics=2``, the minimum of two Q networks (TD3 / SAC's remedy for overestimation);
- ``priordata``: ``prior_data="prior"``, fitted and scored on the transitions collected with z from the prior;
- ``twin-priordata``: both;
- ``zfree``: ``prior_critic_input="state"``, a prior critic Q~(s, a) without the uninformative z0 input;
- ``maintarget``: ``prior_target="main"``, bootstrapped from the critic's target network at z0;
- ``ensemble5``: ``prior_n_critics=5``, the minimum of five (a pessimistic ensemble);
- ``cql5``: ``prior_conservative_weight=5``, a conservative (CQL) penalty on actions the data do not cover;
- ``mc``: ``prior_target="mc"`` with ``prior_data="prior"``, fitted to the Monte-Carlo soft returns of the prior-z
  trajectories (bootstrapped only where a trajectory was cut), and scored on the same rows.

Two experiments, both with the reference runs of an existing experiment (``Experiment.shared``: the same runs, the
same eval seed, so the comparisons are paired with common random numbers):

- ``prior-critic``: the *selection*, on SafePointGoal at crash penalties 2 and 5, 5 seeds, every design at alpha
  0.1 and alpha 1; alpha 0 (PEARL), alpha 0.1 and alpha 1 (the paper's form) and the prior-data variants are the
  ``safe-point`` experiment's runs. The selection rule (docs/pearl.md, "The selection rule", written before any
  run) reads the training-task measures only; alpha 1 is run for the two designs it selects;
- ``prior-critic-walker``: the *confirmation* on Walker2D-vel at ``cpu``, 4 seeds, the selected design(s) against
  ``table1``'s PEARL, PEARL+ (the paper's form), its twin and prior-data variants and Fine-Tune (the bar).
"""

from __future__ import annotations

from typing import Any

from pearl_paper.experiments.families import SAFE_POINT, WALKER2D_VEL
from pearl_paper.experiments.safe_point import SAFE_POINT_CRASH5, SAFE_POINT_EXPERIMENT
from pearl_paper.experiments.spec import Claim, Experiment, Variant
from pearl_paper.experiments.table1 import TABLE1
from pearl_paper.experiments.table3 import alpha_variant

# name -> (what it is, PEARLPlus overrides on top of the paper's form)
DESIGNS: dict[str, tuple[str, dict[str, Any]]] = {
    "twin": ("twin prior critic", {"prior_n_critics": 2}),
    "priordata": ("prior-z data only", {"prior_data": "prior"}),
    "twin-priordata": ("twin, prior-z data only", {"prior_n_critics": 2, "prior_data": "prior"}),
    "zfree": ("z-free prior critic Q~(s, a)", {"prior_critic_input": "state"}),
    "maintarget": ("bootstrapped from the critic's target at z0", {"prior_target": "main"}),
    "ensemble5": ("minimum of a 5-network ensemble", {"prior_n_critics": 5}),
    "cql5": ("conservative penalty, weight 5", {"prior_conservative_weight": 5.0}),
    # added after most alpha-0.1 runs of the seven above were in (docs/pearl.md); the selection rule is unchanged
    "mc": ("Monte-Carlo targets on prior-z data", {"prior_target": "mc", "prior_data": "prior"}),
}
SELECTION_ALPHAS = (0.1, 1.0)
SOURCE = "the prior-critic selection (not in the paper)"


def design_variant(design: str, alpha: float, prefix: str = "") -> Variant:
    """
    PEARL+ with ``prior_coef=alpha`` and the prior-critic design ``design``.

    :param design: a key of :data:`DESIGNS`
    :param alpha: the prior coefficient
    :param prefix: the variant name's prefix (``""``: ``alpha-<alpha>-<design>``, the safe-point naming; ``"pearlplus"``:
        ``pearlplus-<design>``, table1's naming at alpha 0.1)
    :return: the variant
    """
    if design not in DESIGNS:
        raise ValueError(f"unknown prior-critic design {design!r}: choose among {sorted(DESIGNS)}")
    what, overrides = DESIGNS[design]
    base = alpha_variant(alpha)
    name = f"{prefix}-{design}" if prefix else f"{base.name}-{design}"
    return Variant(name, f"PEARL+ (alpha {alpha:g}, {what})", "pearlplus", {**base.overrides, **overrides})


# -- selection: SafePointGoal -------------------------------------------------------------------------------
SELECTION_VARIANTS = (
    alpha_variant(0.0),
    *(alpha_variant(alpha) for alpha in SELECTION_ALPHAS),
    *(design_variant(design, alpha) for alpha in SELECTION_ALPHAS for design in DESIGNS),
)
# the safe-point experiment's runs: alpha 0 / 0.1 / 1 and the prior-data variants are declared identically there
_SHARED_SAFE_POINT = ("alpha-0", "alpha-0.1", "alpha-1", "alpha-0.1-priordata", "alpha-1-priordata")

SELECTION_CLAIMS = tuple(
    claim
    for family in (SAFE_POINT.name, SAFE_POINT_CRASH5.name)
    for design in DESIGNS
    for claim in (
        Claim(family, f"alpha-0.1-{design}", "alpha-0", "violation", 0, "lower", source=SOURCE),
        Claim(family, f"alpha-0.1-{design}", "alpha-0.1", "violation", 0, "lower", source=SOURCE),
        Claim(family, f"alpha-0.1-{design}", "alpha-0", "return", 0, "higher", source=SOURCE),
        Claim(family, f"alpha-0.1-{design}", "alpha-0", "violation", -1, "equal", source=SOURCE),
        Claim(family, f"alpha-0.1-{design}", "alpha-0", "return", -1, "not_lower", source=SOURCE),
    )
)

PRIOR_CRITIC = Experiment(
    name="prior-critic",
    title="Prior-critic designs: the selection on SafePointGoal",
    description=(
        "PEARL+ with eight prior-critic designs at alpha 0.1 (and 1 for the two the pre-written rule selects) on "
        "SafePointGoalMeta-v0 with crash penalties 2 and 5, against alpha 0 (PEARL) and the paper's form"
    ),
    families=(SAFE_POINT, SAFE_POINT_CRASH5),
    variants=SELECTION_VARIANTS,
    seeds=(0, 1, 2, 3, 4),
    budget="cpu",
    eval_seed=SAFE_POINT_EXPERIMENT.eval_seed,
    reference="alpha-0",
    claims=SELECTION_CLAIMS,
    shared={name: SAFE_POINT_EXPERIMENT.name for name in _SHARED_SAFE_POINT},
    # alpha 1 of every design, except those another experiment owns and plans anyway (safe-point's alpha-1-priordata)
    after_selection=tuple(f"alpha-1-{design}" for design in DESIGNS if f"alpha-1-{design}" not in _SHARED_SAFE_POINT),
)

# -- confirmation: Walker2D-vel -----------------------------------------------------------------------------
_SHARED_TABLE1 = ("pearl", "pearlplus", "finetune", "pearlplus-twin", "pearlplus-priordata")
CONFIRMATION_VARIANTS = (
    *(variant for variant in TABLE1.variants if variant.name in _SHARED_TABLE1),
    *(design_variant(design, 0.1, "pearlplus") for design in DESIGNS if design not in ("twin", "priordata")),
)
CONFIRMATION_CLAIMS = tuple(
    claim
    for variant in CONFIRMATION_VARIANTS
    if variant.name.startswith("pearlplus-")
    for claim in (
        Claim(WALKER2D_VEL.name, variant.name, "pearl", "violation", 0, "lower", source=SOURCE),
        Claim(WALKER2D_VEL.name, variant.name, "pearlplus", "violation", 0, "lower", source=SOURCE),
        Claim(WALKER2D_VEL.name, variant.name, "pearl", "violation", -1, "equal", source=SOURCE),
        Claim(WALKER2D_VEL.name, variant.name, "pearl", "return", -1, "not_lower", source=SOURCE),
    )
)

PRIOR_CRITIC_WALKER = Experiment(
    name="prior-critic-walker",
    title="Prior-critic designs: the confirmation on Walker2D-vel",
    description=(
        "PEARL+ with the selected prior-critic design(s) at alpha 0.1 on Walker2dVelMeta-v0 against table1's PEARL, "
        "PEARL+ (the paper's form), its twin and prior-data variants and Fine-Tune (the task-independent bar)"
    ),
    families=(WALKER2D_VEL,),
    variants=CONFIRMATION_VARIANTS,
    seeds=(0, 1, 2, 3),
    budget="cpu",
    eval_seed=TABLE1.eval_seed,
    reference="pearl",
    claims=CONFIRMATION_CLAIMS,
    shared={name: TABLE1.name for name in _SHARED_TABLE1},
    # the designs the prior-critic selection picks; table1's twin and prior-data runs are table1's to plan
    after_selection=tuple(
        variant.name
        for variant in CONFIRMATION_VARIANTS
        if variant.name.startswith("pearlplus-") and variant.name not in _SHARED_TABLE1
    ),
    selected_by="prior-critic",
)
