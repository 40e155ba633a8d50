"""sb3-pearl: PEARL and PEARL+ (prior-safe context-based meta-RL) for Stable-Baselines3."""

# Before MuJoCo and gymnasium-robotics are imported: an offscreen MuJoCo backend when there is no display, and
# without gymnasium-robotics' Adroit notice (sb3_pearl.common.runtime).
from sb3_pearl.common.runtime import drop_adroit_notice, select_mujoco_gl

select_mujoco_gl()
drop_adroit_notice()

from sb3_pearl.envs import register_envs  # noqa: E402
from sb3_pearl.finetune import FineTune  # noqa: E402
from sb3_pearl.maml import MAML  # noqa: E402
from sb3_pearl.oracle import Oracle  # noqa: E402
from sb3_pearl.pearl import PEARL, PEARLPlus  # noqa: E402

register_envs()

__version__ = "0.1.0"

__all__ = ["MAML", "PEARL", "FineTune", "Oracle", "PEARLPlus", "__version__", "register_envs"]
