from sb3_pearl.pearl.pearl import PEARL, PEARLPlus
from sb3_pearl.pearl.policies import MlpPolicy, PEARLPolicy

__all__ = ["PEARL", "MlpPolicy", "PEARLPlus", "PEARLPolicy"]
