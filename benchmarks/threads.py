"""The default torch thread count against every explicit one: env steps per second of short ``learn`` runs.

Each configuration learns ``--steps`` env steps once per thread setting, each run in its own process and the settings
alternated in ``--repeats`` rounds (a neighbour's load hits them alike): ``--num-threads``-style explicit counts
1..cores (``torch.set_num_threads`` before ``learn``) and the default (nothing set: ``learn`` applies
:func:`sb3_pearl.common.threads.default_num_threads`). Prints fps (median of the rounds), the count the default
picked, and the default's fps as a ratio of the best explicit setting (target >= 0.9), with the machine's load.

Configurations: ``safe-point`` (the zoo's SafePointGoalMeta-v0 PEARL+ entry, 64x64 networks: the small configuration),
``walker-cpu`` (the `cpu` preset's Walker2D-vel PEARL+ entry, 2x128) and ``paper-step`` (PEARL+ gradient steps at
the paper's sizes, 3x300: gradient steps per second instead of env steps, from benchmarks/throughput.py).

    python benchmarks/threads.py [--configs safe-point walker-cpu paper-step] [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]

# One run in a fresh interpreter: argv = config, threads ("default" or a count), steps; prints one JSON line.
CHILD = """
import json, sys, time
import torch as th
config, threads, steps = sys.argv[1], sys.argv[2], int(sys.argv[3])
import sb3_pearl
from stable_baselines3.common.logger import configure
from sb3_pearl import PEARLPlus
if threads != "default":
    th.set_num_threads(int(threads))
if config == "paper-step":
    from benchmarks.throughput import SIZES, make_pearl
    size = SIZES["paper"]
    model = make_pearl(PEARLPlus, size)
    from sb3_pearl.common.threads import apply_default_num_threads
    apply_default_num_threads(model.policy)  # what learn() does first
    model.train(gradient_steps=1, batch_size=size.rows)  # warm-up
    start = time.perf_counter()
    model.train(gradient_steps=steps, batch_size=size.rows)
else:
    import gymnasium as gym
    if config == "safe-point":
        import yaml
        from sb3_pearl.config import HYPERPARAMS_DIR
        entry = dict(yaml.safe_load(open(HYPERPARAMS_DIR / "pearlplus.yml"))["SafePointGoalMeta-v0"])
        for key in ("n_timesteps", "policy", "n_envs"):
            entry.pop(key, None)
        entry["policy_kwargs"] = eval(entry["policy_kwargs"], {})  # a literal dict in the project's own YAML
        env_id = "SafePointGoalMeta-v0"
    else:
        from sb3_pearl.budgets import load_budget, model_kwargs
        entry = model_kwargs(load_budget("cpu", "walker2d-vel", "pearlplus")["kwargs"])
        env_id = "Walker2dVelMeta-v0"
    model = PEARLPlus("MlpPolicy", gym.make(env_id), seed=0, **entry)
    model.set_logger(configure(None, [""]))
    start = time.perf_counter()
    model.learn(steps)
print(json.dumps({"fps": steps / (time.perf_counter() - start), "threads": th.get_num_threads()}))
"""

STEPS = {"safe-point": 3000, "walker-cpu": 8000, "paper-step": 4}


def run_once(config: str, threads: str) -> dict[str, float]:
    """One run of ``config`` with ``threads`` (a count, or "default"); its fps and the count it ran with."""
    env = {key: value for key, value in os.environ.items() if key not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run(
        [sys.executable, "-c", CHILD, config, threads, str(STEPS[config])],
        cwd=ROOT,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", nargs="+", choices=sorted(STEPS), default=list(STEPS))
    parser.add_argument("--repeats", type=int, default=2, help="rounds over the thread settings (the median is reported)")
    parser.add_argument("--max-threads", type=int, default=len(os.sched_getaffinity(0)), help="explicit counts 1..this")
    args = parser.parse_args()
    settings = [str(n) for n in range(1, args.max_threads + 1)] + ["default"]
    print(f"cores: {len(os.sched_getaffinity(0))}; load average at start: {os.getloadavg()}")
    columns = " | ".join(f"{s} thr" if s != "default" else "default" for s in settings)
    print(f"| config | unit | {columns} | default picked | default / best explicit |")
    print("|---" * (len(settings) + 4) + "|")
    for config in args.configs:
        runs: dict[str, list[dict[str, float]]] = {s: [] for s in settings}
        for _ in range(args.repeats):
            for setting in settings:
                runs[setting].append(run_once(config, setting))
        fps = {s: statistics.median(r["fps"] for r in results) for s, results in runs.items()}
        best = max(fps[s] for s in settings if s != "default")
        picked = sorted({int(r["threads"]) for r in runs["default"]})
        unit = "updates/s" if config == "paper-step" else "env steps/s"
        print(
            f"| {config} | {unit} | " + " | ".join(f"{fps[s]:.1f}" for s in settings) + f" | {picked} "
            f"| {fps['default'] / best:.2f} |",
            flush=True,
        )
    print(f"load average at the end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
