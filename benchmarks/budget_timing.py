"""Measured unit costs behind the budget presets, and the estimated wall time of one reproduction run.

For each (family, algorithm) of a preset, on one torch thread:

- ``collect``: seconds per env step of training-time collection (env step + policy act + buffer),
  measured on a short ``learn`` with almost no gradient steps (PEARL / PEARL+), or together with the
  gradient steps for Fine-Tune (one step per env step) and MAML (whole iterations);
- ``update``: seconds per PEARL / PEARL+ gradient step with the preset's networks and batch;
- ``meta-test``: seconds per env step of the meta-test protocol (predict + env + observe + adapt),
  on an untrained model (trajectories run to the horizon; a trained walker that falls is cheaper).

The estimate of a run is ``n_timesteps * collect + gradient steps * update + meta-test steps * meta-test``,
the meta-test steps being the upper bound ``tasks x repeats x (K + 1) x horizon`` of the held-out,
shifted and competence meta-tests. Only a few hundred updates and env steps are timed, not runs.
The machine is shared: the load average is printed with the numbers.

    python benchmarks/budget_timing.py --preset cpu --families walker2d-vel highway-merge --algos pearl pearlplus
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import gymnasium as gym
import torch as th

import sb3_pearl  # noqa: F401  (registers the task families)
from pearl_paper.experiments.families import get_family
from sb3_pearl.budgets import load_budget, model_kwargs, preset_entries
from sb3_pearl.evaluation.meta_test import meta_test
from sb3_pearl.registry import algorithm_class


def pearl_gradient_steps(budget: dict[str, Any]) -> int:
    """Gradient steps of a PEARL / PEARL+ run: iteration 0 (initial data) then one full set per collected iteration."""
    kwargs = budget["kwargs"]
    n_train = kwargs.get("n_train_tasks", 100)
    initial = n_train * kwargs.get("num_initial_steps", 2000)
    per_itr = kwargs.get("num_tasks_sample", 5) * (
        kwargs.get("num_steps_prior", 400)
        + kwargs.get("num_steps_posterior", 0)
        + kwargs.get("num_extra_rl_steps_posterior", 600)
    )
    steps = kwargs.get("num_train_steps_per_itr", 2000)
    remaining = max(budget["n_timesteps"] - initial, 0)
    return int(steps * (min(budget["n_timesteps"], initial) / max(initial, 1) + remaining / per_itr))


def meta_test_steps(budget: dict[str, Any], horizon: int, shift: bool) -> int:
    """Upper bound of the env steps of a run's meta-tests (held-out, shifted if declared, competence)."""
    settings = [budget["meta_test"], budget["competence_meta_test"]] + ([budget["shift_meta_test"]] if shift else [])
    return sum(s["n_tasks"] * s["n_repeats"] * (s["n_adapt"] + 1) * horizon for s in settings)


def time_meta_test(model: Any, env: gym.Env, task: dict[str, Any], n_adapt: int = 2) -> float:
    """Seconds per env step of the meta-test protocol on one task."""
    start = time.perf_counter()
    result = meta_test(model, env, [task], n_adapt=n_adapt, n_repeats=1, seed=0)
    steps = sum(int(row["length"]) for row in result.rows)
    return (time.perf_counter() - start) / max(steps, 1)


def measure(
    preset: str, family_name: str, algo: str, n_updates: int, n_steps: int, overrides: dict[str, Any] | None = None
) -> dict[str, float]:
    """Unit costs and the estimate of one (family, algorithm) run of a preset (with a variant's overrides)."""
    family = get_family(family_name)
    budget = load_budget(preset, family.budget_name, algo)
    budget["kwargs"].update(overrides or {})
    env_kwargs = dict(family.env_kwargs)
    horizon = int(gym.spec(family.env_id).max_episode_steps or 200)
    kwargs = model_kwargs(budget["kwargs"])
    cls = algorithm_class(algo)
    out: dict[str, float] = {}
    if algo in ("pearl", "pearlplus"):
        probe = {
            **kwargs,
            "num_initial_steps": max(kwargs.get("batch_size", 256), kwargs.get("embedding_batch_size", 100)),
            "num_train_steps_per_itr": 1,
        }
        model = cls("MlpPolicy", gym.make(family.env_id, **env_kwargs), seed=0, **probe)
        initial = model.n_train_tasks * model.num_initial_steps
        model.learn(initial)  # fills every task's buffers
        start = time.perf_counter()
        model.learn(n_steps, reset_num_timesteps=False)
        out["collect_s"] = (time.perf_counter() - start) / n_steps
        model.train(gradient_steps=3, batch_size=model.batch_size)  # warm-up
        start = time.perf_counter()
        model.train(gradient_steps=n_updates, batch_size=model.batch_size)
        out["update_s"] = (time.perf_counter() - start) / n_updates
        grads = pearl_gradient_steps(budget)
        train_s = budget["n_timesteps"] * out["collect_s"] + grads * out["update_s"]
        out["gradient_steps"] = grads
    else:
        model = cls(
            "MlpPolicy", gym.make(family.env_id, **env_kwargs) if budget["n_envs"] == 1 else family.env_id, seed=0, **kwargs
        )
        warm = kwargs.get("learning_starts", 0) + 200 if algo == "finetune" else 1
        model.learn(warm)
        start = time.perf_counter()
        model.learn(n_steps, reset_num_timesteps=False)
        steps = max(model.num_timesteps - warm, 1)
        out["collect_s"] = (time.perf_counter() - start) / steps
        train_s = budget["n_timesteps"] * out["collect_s"]
    env = gym.make(family.env_id, **env_kwargs)
    task = env.unwrapped.sample_tasks(1, seed=123)[0]  # type: ignore[attr-defined]
    out["meta_test_s"] = time_meta_test(model, env, task)
    mt_steps = meta_test_steps(budget, horizon, family.shift_env_kwargs is not None)
    out["meta_test_steps"] = mt_steps
    out["train_min"] = train_s / 60
    out["meta_test_min"] = mt_steps * out["meta_test_s"] / 60
    out["total_min"] = out["train_min"] + out["meta_test_min"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--families", nargs="+", default=None)
    parser.add_argument("--algos", nargs="+", default=["pearl", "pearlplus"])
    parser.add_argument("--updates", type=int, default=100, help="timed PEARL gradient steps")
    parser.add_argument("--steps", type=int, default=1000, help="timed training env steps")
    parser.add_argument(
        "--overrides", type=json.loads, default=None, help="variant kwargs, JSON: '{\"prior_critic_arch\": [300, 300, 300]}'"
    )
    args = parser.parse_args()
    th.set_num_threads(1)
    entries = preset_entries(args.preset)
    families = args.families or list(entries)
    print(f"preset {args.preset}; load average before: {os.getloadavg()}; CPU threads: {os.cpu_count()}; torch threads 1")
    header = (
        "| family | algo | collect ms/step | update ms | meta-test ms/step | grad steps | train min | meta-test min "
        "| total min |"
    )
    print(header)
    print("|" + "---|" * 9)
    for family in families:
        for algo in args.algos:
            if algo not in entries.get(get_family(family).budget_name, []):
                continue
            r = measure(args.preset, family, algo, args.updates, args.steps, args.overrides)
            update = f"{1e3 * r['update_s']:.1f}" if "update_s" in r else "-"
            grads = f"{r['gradient_steps']:.0f}" if "gradient_steps" in r else "-"
            print(
                f"| {family} | {algo} | {1e3 * r['collect_s']:.2f} | {update} | {1e3 * r['meta_test_s']:.2f} | {grads} | "
                f"{r['train_min']:.1f} | {r['meta_test_min']:.1f} | {r['total_min']:.1f} |",
                flush=True,
            )
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
