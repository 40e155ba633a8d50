"""The paper's claim on the fast family: PEARL+ is safer than PEARL before adaptation.

Trains PEARL and PEARL+ with the same settings and seeds on ``SafePointGoalMeta-v0``, then runs
the meta-test protocol on the held-out tasks: trajectory k = 0 with z from the prior, k >= 1 with
the posterior of all earlier trajectories (deterministic actions). Prints, per algorithm and k,
the mean return and the violation rate (share of trajectories that entered the hazard), and
writes them as JSON.

    python benchmarks/safe_point_claim.py --steps 20000 --seeds 0 1 --out docs/safe_point_claim.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th

from sb3_pearl import PEARL, PEARLPlus
from sb3_pearl.common.meta_test import meta_test as run_meta_test

# The reference point-robot settings (oyster configs/point-robot.json: fixed entropy 1,
# reward_scale 100, kl 0.1), scaled down to run in minutes on one core.
SETTINGS: dict[str, Any] = dict(
    n_train_tasks=40,
    n_test_tasks=20,
    num_initial_steps=150,
    num_tasks_sample=5,
    num_steps_prior=60,
    num_steps_posterior=0,
    num_extra_rl_steps_posterior=60,
    num_train_steps_per_itr=300,
    meta_batch=8,
    batch_size=128,
    embedding_batch_size=60,
    encoder_arch=[64, 64],
    policy_kwargs=dict(net_arch=[64, 64]),
    ent_coef=1.0,
    reward_scale=100.0,
)


def meta_test(model: PEARLPlus, n_adapt: int) -> dict[str, np.ndarray]:
    """The project's meta-test protocol on the held-out tasks: returns and violations, (n_test_tasks, n_adapt + 1)."""
    result = run_meta_test(model, gym.make("SafePointGoalMeta-v0"), model.test_tasks, n_adapt=n_adapt, seed=0)
    shape = (len(model.test_tasks), n_adapt + 1)
    returns, violated = np.zeros(shape), np.zeros(shape)
    for row in result.rows:
        returns[row["task"], row["k"]] = row["return"]
        violated[row["task"], row["k"]] = float(row["violated"])
    return {"return": returns, "violated": violated}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--n-adapt", type=int, default=2)
    parser.add_argument("--reward-scale", type=float, default=SETTINGS["reward_scale"])
    parser.add_argument("--algos", nargs="+", default=["PEARL", "PEARL+"], choices=["PEARL", "PEARL+"])
    parser.add_argument("--bf16", action="store_true", help="use_bf16=True (bfloat16 hidden layers in gradient steps)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    SETTINGS["reward_scale"] = args.reward_scale
    SETTINGS["use_bf16"] = args.bf16
    th.set_num_threads(1)
    results: dict[str, Any] = {"settings": {**SETTINGS, "policy_kwargs": str(SETTINGS["policy_kwargs"])}, "steps": args.steps}
    for name, cls in [(n, c) for n, c in (("PEARL", PEARL), ("PEARL+", PEARLPlus)) if n in args.algos]:
        per_seed = []
        for seed in args.seeds:
            start = time.time()
            # PEARL+'s extra Q-network has the size of the SAC Q-network, as the paper's "300-Node" setting
            extra = {"prior_critic_arch": SETTINGS["policy_kwargs"]["net_arch"]} if cls is PEARLPlus else {}
            model = cls("MlpPolicy", "SafePointGoalMeta-v0", seed=seed, **SETTINGS, **extra)
            model.learn(args.steps)
            out = meta_test(model, args.n_adapt)
            per_seed.append(out)
            print(
                f"{name} seed {seed} ({time.time() - start:.0f} s): return per k {out['return'].mean(0).round(1).tolist()}, "
                f"violation rate per k {out['violated'].mean(0).round(2).tolist()}",
                flush=True,
            )
        returns = np.stack([r["return"] for r in per_seed])  # (seeds, tasks, k)
        violated = np.stack([r["violated"] for r in per_seed])
        results[name] = {
            "return_mean_per_k": returns.mean(axis=(0, 1)).tolist(),
            "violation_rate_per_k": violated.mean(axis=(0, 1)).tolist(),
            "violation_rate_per_seed_k0": violated[:, :, 0].mean(axis=1).tolist(),
        }
    print("| algorithm | k | mean return | violation rate |")
    print("|---|---|---|---|")
    for name in args.algos:
        for k in range(args.n_adapt + 1):
            r = results[name]
            print(f"| {name} | {k} | {r['return_mean_per_k'][k]:.1f} | {r['violation_rate_per_k'][k]:.2f} |")
    if args.out is not None:
        args.out.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
