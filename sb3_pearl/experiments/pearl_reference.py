"""``pearl-reference``: our PEARL against a published PEARL, on the reference's own family and configuration (issue 19).

PEARL on HalfCheetahVelMeta-v0 with the reference implementation's cheetah-vel configuration (katerakelly/oyster,
``configs/cheetah-vel.json`` over ``configs/default.py``): the ``paper`` preset holds it as published, the ``cpu``
preset with the reductions a CPU core needs (fewer RL rows per task, then narrower networks; docs/reproduce.md lists
every value, its source and every reduction). Both record the learning curve on the held-out tasks every 20k env
steps with the reference's evaluation protocol (``sb3_pearl/reproduce/curve.py``), so that the curve can be laid
beside published PEARL curves at the same env steps. No claims: the comparison is the curve itself.
"""

from __future__ import annotations

from sb3_pearl.experiments.families import HALF_CHEETAH_VEL
from sb3_pearl.experiments.spec import Experiment, Variant

PEARL_REFERENCE = Experiment(
    name="pearl-reference",
    title="PEARL on HalfCheetah-Vel with the reference configuration",
    description=(
        "PEARL on HalfCheetahVelMeta-v0 with the PEARL reference implementation's cheetah-vel configuration (reduced "
        "for a CPU core at the cpu preset, docs/reproduce.md), 500k env steps, learning curve every 20k steps"
    ),
    families=(HALF_CHEETAH_VEL,),
    variants=(Variant("pearl", "PEARL", "pearl"),),
    seeds=(0, 1, 2),
    budget="cpu",
    eval_seed=10_005,
    reference="pearl",
)
