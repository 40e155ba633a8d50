"""MAML-TRPO (Finn et al. 2017), the paper's gradient-based meta-RL baseline."""

from sb3_pearl.maml.maml import MAML
from sb3_pearl.maml.policies import MAMLPolicy, MlpPolicy

__all__ = ["MAML", "MAMLPolicy", "MlpPolicy"]
