"""Fine-Tune's adaptation budget: cost against benefit of ``adapt_gradient_steps`` (and the adaptation minibatch).

Pretrains one Fine-Tune model with an env's zoo entry (``zoo_hyperparams/finetune.yml``) for ``--steps`` env
steps, then runs the meta-test protocol (k = 0..K, deterministic trajectories, ``adapt()`` after each) on
*training* tasks (so that the choice is not made on the held-out tasks the tables report) for every
setting of ``--adapt-steps`` x ``--adapt-batch``, from the same pretrained model and the same seed.
Prints, per setting, the mean return per k, the tasks better at k = K than at k = 0 and the time of the
meta-test, wall and CPU (one thread: the CPU time is the wall time on an idle core, which matters on a
shared machine), and writes them as JSON.

    python studies/finetune_adapt_budget.py --env PointGoalMeta-v0 --steps 6000 --adapt-steps 200 100 50 25
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
import yaml

import sb3_pearl  # noqa: F401  (registers the task families)
from sb3_pearl.evaluation.meta_test import meta_test
from sb3_pearl.finetune import FineTune
from sb3_pearl.zoo import default_config
from sb3_pearl.zoo.safe_config import parse_dict_string

ZOO_KEYS = ("n_timesteps", "policy", "n_envs", "meta_test")


def zoo_kwargs(env_id: str) -> dict[str, Any]:
    """FineTune constructor kwargs of the env's entry in ``zoo_hyperparams/finetune.yml``."""
    with open(default_config("finetune")) as file:
        entry = dict(yaml.safe_load(file)[env_id])
    kwargs = {key: value for key, value in entry.items() if key not in ZOO_KEYS}
    if isinstance(kwargs.get("policy_kwargs"), str):
        kwargs["policy_kwargs"] = parse_dict_string(kwargs["policy_kwargs"], "policy_kwargs")
    return kwargs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="PointGoalMeta-v0")
    parser.add_argument("--steps", type=int, default=6000, help="pretraining env steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-tasks", type=int, default=10, help="training tasks of the meta-test")
    parser.add_argument("--n-adapt", type=int, default=5)
    parser.add_argument("--adapt-steps", type=int, nargs="+", default=[200, 100, 50, 25])
    parser.add_argument("--adapt-batch", type=int, nargs="+", default=[0], help="adaptation minibatch (0: batch_size)")
    parser.add_argument("--model", default=None, help="reuse this pretrained zip (written there if missing)")
    parser.add_argument("--out", default=None, help="JSON file of the results")
    args = parser.parse_args()
    th.set_num_threads(1)

    kwargs = zoo_kwargs(args.env)
    start, cpu_start = time.perf_counter(), time.process_time()
    if args.model and os.path.isfile(args.model):
        model = FineTune.load(args.model)
        pretrain_s = pretrain_cpu_s = float("nan")
    else:
        model = FineTune("MlpPolicy", args.env, seed=args.seed, verbose=0, **kwargs)
        model.learn(args.steps)
        pretrain_s, pretrain_cpu_s = time.perf_counter() - start, time.process_time() - cpu_start
        if args.model:
            model.save(args.model)
    print(
        f"{args.env}: pretrained {args.steps} steps in {pretrain_s:.0f} s ({pretrain_cpu_s:.0f} s CPU); "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    env = gym.make(args.env)
    tasks = model.train_tasks[: args.n_tasks]
    results: list[dict[str, Any]] = []
    for batch in args.adapt_batch:
        for steps in args.adapt_steps:
            model.adapt_gradient_steps = steps
            model.adapt_batch_size = batch or None
            start, cpu_start = time.perf_counter(), time.process_time()
            result = meta_test(model, env, tasks, n_adapt=args.n_adapt, seed=args.seed)
            elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
            returns = np.array([[row["return"] for row in result.rows if row["task"] == t] for t in range(len(tasks))])
            means = returns.mean(axis=0)
            better = int((returns[:, -1] > returns[:, 0]).sum())
            results.append(
                {
                    "adapt_gradient_steps": steps,
                    "adapt_batch_size": batch or model.batch_size,
                    "return_per_k": [round(float(m), 2) for m in means],
                    "better_at_K": better,
                    "meta_test_s": round(elapsed, 1),
                    "meta_test_cpu_s": round(cpu, 1),
                    "adapt_calls": len(tasks) * args.n_adapt,
                }
            )
            cells = " ".join(f"{m:7.2f}" for m in means)
            print(
                f"steps {steps:4d} batch {batch or model.batch_size:4d} | {cells} | better at k={args.n_adapt}: "
                f"{better}/{len(tasks)} | {elapsed:6.1f} s ({cpu:6.1f} s CPU)",
                flush=True,
            )
    if args.out:
        with open(args.out, "w") as file:
            json.dump(
                {
                    "env": args.env,
                    "steps": args.steps,
                    "pretrain_s": pretrain_s,
                    "pretrain_cpu_s": pretrain_cpu_s,
                    "results": results,
                },
                file,
                indent=1,
            )


if __name__ == "__main__":
    main()
