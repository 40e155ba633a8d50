"""Tables I-III on Highway-Merge again, at the PEARL reference's entropy setting (``merge-premise``'s follow-up).

``merge-premise`` trained PEARL on Highway-Merge with the reference's fixed entropy coefficient 1 and reward scale 5
(instead of SB3's automatic entropy and reward scale 1, Table I's ``cpu`` setting). Its decision rule (written before
its runs, :mod:`pearl_paper.experiments.merge_premise`) reads the posterior AUC against z0, the return across k and
PEARL's k = 0 crash rate; where the encoder carries task information and PEARL's prior crashes, the rule asks for the
merge row of Table I again at that setting (PEARL and PEARL+, 4 seeds, with the shift column), then Table II's
ablation and Table III's alpha sweep on merge (3 seeds each). Table III was extended to 4 seeds (the paper's count:
"each mean and standard deviation is calculated on 4 independent runs") once its 3-seed verdicts, reported in
docs/results.md, were in. The rows next to Table I's then went to its 10 seeds, as compute allowed: Table III's
alpha 0 (alpha 0.1 is Table I's PEARL+ already) and Table II's 300-node PEARL+ beside PEARL (``variant_seeds``).
Once those were in, Table II's two other rows (without the prior critic, and 100 nodes) were declared at the same 10
seeds, so that the whole table is paired with PEARL on one set of seeds; Table III's alpha 0.01, 1 and 5 rows keep
their 4 seeds.

The three experiments below are those tables' merge variants with ``ent_coef=1.0`` and ``reward_scale=5.0`` added to
their overrides (variant names get the suffix ``-fixed-entropy``), with the tables' own paper cells and claims renamed
to match. Nothing else changes: same ``cpu`` preset, networks and budget. All three use Table I's eval seed (10001),
the one of ``merge-premise``, so that one run serves every table that declares the same model (common random
numbers): PEARL's runs are ``merge-premise``'s (seeds 0-1 done there, 2-3 run into its folder; each experiment's
report shows the seeds it declares), and PEARL+ at alpha 0.1 is both Table I's PEARL+ row and Table III's alpha 0.1
column. The original tables keep their own eval seeds and their runs at the ``cpu`` setting.

A PEARL+ form recommended by the prior-critic selection (``prior-critic``), once there is one, joins ``merge-table1`` as a
variant; none is recommended yet.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

from pearl_paper.experiments.families import HIGHWAY_MERGE
from pearl_paper.experiments.merge_premise import MERGE_PREMISE, REFERENCE_ENTROPY
from pearl_paper.experiments.spec import Experiment, Variant
from pearl_paper.experiments.table1 import TABLE1
from pearl_paper.experiments.table2 import TABLE2
from pearl_paper.experiments.table3 import TABLE3

SUFFIX = "-fixed-entropy"


def at_reference_entropy(variant: Variant) -> Variant:
    """``variant`` with the reference's entropy setting added to its overrides, named ``<name>-fixed-entropy``."""
    overrides = {**dict(variant.overrides), **REFERENCE_ENTROPY}
    return Variant(f"{variant.name}{SUFFIX}", f"{variant.label}, fixed entropy 1, reward scale 5", variant.algo, overrides)


def merge_at_reference_entropy(
    base: Experiment,
    name: str,
    variant_names: Sequence[str],
    seeds: Sequence[int],
    shared: Mapping[str, str],
    same_as: Mapping[str, Variant] | None = None,
    variant_seeds: Mapping[str, Sequence[int]] | None = None,
) -> Experiment:
    """
    ``base``'s Highway-Merge variants ``variant_names`` at the reference's entropy setting, with ``base``'s merge paper
    cells and claims renamed to them (claims between two chosen variants only).

    :param base: the paper table (``TABLE1``, ``TABLE2``, ``TABLE3``)
    :param name: the new experiment's name
    :param variant_names: the base variants to take, the reference first
    :param seeds: model seeds
    :param shared: new variant name -> the experiment that owns its runs
    :param same_as: base variant name -> the variant of another of these experiments that declares the same model
        (its runs serve both; e.g. Table III's alpha 0.1 is Table I's PEARL+)
    :param variant_seeds: base variant name -> its model seeds, where they are not ``seeds``
    :return: the experiment
    """
    same_as = dict(same_as or {})
    for base_name, variant in same_as.items():
        mine = at_reference_entropy(base.variant(base_name))
        if not mine.same_model(variant):
            raise ValueError(f"{name}: {base_name} is not the model of {variant.name}: {mine} against {variant}")
    variants = tuple(same_as.get(variant) or at_reference_entropy(base.variant(variant)) for variant in variant_names)
    rename = {base_name: variant.name for base_name, variant in zip(variant_names, variants)}
    merge = HIGHWAY_MERGE.name
    paper = tuple(
        dataclasses.replace(cell, variant=rename[cell.variant])
        for cell in base.paper
        if cell.family == merge and cell.variant in rename
    )
    claims = tuple(
        dataclasses.replace(claim, variant=rename[claim.variant], reference=rename[claim.reference])
        for claim in base.claims
        if claim.family == merge and claim.variant in rename and claim.reference in rename
    )
    return Experiment(
        name=name,
        title=f"{base.title.split(':')[0]} on Highway-Merge at the reference's entropy setting",
        description=f"{base.title}: its Highway-Merge variants with the PEARL reference's fixed entropy coefficient 1 "
        "and reward scale 5 (merge-premise's setting), everything else as the cpu preset",
        families=(HIGHWAY_MERGE,),
        variants=variants,
        seeds=tuple(seeds),
        variant_seeds={rename[base_name]: tuple(s) for base_name, s in (variant_seeds or {}).items()},
        budget=base.budget,
        eval_seed=MERGE_PREMISE.eval_seed,
        reference=rename[variant_names[0]],
        paper=paper,
        claims=claims,
        shared=shared,
    )


PEARL_RUNS = {f"pearl{SUFFIX}": MERGE_PREMISE.name}  # merge-premise's PEARL at this setting

# Table I's 10 seeds (0-3 first, 4-9 added for the pre-written rules: pearl_paper.experiments.table1_rules)
TABLE1_SEEDS = tuple(range(10))
MERGE_TABLE1 = merge_at_reference_entropy(TABLE1, "merge-table1", ("pearl", "pearlplus"), TABLE1_SEEDS, PEARL_RUNS)
MERGE_TABLE2 = merge_at_reference_entropy(
    TABLE2,
    "merge-table2",
    ("pearl", "pearlplus-wo", "pearlplus-300", "pearlplus-100"),
    TABLE1_SEEDS,  # every row at Table I's 10 seeds: paired with PEARL on one set of seeds
    PEARL_RUNS,
)
# alpha 0.1 is Table I's PEARL+ (same model): its runs are merge-table1's
PEARLPLUS = MERGE_TABLE1.variant(f"pearlplus{SUFFIX}")
MERGE_TABLE3 = merge_at_reference_entropy(
    TABLE3,
    "merge-table3",
    ("alpha-0", "alpha-0.01", "alpha-0.1", "alpha-1", "alpha-5"),
    (0, 1, 2, 3),
    {PEARLPLUS.name: MERGE_TABLE1.name},
    same_as={"alpha-0.1": PEARLPLUS},
    variant_seeds={"alpha-0": TABLE1_SEEDS, "alpha-0.1": TABLE1_SEEDS},  # the rows beside Table I at its 10 seeds
)
