"""Adaptation curves of a reproduction group (matplotlib, Agg): return and violation rate against k, one line per variant.

Solid lines: the meta-test on the family's test tasks; dashed, in the same colour: the meta-test on the shifted
task distribution, where the runs have one.

Returns: mean over seeds with the 95% t interval over seeds (no bar with one seed). Violation rates:
the pooled rate with its 95% Wilson interval (defined with one seed too).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from sb3_pearl.experiments.spec import Experiment  # noqa: E402
from sb3_pearl.reproduce.report import cell_stats, last_k  # noqa: E402


def _error_bars(mean: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    return np.nan_to_num(np.maximum(np.stack([mean - low, high - mean]), 0.0))


def plot_group(
    experiment: Experiment,
    group: Mapping[str, Mapping[int, dict[str, Any]]],
    path: str | os.PathLike[str],
    title: str = "",
) -> None:
    """
    Write the adaptation curves of one (experiment, budget, family) group.

    :param experiment: the experiment (variant order and labels)
    :param group: variant -> seed -> result
    :param path: PNG path
    :param title: figure title
    """
    fig, (ax_return, ax_violation) = plt.subplots(1, 2, figsize=(10, 4))
    present = [v for v in experiment.variants if v.name in group]
    for index, variant in enumerate(present):
        colour = f"C{index}"
        for section, style in (("meta_test", "-"), ("shift", "--")):
            results = {seed: r for seed, r in group[variant.name].items() if r.get(section)}
            if not results:
                continue
            ks = list(range(last_k(results, section) + 1))
            points = [(k, s) for k, s in ((k, cell_stats(results, k, section)) for k in ks) if s is not None]
            if not points:
                continue
            offset = 0.04 * (index - (len(present) - 1) / 2) + (0.02 if section == "shift" else 0.0)  # lines apart
            x = np.array([k for k, _ in points], dtype=np.float64) + offset
            ret = np.array([s.ret.mean for _, s in points])
            ret_bars = _error_bars(ret, np.array([s.ret.low for _, s in points]), np.array([s.ret.high for _, s in points]))
            rate = np.array([s.pooled_rate for _, s in points])
            rate_bars = _error_bars(
                rate, np.array([s.pooled_low for _, s in points]), np.array([s.pooled_high for _, s in points])
            )
            seeds = max(s.n_seeds for _, s in points)
            where = "" if section == "meta_test" else ", shifted tasks"
            label = f"{variant.label} ({seeds} seed{'s' if seeds > 1 else ''}{where})"
            bars = dict(marker="o", capsize=3, color=colour, linestyle=style, label=label)
            ax_return.errorbar(x, ret, yerr=ret_bars, **bars)  # type: ignore[arg-type]
            ax_violation.errorbar(x, rate, yerr=rate_bars, **bars)  # type: ignore[arg-type]
    ax_return.set_xlabel("trajectory k (0: prior)")
    ax_return.set_ylabel("mean return (95% t over seeds)")
    ax_violation.set_xlabel("trajectory k (0: prior)")
    ax_violation.set_ylabel("violation rate (pooled, 95% Wilson)")
    ax_violation.set_ylim(-0.02, 1.02)
    for ax in (ax_return, ax_violation):
        ax.grid(alpha=0.3)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax_return.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
