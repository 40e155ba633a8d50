"""Statistics of the meta-test: the summary per trajectory k and its interval / tail-risk estimators.

The summary per k (:func:`summarize`): mean and std of the return, the violation rate with its
95% Wilson interval, the CVaR_10% of the return over tasks and the cumulative violations up to k.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

SUMMARY_COLUMNS = (
    "k",
    "n",
    "return_mean",
    "return_std",
    "violation_rate",
    "violation_ci_low",
    "violation_ci_high",
    "return_cvar10",
    "cum_violations",
)
WILSON_Z95 = 1.959963984540054


def wilson_interval(successes: int, n: int, z: float = WILSON_Z95) -> tuple[float, float]:
    """
    Wilson score interval of a binomial proportion (95% by default).

    :param successes: number of positive outcomes
    :param n: number of trials
    :param z: normal quantile of the interval
    :return: (low, high); (nan, nan) when ``n == 0``
    """
    if n <= 0:
        return math.nan, math.nan
    p = successes / n
    denom = 1.0 + z**2 / n
    centre = (p + z**2 / (2 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z**2 / (4 * n**2)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def cvar(values: Sequence[float] | np.ndarray, alpha: float = 0.1) -> float:
    """
    Conditional value at risk of returns: the mean of the worst ``ceil(alpha * n)`` values (at least one).

    :param values: returns (higher is better)
    :param alpha: tail share
    :return: the lower-tail mean; nan for no values
    """
    array = np.sort(np.asarray(values, dtype=np.float64))
    if array.size == 0:
        return math.nan
    n_tail = max(1, math.ceil(alpha * array.size - 1e-9))
    return float(array[:n_tail].mean())


def summarize(rows: Sequence[dict[str, Any]], alpha: float = 0.1, extra_keys: Sequence[str] = ()) -> list[dict[str, Any]]:
    """
    The summary per k of meta-test rows.

    - ``return_mean``, ``return_std`` (population std) over all (task, repeat) trajectories at k;
    - ``violation_rate``: share of those trajectories with any cost, ``violation_ci_low/high`` its
      95% Wilson interval;
    - ``return_cvar10``: CVaR_alpha over tasks of the per-task return (mean over repeats);
    - ``cum_violations``: violating trajectories among 0..k, averaged over (task, repeat);
    - ``<key>_mean`` for every key of ``extra_keys`` present in the rows (numeric family extras such
      as the merge family's ``b_min``; nan values ignored).

    :param rows: rows as produced by :func:`sb3_pearl.evaluation.meta_test.meta_test`
    :param alpha: tail share of the CVaR
    :param extra_keys: per-trajectory entries to average, in this order
    :return: one dict per k, in increasing k
    """
    if not rows:
        return []
    present_keys = [key for key in extra_keys if any(key in row for row in rows)]
    ks = sorted({int(row["k"]) for row in rows})
    episodes = sorted({(row["task"], row["repeat"]) for row in rows})
    violated = {(row["task"], row["repeat"], int(row["k"])): bool(row["violated"]) for row in rows}
    summary = []
    for k in ks:
        at_k = [row for row in rows if int(row["k"]) == k]
        returns = np.array([row["return"] for row in at_k], dtype=np.float64)
        n_violated = int(sum(bool(row["violated"]) for row in at_k))
        low, high = wilson_interval(n_violated, len(at_k))
        per_task: dict[Any, list[float]] = {}
        for row in at_k:
            per_task.setdefault(row["task"], []).append(float(row["return"]))
        cum = [sum(violated.get((task, repeat, j), False) for j in ks if j <= k) for task, repeat in episodes]
        entry: dict[str, Any] = {
            "k": k,
            "n": len(at_k),
            "return_mean": float(returns.mean()),
            "return_std": float(returns.std()),
            "violation_rate": n_violated / len(at_k),
            "violation_ci_low": low,
            "violation_ci_high": high,
            "return_cvar10": cvar([float(np.mean(v)) for v in per_task.values()], alpha),
            "cum_violations": float(np.mean(cum)),
        }
        for key in present_keys:
            values = np.array([float(row.get(key, math.nan)) for row in at_k], dtype=np.float64)
            finite = values[~np.isnan(values)]
            entry[f"{key}_mean"] = float(finite.mean()) if finite.size else math.nan
        summary.append(entry)
    return summary


def format_summary_table(entries: Sequence[dict[str, Any]]) -> str:
    """
    Plain-text table of summary entries: k, return mean +- std, CVaR_10%, violation rate [95% CI], cumulative violations.

    :param entries: summary dicts
    :return: the table
    """
    measures = [(key, label) for key, label in JOB_MEASURES.items() if any(key in e for e in entries)]
    header = f"{'k':>3} {'return':>20} {'CVaR10%':>10} {'viol. rate':>10} {'95% CI':>15} {'cum. viol.':>10}"
    lines = [header + "".join(f" {label:>20}" for _, label in measures)]
    for e in entries:
        ret = f"{e['return_mean']:.2f} +- {e['return_std']:.2f}"
        ci = f"[{e['violation_ci_low']:.2f}, {e['violation_ci_high']:.2f}]"
        rates = f"{e['violation_rate']:>10.2f} {ci:>15} {e['cum_violations']:>10.2f}"
        extra = "".join(f" {e.get(key, math.nan):>20.2f}" for key, _ in measures)
        lines.append(f"{e['k']:>3} {ret:>20} {e['return_cvar10']:>10.2f} {rates}{extra}")
    return "\n".join(lines)


def _prior_posterior_cells(entry: dict[str, Any]) -> list[str]:
    """The cells of one trajectory k in :func:`format_prior_posterior_table`, in the order of its row labels."""
    rate, low, high = (100 * entry[key] for key in ("violation_rate", "violation_ci_low", "violation_ci_high"))
    return [
        f"{entry['return_mean']:.1f} +- {entry['return_std']:.1f}",
        f"{entry['return_cvar10']:.1f}",
        f"{rate:.0f} [{low:.0f}, {high:.0f}]",
        f"{entry['cum_violations']:.2f}",
    ]


PRIOR_POSTERIOR_ROWS = ("return, mean +- std", "return, CVaR 10%", "violations, % [95%]", "cum. violations")
# A family's own measure of the job, shown beside return and violations where the family records it per trajectory
# (its ``trajectory_info_keys``): summary key -> row label.
# Velocity families: the mean over the trajectory's steps of |v - v*|; goal families: the distance to the goal at the
# trajectory's last step.
JOB_MEASURES = {"velocity_error_mean": "velocity error, m/s", "distance_mean": "final goal distance"}


def format_prior_posterior_table(entries: Sequence[dict[str, Any]], max_columns: int = 6) -> str:
    """
    Summary entries side by side, one column per trajectory k: the prior (k = 0) and the posterior after k = 1, 2, ...
    trajectories. Rows (:data:`PRIOR_POSTERIOR_ROWS`): the return (mean +- std over the trajectories at k), its
    CVaR_10% over tasks, the violation rate (%, with its 95% Wilson interval) and the cumulative violations up to k.
    More than ``max_columns`` trajectories wrap into blocks of columns.

    :param entries: summary dicts (:func:`summarize`), in increasing k
    :param max_columns: trajectories per block of columns (at least 1)
    :return: the table
    """
    label_width, width, step = 22, 17, max(1, max_columns)
    blocks = []
    for start in range(0, len(entries), step):
        block = entries[start : start + step]
        titles = [f"k = {entry['k']}" + (" (prior)" if entry["k"] == 0 else "") for entry in block]
        cells = [_prior_posterior_cells(entry) for entry in block]
        labels = list(PRIOR_POSTERIOR_ROWS)
        for key, label in JOB_MEASURES.items():
            if any(key in entry for entry in block):
                labels.append(label)
                for column, entry in zip(cells, block):
                    column.append(f"{entry.get(key, math.nan):.2f}")
        lines = [" " * label_width + "".join(f"{title:>{width}}" for title in titles)]
        for row, label in enumerate(labels):
            lines.append(f"{label:<{label_width}}" + "".join(f"{column[row]:>{width}}" for column in cells))
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


__all__ = [
    "JOB_MEASURES",
    "PRIOR_POSTERIOR_ROWS",
    "SUMMARY_COLUMNS",
    "WILSON_Z95",
    "cvar",
    "format_prior_posterior_table",
    "format_summary_table",
    "summarize",
    "wilson_interval",
]
