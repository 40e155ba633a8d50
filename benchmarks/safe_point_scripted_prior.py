"""Task-independent scripted policies on ``SafePointGoalMeta-v0``: what a prior policy could score at k = 0.

A prior policy acts before it has seen any data of the task, so any fixed, task-independent policy is a
candidate for it. PEARL+'s prior term maximises the prior policy's return averaged over tasks; two
scripted candidates bound what that optimum is worth on this family:

- ``still``: stay at the start (the origin). Every goal lies on the unit circle, so the return is
  exactly -horizon (-30), and the hazards (0.35-0.85 from the origin) are never entered;
- ``wait-at-0.3``: go to (0, 0.3), inside the hazard-free inner disc (radius 0.35) with a margin, towards
  the middle of the goal arc, and wait there.

Prints, per crash penalty, the mean return and the violation rate over ``--n-tasks`` tasks drawn by the
env's own ``sample_tasks`` (seed ``--seed``), to compare with the k = 0 rows of docs/results.md:

    python benchmarks/safe_point_scripted_prior.py --n-tasks 500
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

import gymnasium as gym
import numpy as np

import sb3_pearl  # noqa: F401  (registers the envs)

ENV_ID = "SafePointGoalMeta-v0"
WAIT_POINT = np.array([0.0, 0.3])


def _still(obs: np.ndarray) -> np.ndarray:
    return np.zeros(2)


def _wait_at(obs: np.ndarray) -> np.ndarray:
    return np.clip(WAIT_POINT - obs, -0.1, 0.1)  # the env's largest step per axis is 0.1


POLICIES: dict[str, Callable[[np.ndarray], np.ndarray]] = {"still": _still, "wait-at-0.3": _wait_at}


def evaluate(policy: Callable[[np.ndarray], np.ndarray], crash_penalty: float, n_tasks: int, seed: int) -> tuple[float, float]:
    """Mean return and violation rate of ``policy`` over ``n_tasks`` tasks (one episode each)."""
    env = gym.make(ENV_ID, crash_penalty=crash_penalty)
    family = env.unwrapped
    returns, violated = [], []
    for index, task in enumerate(family.sample_tasks(n_tasks, seed=seed)):  # type: ignore[attr-defined]
        family.set_task(task)  # type: ignore[attr-defined]
        obs, _ = env.reset(seed=seed + index)
        total, cost, done = 0.0, 0.0, False
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(np.asarray(obs)))
            total += float(reward)
            cost += float(info.get("cost", 0.0))
            done = terminated or truncated
        returns.append(total)
        violated.append(cost > 0)
    return float(np.mean(returns)), float(np.mean(violated))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n-tasks", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print("| crash penalty | policy | mean return | violation rate |")
    print("|---|---|---|---|")
    for crash_penalty in (2.0, 5.0):
        for name, policy in POLICIES.items():
            ret, rate = evaluate(policy, crash_penalty, args.n_tasks, args.seed)
            print(f"| {crash_penalty:g} | {name} | {ret:.1f} | {rate:.1%} |")


if __name__ == "__main__":
    main()
