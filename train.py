"""Train PEARL / PEARL+ (and the baselines) with rl-baselines3-zoo's command line.

    python train.py --algo pearlplus --env SafePointGoalMeta-v0
    python train.py --algo pearl --env HalfCheetahVelMeta-v0 --vec-env subproc -P

Every rl_zoo3 flag works (``python train.py -h``); hyperparameters default to
``zoo_hyperparams/<algo>.yml``. See ``docs/cli.md`` and :mod:`sb3_pearl.zoo`.
"""

from sb3_pearl.zoo import train

if __name__ == "__main__":
    train()
