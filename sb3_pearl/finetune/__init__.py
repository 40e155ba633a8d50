from sb3_pearl.finetune.discrete_sac import DiscreteSAC, DiscreteSACPolicy
from sb3_pearl.finetune.finetune import FineTune

__all__ = ["DiscreteSAC", "DiscreteSACPolicy", "FineTune"]
