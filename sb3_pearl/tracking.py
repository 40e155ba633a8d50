"""Velocity tracking of a trained model on a velocity family (Walker2D-vel, HalfCheetah-Vel).

The competence criterion of these families is the mean absolute error of the forward velocity per step of the
posterior trajectories (declared by the paper's harness, ``pearl_paper.experiments.families``). That one number mixes
two failures that call for different remedies:

- the *mean-speed error* ``|mean_t v_t - v*|`` of each trajectory: the policy walks at the wrong speed (a
  locomotion skill not learnt, or a task not inferred);
- the gait's *oscillation* around its own mean (``std_t v_t``): a walking gait's forward velocity swings within
  each stride, and the acceleration from rest at the start counts too.

The per-step error is never below the mean-speed error (``mean |v - v*| >= |mean v - v*|``). Regressing each
trajectory's mean speed on its target tells the two causes of a mean-speed error apart: a slope near 1 with a
large error is a task not inferred for some tasks, a slope well below 1 with the mean speed still ordered by
the target is inference that works and a gait that does not reach the speed.

Every trajectory starts from rest, so the per-step error also holds the time the policy takes to reach its speed.
The split *by part of the episode* (``parts``: the per-step error over equal step ranges of the horizon, default
four) tells a policy that reaches the target late (a large error in the first parts, a small one in the last)
from one that never reaches it (the same error in every part).

``python -m sb3_pearl.tracking RUN [RUN ...] [--plot out.png]`` reruns each harness run's competence
meta-test (its training tasks, settings and eval seed from ``result.json``: the trajectories its competence value
was measured on, where the machine and package versions are the same; it warns when the per-step error differs) with
the velocity trace, and prints the split per task and by part of the episode; ``--plot`` draws each task's mean speed
against its target and the error by part of the episode (``--bar``: the competence bar on it).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_pearl.common.checks import positive_int
from sb3_pearl.evaluation.held_out import run_meta_test
from sb3_pearl.evaluation.meta_test import MetaTestResult

VELOCITY_KEY = "x_velocity"  # the forward velocity in gymnasium's MuJoCo info dicts
TARGET_KEY = "velocity"  # the target velocity in a velocity family's task dict
REWARD_KEY = "reward_forward"  # -|v - v*| per step: recorded with the velocity so the two can be checked against each other


class TrackingError(ValueError):
    """Input the split cannot be made on (not a velocity family, no trace, not a finished harness run)."""


def error_by_part(errors: Sequence[np.ndarray], n_parts: int, horizon: int | None = None) -> list[dict[str, Any]]:
    """
    The per-step error over equal step ranges of the episode, each trajectory weighted once.

    Part ``i`` covers steps ``[floor(i H / n), floor((i + 1) H / n))`` of the horizon ``H``; its error is the mean over
    the trajectories that reach it of their mean error within it. A trajectory ended early (a fall) counts only in the
    parts it reached, so a later part describes the trajectories that survived to it (its ``n_trajectories`` says how
    many). Where every trajectory runs the whole horizon and the parts are of equal length, the parts average to the
    per-step error.

    :param errors: per trajectory, its per-step errors ``|v_t - v*|`` (steps,)
    :param n_parts: number of parts
    :param horizon: the episode's step limit (None: the longest trajectory)
    :return: per part: ``first_step``, ``end_step`` (exclusive), ``error`` (None where no trajectory reaches the part)
        and ``n_trajectories``
    """
    if n_parts < 1:
        raise ValueError(f"error_by_part: n_parts must be >= 1, got {n_parts}")
    longest = max(len(e) for e in errors)
    if horizon is None:
        horizon = longest
    elif horizon < longest:
        raise ValueError(f"error_by_part: a trajectory has {longest} steps, more than the horizon {horizon}")
    bounds = [i * horizon // n_parts for i in range(n_parts + 1)]
    parts = []
    for first, end in zip(bounds[:-1], bounds[1:]):
        means = [float(e[first:end].mean()) for e in errors if len(e) > first and end > first]
        parts.append(
            {
                "first_step": first,
                "end_step": end,
                "error": float(np.mean(means)) if means else None,
                "n_trajectories": len(means),
            }
        )
    return parts


def velocity_tracking(
    result: MetaTestResult,
    min_k: int = 1,
    velocity_key: str = VELOCITY_KEY,
    target_key: str = TARGET_KEY,
    n_parts: int = 4,
    horizon: int | None = None,
) -> dict[str, Any]:
    """
    Split the per-step velocity error of the trajectories ``k >= min_k`` into the mean-speed error and the oscillation,
    and over parts of the episode.

    :param result: a meta-test whose traces hold ``velocity_key`` and whose tasks hold ``target_key``
    :param min_k: first trajectory index counted (1: the posterior trajectories, as the competence criterion)
    :param velocity_key: per-step trace of the forward velocity
    :param target_key: task entry of the target velocity
    :param n_parts: equal step ranges of the horizon the per-step error is also split over (:func:`error_by_part`)
    :param horizon: the episode's step limit the parts divide (None: the longest trajectory)
    :return: ``per_step_error``, ``mean_speed_error``, ``oscillation`` (means over trajectories), ``slope`` and
        ``intercept`` of the least-squares line of mean speed on target (None with fewer than two distinct targets),
        ``n_trajectories``, ``tasks`` (per task: target, mean speed and the three errors, averaged over its
        trajectories) and ``parts`` (:func:`error_by_part`)
    """
    per_traj: list[tuple[int, float, float, float, float, float]] = []  # task, target, mean v, per-step, mean-speed, std
    step_errors: list[np.ndarray] = []  # per trajectory: |v_t - v*| (steps,)
    for trace in result.traces:
        if int(trace["k"]) < min_k or not trace.get(velocity_key):
            continue
        task = int(trace["task"])
        if target_key not in result.tasks[task]:
            raise TrackingError(
                f"velocity_tracking: task {task} has no {target_key!r} entry ({result.tasks[task]}): not a velocity family"
            )
        target = float(result.tasks[task][target_key])
        v = np.asarray(trace[velocity_key], dtype=np.float64)  # (steps,)
        mean_v = float(v.mean())
        step_errors.append(np.abs(v - target))
        per_traj.append((task, target, mean_v, float(step_errors[-1].mean()), abs(mean_v - target), float(v.std())))
    if not per_traj:
        raise TrackingError(f"velocity_tracking: no trajectory with k >= {min_k} has a {velocity_key!r} trace")
    table = np.array([row[1:] for row in per_traj])  # (trajectories, 5): target, mean v, per-step, mean-speed, std
    tasks = []
    for task in sorted({row[0] for row in per_traj}):
        rows = table[[i for i, row in enumerate(per_traj) if row[0] == task]]
        tasks.append(
            {
                "task": task,
                "target": float(rows[0, 0]),
                "mean_speed": float(rows[:, 1].mean()),
                "per_step_error": float(rows[:, 2].mean()),
                "mean_speed_error": float(rows[:, 3].mean()),
                "oscillation": float(rows[:, 4].mean()),
                "n_trajectories": len(rows),
            }
        )
    slope: float | None = None
    intercept: float | None = None
    if len(np.unique(table[:, 0])) > 1:
        slope, intercept = (float(x) for x in np.polyfit(table[:, 0], table[:, 1], 1))
    return {
        "per_step_error": float(table[:, 2].mean()),
        "mean_speed_error": float(table[:, 3].mean()),
        "oscillation": float(table[:, 4].mean()),
        "slope": slope,
        "intercept": intercept,
        "n_trajectories": len(per_traj),
        "min_k": min_k,
        "tasks": tasks,
        "parts": error_by_part(step_errors, n_parts, horizon),
    }


def harness_run(run: str | Path) -> tuple[Path, dict[str, Any]]:
    """
    A finished harness run of a velocity family, checked before any rollout: its folder and ``result.json`` record.

    :param run: ``results/<exp>/<family>/<variant>/seed<N>/``
    :return: the folder and its record
    :raises TrackingError: not such a folder (a train.py run folder, a model zip, ...), or not a velocity family
    """
    folder = Path(run)
    if not (folder / "result.json").is_file() or not (folder / "model.zip").is_file():
        what = "a file" if folder.is_file() else ("no result.json and model.zip in it" if folder.is_dir() else "missing")
        raise TrackingError(
            f"{what}: tracking reruns the competence meta-test a finished harness run recorded, so it takes such a run's "
            "folder (results/<exp>/<family>/<variant>/seed<N>/ with result.json and model.zip); for a train.py run or a "
            "model zip, enjoy.py shows the velocity error of its meta-test"
        )
    record = json.loads((folder / "result.json").read_text())
    if not (record.get("competence") or {}).get("settings") or "eval_seed" not in record:
        raise TrackingError(f"{folder}/result.json has no competence settings or eval_seed: not a finished harness run")
    criteria = (record.get("competence") or {}).get("criteria") or []
    if not any(criterion.get("key") == REWARD_KEY for criterion in criteria):
        family = ((record.get("spec") or {}).get("family") or {}).get("env_id", "its family")
        raise TrackingError(
            f"{family} is not a velocity family (its competence is not the per-step velocity error, {REWARD_KEY}): "
            "tracking splits that error; Walker2dVelMeta-v0, HalfCheetahVelMeta-v0 and the Ant velocity families have it"
        )
    return folder, record


def rerun_competence(run: str | Path, n_tasks: int | None = None) -> MetaTestResult:
    """
    The competence meta-test of a harness run folder again, with the velocity trace.

    :param run: ``results/<exp>/<family>/<variant>/seed<N>/`` with ``result.json`` (that holds a competence record) and
        ``model.zip``, of any algorithm of the project (its class from the record's variant)
    :param n_tasks: training tasks (None: the number the competence check used)
    :return: the meta-test
    """
    from sb3_pearl.diagnose import find_run, load_model  # the run-folder layout, as ``diagnose``
    from sb3_pearl.registry import algorithm_class

    folder, record = harness_run(run)
    model_path, env_id, env_kwargs = find_run(folder)
    settings = record["competence"]["settings"]
    algo = ((record.get("spec") or {}).get("variant") or {}).get("algo")
    env = gym.make(env_id, **env_kwargs)
    device = str(record.get("device", "cpu"))  # where its competence was measured
    try:
        if algo is None:  # a record without its variant: a PEARL / PEARL+ run, as diagnose loads it
            model: Any = load_model(model_path, env, device=device)
        else:
            model = algorithm_class(algo).load(model_path, env=env, device=device)  # type: ignore[attr-defined]
        tasks = list(model.train_tasks)[: int(n_tasks or settings["n_tasks"])]
        return run_meta_test(model, env, tasks, settings, int(record["eval_seed"]), [VELOCITY_KEY, REWARD_KEY])
    finally:
        env.close()


def committed_per_step_error(run: str | Path) -> float | None:
    """
    The per-step velocity error a harness run's result.json holds (its competence criterion on ``reward_forward``).

    :param run: the run folder
    :return: the value, None when the record has none
    """
    record = json.loads((Path(run) / "result.json").read_text())
    for criterion in (record.get("competence") or {}).get("criteria") or []:
        if criterion.get("key") == REWARD_KEY and criterion.get("value") is not None:
            return float(criterion["value"])
    return None


def format_tracking(name: str, tracking: Mapping[str, Any]) -> str:
    """
    A text table of :func:`velocity_tracking`: one line per task, then the means and the fitted line.

    :param name: the heading (the run folder)
    :param tracking: :func:`velocity_tracking`'s result
    :return: the table
    """
    lines = [
        f"{name}: {tracking['n_trajectories']} trajectories (k >= {tracking['min_k']})",
        f"{'task':>5} {'target':>7} {'mean v':>7} {'per-step err':>13} {'mean-speed err':>15} {'oscillation':>12}",
    ]
    for row in tracking["tasks"]:
        lines.append(
            f"{row['task']:>5} {row['target']:>7.2f} {row['mean_speed']:>7.2f} {row['per_step_error']:>13.3f}"
            f" {row['mean_speed_error']:>15.3f} {row['oscillation']:>12.3f}"
        )
    lines.append(
        f"{'mean':>5} {'':>7} {'':>7} {tracking['per_step_error']:>13.3f} {tracking['mean_speed_error']:>15.3f}"
        f" {tracking['oscillation']:>12.3f}"
    )
    if tracking["slope"] is not None:
        lines.append(f"least-squares line: mean speed = {tracking['slope']:.2f} x target {tracking['intercept']:+.2f}")
    parts = [
        (f"steps {part['first_step']}-{part['end_step'] - 1}: " if part["end_step"] > part["first_step"] else "no steps: ")
        + ("n/a" if part["error"] is None else f"{part['error']:.3f} ({part['n_trajectories']} traj.)")
        for part in tracking["parts"]
    ]
    lines.append("per-step error by part of the episode: " + "; ".join(parts))
    return "\n".join(lines)


def plot_tracking(runs: Mapping[str, Mapping[str, Any]], path: str | Path, title: str = "", bar: float | None = None) -> None:
    """
    Two panels: each task's mean speed against its target (with the line of perfect tracking), and the per-step error
    by part of the episode; one colour per run.

    :param runs: name -> :func:`velocity_tracking`
    :param path: the PNG
    :param title: figure title
    :param bar: the competence bar on the per-step error, drawn on the second panel (None: none)
    """
    from sb3_pearl.evaluation.figures import _save, plt  # the package's matplotlib set-up (Agg backend)

    fig, (ax, parts_ax) = plt.subplots(1, 2, figsize=(11, 4.5))
    top, worst = 0.0, 0.0
    for name, tracking in runs.items():
        targets = [row["target"] for row in tracking["tasks"]]
        speeds = [row["mean_speed"] for row in tracking["tasks"]]
        top = max(top, *targets, *speeds)
        (line,) = ax.plot(targets, speeds, "o", alpha=0.8, label=f"{name} (per-step error {tracking['per_step_error']:.2f})")
        parts = [part for part in tracking["parts"] if part["error"] is not None]
        middles = [(part["first_step"] + part["end_step"]) / 2 for part in parts]
        parts_ax.plot(middles, [part["error"] for part in parts], "o-", color=line.get_color(), label=name)
        worst = max(worst, *(part["error"] for part in parts))
    ax.plot([0, top], [0, top], "k--", lw=1, label="perfect tracking")
    ax.set_xlabel("target velocity [m/s]")
    ax.set_ylabel("mean forward velocity of the posterior trajectories [m/s]")
    ax.legend(fontsize=7)
    if bar is not None:
        parts_ax.axhline(bar, color="k", ls="--", lw=1, label=f"competence bar ({bar:g})")
    parts_ax.set_xlabel("step of the episode (middle of each part)")
    parts_ax.set_ylabel("per-step velocity error in that part [m/s]")
    parts_ax.set_ylim(0, 1.45 * max(worst, bar or 0.0))  # room above the lines for the legend
    parts_ax.legend(fontsize=7, loc="upper center", ncol=2)
    _save(fig, path, title)


def parser() -> argparse.ArgumentParser:
    """The command line of :func:`main`."""
    p = argparse.ArgumentParser(prog="python -m sb3_pearl.tracking", description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="harness run folders (result.json + model.zip) of a velocity family")
    p.add_argument("--n-tasks", type=positive_int, default=None, help="training tasks (default: the competence check's)")
    p.add_argument("--parts", type=positive_int, default=4, help="equal parts of the episode the error is split over (4)")
    p.add_argument(
        "--plot", default=None, metavar="PNG", help="draw mean speed against target and the error by part to this PNG"
    )
    p.add_argument("--title", default="", help="title of the figure")
    p.add_argument("--bar", type=float, default=None, help="competence bar drawn on the error-by-part panel (e.g. 0.3)")
    p.add_argument("--json", action="store_true", help="print JSON instead of the tables")
    return p


def main(argv: Sequence[str] | None = None) -> dict[str, dict[str, Any]]:
    """
    Rerun each run's competence meta-test and print its velocity tracking.

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: run folder -> :func:`velocity_tracking`
    """
    from sb3_pearl.diagnose import RunFolderError, find_run

    p = parser()
    args = p.parse_args(argv)
    results: dict[str, dict[str, Any]] = {}
    for run in args.runs:
        try:
            rerun = rerun_competence(run, args.n_tasks)  # checks the folder and family first (harness_run)
            horizon = gym.spec(find_run(run)[1]).max_episode_steps  # the parts divide the episode, not the survivors
            results[run] = velocity_tracking(rerun, n_parts=args.parts, horizon=horizon)
        except (RunFolderError, TrackingError) as error:
            p.error(f"{run}: {error}")
        committed = committed_per_step_error(run) if args.n_tasks is None else None
        results[run]["committed_per_step_error"] = committed
        if committed is not None and not np.isclose(results[run]["per_step_error"], committed, rtol=1e-6, atol=1e-9):
            print(
                f"warning: {run}: the rerun's per-step error {results[run]['per_step_error']:.6f} is not result.json's "
                f"{committed:.6f} (another machine, device or package versions): the split describes other trajectories",
                file=sys.stderr,
            )
        if not args.json:
            print(format_tracking(run, results[run]), flush=True)
    if args.json:
        print(json.dumps(results, indent=1))
    if args.plot:
        names = {run: " ".join(Path(run).parts[-3:]) for run in results}  # <family> <variant> seed<N>
        plot_tracking({names[run]: tracking for run, tracking in results.items()}, args.plot, args.title, args.bar)
    return results


if __name__ == "__main__":
    main()
