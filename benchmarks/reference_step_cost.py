"""Cost of PEARL's reference cheetah-vel configuration on this CPU, and of its reductions (the ``cpu`` preset's).

For each configuration (RL rows per task, network width), on one torch thread: seconds per gradient step
(``meta_batch`` 16 tasks, 100 context rows each, the configuration's rows and widths) and per training env step
(collection), and the projected core-hours of one ``pearl-reference`` run to ``--steps`` env steps: the reference's
gradient steps (2000 per 5000-step iteration after the 200k-step initial pool; ``pearl_gradient_steps``) plus
collection plus the learning curve's evaluations (30 tasks x 3 trajectories x 200 steps every 20k steps). Ratios to the
full configuration are measured in the same run; the machine's load average is printed with them.

    python -m benchmarks.reference_step_cost --updates 30   # from the repository root (it imports benchmarks.*)
"""

from __future__ import annotations

import argparse
import copy
import os
import platform
import time

import gymnasium as gym
import torch as th

import sb3_pearl  # noqa: F401  (registers the envs)
from benchmarks.budget_timing import pearl_gradient_steps
from sb3_pearl import PEARL
from sb3_pearl.budgets import load_budget, model_kwargs

CONFIGS = ((256, 300), (128, 300), (64, 300), (64, 256), (64, 200), (32, 300))


def measure(batch_size: int, width: int, n_updates: int) -> tuple[float, float]:
    """Seconds per gradient step and per collected env step of the reference configuration with these rows and widths."""
    budget = load_budget("paper", "cheetah-vel", "pearl")
    kwargs = model_kwargs(copy.deepcopy(budget["kwargs"]))
    kwargs.update(batch_size=batch_size, policy_kwargs={"net_arch": [width] * 3})
    # Fewer training tasks and initial steps than the run: enough data for the meta-batch, the step cost is the same.
    kwargs.update(n_train_tasks=16, num_initial_steps=batch_size + 100, buffer_size=10_000)
    model = PEARL("MlpPolicy", gym.make("HalfCheetahVelMeta-v0"), seed=0, **{**kwargs, "num_train_steps_per_itr": 1})
    model.learn(16 * (batch_size + 100))
    start = time.perf_counter()
    model.learn(2000, reset_num_timesteps=False)
    collect = (time.perf_counter() - start) / 2000
    model.train(gradient_steps=3, batch_size=batch_size)
    start = time.perf_counter()
    model.train(gradient_steps=n_updates, batch_size=batch_size)
    return (time.perf_counter() - start) / n_updates, collect


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--updates", type=int, default=30, help="gradient steps timed per configuration")
    parser.add_argument("--steps", type=int, default=500_000, help="env steps of the projected run")
    parser.add_argument(
        "--configs", default=",".join(f"{b}x{w}" for b, w in CONFIGS), help="rows-per-task x width, the first the reference"
    )
    args = parser.parse_args()
    th.set_num_threads(1)
    budget = load_budget("paper", "cheetah-vel", "pearl")
    budget["n_timesteps"] = args.steps
    grads = pearl_gradient_steps(budget)
    curve_steps = (args.steps // 20_000) * 30 * 3 * 200
    print(f"CPU: {platform.processor() or platform.machine()}, load average {os.getloadavg()}, torch {th.__version__}")
    print(f"{grads} gradient steps, {args.steps} env steps and {curve_steps} curve env steps to {args.steps} steps")
    print("| rows per task | width | s / gradient step | ratio to 256 x 300 | s / env step | core-hours to 500k |")
    print("|---|---|---|---|---|---|")
    full = None
    configs = [tuple(int(v) for v in item.split("x")) for item in args.configs.split(",")]
    for batch_size, width in configs:
        step, collect = measure(batch_size, width, args.updates)
        full = full or step
        hours = (grads * step + (args.steps + curve_steps) * collect) / 3600
        ratio = step / full
        print(f"| {batch_size} | {width} | {step:.3f} | {ratio:.2f} | {collect * 1000:.2f} ms | {hours:.1f} |", flush=True)
    print(f"load average at the end {os.getloadavg()}")


if __name__ == "__main__":
    main()
