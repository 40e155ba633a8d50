"""Figures of the meta-test (matplotlib, Agg backend): adaptation curves, violation bars, b_min scatter, step traces.

Command line, over one or more run folders (each holding ``meta_test.json``) or JSON files::

    python -m sb3_pearl.plots logs/pearl/SafePointGoalMeta-v0_1 logs/pearlplus/SafePointGoalMeta-v0_1 -o cmp.png

writes ``cmp.png`` (adaptation curves: return and violation rate vs k, one line per run; without ``-o``:
``plots.png`` in the first run's folder), ``cmp_violations.png`` (violation-rate bars at k = 0, 1, 3, 5)
and, when the runs recorded them, ``cmp_b_min.png`` (the rows hold ``b_min``: the merge family) and
``cmp_speed.png`` (per-step traces: the first of the family's ``step_trace_keys`` found, e.g. the merge
family's ``ego_speed``).
``--kind`` picks one figure.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from sb3_pearl.common.atomic import atomic_path  # noqa: E402
from sb3_pearl.evaluation.meta_test import PAPER_KS, MetaTestResult, read_json  # noqa: E402

if TYPE_CHECKING:
    from sb3_pearl.envs.task_protocol import Task
    from sb3_pearl.pearl.diagnostics.rollouts import FixedZRollout

KINDS = ("adaptation", "violations", "b_min", "speed")
# The merge family's per-trajectory minimum braking at the merge [m/s^2] (a trajectory info key of its rows).
B_MIN_KEY = "b_min"


# The first figure's name without -o (next to the run's own adaptation.png, which the final meta-test wrote).
DEFAULT_OUTPUT = "plots.png"


def load_run(path: str | os.PathLike[str]) -> tuple[str, MetaTestResult]:
    """
    Read a run's meta-test: train.py's ``meta_test.json`` or the reproduction harness's ``result.json`` (its
    ``meta_test`` section, the same record: :mod:`sb3_pearl.evaluation.held_out`).

    :param path: a run folder (with ``meta_test.json`` or ``result.json``) or the JSON file itself
    :return: a label (the algorithm's zoo name or the harness variant, else the folder name) and the result
    """
    path = Path(path)
    json_path = path / "meta_test.json" if path.is_dir() else path
    if path.is_dir() and not json_path.is_file() and (path / "result.json").is_file():
        json_path = path / "result.json"
    if not json_path.is_file():
        raise FileNotFoundError(
            f"{json_path} not found: pass a run folder written by train.py or by the harness (or its meta_test.json)"
        )
    if json_path.name == "result.json":  # a harness run: the held-out meta-test record, labelled by its variant
        harness = read_json(json_path)
        return str(harness["variant"]), MetaTestResult.from_dict(harness["meta_test"])
    result = MetaTestResult.from_json(json_path)
    label = str(result.config.get("algo") or json_path.parent.parent.name or json_path.parent.name)
    return label, result


def load_runs(paths: Sequence[str | os.PathLike[str]], labels: Sequence[str] | None = None) -> dict[str, MetaTestResult]:
    """
    Read several runs; labels that repeat get the run folder's name appended.

    :param paths: run folders or JSON files
    :param labels: explicit labels (same length as ``paths``)
    :return: results by label, in order
    """
    if labels is not None and len(labels) != len(paths):
        raise ValueError(f"got {len(labels)} labels for {len(paths)} runs")
    loaded = [load_run(p) for p in paths]
    names = list(labels) if labels is not None else [label for label, _ in loaded]
    runs: dict[str, MetaTestResult] = {}
    for name, path, (_, result) in zip(names, paths, loaded):
        key = name if name not in runs and names.count(name) == 1 else f"{name} ({Path(path).name})"
        runs[key] = result
    return runs


def _yerr(rate: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Asymmetric error bars of an interval, never negative (nan intervals give no bar)."""
    return np.nan_to_num(np.maximum(np.stack([rate - low, high - rate]), 0.0))


def _save(fig: Figure, path: str | os.PathLike[str], title: str = "") -> None:
    """Lay out, title (if any), write (atomically) and close a figure."""
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)


def plot_adaptation(runs: Mapping[str, MetaTestResult], path: str | os.PathLike[str], title: str = "") -> None:
    """
    Adaptation curves: mean return (+- std) and violation rate (95% Wilson interval) against k, one line per run.

    :param runs: results by label
    :param path: PNG file
    :param title: figure title
    """
    fig, (ax_ret, ax_viol) = plt.subplots(1, 2, figsize=(10, 3.8))
    for label, result in runs.items():
        ks = np.array([e["k"] for e in result.summary])
        mean = np.array([e["return_mean"] for e in result.summary], dtype=float)
        std = np.array([e["return_std"] for e in result.summary], dtype=float)
        (line,) = ax_ret.plot(ks, mean, marker="o", label=label)
        ax_ret.fill_between(ks, mean - std, mean + std, color=line.get_color(), alpha=0.15)
        rate = np.array([e["violation_rate"] for e in result.summary], dtype=float)
        low = np.array([e["violation_ci_low"] for e in result.summary], dtype=float)
        high = np.array([e["violation_ci_high"] for e in result.summary], dtype=float)
        ax_viol.errorbar(ks, rate, yerr=_yerr(rate, low, high), marker="o", capsize=3, label=label, color=line.get_color())
    ax_ret.set_xlabel("trajectory k (0 = prior)")
    ax_ret.set_ylabel("return")
    ax_ret.set_title("return (mean +- std)")
    ax_viol.set_xlabel("trajectory k (0 = prior)")
    ax_viol.set_ylabel("violation rate")
    ax_viol.set_ylim(-0.02, 1.02)
    ax_viol.set_title("violation rate (95% CI)")
    for ax in (ax_ret, ax_viol):
        ax.grid(alpha=0.3)
        ax.xaxis.get_major_locator().set_params(integer=True)  # type: ignore[call-arg]
    ax_ret.legend(fontsize="small")
    _save(fig, path, title)


def plot_violation_bars(
    runs: Mapping[str, MetaTestResult], path: str | os.PathLike[str], ks: Sequence[int] = PAPER_KS, title: str = ""
) -> None:
    """
    Violation rate at the paper's columns (k = 0, 1, 3, 5) as grouped bars with 95% intervals.

    :param runs: results by label
    :param path: PNG file
    :param ks: the trajectories shown
    :param title: figure title
    """
    fig, ax = plt.subplots(figsize=(max(5, 1.5 * len(ks) * max(1, len(runs)) / 2), 3.8))
    width = 0.8 / max(1, len(runs))
    for i, (label, result) in enumerate(runs.items()):
        entries = [e for e in result.summary if e["k"] in ks]
        xs = np.array([list(ks).index(e["k"]) for e in entries]) + (i - (len(runs) - 1) / 2) * width
        rate = np.array([e["violation_rate"] for e in entries], dtype=float)
        low = np.array([e["violation_ci_low"] for e in entries], dtype=float)
        high = np.array([e["violation_ci_high"] for e in entries], dtype=float)
        ax.bar(xs, rate, width, yerr=_yerr(rate, low, high), capsize=3, label=label)
    ax.set_xticks(range(len(ks)), [f"{k} traj." for k in ks])
    ax.set_ylabel("violation rate")
    ax.set_ylim(0, 1.02)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize="small")
    ax.set_title(title or "violation rate before (0) and after adaptation")
    _save(fig, path)


def plot_prior_paths(
    paths: Sequence[Sequence[FixedZRollout]],
    tasks: Sequence[Task],
    path: str | os.PathLike[str],
    hazard_radius: float | None = None,
    title: str = "",
) -> None:
    """
    The prior policy's k = 0 paths on point-robot tasks: one panel per task, one line per prior draw.

    Red lines entered a hazard (``cost > 0``), grey ones did not; the task's goal is a star and its hazard
    (``task["hazard"]``, drawn when ``hazard_radius`` is given) a red disc. The start is the origin.

    :param paths: ``paths[j][i]``: task j, draw i (:func:`sb3_pearl.pearl.diagnostics.paths.prior_paths`)
    :param tasks: the tasks, in the order of ``paths``
    :param path: PNG path
    :param hazard_radius: the family's hazard radius (None: no hazard drawn)
    :param title: figure title
    """
    if len(paths) != len(tasks) or not paths:
        raise ValueError(f"need one list of rollouts per task, got {len(paths)} for {len(tasks)} tasks")
    n = len(tasks)
    columns = min(n, 4)
    rows = (n + columns - 1) // columns
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 3.2 * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    for ax, task, rollouts in zip(axes.flat, tasks, paths):
        if hazard_radius is not None and "hazard" in task:
            ax.add_patch(plt.Circle(tuple(task["hazard"]), hazard_radius, color="tab:red", alpha=0.2, linewidth=0))
        for rollout in rollouts:
            xy = rollout.observations[:, :2]  # (T + 1, 2) positions
            colour, alpha = ("tab:red", 0.9) if rollout.violated else ("0.35", 0.6)
            ax.plot(xy[:, 0], xy[:, 1], color=colour, alpha=alpha, linewidth=1)
            ax.plot(xy[-1, 0], xy[-1, 1], marker=".", color=colour, alpha=alpha)
        if "goal" in task:
            ax.plot(*task["goal"][:2], marker="*", markersize=14, color="tab:green", markeredgecolor="black")
        ax.plot(0.0, 0.0, marker="s", color="black", markersize=4)
        violated = sum(r.violated for r in rollouts)
        ax.set_title(f"{violated}/{len(rollouts)} in the hazard", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    _save(fig, path, title)


def has_row_values(runs: Mapping[str, MetaTestResult], key: str) -> bool:
    """Whether any run's rows hold a finite value of the per-trajectory entry ``key``."""
    return any(np.isfinite(float(row.get(key, np.nan))) for result in runs.values() for row in result.rows)


def has_b_min(runs: Mapping[str, MetaTestResult]) -> bool:
    """Whether any run recorded the merge family's ``b_min``."""
    return has_row_values(runs, B_MIN_KEY)


def plot_b_min(runs: Mapping[str, MetaTestResult], path: str | os.PathLike[str], title: str = "") -> None:
    """
    b_min (the paper's minimum braking at the merge, m/s^2) of every merged trajectory against k, one colour per run.

    :param runs: results by label
    :param path: PNG file
    :param title: figure title
    """
    fig, ax = plt.subplots(figsize=(6, 3.8))
    rng = np.random.default_rng(0)
    offsets = np.linspace(-0.2, 0.2, max(1, len(runs))) if len(runs) > 1 else np.zeros(1)
    for offset, (label, result) in zip(offsets, runs.items()):
        rows = [row for row in result.rows if np.isfinite(float(row.get(B_MIN_KEY, np.nan)))]
        ks = np.array([row["k"] for row in rows], dtype=float)
        values = np.array([row[B_MIN_KEY] for row in rows], dtype=float)
        ax.scatter(ks + offset + rng.uniform(-0.05, 0.05, len(ks)), values, s=12, alpha=0.7, label=label)
    ax.set_xlabel("trajectory k (0 = prior)")
    ax.set_ylabel("b_min [m/s^2]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    ax.set_title(title or "minimum braking at the merge")
    _save(fig, path)


def trace_keys(runs: Mapping[str, MetaTestResult]) -> list[str]:
    """The per-step trace keys the runs hold, in the order their families declare them (``step_trace_keys``)."""
    keys: dict[str, None] = {}
    for result in runs.values():
        keys.update((key, None) for key in result.trace_keys if any(key in trace for trace in result.traces))
    return list(keys)


def has_traces(runs: Mapping[str, MetaTestResult], key: str | None = None) -> bool:
    """Whether any run recorded per-step traces of ``key`` (None: of any key)."""
    if key is None:
        return bool(trace_keys(runs))
    return any(key in trace for result in runs.values() for trace in result.traces)


def plot_speed_profiles(
    runs: Mapping[str, MetaTestResult],
    path: str | os.PathLike[str],
    key: str | None = None,
    after_k: int | None = None,
    title: str = "",
) -> None:
    """
    Step-trace profiles (e.g. the merge family's ego speed) before (k = 0) and after adaptation (k = ``after_k``,
    default the last k): one row per run.

    :param runs: results by label
    :param path: PNG file
    :param key: the traced info entry (None: the first one the runs hold, see :func:`trace_keys`)
    :param after_k: the trajectory shown as "after adaptation"
    :param title: figure title
    """
    if key is None:
        keys = trace_keys(runs)
        if not keys:
            raise ValueError("plot_speed_profiles: the runs hold no per-step traces (their env declares no step_trace_keys)")
        key = keys[0]
    n = max(1, len(runs))
    fig, axes = plt.subplots(n, 2, figsize=(10, 3 * n), squeeze=False, sharey=True)
    for row_axes, (label, result) in zip(axes, runs.items()):
        last = after_k if after_k is not None else max((t["k"] for t in result.traces), default=0)
        for ax, k, name in (
            (row_axes[0], 0, "before adaptation (k = 0)"),
            (row_axes[1], last, f"after adaptation (k = {last})"),
        ):
            for trace in result.traces:
                if trace["k"] == k and key in trace:
                    ax.plot(np.arange(len(trace[key])), trace[key], alpha=0.6, lw=1)
            ax.set_title(f"{label}: {name}", fontsize="medium")
            ax.set_xlabel("policy step")
            ax.grid(alpha=0.3)
        row_axes[0].set_ylabel(f"{key} [m/s]" if "speed" in key else key)
    _save(fig, path, title)


def plot_all(
    runs: Mapping[str, MetaTestResult], output: str | os.PathLike[str], kinds: Sequence[str] = KINDS, title: str = ""
) -> list[str]:
    """
    Write the figures of ``kinds`` that the runs have data for.

    The first figure goes to ``output``; the others next to it as ``<stem>_<kind>.png``.

    :param runs: results by label
    :param output: PNG path
    :param kinds: among :data:`KINDS`
    :param title: figure title
    :return: the written paths
    """
    output = Path(output)
    written: list[str] = []
    for kind in kinds:
        if kind == "b_min" and not has_b_min(runs):
            continue
        if kind == "speed" and not has_traces(runs):
            continue
        path = output if not written else output.with_name(f"{output.stem}_{kind}{output.suffix or '.png'}")
        if kind == "adaptation":
            plot_adaptation(runs, path, title)
        elif kind == "violations":
            plot_violation_bars(runs, path, title=title)
        elif kind == "b_min":
            plot_b_min(runs, path, title)
        elif kind == "speed":
            plot_speed_profiles(runs, path, title=title)
        else:
            raise ValueError(f"unknown figure kind {kind!r}: expected one of {KINDS}")
        written.append(str(path))
    return written


def default_output(run: str | os.PathLike[str]) -> Path:
    """
    Where the figures go without ``-o``: :data:`DEFAULT_OUTPUT` in the run's folder (the folder of a JSON file given).

    :param run: the first run folder or ``meta_test.json`` of the command line
    :return: the path of the first figure
    """
    path = Path(run)
    return (path if path.is_dir() else path.parent) / DEFAULT_OUTPUT


def main(argv: Sequence[str] | None = None) -> None:
    """Command line: ``python -m sb3_pearl.plots RUN_DIR [RUN_DIR ...] -o out.png``."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run folders (logs/<algo>/<EnvId>_<n>) or meta_test.json files")
    parser.add_argument(
        "-o",
        "--output",
        default=None,
        help=f"PNG file of the first figure (default: {DEFAULT_OUTPUT} in the first run's folder)",
    )
    parser.add_argument("--kind", choices=[*KINDS, "all"], default="all", help="which figure (default: every one with data)")
    parser.add_argument("--labels", nargs="+", default=None, help="legend labels, one per run")
    parser.add_argument("--title", default="", help="figure title")
    args = parser.parse_args(argv)
    if args.labels is not None and len(args.labels) != len(args.runs):
        parser.error(f"--labels: {len(args.labels)} labels for {len(args.runs)} runs (give one per run)")
    if args.output is not None and not Path(args.output).resolve().parent.is_dir():
        parser.error(f"-o/--output: the folder of {args.output} does not exist")
    try:  # bad runs: one line naming the path, no traceback
        runs = load_runs(args.runs, args.labels)
    except (FileNotFoundError, ValueError) as error:
        parser.error(str(error))
    kinds = KINDS if args.kind == "all" else (args.kind,)
    output = args.output or default_output(args.runs[0])
    for path in plot_all(runs, output, kinds, args.title):
        print(f"Saved {path}")


if __name__ == "__main__":
    main()
