"""``pearl-reference``: our PEARL against a published PEARL, on the reference's own family and configuration.

PEARL on HalfCheetahVelMeta-v0 with the reference implementation's cheetah-vel configuration (katerakelly/oyster,
``configs/cheetah-vel.json`` over ``configs/default.py``): the ``paper`` preset holds it as published, the ``cpu``
preset with the reductions a CPU core needs (fewer RL rows per task, then narrower networks; docs/reproduce.md lists
every value, its source and every reduction). Both record the learning curve on the held-out tasks every 20k env
steps with the reference's evaluation protocol (``pearl_paper/reproduce/curve.py``), so that the curve can be laid
beside published PEARL curves at the same env steps. No claims: the comparison is the curve itself.

The second family, ``walker2d-vel-long``, is Walker2D-vel with the ``cpu`` preset's networks trained to 500k env steps
with a curve (2 seeds: ``--family walker2d-vel-long --seeds 0,1``): the env-step count at which PEARL meets the
family's competence criteria on training tasks, or the statement that it does not by 500k. It does not (docs/results.md):
the curve flattens at 0.7-0.8 m/s, more than twice the bar.

The third family, ``walker2d-vel-ref``, is the next candidate for the `cpu-long` budget: Walker2D-vel at the
configuration that made our PEARL competent on cheetah-vel, i.e. the reference's networks and schedule (the ``paper``
preset's Walker2D-vel entry: 3x300 networks, 3x200 encoder, meta-batch 16, 2000 gradient steps per 5 x (400 + 600)-step
iteration, 2000 initial steps per training task) with cheetah-vel's one reduction, 32 RL rows per task instead of 256;
the family's own tasks (40 / 10), episodes and criteria. 500k env steps, a curve every 20k (``--family
walker2d-vel-ref --seeds 0,1``): if it becomes competent, the env-step count is the `cpu-long` budget of Table I's
Walker row. It was not by 500k (velocity error 0.65 m/s, still falling; docs/results.md).

The fourth family, ``walker2d-vel-ref-long``, is walker2d-vel-ref unchanged but trained to 1.5M env steps: the
tracking diagnostic found the walker too slow on the fast targets rather than in the wrong task (a locomotion skill
still being learnt), and a straight line through walker2d-vel-ref's curve crosses the 0.3 m/s bar near 0.9M env steps.
It takes longer than one session, so it resumes across sessions (``--family walker2d-vel-ref-long --seeds 0``;
``reproduce status pearl-reference`` gives the CPU time left). Its first 500k env steps are walker2d-vel-ref's (same
configuration and seed): on the same CPU model its curve repeats walker2d-vel-ref's point by point, a free check of
the harness' determinism.

The fifth family, ``ant3d-vel-long``, asks the same question of Ant-3D-Vel, the paper's other MuJoCo family of Tables
I and II, once Walker2D-vel had no ``cpu-long`` budget within reach: PEARL at the ``cpu`` preset's Ant-3D-Vel entry
(Table I's networks, batch and schedule) trained to 500k env steps instead of 80k, with the curve and the competence
check every 20k (``--family ant3d-vel-long --seeds 0``). The first competent env-step count, if any, is the budget of
a Table I Ant-3D-Vel row at which PEARL is competent. Written before the run: one seed first; a second only if the
first becomes competent (name the seeds: the experiment's default is 0-2).
"""

from __future__ import annotations

import dataclasses

from pearl_paper.experiments.families import ANT3D_VEL, HALF_CHEETAH_VEL, WALKER2D_VEL
from pearl_paper.experiments.spec import Experiment, Family, Variant

# PEARL's learning curve on Walker2D-vel at the `cpu` networks, to 500k env steps: where does it become competent
# (the family's pre-written criteria, checked at every curve point)? That env-step count becomes the `cpu-long` budget.
WALKER2D_VEL_LONG: Family = dataclasses.replace(
    WALKER2D_VEL, name="walker2d-vel-long", title="Walker-2D-Vel, 500k steps", budget_family="walker2d-vel-long"
)

# The same question at the reference's networks with cheetah-vel's row reduction (the configuration competent there).
WALKER2D_VEL_REF: Family = dataclasses.replace(
    WALKER2D_VEL,
    name="walker2d-vel-ref",
    title="Walker-2D-Vel, reference networks, 500k steps",
    budget_family="walker2d-vel-ref",
)

# The same configuration trained three times longer: where does the curve, still falling at 500k, cross the bar?
WALKER2D_VEL_REF_LONG: Family = dataclasses.replace(
    WALKER2D_VEL,
    name="walker2d-vel-ref-long",
    title="Walker-2D-Vel, reference networks, 1.5M steps",
    budget_family="walker2d-vel-ref-long",
)

# Ant-3D-Vel at Table I's `cpu` entry trained to 500k env steps: is there a budget at which PEARL is competent there?
ANT3D_VEL_LONG: Family = dataclasses.replace(
    ANT3D_VEL, name="ant3d-vel-long", title="Ant-3D-Vel, 500k steps", budget_family="ant3d-vel-long"
)

PEARL_REFERENCE = Experiment(
    name="pearl-reference",
    title=(
        "PEARL's learning curves to 500k env steps (walker2d-vel-ref-long: 1.5M): HalfCheetah-Vel (the reference "
        "configuration), Walker2D-vel, Ant-3D-Vel"
    ),
    description=(
        "PEARL on HalfCheetahVelMeta-v0 with the PEARL reference implementation's cheetah-vel configuration (reduced "
        "for a CPU core at the cpu preset, docs/reproduce.md), and on Walker2D-vel with the cpu preset's networks "
        "(walker2d-vel-long) and with the reference's networks and cheetah-vel's row reduction (walker2d-vel-ref); 500k env "
        "steps (walker2d-vel-ref-long: 1.5M), learning curve every 20k steps; Ant-3D-Vel at the cpu preset's networks "
        "to 500k (ant3d-vel-long)"
    ),
    families=(HALF_CHEETAH_VEL, WALKER2D_VEL_LONG, WALKER2D_VEL_REF, WALKER2D_VEL_REF_LONG, ANT3D_VEL_LONG),
    variants=(Variant("pearl", "PEARL", "pearl"),),
    seeds=(0, 1, 2),
    budget="cpu",
    eval_seed=10_005,
    reference="pearl",
)
