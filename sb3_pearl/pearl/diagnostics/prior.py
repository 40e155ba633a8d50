"""The prior term of a diagnosed model: PEARL+'s settings, or none for a PEARL model (which has no prior term)."""

from __future__ import annotations

from typing import NamedTuple

from sb3_pearl.common.networks import LatentCritic
from sb3_pearl.pearl.pearl import PEARL
from sb3_pearl.pearl.pearl_plus import PEARLPlus


class PriorTerm(NamedTuple):
    """What the diagnostics read of a model's prior term."""

    coef: float  # prior_coef, the weight of the actor's prior term (0: none)
    critic_mode: str  # "separate", "shared" or "none" (PEARL)
    critic: LatentCritic | None  # the separate prior critic Q~, if any
    monte_carlo: bool  # the replay batches carry Monte-Carlo returns (prior_target="mc")


def prior_term(model: PEARL) -> PriorTerm:
    """
    The prior term ``model`` trains with.

    :param model: a PEARL or PEARL+ model
    :return: its settings (a PEARL model: weight 0, no prior critic)
    """
    if isinstance(model, PEARLPlus):
        return PriorTerm(model.prior_coef, model.prior_critic_mode, model.prior_critic, model.prior_target == "mc")
    return PriorTerm(0.0, "none", None, False)
