"""sb3-pearl: PEARL and PEARL+ (prior-safe context-based meta-RL) for Stable-Baselines3."""

from sb3_pearl.envs import register_envs
from sb3_pearl.finetune import FineTune
from sb3_pearl.maml import MAML
from sb3_pearl.pearl import PEARL, PEARLPlus

register_envs()

__version__ = "0.1.0"

__all__ = ["MAML", "PEARL", "FineTune", "PEARLPlus", "__version__", "register_envs"]
