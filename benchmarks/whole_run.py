"""Whole-run speed: env steps per CPU-second of PEARL+ `cpu` runs, this tree against an earlier commit, in one run.

For each family (default: Walker2D-vel and Highway-Merge), a PEARL+ model with the `cpu` budget preset's settings
learns ``--steps`` env steps (seed 0; ``--threads one``: one torch thread, ``default``: each commit's own default)
once with this working tree's code and once with the code of
``--base`` (checked out into a temporary git worktree, removed afterwards), alternating base / new in each repeat so
that a neighbour's load hits both alike. Each run is its own process; its CPU time (``time.process_time``) counts
collection, gradient steps and everything else of ``learn`` (not the imports or the model's construction).

Prints a Markdown table and writes a bar figure (``--figure``).

    python benchmarks/whole_run.py [--base bb89ea7] [--steps 25000] [--repeats 1] [--threads one|default]
        [--figure docs/figures/whole_run_speed.png]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
FAMILIES = {"walker2d-vel": "Walker2dVelMeta-v0", "highway-merge": "HighwayMergeMeta-v0"}

# One run, in a fresh interpreter with the tree under test first on the path: prints one JSON line.
CHILD = """
import json, sys, time
import torch as th
if sys.argv[4] == "one":
    th.set_num_threads(1)
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
import sb3_pearl
from sb3_pearl import PEARLPlus
from sb3_pearl.budgets import load_budget, model_kwargs
family, env_id, steps = sys.argv[1], sys.argv[2], int(sys.argv[3])  # sys.argv[4]: "one" or "default" threads
budget = load_budget("cpu", family, "pearlplus")
model = PEARLPlus("MlpPolicy", make_vec_env(env_id, n_envs=1, seed=0), seed=0, **model_kwargs(budget["kwargs"]))
model.set_logger(configure(None, [""]))
train, spent = model.train, [0.0]
def timed_train(*args, **kwargs):
    start = time.process_time()
    train(*args, **kwargs)
    spent[0] += time.process_time() - start
model.train = timed_train
cpu, wall = time.process_time(), time.perf_counter()
model.learn(steps)
cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
print(json.dumps({"steps": model.num_timesteps, "cpu_s": cpu, "wall_s": wall, "train_cpu_s": spent[0],
                  "updates": model._n_updates, "threads": th.get_num_threads(), "module": sb3_pearl.__file__}))
"""


def run_once(tree: pathlib.Path, family: str, steps: int, threads: str) -> dict[str, float]:
    """One ``learn`` with the code of ``tree`` and ``threads`` ("one", or "default": its own default); the measurements."""
    env = {key: value for key, value in os.environ.items() if key not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env["PYTHONPATH"] = str(tree)
    out = subprocess.run(
        [sys.executable, "-c", CHILD, family, FAMILIES[family], str(steps), threads],
        cwd=tree,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    result = json.loads(out.strip().splitlines()[-1])
    if not str(result["module"]).startswith(str(tree)):
        raise RuntimeError(f"the run imported {result['module']}, not the code of {tree}")
    return result


def figure(rates: dict[str, dict[str, float]], base: str, path: pathlib.Path, caption: str) -> None:
    """Bar chart: env steps per CPU-second of each family, base and new side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    families = list(rates)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    width = 0.38
    for offset, (key, label) in enumerate([("base", f"before ({base})"), ("new", "this tree")]):
        xs = [i + (offset - 0.5) * width for i in range(len(families))]
        bars = ax.bar(xs, [rates[f][key] for f in families], width, label=label)
        ax.bar_label(bars, fmt="%.0f", fontsize=8)
    for i, family in enumerate(families):
        ax.text(i, 0.5 * max(rates[family].values()), f"{rates[family]['new'] / rates[family]['base']:.2f}x", ha="center")
    ax.set_xticks(range(len(families)), families)
    ax.set_ylabel("env steps per CPU-second")
    ax.set_title(caption, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", default="bb89ea7", help="the commit to compare against")
    parser.add_argument("--steps", type=int, default=25_000, help="env steps of each run")
    parser.add_argument("--repeats", type=int, default=1, help="base / new pairs per family (the median is reported)")
    parser.add_argument(
        "--threads",
        choices=["one", "default"],
        default="one",
        help="one torch thread in both runs (the code's speed), or each commit's own default (what a user gets)",
    )
    parser.add_argument("--families", nargs="+", choices=sorted(FAMILIES), default=list(FAMILIES))
    parser.add_argument("--figure", type=pathlib.Path, default=ROOT / "docs" / "figures" / "whole_run_speed.png")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        base_tree = pathlib.Path(scratch) / "base"
        subprocess.run(["git", "worktree", "add", "--detach", str(base_tree), args.base], cwd=ROOT, check=True)
        try:
            runs: dict[str, dict[str, list[dict[str, float]]]] = {f: {"base": [], "new": []} for f in args.families}
            for _ in range(args.repeats):
                for family in args.families:
                    for key, tree in (("base", base_tree), ("new", ROOT)):
                        result = run_once(tree, family, args.steps, args.threads)
                        runs[family][key].append(result)
                        print(f"{family} {key}: {json.dumps(result)}", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base_tree)], cwd=ROOT, check=True)
    print(
        "\n| family | steps | base steps/CPU-s | new steps/CPU-s | new/base | base train CPU-s | new train CPU-s "
        "| train new/base |\n|---|---|---|---|---|---|---|---|"
    )
    rates: dict[str, dict[str, float]] = {}
    for family, by_key in runs.items():
        rate = {key: statistics.median(r["steps"] / r["cpu_s"] for r in results) for key, results in by_key.items()}
        train = {key: statistics.median(r["train_cpu_s"] for r in results) for key, results in by_key.items()}
        rates[family] = rate
        print(
            f"| {family} | {args.steps} | {rate['base']:.0f} | {rate['new']:.0f} | {rate['new'] / rate['base']:.2f} "
            f"| {train['base']:.0f} | {train['new']:.0f} | {train['base'] / train['new']:.2f}x faster |"
        )
    threads = "one torch thread" if args.threads == "one" else "each commit's default thread count"
    caption = f"PEARL+ `cpu` preset, {args.steps} env steps, {threads}, median of {args.repeats}"
    figure(rates, args.base, args.figure, caption)
    print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
