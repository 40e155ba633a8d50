"""``make demo``: the project's point in a few minutes: PEARL against PEARL+ from the committed headline models, then a
short training run through train.py's pipeline.

1. **The headline** (:data:`HEADLINE`: Highway-Merge at the PEARL reference's fixed entropy, PEARL against PEARL+): the
   paper's table (trajectories k = 0, 1, 3, 5: violation rate and return, with 95% intervals) from the committed
   re-measured meta-test of every seed (``meta_test_large.json``: 100 held-out tasks x 10 prior draws, the README's
   headline; each run's own ``result.json`` meta-test where a run has none), the paired difference PEARL+ - PEARL over
   seeds, Table I's verdicts, and the figure (``<log folder>/demo/headline.png``). Read from ``results/``, so it
   follows the committed results as they change.
2. **The replay**: the committed ``model.zip`` of a few seeds of each, meta-tested again on the first tasks and prior
   draws of their committed meta-test (same tasks, same eval seed, common random numbers): the same table for the
   replayed trajectories, and whether every replayed trajectory equals its committed row.
3. **A short training run**: PEARL+ on SafePointGoalMeta-v0 with :func:`sb3_pearl.zoo.train` (``train.py``'s
   pipeline, one torch thread), which writes the zoo run folder ``logs/pearlplus/SafePointGoalMeta-v0_<n>/`` with its
   meta-test; ``enjoy.py`` replays it.

    python -m pearl_paper.demo                       # all three (its duration: docs/cli.md, "make demo")
    python -m pearl_paper.demo --skip-training       # the headline and the replay only
    python -m pearl_paper.demo --replay-seeds 0 --n-tasks 5 --n-repeats 1 -n 2000   # a smaller one
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from huggingface_sb3 import EnvironmentName

from pearl_paper.experiments.table1_rules import MERGE_REMEASURE
from pearl_paper.reproduce.layout import check_result_path, read_run_result
from pearl_paper.reproduce.stats import Interval, paired_differences, t_interval
from sb3_pearl.common.checks import non_negative_int, positive_int
from sb3_pearl.evaluation.held_out import run_meta_test
from sb3_pearl.evaluation.meta_test import PAPER_KS, MetaTestResult, read_json
from sb3_pearl.evaluation.statistics import summarize, wilson_interval
from sb3_pearl.zoo import train
from sb3_pearl.zoo.algos import register_algos
from sb3_pearl.zoo.rl_zoo3_coupling import get_latest_run_id

# The headline comparison, by label: the committed variant folders under results/ (every seed<N>/ with a result.json
# counts). Decided by Table I's pre-written rules (docs/results.md, "Table I on Highway-Merge at the reference's
# entropy setting"); the README's headline table holds the same numbers.
HEADLINE: dict[str, str] = {
    "PEARL": "merge-premise/highway-merge/pearl-fixed-entropy",
    "PEARL+": "merge-table1/highway-merge/pearlplus-fixed-entropy",
}
HEADLINE_TITLE = "Highway-Merge (fixed entropy 1, reward scale 5): PEARL vs PEARL+ (alpha 0.1)"
TRAIN_ENV_ID = "SafePointGoalMeta-v0"
DEFAULT_RESULTS = Path(__file__).resolve().parent.parent / "results"  # the checkout's committed results


def default_results_dir() -> Path:
    """The committed ``results/`` of the checkout this package runs from, else ``./results``."""
    return DEFAULT_RESULTS if DEFAULT_RESULTS.is_dir() else Path("results")


def headline_runs(results_dir: str | os.PathLike[str], headline: Mapping[str, str] = HEADLINE) -> dict[str, dict[int, Path]]:
    """
    The finished runs of the headline variants: label -> seed -> run folder (``result.json`` present).

    :param results_dir: the results folder
    :param headline: label -> variant folder relative to ``results_dir``
    :return: the run folders, seeds in increasing order
    """
    runs: dict[str, dict[int, Path]] = {}
    for label, variant in headline.items():
        folders = [path.parent for path in Path(results_dir, variant).glob("seed*/result.json")]
        runs[label] = {int(folder.name[4:]): folder for folder in sorted(folders, key=lambda f: int(f.name[4:]))}
    return runs


def committed_meta_test(run_dir: str | os.PathLike[str]) -> tuple[MetaTestResult, dict[str, Any]]:
    """
    The held-out meta-test a harness run committed (``result.json``'s ``meta_test`` section) and the whole record.

    :param run_dir: the run folder
    :return: the meta-test and the result record
    """
    record = read_run_result(Path(run_dir, "result.json"))  # refused if it is not the result of its folder's run
    return MetaTestResult.from_dict(record["meta_test"]), record


def remeasured_meta_test(run_dir: str | os.PathLike[str]) -> MetaTestResult | None:
    """
    The run's re-measured meta-test (``reproduce remeasure``'s record, Table I's larger design, which the README's
    headline reads): k = 0 from every prior draw (100 tasks x 10), k >= 1 from the adapted pass.

    :param run_dir: the run folder
    :return: the meta-test, or None if the run has no re-measured record
    """
    path = Path(run_dir, MERGE_REMEASURE.file_name)
    if not path.is_file():
        return None
    record = read_json(path)  # an empty or cut file is an error that names it
    if not isinstance(record, dict) or "prior" not in record or "adapted" not in record:
        raise ValueError(
            f"{path} is not a re-measured record (no prior / adapted pass): rerun `python -m pearl_paper.reproduce remeasure`"
        )
    check_result_path(path, record)  # a copied or moved record must not stand for another run
    prior, adapted = record["prior"], record["adapted"]
    rows = prior["rows"] + [row for row in adapted["rows"] if int(row["k"]) > 0]  # the rows the summary was made from
    repeats = {"n_repeats": prior["config"]["n_repeats"], "adapted_repeats": adapted["config"]["n_repeats"]}
    config = {**adapted["config"], **repeats}
    return MetaTestResult.from_dict({"rows": rows, "summary": record["summary"], "config": config})


def headline_meta_tests(found: Mapping[str, Mapping[int, Path]]) -> tuple[dict[str, dict[int, MetaTestResult]], bool]:
    """
    The meta-tests the headline table shows: every run's re-measured one when every run has it (the README's
    numbers), else every run's own (``result.json``), so that the paired differences compare like with like.

    :param found: label -> seed -> run folder (:func:`headline_runs`)
    :return: label -> seed -> meta-test, and whether they are the re-measured ones
    """
    remeasured = {label: {seed: remeasured_meta_test(run) for seed, run in seeds.items()} for label, seeds in found.items()}
    if all(result is not None for seeds in remeasured.values() for result in seeds.values()):
        return {label: {seed: r for seed, r in seeds.items() if r is not None} for label, seeds in remeasured.items()}, True
    return {label: {seed: committed_meta_test(run)[0] for seed, run in seeds.items()} for label, seeds in found.items()}, False


def pool(results: Sequence[MetaTestResult]) -> MetaTestResult:
    """
    Several seeds' meta-tests as one (tasks renumbered so that every seed's tasks stay apart): the pooled trajectories
    of the Wilson intervals and of the figure.

    :param results: one meta-test per seed
    :return: the pooled meta-test
    """
    rows: list[dict[str, Any]] = []
    offset = 0
    for result in results:
        rows += [{**row, "task": int(row["task"]) + offset} for row in result.rows]
        offset += 1 + max((int(row["task"]) for row in result.rows), default=-1)
    config = dict(results[0].config) if results else {}
    keys = config.get("trajectory_info_keys") or []
    return MetaTestResult(rows=rows, summary=summarize(rows, extra_keys=keys), config=config)


def _entry(result: MetaTestResult, k: int) -> dict[str, Any] | None:
    try:
        return result.summary_at(k)
    except KeyError:
        return None


def _per_unit_returns(result: MetaTestResult, k: int, unit: str) -> dict[int, float]:
    """Mean return at k per seed (``unit="seed"``: the result's mean) or per task (``unit="task"``)."""
    if unit == "seed":
        entry = _entry(result, k)
        return {0: float(entry["return_mean"])} if entry else {}
    per_task: dict[int, list[float]] = {}
    for row in result.rows:
        if int(row["k"]) == k:
            per_task.setdefault(int(row["task"]), []).append(float(row["return"]))
    return {task: float(np.mean(values)) for task, values in per_task.items()}


def _fmt(interval: Interval, scale: float = 1.0, signed: bool = False) -> str:
    sign = "+" if signed else ""
    if not (math.isfinite(interval.low) and math.isfinite(interval.high)):
        return f"{scale * interval.mean:{sign}.1f}"
    return f"{scale * interval.mean:{sign}.1f} [{scale * interval.low:{sign}.1f}, {scale * interval.high:{sign}.1f}]"


def paper_table(
    by_seed: Mapping[str, Mapping[int, MetaTestResult]],
    ks: Sequence[int] = PAPER_KS,
    return_unit: str = "seed",
    paired: bool = True,
) -> str:
    """
    The paper's table with intervals, in two parts: the violation rate (%) of the pooled trajectories with its 95% Wilson
    interval, and the mean return with a 95% t interval (over seeds, or over seed x task means with
    ``return_unit="task"``), per algorithm and k; with ``paired`` and two algorithms, each part ends with the paired
    difference (second - first, 95% t over the seeds both have).

    :param by_seed: label -> seed -> meta-test
    :param ks: the trajectories shown
    :param return_unit: ``"seed"`` or ``"task"``: the unit of the return's interval
    :param paired: add the paired difference
    :return: the table
    """
    width = 20
    header = f"{'':<18}" + "".join(f"{f'k = {k}' + (' (prior)' if k == 0 else ''):>{width}}" for k in ks)
    pooled = {label: pool(list(seeds.values())) for label, seeds in by_seed.items()}
    lines = ["Violation rate, % [95% interval]", header]
    for label in by_seed:
        cells = []
        for k in ks:
            entry = _entry(pooled[label], k)
            if entry is None:
                cells.append("-")
                continue
            low, high = wilson_interval(round(entry["violation_rate"] * entry["n"]), int(entry["n"]))
            cells.append(_fmt(Interval(entry["violation_rate"], low, high, int(entry["n"])), 100))
        lines.append(f"{label:<18}" + "".join(f"{cell:>{width}}" for cell in cells))
    pairs = list(by_seed.items()) if paired and len(by_seed) == 2 else []
    if pairs:
        lines.append(_difference_row(pairs, ks, "violation_rate", 100, width))
    lines += ["Return [95% interval]", header]
    for label, seeds in by_seed.items():
        cells = []
        for k in ks:
            per_unit = [value for result in seeds.values() for value in _per_unit_returns(result, k, return_unit).values()]
            cells.append(_fmt(t_interval(per_unit)) if per_unit else "-")
        lines.append(f"{label:<18}" + "".join(f"{cell:>{width}}" for cell in cells))
    if pairs:
        lines.append(_difference_row(pairs, ks, "return_mean", 1, width))
    return "\n".join(lines)


def _difference_row(
    pairs: Sequence[tuple[str, Mapping[int, MetaTestResult]]], ks: Sequence[int], metric: str, scale: float, width: int
) -> str:
    """The paired difference (second - first) of ``metric`` at each k, 95% t over the common seeds."""
    (first, reference), (second, variant) = pairs
    cells = []
    for k in ks:
        values = [
            {seed: float(entry[metric]) for seed, result in runs.items() if (entry := _entry(result, k)) is not None}
            for runs in (variant, reference)
        ]
        cells.append(_fmt(t_interval(list(paired_differences(*values).values())), scale, signed=True))
    return f"{second + ' - ' + first:<18}" + "".join(f"{cell:>{width}}" for cell in cells)


def describe(by_seed: Mapping[str, Mapping[int, MetaTestResult]]) -> str:
    """One line: seeds, tasks x draws per seed, eval seed."""
    parts = []
    for label, seeds in by_seed.items():
        first = next(iter(seeds.values()))
        config = first.config
        adapted = f" (k >= 1: {config['adapted_repeats']} each)" if "adapted_repeats" in config else ""
        parts.append(
            f"{label}: seeds {', '.join(map(str, seeds))}, {config.get('n_tasks')} held-out tasks x "
            f"{config.get('n_repeats')} prior draws each{adapted}"
        )
    eval_seed = next(iter(next(iter(by_seed.values())).values())).config.get("eval_seed")
    return "; ".join(parts) + f" (eval seed {eval_seed}, common random numbers)"


def replay(
    run_dir: str | os.PathLike[str], algo: str, n_tasks: int, n_repeats: int, label: str
) -> tuple[MetaTestResult, int, int]:
    """
    Meta-test a committed model again on the first ``n_tasks`` tasks and ``n_repeats`` prior draws of its committed
    meta-test (same eval seed, common random numbers: the same trajectories), and compare with the committed rows.

    :param run_dir: the harness run folder (``model.zip``, ``result.json``)
    :param algo: the zoo algorithm name of the model
    :param n_tasks: tasks replayed (at most the committed number)
    :param n_repeats: prior draws per task (at most the committed number)
    :param label: the progress bar's text
    :return: the replayed meta-test, the number of its trajectories equal to the committed ones, and their number
    """
    from sb3_pearl.zoo.rl_zoo3_coupling import ALGOS

    committed, record = committed_meta_test(run_dir)
    n_tasks, n_repeats = min(n_tasks, len(committed.tasks)), min(n_repeats, int(committed.config["n_repeats"]))
    env = gym.make(record["spec"]["family"]["env_id"], **(record["spec"]["family"].get("env_kwargs") or {}))
    model = ALGOS[algo].load(os.path.join(run_dir, "model.zip"), device="cpu")
    settings = {"n_adapt": int(committed.config["n_adapt"]), "n_repeats": n_repeats, "deterministic": True}
    try:
        result = run_meta_test(
            model, env, committed.tasks[:n_tasks], settings, int(record["eval_seed"]), progress_bar=True, description=label
        )
    finally:
        env.close()
    expected = {(int(r["task"]), int(r["repeat"]), int(r["k"])): r for r in committed.rows}
    same = sum(
        1
        for row in result.rows
        if (key := (int(row["task"]), int(row["repeat"]), int(row["k"]))) in expected
        and math.isclose(float(row["return"]), float(expected[key]["return"]), rel_tol=1e-9, abs_tol=1e-9)
        and bool(row["violated"]) == bool(expected[key]["violated"])
    )
    return result, same, len(result.rows)


def training_argv(args: argparse.Namespace) -> list[str]:
    """The ``train.py`` command line of the demo's training run."""
    return [
        *("--algo", "pearlplus", "--env", TRAIN_ENV_ID, "-f", args.log_folder, "--seed", str(args.seed)),
        *("-n", str(args.n_timesteps), "--num-threads", "1", "--eval-freq", "-1", "--verbose", "0", "-P"),
    ]


def demo_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m pearl_paper.demo``."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", default=None, help="the committed results folder (default: the checkout's results/)")
    parser.add_argument(
        "--replay-seeds", type=non_negative_int, nargs="*", default=[0, 1], help="seeds of each headline model to replay"
    )
    parser.add_argument("--n-tasks", type=positive_int, default=20, help="held-out tasks replayed per model")
    parser.add_argument("--n-repeats", type=positive_int, default=2, help="prior draws replayed per task")
    parser.add_argument("-n", "--n-timesteps", type=positive_int, default=10_000, help="env steps of the training run")
    parser.add_argument("--skip-training", action="store_true", help="only the headline and the replay")
    parser.add_argument("-f", "--log-folder", default="logs", help="zoo log folder (the training run, the figures)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the training run")
    return parser


def _headline(
    found: Mapping[str, Mapping[int, Path]], out_dir: Path
) -> tuple[dict[str, dict[int, MetaTestResult]], list[str]]:
    """Print the committed headline table and write its figure; return the meta-tests and the figure paths."""
    from sb3_pearl.evaluation.figures import plot_all  # matplotlib only when needed

    headline, remeasured = headline_meta_tests(found)
    print(f"=== {HEADLINE_TITLE} ===")
    source = f"re-measured on Table I's design, {MERGE_REMEASURE.file_name}" if remeasured else "each run's own meta-test"
    print("Committed results (" + ", ".join(f"results/{variant}" for variant in HEADLINE.values()) + f"; {source})")
    print(describe(headline))
    print("Violation: a crash or a failed merge. Intervals: Wilson over the pooled trajectories (violations),")
    print("t over seeds (returns); the difference rows are paired over seeds (t).\n")
    print(paper_table(headline))
    out_dir.mkdir(parents=True, exist_ok=True)
    pooled = {label: pool(list(seeds.values())) for label, seeds in headline.items()}
    figures = plot_all(pooled, out_dir / "headline.png", kinds=("adaptation", "violations"), title=HEADLINE_TITLE)
    for path in figures:
        print(f"Saved {path}")
    return headline, figures


def _decided(results_dir: Path) -> list[str]:
    """Print the README's headline numbers: Table I's verdicts on the re-measured meta-test (1,000 prior trajectories a
    seed, ``reproduce remeasure``) by the pre-written rules; return the printed lines."""
    from pearl_paper.reproduce.table1_verdicts import decide_family, decision_lines

    lines = decision_lines(decide_family("highway-merge", results_dir))
    print("\n=== Table I decided (the README's headline: the re-measured meta-test, the rules written before the runs) ===")
    print("\n".join(lines))
    return lines


def _replay_all(
    found: Mapping[str, Mapping[int, Path]], headline: Mapping[str, Mapping[int, MetaTestResult]], args: argparse.Namespace
) -> tuple[dict[str, dict[int, MetaTestResult]], tuple[int, int]]:
    """Replay the chosen seeds of every headline model and print their table; return them and the matching count."""
    replayed: dict[str, dict[int, MetaTestResult]] = {}
    same = total = 0
    for label, seeds in found.items():
        for seed in [seed for seed in args.replay_seeds if seed in seeds]:
            algo = "pearl" if headline[label][seed].config.get("algorithm") == "PEARL" else "pearlplus"
            result, n_same, n = replay(seeds[seed], algo, args.n_tasks, args.n_repeats, f"Replaying {label} seed {seed}")
            replayed.setdefault(label, {})[seed] = result
            same, total = same + n_same, total + n
    if replayed:
        print(f"\n=== The committed models, replayed (model.zip of seeds {', '.join(map(str, args.replay_seeds))}) ===")
        print(describe(replayed))
        print("Intervals: Wilson over the replayed trajectories (violations), t over seed x task means (returns);")
        print("a subset of each run's own meta-test in result.json (not of the re-measured one above), so wider.\n")
        print(paper_table(replayed, return_unit="task", paired=False))
        verdict = "identical to" if same == total else "DIFFERENT from"
        print(f"\n{same} of {total} replayed trajectories {verdict} their committed result.json rows.")
    return replayed, (same, total)


def _train(args: argparse.Namespace) -> MetaTestResult:
    """The short training run through train.py's pipeline; return its final meta-test."""
    print(f"\n=== A short training run: PEARL+ on {TRAIN_ENV_ID}, {args.n_timesteps:,} env steps (train.py's pipeline) ===")
    train(training_argv(args))
    log_path = os.path.join(args.log_folder, "pearlplus")
    run_dir = os.path.join(log_path, f"{TRAIN_ENV_ID}_{get_latest_run_id(log_path, EnvironmentName(TRAIN_ENV_ID))}")
    trained = MetaTestResult.from_json(os.path.join(run_dir, "meta_test.json"))
    print(f"Run folder {run_dir}: model, meta_test.csv / .json, adaptation.png")
    print(trained.format_summary())
    print(f"Replay it: python enjoy.py --algo pearlplus --env {TRAIN_ENV_ID} -f {args.log_folder} --no-render")
    return trained


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """
    The demo (module docstring).

    :param argv: command-line arguments
    :return: ``headline`` (label -> seed -> the committed meta-test the table shows, :func:`headline_meta_tests`),
        ``replay`` (label -> seed -> replayed meta-test), ``matching`` (trajectories equal to the committed ones, and
        their number), ``training`` (the training run's meta-test, absent with ``--skip-training``), ``decided`` (the
        verdict lines), ``figures`` (written paths)
    """
    args = demo_parser().parse_args(argv)
    register_algos()
    th.set_num_threads(1)
    start = time.time()
    results_dir = Path(args.results) if args.results else default_results_dir()
    found = headline_runs(results_dir)
    missing = [label for label, seeds in found.items() if not seeds]
    summary: dict[str, Any] = {"headline": {}, "replay": {}, "matching": (0, 0), "figures": []}
    if missing:  # e.g. installed from a wheel: results/ is not part of the package
        print(f"No committed runs of {', '.join(missing)} under {results_dir} (a checkout has them): no headline, no replay")
    else:
        summary["headline"], summary["figures"] = _headline(found, Path(args.log_folder, "demo"))
        summary["decided"] = _decided(results_dir)
        summary["replay"], summary["matching"] = _replay_all(found, summary["headline"], args)
    if not args.skip_training:
        summary["training"] = _train(args)
    print(f"\nDemo done in {time.time() - start:.0f} s.")
    return summary


if __name__ == "__main__":
    try:
        main()
    except ValueError as error:  # a results file that cannot stand for its run: one line naming it
        print(f"demo: error: {error}", file=sys.stderr)
        sys.exit(2)
