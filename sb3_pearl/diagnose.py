"""``python -m sb3_pearl.diagnose <run folder or model.zip>``: the prior-safety diagnostics of a trained model.

Prints :func:`sb3_pearl.pearl.diagnostics.compute_diagnostics` as a table (``--json``: as JSON).
The model and its env id are found in:

- a reproduction-harness run folder ``results/<exp>/<family>/<variant>/seed<N>/`` holding
  ``result.json`` (whose spec names the env id, and possibly env kwargs) and ``model.zip``;
- an rl-zoo run folder ``logs/<algo>/<EnvId>_<n>/`` holding ``<EnvId>.zip`` and
  ``<EnvId>/config.yml`` (env kwargs from ``<EnvId>/args.yml``);
- a model zip: the env id comes from ``--env-id`` or from the zip's folder (either layout above).

``--env-id`` overrides the env id found. See docs/diagnostics.md for how to read the numbers.

``--paths out.png`` (point families, whose observation is the 2-D position) also draws the prior policy's
k = 0 paths on ``--paths-tasks`` held-out tasks spread over the goal angles, ``--paths-z0`` prior draws each
(:func:`sb3_pearl.evaluation.figures.plot_prior_paths`).
"""

from __future__ import annotations

import argparse
import json
import os
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import sb3_pearl  # noqa: F401  (registers the envs)
from sb3_pearl.common.checks import non_negative_int, positive_int
from sb3_pearl.common.persistence import read_model_data
from sb3_pearl.envs.task_protocol import Task
from sb3_pearl.pearl import PEARL, PEARLPlus
from sb3_pearl.pearl.diagnostics import (
    DEFAULT_N_GRAD_BATCHES,
    DEFAULT_N_POSTERIOR_SAMPLES,
    DEFAULT_N_TASKS,
    DEFAULT_N_Z0,
    compute_diagnostics,
    format_diagnostics,
    prior_term,
)
from sb3_pearl.zoo.model_checks import check_saved_model_family
from sb3_pearl.zoo.safe_config import load_run_yaml
from sb3_pearl.zoo.usage import UsageError

LAYOUT_HELP = (
    "expected a run folder with result.json and model.zip (reproduction harness: results/<exp>/<family>/<variant>/seed<N>/), "
    "an rl-zoo run folder logs/<algo>/<EnvId>_<n>/ with <EnvId>.zip and <EnvId>/config.yml, or a model zip "
    "(with --env-id if its folder is neither)"
)
# Keys that may name the env id in a harness result.json (at any depth of nested dicts).
ENV_ID_KEYS = ("env_id", "env", "env_name")


class RunFolderError(ValueError):
    """The path is not a run folder or model zip the diagnostics can read."""


def _env_from_result(path: Path) -> tuple[str | None, dict[str, Any]]:
    """
    Env id (a registered one) and env kwargs named in a harness ``result.json``.

    The shallowest dict (breadth first through nested dicts, e.g. ``spec`` then ``spec["family"]``) with an
    ``env_id`` / ``env`` / ``env_name`` entry naming a registered env wins; ``env_kwargs`` is read beside it.
    """
    with open(path) as file:
        data = json.load(file)
    queue: deque[Any] = deque([data])
    while queue:
        section = queue.popleft()
        if not isinstance(section, dict):
            continue
        for key in ENV_ID_KEYS:
            value = section.get(key)
            if isinstance(value, str) and value in gym.registry:
                kwargs = section.get("env_kwargs")
                return value, dict(kwargs) if isinstance(kwargs, dict) else {}
        queue.extend(value for value in section.values() if isinstance(value, dict))
    return None, {}


def _zoo_env_folders(folder: Path) -> list[Path]:
    """Sub-folders ``<EnvId>/`` holding a ``config.yml`` (rl-zoo run folder)."""
    return sorted(sub for sub in folder.iterdir() if sub.is_dir() and (sub / "config.yml").is_file())


def _zoo_env_kwargs(env_folder: Path) -> dict[str, Any]:
    args_path = env_folder / "args.yml"
    if not args_path.is_file():
        return {}
    saved = load_run_yaml(args_path) or {}  # never yaml.UnsafeLoader: a run folder is data
    return dict(saved.get("env_kwargs") or {})


def find_run(path: str | os.PathLike[str], env_id: str | None = None) -> tuple[Path, str, dict[str, Any]]:
    """
    The model zip, env id and env kwargs of a run folder or model zip (module docstring).

    :param path: a run folder (harness or rl-zoo layout) or a model zip
    :param env_id: env id overriding the one found (required for a zip outside both layouts)
    :return: model path, env id, env kwargs
    """
    target = Path(path)
    if not target.exists():
        raise RunFolderError(f"{target} does not exist: {LAYOUT_HELP}")
    folder = target.parent if target.is_file() else target
    model_path: Path | None = target if target.is_file() else None
    found_env: str | None = None
    env_kwargs: dict[str, Any] = {}
    if (folder / "result.json").is_file():
        found_env, env_kwargs = _env_from_result(folder / "result.json")
        if model_path is None:
            model_path = folder / "model.zip"
    else:
        env_folders = _zoo_env_folders(folder)
        if len(env_folders) > 1 and env_id is None:
            raise RunFolderError(f"{folder} holds several <EnvId>/config.yml ({[f.name for f in env_folders]}): pass --env-id")
        chosen = [f for f in env_folders if env_id is None or f.name == env_id]
        if chosen:
            found_env, env_kwargs = chosen[0].name, _zoo_env_kwargs(chosen[0])
            if model_path is None:
                model_path = folder / f"{found_env}.zip"
    if model_path is None:
        raise RunFolderError(f"{folder} is not a run folder: {LAYOUT_HELP}")
    if not model_path.is_file() or model_path.suffix != ".zip":
        raise RunFolderError(f"no model zip at {model_path}: {LAYOUT_HELP}")
    env_id = env_id or found_env
    if env_id is None:
        raise RunFolderError(f"cannot tell the env id of {model_path}: pass --env-id ({LAYOUT_HELP})")
    if env_id not in gym.registry:
        raise RunFolderError(f"unknown env id {env_id!r} (not registered with gymnasium)")
    return model_path, env_id, env_kwargs


def load_model(model_path: str | Path, env: gym.Env, device: str = "auto", env_id: str | None = None) -> PEARL:
    """
    Load a PEARL or PEARL+ zip with its own class (PEARL when it has no prior critic).

    :param model_path: the zip
    :param env: the env it is used with
    :param device: torch device
    :param env_id: the env's id: a model of another task family is then refused with a message naming the
        ``--env-id`` to pass (without it, the constructor's error)
    :return: the model
    """
    try:
        data = read_model_data(model_path)  # a truncated or corrupt zip: an error that says so
    except ValueError as error:
        raise RunFolderError(str(error)) from None
    if any(key not in data for key in PEARL.saved_data_keys):
        raise RunFolderError(f"{model_path} is not a PEARL / PEARL+ model: the diagnostics need one")
    if env_id is not None:
        try:
            check_saved_model_family(str(model_path), env, env_id, "--env-id")
        except UsageError as error:
            raise RunFolderError(str(error)) from None
    cls = PEARLPlus if PEARLPlus._variant_of(data) is not None else PEARL  # a PEARL model (no prior term): PEARL
    return cls.load(model_path, env=env, device=device)


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(
        prog="python -m sb3_pearl.diagnose",
        description="Prior-safety diagnostics of a trained PEARL / PEARL+ model: posterior-prior overlap, k = 0 "
        "violations against the distance of z0 to the posteriors, prior-critic calibration and the actor's "
        "gradient conflict (docs/diagnostics.md).",
    )
    p.add_argument("path", help="run folder (result.json + model.zip, or rl-zoo logs/<algo>/<EnvId>_<n>/) or a model zip")
    p.add_argument("--env-id", default=None, help="env id (default: from the run folder)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the diagnostics' draws and resets")
    p.add_argument("--n-tasks", type=positive_int, default=DEFAULT_N_TASKS, help="training / held-out tasks used")
    p.add_argument("--n-z0", type=positive_int, default=DEFAULT_N_Z0, help="prior draws rolled out per task")
    p.add_argument("--n-posterior-samples", type=positive_int, default=DEFAULT_N_POSTERIOR_SAMPLES, help="per training task")
    p.add_argument(
        "--n-grad-batches", type=positive_int, default=DEFAULT_N_GRAD_BATCHES, help="meta-batches of the gradient conflict"
    )
    p.add_argument("--max-steps", type=positive_int, default=None, help="cap on trajectory length")
    p.add_argument("--device", default="cpu", help="torch device")
    p.add_argument("--json", action="store_true", help="print JSON instead of the table")
    p.add_argument("--paths", default=None, metavar="PNG", help="also draw the k = 0 paths (point families) to this PNG")
    p.add_argument("--paths-tasks", type=positive_int, default=4, help="held-out tasks drawn by --paths (one panel each)")
    p.add_argument("--paths-z0", type=positive_int, default=10, help="prior draws per task drawn by --paths")
    return p


def spread_tasks(tasks: list[Task], n: int) -> list[Task]:
    """
    ``n`` of ``tasks`` spread over their goal directions: evenly spaced in the order of the goal angle when
    every task has a 2-D ``"goal"``, else evenly spaced in the given order.

    :param tasks: the candidate tasks
    :param n: how many to pick (all of them if there are fewer)
    :return: the picked tasks
    """
    if all("goal" in task and len(task["goal"]) == 2 for task in tasks):
        tasks = sorted(tasks, key=lambda task: float(np.arctan2(task["goal"][1], task["goal"][0])))
    n = min(n, len(tasks))
    return [tasks[int(i)] for i in np.linspace(0, len(tasks) - 1, n).round()]


def draw_prior_paths(model: PEARL, env: gym.Env, out: str, n_tasks: int, n_z0: int, seed: int, max_steps: int | None) -> None:
    """
    Draw the k = 0 paths of ``model`` on ``n_tasks`` held-out tasks spread over the goal angles (``--paths``).

    :param model: a PEARL / PEARL+ model of a point family
    :param env: its env
    :param out: PNG path
    :param n_tasks: tasks (panels)
    :param n_z0: prior draws per task, drawn with ``np.random.default_rng(seed)``
    :param seed: seed of the draws and resets
    :param max_steps: trajectory cap
    """
    from sb3_pearl.evaluation.figures import plot_prior_paths
    from sb3_pearl.pearl.diagnostics.paths import prior_paths

    if min(n_tasks, n_z0) < 1:
        raise ValueError("--paths-tasks and --paths-z0 must be >= 1")
    tasks = spread_tasks(list(model.test_tasks or model.train_tasks), n_tasks)
    z0 = np.random.default_rng(seed).standard_normal((n_z0, model.latent_dim))
    paths = prior_paths(model, env, tasks, z0, seed, max_steps)
    radius = getattr(env.unwrapped, "hazard_radius", None)
    rate = np.mean([r.violated for rollouts in paths for r in rollouts])
    label = f"{type(model).__name__} (prior_coef {prior_term(model).coef:g})"
    plot_prior_paths(paths, tasks, out, hazard_radius=radius, title=f"{label}: k = 0 paths, {rate:.0%} in a hazard")


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """
    Run the diagnostics from the command line and print them.

    :param argv: arguments (default: ``sys.argv[1:]``)
    :return: the diagnostics
    """
    p = parser()
    args = p.parse_args(argv)
    try:
        model_path, env_id, env_kwargs = find_run(args.path, args.env_id)
        env = gym.make(env_id, **env_kwargs)
        model = load_model(model_path, env, args.device, env_id)
    except RunFolderError as error:
        p.error(str(error))
    if args.paths:
        from sb3_pearl.pearl.diagnostics.paths import check_position_observation

        try:
            check_position_observation(model)  # before the diagnostics' minute of rollouts
        except ValueError as error:
            p.error(f"--paths: {error}")
    result = compute_diagnostics(
        model,
        env,
        seed=args.seed,
        n_tasks=args.n_tasks,
        n_z0=args.n_z0,
        n_posterior_samples=args.n_posterior_samples,
        n_grad_batches=args.n_grad_batches,
        max_steps=args.max_steps,
    )
    result["run"] = {"model": str(model_path), "env_id": env_id, "env_kwargs": env_kwargs}
    if args.json:
        print(json.dumps(result, indent=1, default=str))
    else:
        print(f"{model_path} on {env_id}" + (f" {env_kwargs}" if env_kwargs else ""))
        print(format_diagnostics(result))
    if args.paths:  # after the printout, so that a failure here loses nothing
        draw_prior_paths(model, env, args.paths, args.paths_tasks, args.paths_z0, args.seed, args.max_steps)
    return result


if __name__ == "__main__":
    main()
