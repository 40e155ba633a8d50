"""Adaptation curves of a reproduction group (matplotlib, Agg): return and violation rate against k, one line per variant.

Solid lines: the meta-test on the family's test tasks; dashed, in the same colour: the meta-test on the shifted
task distribution, where the runs have one.

Returns: mean over seeds with the 95% t interval over seeds (no bar with one seed). Violation rates:
the pooled rate with its 95% Wilson interval (defined with one seed too).

A second figure (:func:`plot_seeds`) shows what those intervals summarise: each seed's violation rate at
k = 0 and at the last k, one line per seed across the variants. The variants of a seed share the test
tasks, env seeds and z0 draws, so a line is a paired comparison.
"""

from __future__ import annotations

import itertools
import math
import os
import textwrap
from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import FuncFormatter, MaxNLocator  # noqa: E402

from pearl_paper.experiments.spec import Criterion, Experiment, Family  # noqa: E402
from pearl_paper.reproduce.cells import cell_stats, last_k, seed_values  # noqa: E402
from pearl_paper.reproduce.curve import curve_value  # noqa: E402
from pearl_paper.reproduce.formatting import seed_count  # noqa: E402


def save_figure(fig: Any, path: str | os.PathLike[str], rect: tuple[float, float, float, float] | None = None) -> None:
    """
    Lay the figure out, write it as a PNG (110 dpi, the project's figures) and free it.

    :param fig: the matplotlib figure
    :param path: PNG path
    :param rect: the area the axes fill (``tight_layout``'s; None: all of it), e.g. to leave room for a legend below
    """
    fig.tight_layout(rect=rect)
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
            label = f"{variant.label} ({seed_count(seeds)}{where})"
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
    save_figure(fig, path)


def plot_seeds(
    experiment: Experiment,
    group: Mapping[str, Mapping[int, dict[str, Any]]],
    path: str | os.PathLike[str],
    title: str = "",
) -> bool:
    """
    Write the per-seed violation rates of one group: k = 0 (left) and the last k (right), one line per seed.

    :param experiment: the experiment (variant order and labels)
    :param group: variant -> seed -> result
    :param path: PNG path
    :param title: figure title
    :return: False (and nothing written) with fewer than two seeds or two variants
    """
    present = [v for v in experiment.variants if v.name in group]
    seeds = sorted({seed for results in group.values() for seed in results})
    if len(seeds) < 2 or len(present) < 2:
        return False
    ks = sorted({0, min(last_k(group[v.name]) for v in present)})  # k = 0 and the last k (once if the same)
    width = max(4.5 * len(ks), 0.8 * len(ks) * len(present) + 3)
    fig, axes = plt.subplots(1, len(ks), figsize=(width, 4.2), sharey=True, squeeze=False)
    x = np.arange(len(present))
    for ax, k in zip(axes[0], ks):
        per_variant = [seed_values(group[v.name], k, "violation") for v in present]
        for index, seed in enumerate(seeds):
            rates = np.array([values.get(seed, np.nan) for values in per_variant])  # (n_variants,), nan: not run
            ax.plot(x, rates, marker="o", color=f"C{index}", label=f"seed {seed}", alpha=0.85)
        means = np.array([np.mean(list(values.values())) if values else np.nan for values in per_variant])
        ax.plot(x, means, color="black", linewidth=2.5, marker="_", markersize=18, linestyle="none", label="mean")
        ax.set_title(f"k = {k}" + (" (prior policy)" if k == 0 else f" (after {k} trajectories)"))
        ax.set_xticks(x)
        ax.set_xticklabels([v.label for v in present], rotation=25, ha="right", fontsize=8)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("violation rate")
    axes[0, -1].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    save_figure(fig, path)
    return True


def _wrap(text: str, width: int) -> str:
    """``text`` broken into lines of at most ``width`` characters (axis labels)."""
    return "\n".join(textwrap.wrap(text, width))


def env_steps_label(steps: float, _position: object = None) -> str:
    """
    An env-step tick: ``0``, ``200k``, ``1.5M`` (full numbers overlap on a 500k-1.5M axis).

    :param steps: the tick's env steps
    :param _position: the tick's index (matplotlib's ``FuncFormatter`` passes it; unused)
    :return: the label
    """
    if abs(steps) >= 1e6:
        return f"{steps / 1e6:g}M"
    if abs(steps) >= 1e3:
        return f"{steps / 1e3:g}k"
    return f"{steps:g}"


def curve_panels(family: Family, checked: Sequence[tuple[int, Criterion]]) -> list[tuple[str, float, str, float | None]]:
    """
    The panels of a learning-curve figure: (curve column, scale, axis label, competence bar).

    The reference's metric, the prior policy's (k = 0) return, its violation rate where the family can violate
    (not HalfCheetah-Vel), then each competence criterion the curves checked.

    :param family: the runs' family
    :param checked: (index, criterion) of the competence criteria the curves hold values of
    :return: one tuple a panel
    """
    panels: list[tuple[str, float, str, float | None]] = [
        ("reference_return", 1.0, "return of the last trajectory (reference protocol)", None),
        ("k0_return", 1.0, "k = 0 return (prior z)", None),
    ]
    if family.has_violations:
        panels.append(("k0_violation", 100.0, "k = 0 violation rate [%]", None))
    panels += [
        (f"criterion_{index}", 1.0, _wrap(f"train: {criterion.description}", 45), criterion.threshold)
        for index, criterion in checked
    ]
    return panels


def plot_curves(
    experiment: Experiment,
    group: Mapping[str, Mapping[int, dict[str, Any]]],
    path: str | os.PathLike[str],
    title: str = "",
    per_seed: bool = False,
) -> bool:
    """
    The learning curves on the test tasks (result.json ``curve``, ``pearl_paper/reproduce/curve.py``) of one group.

    First panel: the reference's metric (mean return of the last evaluation trajectory) against env steps, mean over
    seeds with the seeds' range shaded; then the prior policy's (k = 0) return and, where the family can violate, its
    violation rate; then one panel per competence criterion of the family (on training tasks, its bar dashed), when the
    curve checks competence (:func:`curve_panels`).

    :param experiment: the experiment (variant order and labels)
    :param group: variant -> seed -> result
    :param path: PNG path
    :param title: figure title
    :param per_seed: one line per seed, each to its own last point (runs in progress reach different env steps),
        instead of the mean over the env steps every seed has reached
    :return: whether a figure was written (False: no run has a curve)
    """
    curves = {
        v.name: [r["curve"] for r in group[v.name].values() if r.get("curve")] for v in experiment.variants if v.name in group
    }
    curves = {name: runs for name, runs in curves.items() if runs}
    if not curves:
        return False
    family_name = next(r["family"] for runs in group.values() for r in runs.values() if r.get("curve"))
    family = experiment.family(family_name)
    competence = family.competence
    checked = [  # (index in the family's criteria, criterion) of the criteria the curves hold values of
        (index, criterion)
        for index, criterion in enumerate(competence)
        if any(math.isfinite(curve_value(row, f"criterion_{index}")) for runs in curves.values() for row in runs[0])
    ]
    panels = curve_panels(family, checked)
    n_rows = math.ceil(len(panels) / 2)  # two panels a row
    fig, axes = plt.subplots(n_rows, 2, figsize=(10, 4 * n_rows), squeeze=False)
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    for color, (name, runs) in enumerate(curves.items()):
        label = f"{experiment.variant(name).label} ({seed_count(len(runs))})"
        if per_seed:
            seeded = [(seed, r["curve"]) for seed, r in sorted(group[name].items()) if r.get("curve")]
            variant_label = experiment.variant(name).label
            for style, (seed, rows) in zip(itertools.cycle(("-", "--", ":", "-.")), seeded):
                steps = [row["env_steps"] for row in rows]
                for ax, (key, scale, _, _) in zip(axes.flat, panels):
                    ys = [curve_value(row, key) * scale for row in rows]
                    ax.plot(steps, ys, color=f"C{color}", linestyle=style, label=f"{variant_label}, seed {seed}")
            continue
        steps = sorted(set.intersection(*(set(row["env_steps"] for row in rows) for rows in runs)))
        for ax, (key, scale, _, _) in zip(axes.flat, panels):
            by_step = [{row["env_steps"]: curve_value(row, key) * scale for row in rows} for rows in runs]
            values = np.array([[points[step] for step in steps] for points in by_step])
            ax.plot(steps, values.mean(axis=0), color=f"C{color}", label=label)
            if len(runs) > 1:
                ax.fill_between(steps, values.min(axis=0), values.max(axis=0), color=f"C{color}", alpha=0.2)
    for point in family.published_curve:  # beside ours, at its own env steps
        axes.flat[0].plot(point.env_steps, point.value, "k*", markersize=10, label=f"published: {point.value:g}")
    right = max(ax.get_xlim()[1] for ax in axes.flat[: len(panels)])
    for ax in axes.flat[: len(panels)]:  # one env-step axis for every panel (a published point may lie beyond ours)
        ax.set_xlim(0, right)
    for ax, (_, _, ylabel, bar) in zip(axes.flat, panels):
        ax.set_xlabel("env steps")
        ax.xaxis.set_major_formatter(FuncFormatter(env_steps_label))
        ax.set_ylabel(ylabel, fontsize=9)
        if bar is not None:
            ax.axhline(bar, color="black", linestyle="--", linewidth=1, label=f"competence bar ({bar:g})")
            ax.legend(fontsize=8)
    axes.flat[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    save_figure(fig, path)
    return True


def plot_prior_selection(
    experiment: Experiment,
    groups: Mapping[str, Mapping[str, Mapping[int, dict[str, Any]]]],
    path: str | os.PathLike[str],
    title: str = "",
) -> bool:
    """
    The two measures the selection rule reads (docs/pearl.md, "The selection rule"), one point per run, every family
    of ``groups`` pooled: left, the calibration of the prior term's critic (rank correlation against relative error,
    the calibrated corner shaded, the design's medians as large markers); right, the prior-optimality gaps on the
    training tasks (return against violation rate, the design's means as large markers; 0 is the scripted bar).

    :param experiment: the ``prior-critic`` experiment (variant order and labels)
    :param groups: family -> variant -> seed -> result
    :param path: PNG path
    :param title: figure title
    :return: False (and nothing written) when no run has the measures
    """
    from pearl_paper.experiments.prior_critic import DESIGNS
    from pearl_paper.reproduce.prior_report import CALIBRATED_RANK_CORR, CALIBRATED_RELATIVE_ERROR, calibration_of, run_gaps

    markers = dict(zip(groups, itertools.cycle("osD^v")))
    points: dict[str, list[tuple[str, float, float, float, float]]] = {}  # variant -> (family, rel, rank, ret, viol)
    for family, group in groups.items():
        for name, runs in group.items():
            for result in runs.values():
                _, relative_error, rank_corr = calibration_of(result)
                return_gap, violation_gap = run_gaps(result, None, "train")
                if math.isfinite(relative_error) and math.isfinite(rank_corr):
                    points.setdefault(name, []).append((family, relative_error, rank_corr, return_gap, violation_gap))
    # the designs the rule ranks (alpha 0.1), with PEARL (the reference) and the paper's form beside them
    ranked = {experiment.reference, "alpha-0.1", *(f"alpha-0.1-{design}" for design in DESIGNS)}
    present = [v for v in experiment.variants if v.name in points and v.name in ranked]
    if not present:
        return False
    fig, (ax_cal, ax_gap) = plt.subplots(1, 2, figsize=(13, 6.4))
    for index, variant in enumerate(present):
        colour = f"C{index % 10}"
        rows = np.array([p[1:] for p in points[variant.name]])  # (n_runs, 4): rel, rank, return gap, violation gap
        for family, *values in points[variant.name]:
            rel, rank, ret, viol = values
            ax_cal.scatter(rank, rel, color=colour, marker=markers[family], s=18, alpha=0.5)
            ax_gap.scatter(ret, 100 * viol, color=colour, marker=markers[family], s=18, alpha=0.5)
        label = f"{variant.label} ({len(rows)} runs)"
        ax_cal.scatter(np.median(rows[:, 1]), np.median(rows[:, 0]), color=colour, s=140, edgecolor="black", label=label)
        ax_gap.scatter(np.nanmean(rows[:, 2]), 100 * np.nanmean(rows[:, 3]), color=colour, s=140, edgecolor="black")
    ax_cal.set_yscale("log")
    low, high = ax_cal.get_ylim()
    ax_cal.fill_between([CALIBRATED_RANK_CORR, 1.0], min(low, 0.01), CALIBRATED_RELATIVE_ERROR, color="green", alpha=0.12)
    ax_cal.text(CALIBRATED_RANK_CORR + 0.02, CALIBRATED_RELATIVE_ERROR * 0.8, "calibrated", color="green", va="top")
    ax_cal.set_ylim(min(low, 0.05), high)
    ax_cal.set_xlim(min(-0.5, ax_cal.get_xlim()[0]), 1.0)
    ax_cal.set_xlabel("rank correlation of Q~(s0, a, z0) with the Monte-Carlo return")
    ax_cal.set_ylabel("relative error: mean |Q~ - MC| / mean |MC| (log)")
    ax_cal.set_title("calibration (large: median over runs)")
    ax_gap.axhline(0.0, color="black", linewidth=0.8)
    ax_gap.axvline(0.0, color="black", linewidth=0.8)
    ax_gap.set_xlabel("k = 0 return minus the scripted bar's (training tasks)")
    ax_gap.set_ylabel("k = 0 violation rate minus the bar's (points)")
    ax_gap.set_title("prior-optimality gap (large: mean over runs; bar at 0, 0)")
    for ax in (ax_cal, ax_gap):
        ax.grid(alpha=0.3)
    handles = [
        plt.Line2D([], [], marker=m, color="grey", linestyle="none", label=f"run, {family}") for family, m in markers.items()
    ]
    fig.legend(handles=ax_cal.get_legend_handles_labels()[0] + handles, fontsize=8, loc="lower center", ncol=3)
    if title:
        fig.suptitle(title)
    save_figure(fig, path, rect=(0.0, 0.16, 1.0, 1.0))
    return True


def plot_decisions(decisions: Sequence[Any], path: str | os.PathLike[str]) -> bool:
    """
    Table I's decided families side by side (:mod:`pearl_paper.reproduce.table1_verdicts`): per seed, the k = 0 violation
    rate of PEARL and PEARL+ with its Wilson 95% interval, a line joining the pair of each seed.

    :param decisions: the :class:`~pearl_paper.reproduce.table1_verdicts.FamilyDecision` of each family
    :param path: PNG path
    :return: False (and nothing written) when no family has a paired seed
    """
    shown = [decision for decision in decisions if decision.paired_seeds]
    if not shown:
        return False
    fig, axes = plt.subplots(1, len(shown), figsize=(5.2 * len(shown), 4.2), squeeze=False)
    for ax, decision in zip(axes[0], shown):
        for index, name in enumerate(decision.variants):
            runs = decision.runs[name]
            seeds = decision.paired_seeds
            rates = np.array([runs[s].summary[0]["violation_rate"] for s in seeds])  # (n_seeds,)
            low = np.array([runs[s].summary[0]["violation_ci_low"] for s in seeds])
            high = np.array([runs[s].summary[0]["violation_ci_high"] for s in seeds])
            x = np.arange(len(seeds)) + (index - 0.5) * 0.25
            label = "PEARL+ (alpha 0.1)" if index else "PEARL"
            ax.errorbar(x, rates, yerr=_error_bars(rates, low, high), fmt="o", color=f"C{index}", capsize=3, label=label)
        for position, seed in enumerate(decision.paired_seeds):
            pair = [decision.runs[name][seed].summary[0]["violation_rate"] for name in decision.variants]
            ax.plot([position - 0.125, position + 0.125], pair, color="grey", alpha=0.6)
        ax.set_xticks(np.arange(len(decision.paired_seeds)))
        ax.set_xticklabels([f"seed {s}" for s in decision.paired_seeds], rotation=45, fontsize=8)
        ax.set_ylabel("k = 0 violation rate (prior policy)")
        ax.set_title(_wrap(f"{decision.family}: safer prior {decision.prior_verdict}", 48), fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, path)
    return True


def plot_tracking(panels: Sequence[Mapping[str, Any]], path: str | os.PathLike[str]) -> bool:
    """
    Velocity tracking on the held-out tasks against the task-independent references, one panel per family: each
    task's adapted (k >= 1) velocity error against its target speed, per agent, with the error of standing still
    (``|v*|``, a line) and of the best constant velocity (``|c - v*|``, crosses).

    :param panels: per family: ``title``, ``speeds`` (shape (n_tasks,): ``|v*|``), ``constant_errors`` (shape
        (n_tasks,)) and ``errors`` (label -> shape (n_tasks,), the agent's per-task error)
    :param path: PNG path
    :return: False (and nothing written) without a panel
    """
    if not panels:
        return False
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.0), squeeze=False)
    for ax, panel in zip(axes[0], panels):
        speeds = np.asarray(panel["speeds"], dtype=np.float64)
        span = np.array([0.0, float(speeds.max())])
        ax.plot(span, span, color="grey", linestyle="--", label="standing still")
        ax.plot(speeds, panel["constant_errors"], "x", color="grey", label="best constant")
        for index, (label, errors) in enumerate(panel["errors"].items()):
            ax.plot(speeds, errors, "o", color=f"C{index}", alpha=0.8, label=label)
        ax.set_xlabel("target speed |v*| (m/s)")
        ax.set_ylabel("velocity error, k >= 1 (m/s)")
        ax.set_title(_wrap(panel["title"], 44), fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    save_figure(fig, path)
    return True
