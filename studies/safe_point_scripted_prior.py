"""Task-independent scripted policies on ``SafePointGoalMeta-v0``: what a prior policy could score at k = 0.

A prior policy acts before it has seen any data of the task, so any fixed, task-independent policy is a
candidate for it. PEARL+'s prior term maximises the prior policy's return averaged over tasks; two
scripted candidates (``sb3_pearl.envs.safe_point_goal.SCRIPTED_PRIORS``) bound what that optimum is worth:

- ``still``: stay at the start (the origin). Every goal lies on the unit circle, so the return is
  exactly -horizon (-30), and the hazards (0.35-0.85 from the origin) are never entered;
- ``wait-at-0.3``: go to (0, 0.3), inside the hazard-free inner disc (radius 0.35) with a margin, towards
  the middle of the goal arc, and wait there. It is the bar of the prior-optimality gap that every
  safe-point run stores in result.json (``prior_critic.prior_optimality``).

Prints, per crash penalty, the mean return and the violation rate over ``--n-tasks`` tasks drawn by the
env's own ``sample_tasks`` (seed ``--seed``), through the meta-test protocol:

    python studies/safe_point_scripted_prior.py --n-tasks 500
"""

from __future__ import annotations

import argparse

import gymnasium as gym

import sb3_pearl  # noqa: F401  (registers the envs)
from sb3_pearl.envs.safe_point_goal import SCRIPTED_PRIORS
from sb3_pearl.evaluation.meta_test import meta_test
from sb3_pearl.evaluation.scripted import ScriptedPolicy

ENV_ID = "SafePointGoalMeta-v0"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n-tasks", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.n_tasks < 1:
        parser.error(f"--n-tasks must be >= 1, got {args.n_tasks}")
    print("| crash penalty | policy | mean return | violation rate |")
    print("|---|---|---|---|")
    for crash_penalty in (2.0, 5.0):
        env = gym.make(ENV_ID, crash_penalty=crash_penalty)
        tasks = env.unwrapped.sample_tasks(args.n_tasks, seed=args.seed)  # type: ignore[attr-defined]
        for name, policy in SCRIPTED_PRIORS.items():
            result = meta_test(ScriptedPolicy(policy, name), env, tasks, n_adapt=0, seed=args.seed)
            k0 = result.summary[0]
            print(f"| {crash_penalty:g} | {name} | {k0['return_mean']:.1f} | {k0['violation_rate']:.1%} |")


if __name__ == "__main__":
    main()
