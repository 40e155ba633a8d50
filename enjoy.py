"""Watch a trained meta-RL model adapt: the prior trajectory, then posterior ones (rl-zoo style).

    python enjoy.py --algo pearlplus --env SafePointGoalMeta-v0 -f logs --n-tasks 3 --n-adapt 3
    python enjoy.py --algo pearl --env HighwayMergeMeta-v0 --video-folder videos --plot

Finds models like rl_zoo3's enjoy (``-f``, ``--exp-id``, ``--load-best``, ``--load-checkpoint``).
See ``docs/cli.md`` and :func:`sb3_pearl.zoo.enjoy`.
"""

from sb3_pearl.zoo import enjoy

if __name__ == "__main__":
    enjoy()
