"""Tables II and III on Highway-Merge with the re-measured meta-test beside the runs' own.

``reproduce remeasure`` meta-tests every finished Highway-Merge run again on Table I's larger design (100 held-out
tasks x 10 prior draws at k = 0; :data:`~pearl_paper.experiments.table1_rules.MERGE_REMEASURE`) and writes
``meta_test_large.json`` beside the run's ``result.json``. Table I's verdicts read it
(:mod:`~pearl_paper.reproduce.table1_verdicts`); :func:`remeasured_section` shows it for the other tables' rows: per
variant, the k = 0 violation rate and the k = 5 return on the re-measured design and on the run's own 200-trajectory
meta-test (the old numbers, same seeds), and the paired k = 0 difference against the table's reference row (PEARL in
Table II, alpha 0 in Table III) on the seeds both have. A run without the record is counted as not re-measured,
never mixed in.
"""

from __future__ import annotations

import os
from typing import Any

from pearl_paper.experiments import get_experiment
from pearl_paper.experiments.table1_rules import MERGE_REMEASURE
from pearl_paper.reproduce.formatting import format_interval
from pearl_paper.reproduce.layout import RESULT_FILE, RunKey, run_dir
from pearl_paper.reproduce.stats import clip_interval, paired_differences, t_interval
from pearl_paper.reproduce.table1_verdicts import RunNumbers, load_run

FAMILY = "highway-merge"
TABLES = ("merge-table2", "merge-table3")
ADAPTED_K = 5


def load_remeasured(
    experiment_name: str, results_dir: str | os.PathLike[str]
) -> tuple[dict[str, dict[int, RunNumbers]], dict[str, list[int]]]:
    """
    The re-measured runs of an experiment's Highway-Merge rows, and the finished runs that lack the record.

    :param experiment_name: ``merge-table2`` or ``merge-table3``
    :param results_dir: root of the results layout
    :return: ``{variant: {seed: numbers}}`` of the re-measured runs, ``{variant: [seeds]}`` of finished runs without
        ``meta_test_large.json``
    """
    experiment = get_experiment(experiment_name)
    runs: dict[str, dict[int, RunNumbers]] = {}
    missing: dict[str, list[int]] = {}
    for variant in experiment.variants:
        runs[variant.name], missing[variant.name] = {}, []
        for seed in experiment.seeds_of(variant.name, FAMILY):
            folder = run_dir(results_dir, RunKey(experiment.owner(variant.name), FAMILY, variant.name, seed))
            numbers = load_run(folder, read_remeasured=True)
            if numbers is not None:
                runs[variant.name][seed] = numbers
            elif (folder / RESULT_FILE).is_file():
                missing[variant.name].append(seed)
    return runs, missing


def _values(runs: dict[int, RunNumbers], k: int, key: str, own: bool) -> dict[int, float]:
    out: dict[int, float] = {}
    for seed, run in runs.items():
        summary = run.own_summary if own else run.summary
        if k in summary:
            out[seed] = float(summary[k][key])
    return out


def _cell(values: dict[int, float], scale: float = 1.0, digits: int = 1, rate: bool = False) -> str:
    """The mean over seeds with its t interval (a rate's clipped to 0-1, which no rate leaves)."""
    if not values:
        return "-"
    interval = t_interval(list(values.values()))
    return format_interval(clip_interval(interval) if rate else interval, digits, scale)


def remeasured_table(experiment_name: str, results_dir: str | os.PathLike[str]) -> list[str]:
    """The markdown table of one experiment's rows, re-measured beside their own meta-test (module docstring)."""
    experiment = get_experiment(experiment_name)
    runs, missing = load_remeasured(experiment_name, results_dir)
    if not any(runs.values()):
        return []
    reference = experiment.reference
    lines = [
        f"#### {experiment.title} ({experiment_name})",
        "",
        f"| row | seeds | k = 0 violation %, re-measured | k = 0, own meta-test | k = {ADAPTED_K} return, re-measured "
        f"| k = {ADAPTED_K} return, own | k = 0 re-measured minus {experiment.variant(reference).label.split(',')[0]} "
        "(paired, points) |",
        "|---|---|---|---|---|---|---|",
    ]
    reference_k0 = _values(runs[reference], 0, "violation_rate", own=False)
    for variant in experiment.variants:
        mine = runs[variant.name]
        if not mine:
            continue
        k0 = _values(mine, 0, "violation_rate", own=False)
        if variant.name == reference:
            paired = "reference"
        else:
            diffs = paired_differences(k0, reference_k0)
            paired = f"{_cell(diffs, 100)} ({len(diffs)} seeds)" if diffs else "-"
        declared = len(experiment.seeds_of(variant.name, FAMILY))
        own_k0 = _values(mine, 0, "violation_rate", own=True)
        returns = [_cell(_values(mine, ADAPTED_K, "return_mean", own=own), digits=2) for own in (False, True)]
        lines.append(
            f"| {variant.label} | {len(mine)} of {declared} | {_cell(k0, 100, rate=True)} | {_cell(own_k0, 100, rate=True)} "
            f"| {returns[0]} | {returns[1]} | {paired} |"
        )
    lacking = [f"{name} seed(s) {seeds}" for name, seeds in missing.items() if seeds]
    if lacking:
        lines += ["", "Finished but not re-measured yet (left out above): " + "; ".join(lacking) + "."]
    return lines + [""]


def remeasured_section(results_dir: str | os.PathLike[str]) -> list[str]:
    """The markdown of Tables II and III re-measured (empty when no run has the record)."""
    tables = [line for name in TABLES for line in remeasured_table(name, results_dir)]
    if not tables:
        return []
    design = (
        f"{MERGE_REMEASURE.n_tasks} held-out tasks x {MERGE_REMEASURE.prior_repeats} prior draws at k = 0 and "
        f"x {MERGE_REMEASURE.adapted_repeats} at k >= 1 a seed, common random numbers"
    )
    header: list[Any] = [
        "### Tables II and III on Highway-Merge, re-measured",
        "",
        f"Each finished run's model meta-tested again on Table I's design ({design}), without retraining "
        "(`python -m pearl_paper.reproduce remeasure`); the run's own meta-test (20 tasks x 10 prior draws) beside it "
        "on the same seeds. Means over seeds with 95% t intervals (a rate's clipped to 0-100); the seeds column counts "
        "the re-measured runs of the seeds the row declares. Rows with different seeds are not paired down a column: "
        "the last column pairs each row with the table's reference on the seeds both have. The rows' own tables below "
        "keep the runs' own numbers.",
        "",
    ]
    return header + tables
