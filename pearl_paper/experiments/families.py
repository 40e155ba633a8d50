"""The task families of the reproduction experiments, with their shifted test distributions and competence criteria.

Names (CLI and results layout): ``safe-point`` (SafePointGoalMeta-v0, the fast family),
``walker2d-vel`` (Walker2dVelMeta-v0), ``ant3d-vel`` (AntVelMeta-v0), ``highway-merge``
(HighwayMergeMeta-v0) and ``cheetah-vel`` (HalfCheetahVelMeta-v0, PEARL's own family: the ``pearl-reference``
experiment).

Competence criteria (docs/reproduce.md): PEARL's *posterior* policy (trajectories k >= 1) on
*training* tasks must meet every criterion of its family before a comparison on that family is
read as a statement about the algorithms rather than about an undertrained model. They were written
before any reproduction run.

Shifted test distributions (``shift_env_kwargs``): task ranges beyond the training box. Where the
default unhealthy penalty depends on the range (the locomotion families), it is pinned to the
training value so that only the tasks change, not the reward.
"""

from __future__ import annotations

from pearl_paper.experiments.spec import Criterion, Family, PriorBar, PublishedPoint

MPH = 0.44704  # m/s per mph (sb3_pearl.envs.highway_merge.MPH)

_NO_FALLS = Criterion(
    description="unhealthy (fall) rate of the posterior trajectories",
    kind="row_mean",
    key="violated",
    threshold=0.1,
    better="lower",
)

_VELOCITY_ERROR = Criterion(
    description="mean absolute error of the forward velocity per step of the posterior trajectories [m/s]",
    kind="trace_mean",
    key="reward_forward",
    scale=-1.0,
    threshold=0.3,
    better="lower",
)

SAFE_POINT = Family(
    name="safe-point",
    env_id="SafePointGoalMeta-v0",
    title="SafePointGoal (the fast family)",
    competence=(
        Criterion(
            description="final distance to the goal of the posterior trajectories (goals lie on the unit circle)",
            kind="trace_last",
            key="distance",
            threshold=0.3,
            better="lower",
        ),
    ),
    return_margin=2.0,
    prior_bar=PriorBar(
        "scripted",
        "wait-at-0.3",
        "scripted: walk to (0, 0.3), inside the hazard-free inner disc, and wait (studies/safe_point_scripted_prior.py)",
    ),
)

WALKER2D_VEL = Family(
    name="walker2d-vel",
    env_id="Walker2dVelMeta-v0",
    title="Walker-2D-Vel",
    shift_env_kwargs={"velocity_low": 2.0, "velocity_high": 3.0, "unhealthy_penalty": 2.0},
    shift_description="target velocities U[2, 3] m/s (training U[0, 2]); unhealthy penalty kept at the training 2.0",
    competence=(
        _VELOCITY_ERROR,
        _NO_FALLS,
    ),
    return_margin=10.0,
    prior_bar=PriorBar("variant", "finetune", "Fine-Tune's k = 0 policy: SAC trained on the task mixture, same budget"),
)

ANT3D_VEL = Family(
    name="ant3d-vel",
    env_id="AntVelMeta-v0",
    title="Ant-3D-Vel",
    shift_env_kwargs={"speed_low": 3.0, "speed_high": 4.0, "unhealthy_penalty": 3.0},
    shift_description="target speeds U[3, 4] m/s (training U[0, 3]), any direction; unhealthy penalty kept at 3.0",
    competence=(
        Criterion(
            description="mean norm of the planar velocity error per step of the posterior trajectories [m/s]",
            kind="trace_mean",
            key="reward_forward",
            scale=-1.0,
            threshold=0.5,
            better="lower",
        ),
        _NO_FALLS,
    ),
    return_margin=10.0,
)

HIGHWAY_MERGE = Family(
    name="highway-merge",
    env_id="HighwayMergeMeta-v0",
    title="Highway-Merge",
    shift_env_kwargs={"density_range": [50.0, 60.0], "speed_range": [70.0 * MPH, 80.0 * MPH]},
    shift_description="density U[50, 60] veh/km and speed U[70, 80] mph (training U[30, 50], U[50, 70])",
    competence=(
        Criterion(
            description="merge success rate of the posterior trajectories",
            kind="row_mean",
            key="merged",
            threshold=0.9,
            better="higher",
        ),
        Criterion(
            description="crash rate of the posterior trajectories",
            kind="row_mean",
            key="violated",
            threshold=0.05,
            better="lower",
        ),
    ),
    return_margin=3.0,
)

HALF_CHEETAH_VEL = Family(
    name="cheetah-vel",
    env_id="HalfCheetahVelMeta-v0",
    title="HalfCheetah-Vel (PEARL's cheetah-vel)",
    competence=(_VELOCITY_ERROR,),
    return_margin=10.0,
    has_violations=False,  # the cheetah never falls: Gymnasium's HalfCheetah has no unhealthy state
    published_curve=(
        PublishedPoint(
            780_000,
            -44.0,
            "an independent PyTorch reimplementation of PEARL (200-step episodes, automatic entropy temperature where the "
            "reference fixes it, the mean of its last 10 evaluations; docs/references.md)",
        ),
    ),
)

FAMILIES: dict[str, Family] = {f.name: f for f in (SAFE_POINT, WALKER2D_VEL, ANT3D_VEL, HIGHWAY_MERGE, HALF_CHEETAH_VEL)}


def get_family(name: str) -> Family:
    """
    The family called ``name``.

    :param name: ``safe-point``, ``walker2d-vel``, ``ant3d-vel`` or ``highway-merge``
    :return: the family
    """
    if name not in FAMILIES:
        raise ValueError(f"unknown family {name!r}: choose among {sorted(FAMILIES)}")
    return FAMILIES[name]
