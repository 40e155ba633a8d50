"""``enjoy.py``: prior and posterior rollouts of a trained model, found like rl_zoo3's enjoy finds it.

The prior trajectory (k = 0) of each test task, then posterior trajectories after adapting on the
earlier ones (k = 1..``--n-adapt``), rendered, recorded as videos or only printed and plotted. After the rollouts, one
table puts the prior and the posterior side by side (:func:`~sb3_pearl.evaluation.statistics.format_prior_posterior_table`).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import torch as th
from gymnasium.envs.registration import load_env_creator
from gymnasium.wrappers import HumanRendering, RecordVideo
from huggingface_sb3 import EnvironmentName
from stable_baselines3.common.utils import set_random_seed

from sb3_pearl.common.checks import non_negative_int, positive_int
from sb3_pearl.common.runtime import has_display
from sb3_pearl.common.threads import apply_default_num_threads, mark_num_threads_explicit
from sb3_pearl.envs.task_observation import training_standardisation
from sb3_pearl.evaluation.held_out import DEFAULT_EVAL_SEED, model_test_tasks, run_meta_test
from sb3_pearl.evaluation.meta_test import ROW_COLUMNS, MetaTestResult
from sb3_pearl.evaluation.statistics import format_prior_posterior_table
from sb3_pearl.oracle import Oracle
from sb3_pearl.zoo.algos import register_algos
from sb3_pearl.zoo.model_checks import check_model_env, check_model_family, check_model_spaces
from sb3_pearl.zoo.rl_zoo3_coupling import ALGOS, create_test_env, get_model_path
from sb3_pearl.zoo.safe_config import UnsafeConfigError, get_saved_hyperparams, load_run_yaml
from sb3_pearl.zoo.usage import CheckedStoreDict, UsageError, check_env_id, exit_on_usage_error


def enjoy_parser() -> argparse.ArgumentParser:
    """The command line of ``enjoy.py`` (rl_zoo3's model-finding flags plus the meta-test ones)."""
    parser = argparse.ArgumentParser(
        description="Roll out a trained meta-RL model on test tasks: the prior trajectory (k = 0), then posterior "
        "trajectories after adapting on the earlier ones (k = 1..--n-adapt).",
    )
    parser.add_argument("--env", help="environment ID", type=EnvironmentName, default="SafePointGoalMeta-v0")
    parser.add_argument("-f", "--folder", help="Log folder", type=str, default="logs")
    parser.add_argument("--algo", help="RL Algorithm", default="pearlplus", type=str, choices=list(ALGOS.keys()))
    parser.add_argument("--exp-id", help="Experiment ID (default: 0: latest, -1: no exp folder)", default=0, type=int)
    parser.add_argument("--load-best", action="store_true", default=False, help="Load the best model (best_model.zip)")
    parser.add_argument("--load-checkpoint", type=positive_int, help="Load the checkpoint of this many timesteps")
    parser.add_argument("--load-last-checkpoint", action="store_true", default=False, help="Load the last checkpoint")
    parser.add_argument("--n-tasks", help="number of test tasks", default=3, type=positive_int)
    parser.add_argument(
        "--n-adapt", help="last trajectory index K (k = 0 prior, 1..K posterior)", default=5, type=non_negative_int
    )
    parser.add_argument("--n-repeats", help="repeats of the sequence per task", default=1, type=positive_int)
    parser.add_argument(
        "--eval-seed",
        help="seed of the held-out tasks (drawn from the env, --env-kwargs for a shifted distribution) and of the common "
        f"random numbers: train.py's final meta-test and the harness use the same draw (default {DEFAULT_EVAL_SEED}; "
        "with --run, the run's own)",
        type=non_negative_int,
        default=None,
    )
    parser.add_argument(
        "--run",
        help="replay a reproduction-harness run folder (results/<experiment>/<family>/<variant>/seed<N>, with model.zip "
        "and result.json) instead of a train.py run: its env kwargs and eval seed are used, nothing is trained",
        type=str,
        default=None,
    )
    parser.add_argument("--stochastic", action="store_true", default=False, help="Use stochastic actions")
    parser.add_argument("--no-render", action="store_true", default=False, help="Do not render the environment")
    parser.add_argument("--video-folder", type=str, default=None, help="Record one video per trajectory here")
    parser.add_argument(
        "--plot",
        nargs="?",
        const="",
        default=None,
        help="Save the adaptation curve (and, for the merge family, speed profiles and the b_min scatter); "
        "optional PNG path (default: <run folder>/enjoy_adaptation.png)",
    )
    parser.add_argument(
        "--seed",
        help="seed of the global RNGs while the model and env are built (the rollouts' resets and prior draws come from "
        "--eval-seed: common random numbers)",
        type=non_negative_int,
        default=0,
    )
    parser.add_argument("--device", help="PyTorch device to be use (ex: cpu, cuda...)", default="auto", type=str)
    parser.add_argument("--num-threads", help="Number of threads for PyTorch (-1 to use default)", default=-1, type=int)
    parser.add_argument("--verbose", help="Verbose mode (0: no output, 1: INFO)", default=1, type=int)
    parser.add_argument(
        "--gym-packages", type=str, nargs="+", default=[], help="Additional external Gym environment package modules to import"
    )
    parser.add_argument(
        "--env-kwargs",
        type=str,
        nargs="+",
        action=CheckedStoreDict,
        help="Optional keyword argument to pass to the env constructor",
    )
    return parser


# The flags that choose the model of a train.py run folder (rl_zoo3's), by their attribute (defaults: the parser's).
ZOO_MODEL_FLAGS = {
    "-f": "folder",
    "--exp-id": "exp_id",
    "--load-best": "load_best",
    "--load-checkpoint": "load_checkpoint",
    "--load-last-checkpoint": "load_last_checkpoint",
}


def _render_modes(env_id: str) -> list[str]:
    spec = gym.spec(env_id)
    creator = load_env_creator(spec.entry_point) if isinstance(spec.entry_point, str) else spec.entry_point
    return list(getattr(creator, "metadata", {}).get("render_modes", []))


def _saved_env_kwargs(log_path: str, env_name: str, hyperparams: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """
    env kwargs of the training run: the config's, overridden by the command line's (rl_zoo3's enjoy rule); and those of
    its evaluation env (``--eval-env-kwargs``, else the same), where train.py's meta-tests ran.

    :return: the training env's kwargs, the evaluation env's
    """
    env_kwargs: dict[str, Any] = dict(hyperparams.pop("env_kwargs", None) or {})
    eval_env_kwargs: dict[str, Any] | None = None
    args_path = os.path.join(log_path, env_name, "args.yml")
    if os.path.isfile(args_path):
        loaded = load_run_yaml(args_path) or {}
        if loaded.get("env_kwargs") is not None:
            env_kwargs = dict(loaded["env_kwargs"])
        if loaded.get("eval_env_kwargs"):
            eval_env_kwargs = dict(loaded["eval_env_kwargs"])
    return env_kwargs, dict(env_kwargs if eval_env_kwargs is None else eval_env_kwargs)


def _harness_run(folder: str, algo: str, env_id: str) -> tuple[dict[str, Any], int]:
    """
    The env kwargs and eval seed of a reproduction-harness run folder, after checking that it holds a finished run of
    ``algo`` on ``env_id`` (a :class:`~sb3_pearl.zoo.usage.UsageError` otherwise).

    :param folder: the run folder (``results/<experiment>/<family>/<variant>/seed<N>``)
    :param algo: ``--algo``
    :param env_id: ``--env``
    :return: the family's env kwargs and the experiment's eval seed
    """
    result_path, model_path = os.path.join(folder, "result.json"), os.path.join(folder, "model.zip")
    if os.path.isfile(folder):
        raise UsageError(f"--run {folder}: a file; pass the run's folder (results/<experiment>/<family>/<variant>/seed<N>)")
    if not (os.path.isfile(result_path) and os.path.isfile(model_path)):
        raise UsageError(f"--run {folder}: not a finished harness run (expected model.zip and result.json in it)")
    try:
        with open(result_path) as file:
            result = json.load(file)
        family, variant = result["spec"]["family"], result["spec"]["variant"]
    except (OSError, ValueError, KeyError) as error:
        raise UsageError(f"--run {folder}: unreadable result.json ({error})") from None
    if family["env_id"] != env_id:
        raise UsageError(f"--run {folder} was trained on {family['env_id']}, not on {env_id}: pass --env {family['env_id']}")
    if variant["algo"] != algo:
        raise UsageError(f"--run {folder} is a {variant['algo']} model: pass --algo {variant['algo']}")
    return dict(family.get("env_kwargs") or {}), int(result["eval_seed"])


def format_task_table(result: MetaTestResult, task: int, repeat: int = 0) -> str:
    """The rows of one task and repeat: k, prior / posterior, return, cost, length (and the family extras)."""
    extras = [key for key in result.columns[len(ROW_COLUMNS) :]]
    header = f"{'k':>3}  {'policy':<9} {'return':>10} {'cost':>6} {'length':>6}" + "".join(f" {key:>10}" for key in extras)
    lines = [header]
    for row in result.rows:
        if row["task"] != task or row["repeat"] != repeat:
            continue
        policy = "prior" if row["k"] == 0 else "posterior"
        line = f"{row['k']:>3}  {policy:<9} {row['return']:>10.2f} {row['cost']:>6.1f} {row['length']:>6d}"
        line += "".join(f" {float(row.get(key, float('nan'))):>10.3g}" for key in extras)
        lines.append(line)
    return "\n".join(lines)


def enjoy(argv: Sequence[str] | None = None) -> MetaTestResult:
    """
    ``enjoy.py``: load a model like rl-zoo and roll out prior then posterior trajectories on test tasks.

    :param argv: command-line arguments (default: ``sys.argv[1:]``)
    :return: the meta-test of the rollouts
    """
    register_algos()
    with exit_on_usage_error():
        return _enjoy(enjoy_parser().parse_args(argv))


def find_model(args: argparse.Namespace, env_name: EnvironmentName) -> tuple[str, str]:
    """
    The model zip and run folder ``enjoy.py`` loads: rl_zoo3's choice (``--exp-id``, ``--load-best``, ...), except that
    the latest run (``--exp-id 0``) is the latest one that holds the model asked for: a newer run folder without it (a
    run stopped or killed before its first save) is skipped, and the message says which folder was used and why.

    :param args: enjoy's arguments
    :param env_name: the env
    :return: the model's path and its run folder
    """
    choice = (args.load_best, args.load_checkpoint, args.load_last_checkpoint)
    candidates = [args.exp_id]
    if args.exp_id == 0:
        pattern = re.compile(re.escape(str(env_name)) + r"_(\d+)")
        root = os.path.join(args.folder, args.algo)
        names = os.listdir(root) if os.path.isdir(root) else []
        numbers = sorted((int(m.group(1)) for m in map(pattern.fullmatch, names) if m is not None), reverse=True)
        candidates = numbers or [0]
    skipped: list[str] = []
    for number in candidates:
        try:
            _, model_path, log_path = get_model_path(number, args.folder, args.algo, env_name, *choice)
        except (AssertionError, ValueError) as error:
            if number == candidates[-1]:
                if os.path.isfile(os.path.join(args.folder, "result.json")):  # -f given a harness run folder
                    hint = f"{args.folder} is a harness run folder; replay it with --run {args.folder}"
                    raise UsageError(f"{error}: {hint}") from None
                raise UsageError(str(error) if not skipped else f"{error}; no newer run folder holds one either") from None
            skipped.append(f"{env_name}_{number}")
            continue
        if skipped:
            print(
                f"Loading the latest run with a model, {log_path}: {', '.join(skipped)} "
                f"{'holds' if len(skipped) == 1 else 'hold'} none (a run stopped before its first save; --exp-id chooses)"
            )
        return model_path, log_path
    raise AssertionError("unreachable: the last candidate returns or raises")


def _enjoy(args: argparse.Namespace) -> MetaTestResult:
    """:func:`enjoy` after parsing; user errors raise :class:`~sb3_pearl.zoo.usage.UsageError`."""
    for module in args.gym_packages:
        importlib.import_module(module)
    env_name: EnvironmentName = args.env
    env_id = env_name.gym_id
    check_env_id(env_id)
    if args.run is not None:  # a harness run folder: model.zip + result.json
        defaults = enjoy_parser()
        chosen = [flag for flag, name in ZOO_MODEL_FLAGS.items() if getattr(args, name) != defaults.get_default(name)]
        if chosen:
            raise UsageError(
                f"--run loads the run folder's model.zip: {', '.join(chosen)} choose a model of a train.py run folder "
                "instead; give one or the other"
            )
        model_path, log_path = os.path.join(args.run, "model.zip"), args.run
        run_env_kwargs, run_eval_seed = _harness_run(args.run, args.algo, env_id)
    else:
        model_path, log_path = find_model(args, env_name)
    eval_seed = args.eval_seed if args.eval_seed is not None else (run_eval_seed if args.run else DEFAULT_EVAL_SEED)
    if args.num_threads > 0:
        th.set_num_threads(args.num_threads)
        mark_num_threads_explicit()
    set_random_seed(args.seed)
    if args.run is None:
        try:
            check_model_env(model_path, env_id)  # a UsageError: the model was trained on another env
        except UnsafeConfigError as error:  # its args.yml would run code
            raise UsageError(str(error)) from None
    print(f"Loading {model_path}")

    if args.run is not None:
        hyperparams: dict[str, Any] = {}  # the harness never normalises nor wraps
        maybe_stats_path, training_kwargs, env_kwargs = None, dict(run_env_kwargs), dict(run_env_kwargs)
    else:
        try:  # the run folder's YAML, read without running code (sb3_pearl.zoo.safe_config)
            hyperparams, maybe_stats_path = get_saved_hyperparams(os.path.join(log_path, env_name), test_mode=True)
            training_kwargs, env_kwargs = _saved_env_kwargs(log_path, env_name, hyperparams)
        except UnsafeConfigError as error:
            raise UsageError(str(error)) from None
        if env_kwargs != training_kwargs:
            print(f"The run's meta-tests ran in its evaluation env (--eval-env-kwargs {env_kwargs}): so do these rollouts")
    shifted = bool(args.env_kwargs)  # (training_kwargs: the distribution the model was trained in, for the oracle)
    if args.env_kwargs:
        env_kwargs.update(args.env_kwargs)
    render = not args.no_render
    if render and args.video_folder is None and not has_display():
        print("No display (DISPLAY is not set): rollouts are not rendered; --video-folder DIR records them as videos")
        render = False
    if args.video_folder is not None:
        env_kwargs["render_mode"] = "rgb_array"
    elif render and "render_mode" not in env_kwargs:
        env_kwargs["render_mode"] = "human" if "human" in _render_modes(env_id) else "rgb_array"
    vec_env = create_test_env(
        env_id,
        n_envs=1,
        stats_path=maybe_stats_path,
        seed=args.seed,
        should_render=False,
        hyperparams=hyperparams,
        env_kwargs=env_kwargs,
    )
    env: gym.Env = vec_env.envs[0]  # type: ignore[attr-defined]
    if args.video_folder is not None:
        env = RecordVideo(env, args.video_folder, episode_trigger=lambda _: True, disable_logger=True)
    elif render and env_kwargs.get("render_mode") == "rgb_array":
        env = HumanRendering(env)

    try:
        model = ALGOS[args.algo].load(model_path, device=args.device)
    except ValueError as error:  # a truncated or corrupt zip, or one of another algorithm
        raise UsageError(str(error)) from None
    apply_default_num_threads(model.policy)  # the fastest count for its networks, unless --num-threads chose one
    if isinstance(model, Oracle) and model.task_standardisation is None:  # saved before it recorded its own
        model.task_standardisation = training_standardisation(env_id, training_kwargs)
    check_model_spaces(model, env, model_path, env_id)  # a UsageError: saved for another env
    check_model_family(model, env, model_path, env_id)  # a UsageError: trained on another family (no args.yml needed)
    try:
        tasks = model_test_tasks(model, env, args.n_tasks, eval_seed, model_path)
    except ValueError as error:  # the draw hits training tasks (few distinct tasks in the family)
        raise UsageError(f"{error} (--eval-seed)") from None
    source = "shifted ranges, " if shifted else ""
    print(f"{len(tasks)} test tasks ({source}eval seed {eval_seed}), trajectories k = 0 (prior) .. {args.n_adapt} (posterior)")

    def name_video(task: int, repeat: int, k: int) -> None:
        if isinstance(env, RecordVideo):
            phase = "prior" if k == 0 else "posterior"
            env.name_prefix = f"{args.algo}-{env_id}-task{task}-rep{repeat}-k{k}-{phase}"

    try:
        settings = {"n_adapt": args.n_adapt, "n_repeats": args.n_repeats, "deterministic": not args.stochastic}
        result = run_meta_test(
            model,
            env,
            tasks,
            settings,
            eval_seed,
            on_trajectory_start=name_video,
            progress_bar=True,
            description="Rollouts (Ctrl-C stops)",
        )
    except KeyboardInterrupt:
        print("Interrupted: no summary")
        raise SystemExit(130) from None
    finally:
        env.close()
    result.config.update(algo=args.algo, env_id=env_id, model_path=model_path)
    for task_index, task in enumerate(result.tasks):
        for repeat in range(args.n_repeats):
            print(f"\nTask {task_index} (repeat {repeat}): {json.dumps(task)}")
            print(format_task_table(result, task_index, repeat))
    n_trajectories = len(result.tasks) * args.n_repeats
    columns = f"the prior (k = 0) and the posterior after k = 1..{args.n_adapt}" if args.n_adapt else "the prior (k = 0)"
    print(f"\nSummary over tasks: {columns}, {n_trajectories} trajectories each")
    print(format_prior_posterior_table(result.summary))
    if args.video_folder is not None:
        print(f"Videos in {args.video_folder}")
    if args.plot is not None:
        from sb3_pearl.evaluation.figures import plot_all

        output = args.plot or os.path.join(log_path, "enjoy_adaptation.png")
        for path in plot_all({args.algo: result}, output, title=f"{args.algo} on {env_id}"):
            print(f"Saved {path}")
    return result


__all__ = ["enjoy", "enjoy_parser", "format_task_table"]
