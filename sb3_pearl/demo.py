"""``make demo``: PEARL and PEARL+ on SafePointGoalMeta-v0 through train.py's pipeline, then the meta-test table.

Each algorithm is trained with the fast entry of ``zoo_hyperparams/<algo>.yml`` (measured with its final
meta-test: PEARL 106 s, PEARL+ 148 s of CPU on one core; docs/cli.md) by :func:`sb3_pearl.zoo.train`
(``rl_zoo3.train.train()``), which writes the usual zoo run folder ``logs/<algo>/SafePointGoalMeta-v0_<n>/``
with ``meta_test.csv``, ``meta_test.json`` and ``adaptation.png``. The demo then prints the paper's columns (trajectories
k = 0, 1, 3, 5: mean return and violation rate over the held-out tasks) and writes a comparison figure.

    python -m sb3_pearl.demo                      # both algorithms, the YAML budget
    python -m sb3_pearl.demo --algos pearlplus -n 5000
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence

from huggingface_sb3 import EnvironmentName
from rl_zoo3 import get_latest_run_id

from sb3_pearl.evaluation.figures import plot_all
from sb3_pearl.evaluation.meta_test import PAPER_KS, MetaTestResult
from sb3_pearl.zoo import train

ENV_ID = "SafePointGoalMeta-v0"


def format_paper_table(runs: dict[str, MetaTestResult], ks: Sequence[int] = PAPER_KS) -> str:
    """
    The paper's meta-test table: one line per algorithm, mean return and violation rate at each k.

    :param runs: results by algorithm name
    :param ks: the trajectories shown
    :return: the table
    """
    header = f"{'algorithm':<12}" + "".join(f" | {f'k={k} return':>12} {'viol.':>6}" for k in ks)
    lines = [header, "-" * len(header)]
    for name, result in runs.items():
        cells = []
        for k in ks:
            try:
                entry = result.summary_at(k)
                cells.append(f" | {entry['return_mean']:>12.2f} {100 * entry['violation_rate']:>5.1f}%")
            except KeyError:
                cells.append(f" | {'-':>12} {'-':>6}")
        lines.append(f"{name:<12}" + "".join(cells))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict[str, MetaTestResult]:
    """
    Train each algorithm with train.py's pipeline, then print and plot the meta-test.

    :param argv: command-line arguments
    :return: the meta-test results by algorithm
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", default=["pearl", "pearlplus"], help="zoo algorithm names")
    parser.add_argument("-n", "--n-timesteps", type=int, default=None, help="override the YAML budget")
    parser.add_argument("-f", "--log-folder", default="logs", help="zoo log folder")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    runs: dict[str, MetaTestResult] = {}
    for algo in args.algos:
        start = time.time()
        print(f"=== Training {algo} on {ENV_ID} (zoo_hyperparams/{algo}.yml) ===", flush=True)
        train(
            [
                *("--algo", algo, "--env", ENV_ID, "-f", args.log_folder, "--seed", str(args.seed)),
                *(() if args.n_timesteps is None else ("-n", str(args.n_timesteps))),
                *("--num-threads", "1", "--eval-freq", "-1", "--verbose", "0", "-P"),
            ]
        )
        log_path = os.path.join(args.log_folder, algo)
        run_dir = os.path.join(log_path, f"{ENV_ID}_{get_latest_run_id(log_path, EnvironmentName(ENV_ID))}")
        runs[algo] = MetaTestResult.from_json(os.path.join(run_dir, "meta_test.json"))
        print(f"{algo}: {time.time() - start:.0f} s, run folder {run_dir}", flush=True)

    first = next(iter(runs.values()))
    print(
        f"\nMeta-test on {ENV_ID}: {first.config.get('n_tasks')} held-out tasks, trajectory k = 0 with z from the prior, "
        "k >= 1 after adapting on trajectories 0..k-1 (deterministic actions); violation = entered the hazard"
    )
    print(format_paper_table(runs))
    figure = os.path.join(args.log_folder, "demo_adaptation.png")
    for path in plot_all(runs, figure, kinds=("adaptation", "violations"), title=f"meta-test on {ENV_ID}"):
        print(f"Saved {path}")
    print(f"Watch the rollouts: python enjoy.py --algo {args.algos[-1]} --env {ENV_ID} -f {args.log_folder} --no-render")
    return runs


if __name__ == "__main__":
    main()
