from sb3_pearl.pearl.pearl import PEARL
from sb3_pearl.pearl.pearl_plus import PEARLPlus
from sb3_pearl.pearl.policies import MlpPolicy, PEARLPolicy

__all__ = ["PEARL", "MlpPolicy", "PEARLPlus", "PEARLPolicy"]
