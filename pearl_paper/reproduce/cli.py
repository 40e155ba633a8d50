"""The command line of ``python -m pearl_paper.reproduce`` (docs/reproduce.md).

::

    python -m pearl_paper.reproduce list
    python -m pearl_paper.reproduce run table1 --family walker2d-vel --budget cpu --seeds 0-3 --jobs 2 \\
        [--variants pearl pearlplus] [--force] [--results-dir results] [--dry-run]
    python -m pearl_paper.reproduce run table1 --backend ray [--address auto] [--gpus-per-run 0.25] [--cpus-per-run 1] \\
        [--retries 1] [--storage-path s3://bucket/tune]           # docs/scale.md
    python -m pearl_paper.reproduce report [--results-dir results] [--out docs/results.md]
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pearl_paper.experiments import EXPERIMENTS, get_experiment
from pearl_paper.experiments.spec import Experiment
from pearl_paper.reproduce.checkpoint import resume_promise
from pearl_paper.reproduce.layout import parse_seeds
from pearl_paper.reproduce.ownership import RunLockedError
from sb3_pearl.budgets import PRESETS
from sb3_pearl.common.checks import output_folder_problem, positive_int

BACKENDS = ("local", "ray")
RAY_OPTIONS = ("address", "cpus_per_run", "gpus_per_run", "retries", "storage_path")


def check_results_dir(path: str) -> None:
    """Refuse, before any run starts, a results dir that is a file or cannot be written."""
    problem = output_folder_problem(path)
    if problem is not None:
        raise ValueError(f"--results-dir {path}: {problem}")


def require_checkpoint(run: str) -> None:
    """Refuse a folder that is not a part-way run's (no ``checkpoint/`` in it), before anything is created there."""
    from pearl_paper.reproduce.checkpoint import CHECKPOINT_DIR

    if not os.path.isdir(os.path.join(run, CHECKPOINT_DIR)):
        raise ValueError(f"{run} has no {CHECKPOINT_DIR}/ folder: give a part-way run's folder")


CONFIRM_RUNS = 200  # a larger plan needs --yes (a typo in --seeds must not start days of runs)


def _add_plan_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments that choose the planned runs of an experiment (``run`` and ``status``)."""
    parser.add_argument("experiment", choices=sorted(EXPERIMENTS), help="the experiment (see `list`)")
    parser.add_argument("--family", nargs="+", default=None, help="families of the experiment (default: all)")
    parser.add_argument("--variants", nargs="+", default=None, help="variants of the experiment (default: all)")
    parser.add_argument("--budget", default=None, choices=PRESETS, help="budget preset (default: the experiment's, cpu)")
    parser.add_argument(
        "--seeds",
        default=None,
        help="model seeds: 0-3, 0,2,5 or 0-3,7, for every chosen variant (default: each variant's declared seeds)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (subcommands ``list``, ``run``, ``report`` and the internal ``run-one``)."""
    parser = argparse.ArgumentParser(
        prog="python -m pearl_paper.reproduce",
        description="Run the paper's experiments (each variant and seed its own process) and rebuild docs/results.md.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    sub.add_parser("list", help="the experiments, their families, variants and default seeds, and the budget presets")

    run = sub.add_parser("run", help="train and meta-test every (family, variant, seed) of an experiment")
    _add_plan_arguments(run)
    run.add_argument(
        "--jobs",
        type=positive_int,
        default=None,
        help="runs at a time, one process and one torch thread each (default: 1 locally, what the Ray cluster fits with ray)",
    )
    run.add_argument("--results-dir", default="results", help="root of the results layout (default: results)")
    run.add_argument("--force", action="store_true", help="rerun runs that already have a result.json")
    run.add_argument("--dry-run", action="store_true", help="print the planned runs and their budgets, run nothing")
    run.add_argument("--yes", action="store_true", help=f"confirm a plan of more than {CONFIRM_RUNS} runs")
    run.add_argument(
        "--backend",
        choices=BACKENDS,
        default="local",
        help="local: child processes on this machine (default); ray: Ray Tune trials on a Ray cluster (docs/scale.md)",
    )
    ray_group = run.add_argument_group("Ray backend (--backend ray; pip install -e '.[ray]')")
    ray_group.add_argument(
        "--address",
        default=None,
        help="Ray cluster: auto, HOST:PORT or ray://HOST:PORT (default: Ray's: $RAY_ADDRESS, a `ray start` cluster "
        "of this machine, else a local Ray for the command)",
    )
    ray_group.add_argument("--cpus-per-run", type=float, default=None, help="CPUs Ray reserves per run (default 1)")
    ray_group.add_argument(
        "--gpus-per-run", type=float, default=None, help="GPUs per run, fractions share a GPU (default 0: the run sees no GPU)"
    )
    ray_group.add_argument("--retries", type=int, default=None, help="times Tune retries a failed run (default 1)")
    ray_group.add_argument(
        "--storage-path",
        default=None,
        help="Ray Tune's experiment storage, a path or URI every node reaches (default: <results-dir>/.tune)",
    )

    report = sub.add_parser("report", help="rebuild the tables and figures of the results page from the results")
    report.add_argument("--results-dir", default="results", help="root of the results layout (default: results)")
    report.add_argument("--out", default="docs/results.md", help="markdown file; its text outside the markers is kept")

    status = sub.add_parser("status", help="finished, resumable and missing runs of an experiment, and the CPU time left")
    _add_plan_arguments(status)
    status.add_argument("--results-dir", default="results", help="root of the results layout (default: results)")

    measure = sub.add_parser(
        "measure",
        help="fill in the prior-critic measures where missing or of an earlier version, and the oracle's shifted "
        "meta-test where its task vector was standardised over the shifted tasks (from model.zip)",
    )
    measure.add_argument("experiments", nargs="*", help="only these experiments (default: all)")
    measure.add_argument("--results-dir", default="results", help="root of the results layout (default: results)")
    measure.add_argument("--force", action="store_true", help="measure runs that already have the measures again")

    remeasure = sub.add_parser(
        "remeasure",
        help="meta-test finished runs again on Table I's larger design (meta_test_large.json beside result.json)",
    )
    remeasure.add_argument(
        "experiments", nargs="*", help="experiments (default: the Highway-Merge tables the Table I rules name)"
    )
    remeasure.add_argument("--seeds", default=None, help="model seeds: 0-3, 0,2,5 (default: each experiment's)")
    remeasure.add_argument("--results-dir", default="results", help="root of the results layout (default: results)")
    remeasure.add_argument("--force", action="store_true", help="remeasure runs that already have the record")

    velocity = sub.add_parser(
        "velocity",
        help="the held-out velocity error of finished runs on the velocity families (velocity_held_out.json), "
        "for the competence rules against the oracle",
    )
    velocity.add_argument("experiments", nargs="+", help="experiments (e.g. oracle walker-table1 pearl-reference)")
    velocity.add_argument("--family", nargs="+", default=None, help="families (default: every velocity family)")
    velocity.add_argument("--seeds", default=None, help="model seeds: 0-3, 0,2,5 (default: each experiment's)")
    velocity.add_argument("--results-dir", default="results", help="root of the results layout (default: results)")
    velocity.add_argument("--force", action="store_true", help="measure runs that already have the record")

    compact = sub.add_parser(
        "compact",
        help="rewrite the replay buffer of part-way runs' checkpoints with only its filled rows (to commit them)",
    )
    compact.add_argument("runs", nargs="+", help="run folders (results/<experiment>/<family>/<variant>/seed<N>)")

    profile = sub.add_parser(
        "reward-profile",
        help="falls against living steps in a part-way run's replay buffer (reward_profile.json in the run's folder)",
    )
    profile.add_argument("runs", nargs="+", help="run folders (results/<experiment>/<family>/<variant>/seed<N>)")
    profile.add_argument("--window", type=positive_int, default=20_000, help="transitions per window (default: 20000)")

    one = sub.add_parser("run-one", help=argparse.SUPPRESS)  # what each child process of `run` executes
    one.add_argument("--experiment", required=True)
    one.add_argument("--family", required=True)
    one.add_argument("--variant", required=True)
    one.add_argument("--seed", type=int, required=True)
    one.add_argument("--budget", required=True, choices=PRESETS)
    one.add_argument("--results-dir", required=True)
    return parser


def _list() -> None:
    for experiment in EXPERIMENTS.values():
        print(f"{experiment.name}: {experiment.title}")
        print(f"  families: {', '.join(f.name for f in experiment.families)}")
        print(f"  variants: {', '.join(f'{v.name} ({v.label})' for v in experiment.variants)}")
        print(f"  default seeds {list(experiment.seeds)}, budget {experiment.budget}, eval seed {experiment.eval_seed}")
        for variant, seeds in experiment.variant_seeds.items():
            print(f"  seeds of {variant}: {list(seeds)}")
        for family, seeds in experiment.family_seeds.items():
            print(f"  seeds on {family}: {list(seeds)}")
    print(f"budget presets: {', '.join(PRESETS)} (sb3_pearl/config/presets/)")


def _variants_after_selection(experiment: Experiment, budget: str, results_dir: str) -> list[str]:
    """The variants ``run`` plans by default: the ``after_selection`` ones only once the rule has selected them."""
    from pearl_paper.reproduce.prior_report import selection_gate

    gate = selection_gate(experiment, budget, results_dir)
    if gate.held:
        why = "not selected by" if gate.final else "awaiting"
        print(
            f"{experiment.name}: {len(gate.held)} variant(s) {why} the selection rule left out ({', '.join(gate.held)})"
            + (
                ""
                if gate.final
                else f"; run the same command again once the {experiment.selected_by or experiment.name} runs "
                "the rule reads are complete"
            )
            + "; name them with --variants to run them anyway"
        )
    if gate.unmeasured:
        print(
            f"{experiment.name}: {len(gate.unmeasured)} finished run(s) lack the prior-critic measures the rule reads "
            f"({', '.join(gate.unmeasured)}): `python -m pearl_paper.reproduce measure {experiment.name}` fills them in"
        )
    return [v.name for v in experiment.variants if v.name not in gate.held]


def _run(args: argparse.Namespace) -> int:
    from pearl_paper.reproduce.scheduler import (
        BackendUnavailableError,
        RunSummary,
        load_ray_backend,
        plan_runs,
        run_experiment,
        undeclared_seeds,
    )

    experiment = get_experiment(args.experiment)
    budget = args.budget or experiment.budget
    seeds = parse_seeds(args.seeds) if args.seeds is not None else None
    given = [name for name in RAY_OPTIONS if getattr(args, name) is not None]
    if args.backend != "ray" and given:
        options = ", ".join("--" + name.replace("_", "-") for name in given)
        raise ValueError(f"{options} only apply to --backend ray")
    variants = args.variants
    if variants is None and experiment.after_selection:
        variants = _variants_after_selection(experiment, budget, args.results_dir)
    planned = plan_runs(experiment, budget, seeds, args.family, variants)  # every name and override checked
    for (family, variant), extra in undeclared_seeds(experiment, planned).items():
        print(
            f"note: {experiment.name} does not declare seeds {extra} for {variant} on {family} (its seeds there: "
            f"{list(experiment.seeds_of(variant, family))}); they run, but the report leaves them out",
            file=sys.stderr,
        )
    if not args.dry_run:
        check_results_dir(args.results_dir)
    if len(planned) > CONFIRM_RUNS and not args.yes and not args.dry_run:
        raise ValueError(f"{len(planned)} runs planned (more than {CONFIRM_RUNS}): check --seeds, then add --yes to confirm")
    if args.dry_run:  # what the run would do with each planned run: skip it (done), resume it or start it
        from pearl_paper.reproduce.status import format_dry_run, run_status

        rows = run_status(experiment, budget, seeds, args.results_dir, args.family, variants)  # held variants: out already
        print(format_dry_run(rows, experiment, budget, args.results_dir, args.force))
        return 0
    common: dict[str, Any] = dict(families=args.family, variants=variants, force=args.force)
    summary: RunSummary
    if args.backend == "ray":
        ray_options = {name: getattr(args, name) for name in given}
        try:
            backend = load_ray_backend()
        except BackendUnavailableError as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
        summary = backend.run_experiment_ray(
            experiment, budget, seeds, args.results_dir, jobs=args.jobs, **common, **ray_options
        )
    else:
        summary = run_experiment(experiment, budget, seeds, args.results_dir, jobs=args.jobs or 1, **common)
    print(
        f"{len(summary.done)} done, {len(summary.skipped)} skipped, {len(summary.failed)} failed"
        + (f", {len(summary.interrupted)} interrupted" if summary.interrupted else "")
    )
    if summary.failed:
        print("failed: " + ", ".join(key.label() for key in summary.failed), file=sys.stderr)
        return 1
    return 130 if summary.interrupted else 0


def main(argv: Sequence[str] | None = None) -> int:
    """
    Parse the command line and run the subcommand.

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: the exit status
    """
    args = build_parser().parse_args(argv)
    if args.command == "run-one":
        return _run_one(args)
    try:
        if args.command == "list":
            _list()
            return 0
        if args.command == "run":
            return _run(args)
        if args.command == "report":
            from pearl_paper.reproduce.report import write_report

            print(f"wrote {write_report(args.results_dir, args.out)}")
            return 0
        if args.command == "status":
            from pearl_paper.reproduce.status import format_status, run_status

            if not os.path.isdir(args.results_dir):
                raise ValueError(f"--results-dir {args.results_dir} does not exist or is not a folder: no run to report on")
            experiment = get_experiment(args.experiment)
            seeds = parse_seeds(args.seeds) if args.seeds is not None else None
            budget = args.budget or experiment.budget
            print(format_status(run_status(experiment, budget, seeds, args.results_dir, args.family, args.variants)))
            return 0
        if args.command == "measure":
            import torch as th

            from pearl_paper.reproduce.prior_measures import measure_results

            th.set_num_threads(1)
            for name in args.experiments:
                get_experiment(name)  # an unknown name fails here, with the known ones
            written = measure_results(args.results_dir, args.experiments or None, args.force)
            print(f"{len(written)} run(s) measured")
            return 0
        if args.command == "remeasure":
            import torch as th

            from pearl_paper.experiments.table1_rules import MERGE_REMEASURE, REMEASURED_EXPERIMENTS
            from pearl_paper.reproduce.remeasure import remeasure_experiments

            th.set_num_threads(1)
            names = args.experiments or list(REMEASURED_EXPERIMENTS)
            for name in names:
                get_experiment(name)  # an unknown name fails here, with the known ones
            chosen = parse_seeds(args.seeds) if args.seeds is not None else None
            written = remeasure_experiments(args.results_dir, names, MERGE_REMEASURE, chosen, args.force)
            print(f"{len(written)} run(s) remeasured")
            return 0
        if args.command == "compact":
            from pearl_paper.reproduce.checkpoint import RunCheckpoint
            from pearl_paper.reproduce.ownership import run_lock

            for run in args.runs:
                require_checkpoint(run)
                with run_lock(Path(run), wait_s=0.0):  # never under a run that is training
                    before, after = RunCheckpoint(run).compact_replay()
                print(f"{run}: replay buffer {before / 1e6:.0f} MB -> {after / 1e6:.0f} MB")
            return 0
        if args.command == "reward-profile":
            from pearl_paper.reproduce.ownership import run_lock
            from pearl_paper.reproduce.reward_profile import checkpoint_reward_profile

            for run in args.runs:
                require_checkpoint(run)  # before the lock, which would create a mistyped folder
                with run_lock(Path(run), wait_s=0.0):  # never under a run that is training
                    path = checkpoint_reward_profile(run, args.window)
                print(f"{run}: wrote {path}")
            return 0
        if args.command == "velocity":
            import torch as th

            from pearl_paper.reproduce.velocity import SPEED_BINS, measure_experiments

            th.set_num_threads(1)
            for name in args.experiments:
                get_experiment(name)  # an unknown name fails here, with the known ones
            others = sorted(set(args.family or ()) - set(SPEED_BINS))
            if others:  # else filtered out in silence: "0 run(s) measured"
                raise ValueError(f"--family {' '.join(others)}: not a velocity family; those are {sorted(SPEED_BINS)}")
            chosen = parse_seeds(args.seeds) if args.seeds is not None else None
            written = measure_experiments(args.results_dir, args.experiments, chosen, args.family, args.force)
            print(f"{len(written)} run(s) measured")
            return 0
    except (ValueError, RunLockedError) as error:  # a bad argument, or a run that another process is training
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    raise AssertionError(f"unhandled command {args.command!r}")


def _run_one(args: argparse.Namespace) -> int:
    """
    The child of ``run``: owns its run folder (a lock) for as long as it trains; errors keep their traceback (run.log).

    SIGTERM or SIGINT during training stops it where it resumes exactly (the next gradient step, env step or iteration
    start, :class:`~sb3_pearl.common.callbacks.StopOnSignalCallback`, as ``train.py``), saves a checkpoint there and
    exits with status 128 + the signal; the same signal again, or one outside training, stops at once (status 130,
    the last checkpoint kept).
    """
    import signal

    from pearl_paper.reproduce.layout import RunKey, run_dir
    from pearl_paper.reproduce.ownership import LOCKED_EXIT, RunLockedError, die_with_parent, run_lock
    from pearl_paper.reproduce.runner import RunStopped, run_one
    from sb3_pearl.common.callbacks import StopOnSignalCallback

    stop_callback, received = StopOnSignalCallback(), []

    def stop(signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if name in received or not stop_callback.training:
            raise KeyboardInterrupt
        received.append(name)
        stop_callback.requested = True
        print(
            f"run-one: received {name}: stopping training at the next gradient step, env step or iteration start, then "
            f"saving a checkpoint there; {name} again stops at once",
            file=sys.stderr,
            flush=True,
        )

    for signum in (signal.SIGTERM, signal.SIGINT):  # the parent's stop, a scheduler's or Ctrl-C
        signal.signal(signum, stop)
    folder = run_dir(args.results_dir, RunKey(args.experiment, args.family, args.variant, args.seed))
    try:
        die_with_parent()
        with run_lock(folder):
            run_one(args.experiment, args.family, args.variant, args.seed, args.budget, args.results_dir, stop=stop_callback)
    except RunLockedError as error:
        print(f"run-one: {error}: nothing done", file=sys.stderr)
        return LOCKED_EXIT
    except RunStopped as stopped:
        print(f"run-one: stopped by {received[0]} {stopped}; {resume_promise(folder)}", file=sys.stderr)
        return 128 + int(signal.Signals[received[0]])
    except KeyboardInterrupt:
        print(f"run-one: interrupted; {resume_promise(folder)}", file=sys.stderr)
        return 130
    return 0
