"""The results of the layout grouped by (experiment, budget, family) and the statistics of one (variant, k) cell: what
the report's tables (:mod:`~pearl_paper.reproduce.report`) and its figures (:mod:`~pearl_paper.reproduce.figures`) read."""

from __future__ import annotations

import math
import os
import re
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pearl_paper.experiments import EXPERIMENTS
from pearl_paper.reproduce.layout import RESULT_FILE, check_result_path, find_results, read_result
from pearl_paper.reproduce.stats import Interval, clip_interval, t_interval
from sb3_pearl.evaluation.statistics import wilson_interval

METRIC_KEYS = {"violation": "violation_rate", "return": "return_mean"}

# variant -> seed -> result.json
Group = dict[str, dict[int, dict[str, Any]]]


@dataclass(frozen=True)
class CellStats:
    """Statistics of one (variant, k) cell over seeds."""

    violation: Interval  # of the rate (0-1) over seeds, clipped to 0-1
    pooled_rate: float
    pooled_low: float
    pooled_high: float
    ret: Interval
    n_trajectories: int
    n_seeds: int


def load_groups(results_dir: str | os.PathLike[str]) -> dict[tuple[str, str, str], Group]:
    """
    Every complete run under ``results_dir``, grouped; an experiment's group holds its declared seeds only (a shared
    variant's owner may hold more seeds, run for another experiment that declares them).

    Every result must own its place: two files for one run, or a file whose fields disagree with its folder
    (:func:`~pearl_paper.reproduce.layout.check_result_path`) are refused, the files named, never one silently kept.

    :param results_dir: root of the results layout
    :return: (experiment, budget preset, family) -> variant -> seed -> result
    """
    groups: dict[tuple[str, str, str], Group] = defaultdict(lambda: defaultdict(dict))
    owners: dict[tuple[str, ...], Path] = {}
    results = [(path, read_result(path)) for path in find_results(results_dir)]
    for path, result in results:  # duplicates first: their message names both files (a backup copy beside the runs)
        run = tuple(str(result[key]) for key in ("experiment", "budget_preset", "family", "variant", "seed"))
        if run in owners:
            raise ValueError(
                f"{owners[run]} and {path} both hold the result of {' '.join(run[:2])} {' '.join(run[2:4])} seed{run[4]}: "
                "a report takes one result per run; delete or move the copy"
            )
        owners[run] = path
    for path, result in results:
        check_result_path(path, result)
        key = (result["experiment"], result["budget_preset"], result["family"])
        groups[key][result["variant"]][int(result["seed"])] = result
    return _shared_and_declared(groups)


def load_partway_curves(results_dir: str | os.PathLike[str]) -> dict[tuple[str, str, str], Group]:
    """
    The learning curves so far of the runs in progress, grouped as :func:`load_groups` groups complete runs: a run
    folder with a readable checkpoint and a ``curve.csv`` but no result.json (a run committed part-way, to be resumed).
    Folders that are not runs of a declared experiment and family, or whose checkpoint cannot be read, are left out.

    :param results_dir: root of the results layout
    :return: (experiment, budget preset, family) -> variant -> seed -> ``{"experiment", "budget_preset", "family",
        "variant", "seed", "num_timesteps", "curve"}`` (the fields of a result.json that the curve figure and table read)
    """
    from pearl_paper.reproduce.checkpoint import RunCheckpoint
    from pearl_paper.reproduce.curve import CURVE_FILE, read_curve

    groups: dict[tuple[str, str, str], Group] = defaultdict(lambda: defaultdict(dict))
    for curve_path in sorted(Path(results_dir).glob(f"*/*/*/seed*/{CURVE_FILE}")):
        folder = curve_path.parent
        experiment_name, family, variant = folder.parts[-4:-1]
        experiment = EXPERIMENTS.get(experiment_name)
        seed = re.fullmatch(r"seed(\d+)", folder.name)
        if (folder / RESULT_FILE).exists() or experiment is None or seed is None:
            continue
        if family not in {f.name for f in experiment.families} or variant not in {v.name for v in experiment.variants}:
            continue
        try:
            state = RunCheckpoint(folder).read_state()
        except ValueError:  # an unreadable state.json: `reproduce run` says what to do with it
            continue
        rows = read_curve(curve_path)
        if state is None or not rows:
            continue
        budget = str((state.get("identity") or {}).get("budget_preset", "unknown"))
        groups[(experiment_name, budget, family)][variant][int(seed.group(1))] = {
            "experiment": experiment_name, "budget_preset": budget, "family": family, "variant": variant,
            "seed": int(seed.group(1)), "num_timesteps": int(state.get("num_timesteps", 0)), "curve": rows,
        }  # fmt: skip
    return _shared_and_declared(groups)


def _shared_and_declared(groups: dict[tuple[str, str, str], Group]) -> dict[tuple[str, str, str], Group]:
    """Shared variants' runs joined to every experiment that shares them; each experiment's declared seeds only."""
    # Shared variants: the owner's runs join the groups of every experiment that shares them (when it has runs).
    for (experiment_name, budget, family), group in list(groups.items()):
        for other in EXPERIMENTS.values():
            for variant, owner in other.shared.items():
                if owner == experiment_name and variant in group and (other.name, budget, family) in groups:
                    groups[(other.name, budget, family)][variant] = group[variant]

    def declared(key: tuple[str, str, str], variant: str, seeds: dict[int, dict[str, Any]]) -> dict[int, dict[str, Any]]:
        experiment = EXPERIMENTS.get(key[0])
        if experiment is None:
            return dict(seeds)
        return {seed: r for seed, r in seeds.items() if seed in experiment.seeds_of(variant, key[2])}

    kept = {
        key: {variant: runs for variant, seeds in group.items() if (runs := declared(key, variant, seeds))}
        for key, group in sorted(groups.items())
    }
    return {key: group for key, group in kept.items() if group}


def summary_at(result: dict[str, Any], k: int, section: str = "meta_test") -> dict[str, Any] | None:
    """The summary entry of trajectory ``k`` of a run's meta-test (``section``: ``meta_test`` or ``shift``)."""
    block = result.get(section) or {}
    for entry in block.get("summary", []):
        if int(entry["k"]) == k:
            return entry
    return None


def last_k(results: Mapping[int, dict[str, Any]], section: str = "meta_test") -> int:
    """The last trajectory index K of the runs' meta-tests (the smallest over runs)."""
    ks = [max(int(e["k"]) for e in (r.get(section) or {}).get("summary", [{"k": 0}])) for r in results.values()]
    return min(ks) if ks else 0


def seed_values(results: Mapping[int, dict[str, Any]], k: int, metric: str, section: str = "meta_test") -> dict[int, float]:
    """Per-seed violation rate or mean return at ``k`` (seeds without that k are left out)."""
    values = {}
    for seed, result in results.items():
        entry = summary_at(result, k, section)
        value = None if entry is None else entry.get(METRIC_KEYS[metric])
        if value is not None and not (isinstance(value, float) and math.isnan(value)):
            values[seed] = float(value)
    return values


def cell_stats(results: Mapping[int, dict[str, Any]], k: int, section: str = "meta_test") -> CellStats | None:
    """
    The statistics of one (variant, k) cell.

    :param results: seed -> result of one variant
    :param k: trajectory index
    :param section: ``meta_test`` or ``shift``
    :return: the statistics, None if no run has trajectory k
    """
    entries = [e for e in (summary_at(r, k, section) for r in results.values()) if e is not None]
    if not entries:
        return None
    rates = [float(e["violation_rate"]) for e in entries]
    returns = [float(e["return_mean"]) for e in entries]
    n = [int(e["n"]) for e in entries]
    violated = sum(round(rate * count) for rate, count in zip(rates, n))
    low, high = wilson_interval(violated, sum(n))
    return CellStats(
        violation=clip_interval(t_interval(rates)),  # a rate's interval stays within 0-1
        pooled_rate=violated / sum(n),
        pooled_low=low,
        pooled_high=high,
        ret=t_interval(returns),
        n_trajectories=sum(n),
        n_seeds=len(entries),
    )
