"""The faster step's constraint on real runs: Highway-Merge `cpu` runs trained after it keep their meta-test.

The faster step changed the PEARL(+) step's code, not its math (commit 4f043cd; ``tests/test_update_speed.py`` compares
100 updates of the old and the new path). Its constraint adds that "a Highway-Merge `cpu` run's meta-test stays inside
its interval". Some committed Highway-Merge rows have seeds trained on both sides of that commit (each result.json
records the commit it was trained from): this script splits every such row by whether its training commit contains
4f043cd, and prints, on the re-measured meta-test (1,000 k = 0 trajectories a seed):

- the seeds before and after, and each side's mean with its 95% t interval over seeds;
- whether the mean after lies inside the interval before;
- the difference after minus before, with a Welch 95% interval (different seeds on each side: not paired), and
  whether that interval holds 0 (the check: where every seed before has the same rate, the interval before has no
  width and the second column alone would flag any change).

The seeds differ between the two sides, and so may the CPU kind (both are printed), so this is a check that the
numbers did not move beyond the spread of seeds, not a test of equality.

    python benchmarks/merge_math_check.py [--results-dir results] [--commit 4f043cd]
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import statistics
import subprocess
from collections import defaultdict

from pearl_paper.experiments.table1_rules import MERGE_REMEASURE
from pearl_paper.reproduce.formatting import format_interval
from pearl_paper.reproduce.stats import Interval, t_interval, t_quantile

ROOT = pathlib.Path(__file__).resolve().parents[1]
MEASURES = (("k = 0 violation, %", 0, "violation_rate", 100.0, 1), ("k = 5 return", 5, "return_mean", 1.0, 2))


def contains(commit: str, ancestor: str) -> bool:
    """Whether ``commit`` has ``ancestor`` in its history (``<sha>-dirty``, a tree with uncommitted edits: its base)."""
    commit = commit.removesuffix("-dirty")
    done = subprocess.run(["git", "merge-base", "--is-ancestor", ancestor, commit], cwd=ROOT, capture_output=True)
    if done.returncode not in (0, 1):
        raise ValueError(f"git cannot compare {commit} with {ancestor}: {done.stderr.decode().strip()}")
    return done.returncode == 0


def welch(after: list[float], before: list[float]) -> Interval:
    """mean(after) - mean(before) with a Welch 95% interval."""
    difference = statistics.fmean(after) - statistics.fmean(before)
    if len(after) < 2 or len(before) < 2:
        return Interval(difference, math.nan, math.nan, len(after) + len(before))
    va, vb = statistics.variance(after) / len(after), statistics.variance(before) / len(before)
    if va + vb == 0:
        return Interval(difference, difference, difference, len(after) + len(before))
    df = (va + vb) ** 2 / (va**2 / (len(after) - 1) + vb**2 / (len(before) - 1))
    half = t_quantile(0.975, df) * math.sqrt(va + vb)
    return Interval(difference, difference - half, difference + half, len(after) + len(before))


def holds(interval: Interval, value: float) -> str:
    """``yes`` / ``NO``: whether ``interval`` holds ``value``; ``-`` when there is no interval (one seed on a side)."""
    if not (math.isfinite(interval.low) and math.isfinite(interval.high)):
        return "-"
    return "yes" if interval.low <= value <= interval.high else "NO"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results-dir", type=pathlib.Path, default=ROOT / "results")
    parser.add_argument("--commit", default="4f043cd", help="the first commit of the faster step (default: 4f043cd)")
    args = parser.parse_args()
    rows: dict[tuple[str, str], dict[bool, list[dict]]] = defaultdict(lambda: {False: [], True: []})
    for large in sorted(args.results_dir.glob(f"merge-*/highway-merge/*/seed*/{MERGE_REMEASURE.file_name}")):
        result = json.loads((large.parent / "result.json").read_text())
        summary = {row["k"]: row for row in json.loads(large.read_text())["summary"]}
        trained_after = contains(result["versions"]["git_commit"], args.commit)
        rows[(result["experiment"], result["variant"])][trained_after].append(
            {"seed": result["seed"], "cpu": result["cpu"]["model"], "summary": summary}
        )
    print(f"Highway-Merge rows with seeds trained both before and after {args.commit} (re-measured meta-test):\n")
    header = ("row", "measure", "seeds before", "seeds after", "before (95% t)", "after (95% t)", "after's mean inside?")
    print("| " + " | ".join((*header, "after - before (Welch 95%)", "holds 0?")) + " |")
    print("|---" * (len(header) + 2) + "|")
    for (experiment, variant), sides in sorted(rows.items()):
        if not (sides[False] and sides[True]):
            continue
        for label, k, key, scale, digits in MEASURES:
            values = {side: [run["summary"][k][key] for run in sides[side]] for side in (False, True)}
            before, after = t_interval(values[False]), t_interval(values[True])
            difference = welch(values[True], values[False])
            seeds = {side: ",".join(str(run["seed"]) for run in sides[side]) for side in (False, True)}
            cells = (
                f"{experiment} {variant}",
                label,
                seeds[False],
                seeds[True],
                format_interval(before, digits, scale),
                format_interval(after, digits, scale),
                holds(before, after.mean),
                format_interval(difference, digits, scale),
                holds(difference, 0.0),
            )
            print("| " + " | ".join(cells) + " |")
    cpus = {side: sorted({run["cpu"] for sides in rows.values() for run in sides[side]}) for side in (False, True)}
    print(f"\nCPU kinds: before {cpus[False]}, after {cpus[True]}")


if __name__ == "__main__":
    main()
