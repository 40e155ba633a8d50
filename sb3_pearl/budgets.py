"""Budget presets: how much each (family, algorithm) run trains and meta-tests, as data.

One YAML file per preset in ``sb3_pearl/config/presets/`` (shipped with the package). ``train.py --budget PRESET``
trains with a family's entry (:mod:`sb3_pearl.zoo.budget`), and the paper's reproduction harness
(``pearl_paper.reproduce``, in the repository beside the package) sizes every run with them; the loader lives here,
with the data it reads, so that both use one set of checks:

- ``smoke``: seconds per run, for the tests;
- ``cpu``: sized for one run <= 45 minutes on one core of the project's CPU machine (docs/reproduce.md has the timing
  measurements behind each number, and the runs that take longer);
- ``paper``: the paper's / the reference implementation's budgets (a GPU machine).

Each file maps family name -> zoo algorithm name -> entry::

    walker2d-vel:
      pearlplus:
        n_timesteps: 150000        # env steps of learn()
        n_envs: 1                  # envs of the training VecEnv (optional, default 1)
        kwargs: {...}              # constructor kwargs of the algorithm (policy_kwargs as a plain dict;
                                   # activation_fn by name: relu, tanh, elu, leaky_relu)
        meta_test: {n_tasks: 20, n_repeats: 10, n_adapt: 5}       # the held-out meta-test
        shift_meta_test: {...}     # optional: the shifted-distribution meta-test (default: meta_test)
        competence_meta_test: {...}  # optional: the training-task meta-test of the competence check

:func:`load_budget` is the one way to read them. A top-level key names a task family; :data:`ENV_PRESET_FAMILY`
says which key ``train.py --budget`` uses for an env id. The other keys (``walker2d-vel-long``, ``...-oracle``,
``...-columns``) are entries of longer or differently sized runs that the harness's experiments name themselves.
"""

from __future__ import annotations

import copy
import functools
from typing import Any

import yaml

from sb3_pearl.config import PRESETS_DIR
from sb3_pearl.evaluation.held_out import META_TEST_DEFAULTS
from sb3_pearl.registry import ACTIVATIONS, algorithm_class, constructor_kwargs

PRESETS: tuple[str, ...] = ("smoke", "cpu", "paper")
#: env id -> the presets' family key whose entries ``train.py --budget`` trains it with
ENV_PRESET_FAMILY: dict[str, str] = {
    "SafePointGoalMeta-v0": "safe-point",
    "Walker2dVelMeta-v0": "walker2d-vel",
    "AntVelMeta-v0": "ant3d-vel",
    "HighwayMergeMeta-v0": "highway-merge",
    "HalfCheetahVelMeta-v0": "cheetah-vel",
}
ENTRY_KEYS = frozenset(
    {"n_timesteps", "n_envs", "policy", "kwargs", "meta_test", "shift_meta_test", "competence_meta_test", "curve"}
)
# The learning curve on the test tasks (optional; the harness's runner draws it, train.py ignores it): every `every`
# env steps, the reference's evaluation on `n_tasks` held-out tasks (n_adapt + 1 trajectories each, the first
# `n_prior_trajectories` with z from the prior) and the k = 0 return and violation rate.
CURVE_KEYS = frozenset({"every", "n_tasks", "n_adapt", "n_prior_trajectories"})
CURVE_DEFAULTS = {"n_adapt": 2, "n_prior_trajectories": 1}
META_TEST_KEYS = frozenset(META_TEST_DEFAULTS)  # the one definition of a meta-test's settings (evaluation/held_out.py)
COMPETENCE_DEFAULTS: dict[str, Any] = {"n_tasks": 10, "n_repeats": 1, "n_adapt": 2, "deterministic": True}
# Presets whose meta-test must measure k = 0 with >= 10 prior draws per task and >= 200 k = 0 trajectories.
STATISTICS_FLOOR: dict[str, tuple[int, int]] = {"cpu": (10, 200), "paper": (10, 200)}


@functools.cache
def _read_preset(preset: str) -> dict[str, Any]:
    if preset not in PRESETS:
        raise ValueError(f"unknown budget preset {preset!r}: choose among {PRESETS}")
    path = PRESETS_DIR / f"{preset}.yml"
    with open(path) as file:
        data = yaml.safe_load(file) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: a preset maps family names to algorithms to entries")
    return data


def preset_entries(preset: str) -> dict[str, list[str]]:
    """
    What a preset holds.

    :param preset: ``smoke``, ``cpu`` or ``paper``
    :return: family name -> the algorithms it has entries for
    """
    return {family: sorted(algos) for family, algos in _read_preset(preset).items()}


def load_budget(preset: str, family: str, algo: str) -> dict[str, Any]:
    """
    The budget of one (family, algorithm) run, validated, with defaults filled in.

    :param preset: ``smoke``, ``cpu`` or ``paper``
    :param family: family name (``walker2d-vel``, ...)
    :param algo: zoo algorithm name (``pearl``, ``pearlplus``, ``finetune``, ``maml``)
    :return: ``{"n_timesteps", "n_envs", "policy", "kwargs", "meta_test", "shift_meta_test",
        "competence_meta_test"}``; ``kwargs`` as written (see :func:`model_kwargs` for the
        constructor's form); a fresh copy
    """
    data = _read_preset(preset)
    if family not in data:
        raise ValueError(f"budget preset {preset!r} has no family {family!r}: it has {sorted(data)}")
    if algo not in (data[family] or {}):
        raise ValueError(
            f"budget preset {preset!r}, family {family!r} has no algorithm {algo!r}: it has {sorted(data[family])}"
        )
    entry = copy.deepcopy(data[family][algo])
    where = f"preset {preset}, {family}/{algo} ({PRESETS_DIR / (preset + '.yml')})"
    budget = validate_entry(entry, algo, where)
    floor = STATISTICS_FLOOR.get(preset)
    if floor is not None:
        check_statistics_floor(budget["meta_test"], floor, where)
    return budget


def validate_entry(entry: Any, algo: str, where: str) -> dict[str, Any]:
    """
    Check one preset entry and fill in its defaults.

    :param entry: the entry as read
    :param algo: zoo algorithm name (its constructor decides which ``kwargs`` are accepted)
    :param where: for the messages
    :return: the completed entry
    """
    if not isinstance(entry, dict):
        raise ValueError(f"{where}: an entry is a mapping with keys {sorted(ENTRY_KEYS)}, got {entry!r}")
    unknown = sorted(set(entry) - ENTRY_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; an entry takes {sorted(ENTRY_KEYS)}")
    for key in ("n_timesteps", "kwargs", "meta_test"):
        if key not in entry:
            raise ValueError(f"{where}: missing key {key!r}")
    n_timesteps = entry["n_timesteps"]
    if not isinstance(n_timesteps, (int, float)) or int(n_timesteps) != n_timesteps or n_timesteps < 1:
        raise ValueError(f"{where}: n_timesteps must be a positive integer, got {n_timesteps!r}")
    n_envs = entry.get("n_envs", 1)
    if not isinstance(n_envs, int) or n_envs < 1:
        raise ValueError(f"{where}: n_envs must be an integer >= 1, got {n_envs!r}")
    kwargs = entry["kwargs"]
    if not isinstance(kwargs, dict):
        raise ValueError(f"{where}: kwargs must be a mapping of constructor kwargs, got {kwargs!r}")
    check_constructor_kwargs(algo, kwargs, where)
    meta_test = _meta_test(entry["meta_test"], META_TEST_DEFAULTS, f"{where} meta_test")
    if meta_test["n_tasks"] is None:
        raise ValueError(f"{where} meta_test: n_tasks is required (the test tasks are drawn with the experiment's eval seed)")
    shift = _meta_test(entry.get("shift_meta_test", meta_test), meta_test, f"{where} shift_meta_test")
    competence = _meta_test(entry.get("competence_meta_test", {}), COMPETENCE_DEFAULTS, f"{where} competence_meta_test")
    extra = {"curve": _curve(entry["curve"], f"{where} curve")} if "curve" in entry else {}
    return {
        "n_timesteps": int(n_timesteps),
        "n_envs": n_envs,
        "policy": entry.get("policy", "MlpPolicy"),
        "kwargs": kwargs,
        "meta_test": meta_test,
        "shift_meta_test": shift,
        "competence_meta_test": competence,
        **extra,
    }


def _curve(settings: Any, where: str) -> dict[str, Any]:
    if not isinstance(settings, dict) or not {"every", "n_tasks"} <= set(settings):
        raise ValueError(f"{where}: a mapping with `every` and `n_tasks` (and {sorted(CURVE_KEYS)}), got {settings!r}")
    unknown = sorted(set(settings) - CURVE_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed {sorted(CURVE_KEYS)}")
    merged = {**CURVE_DEFAULTS, **settings}
    for key, low in (("every", 1), ("n_tasks", 1), ("n_adapt", 0), ("n_prior_trajectories", 1)):
        if not isinstance(merged[key], int) or isinstance(merged[key], bool) or merged[key] < low:
            raise ValueError(f"{where}: {key} must be an integer >= {low}, got {merged[key]!r}")
    if merged["n_prior_trajectories"] > merged["n_adapt"] + 1:
        raise ValueError(f"{where}: n_prior_trajectories must be at most n_adapt + 1 (the trajectories per task)")
    return merged


def _meta_test(settings: Any, defaults: dict[str, Any], where: str) -> dict[str, Any]:
    if not isinstance(settings, dict):
        raise ValueError(f"{where}: a mapping with keys among {sorted(META_TEST_KEYS)}, got {settings!r}")
    unknown = sorted(set(settings) - META_TEST_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed {sorted(META_TEST_KEYS)}")
    merged = {**defaults, **settings}
    for key in ("n_tasks", "n_repeats"):
        if merged.get(key) is not None and (not isinstance(merged[key], int) or merged[key] < 1):
            raise ValueError(f"{where}: {key} must be an integer >= 1, got {merged[key]!r}")
    if not isinstance(merged["n_adapt"], int) or merged["n_adapt"] < 0:
        raise ValueError(f"{where}: n_adapt must be an integer >= 0, got {merged['n_adapt']!r}")
    return merged


def check_statistics_floor(meta_test: dict[str, Any], floor: tuple[int, int], where: str) -> None:
    """
    Raise unless the meta-test draws k = 0 at least ``floor[0]`` times per task and ``floor[1]`` times in all.

    :param meta_test: the meta-test settings
    :param floor: (minimum n_repeats, minimum n_tasks * n_repeats)
    :param where: for the message
    """
    min_repeats, min_trajectories = floor
    n_k0 = meta_test["n_tasks"] * meta_test["n_repeats"]
    if meta_test["n_repeats"] < min_repeats or n_k0 < min_trajectories:
        raise ValueError(
            f"{where}: the meta-test needs n_repeats >= {min_repeats} prior draws per test task and n_tasks * n_repeats "
            f">= {min_trajectories} k = 0 trajectories, got {meta_test['n_tasks']} x {meta_test['n_repeats']}"
        )


def check_constructor_kwargs(algo: str, kwargs: dict[str, Any], where: str) -> None:
    """
    Raise a clear error for a kwarg the algorithm's constructor does not take (or that the runner sets itself).

    :param algo: zoo algorithm name
    :param kwargs: the kwargs
    :param where: for the message
    """
    cls = algorithm_class(algo)
    accepted = constructor_kwargs(cls) - {"policy"}
    unknown = sorted(set(kwargs) - accepted)
    if unknown:
        raise ValueError(f"{where}: {cls.__name__} does not take {unknown}; accepted kwargs: {sorted(accepted)}")
    policy_kwargs = kwargs.get("policy_kwargs")
    if policy_kwargs is not None and not isinstance(policy_kwargs, dict):
        raise ValueError(f"{where}: policy_kwargs must be a mapping (e.g. {{net_arch: [128, 128]}}), got {policy_kwargs!r}")
    activation = (policy_kwargs or {}).get("activation_fn")
    if activation is not None and activation not in ACTIVATIONS:
        raise ValueError(f"{where}: policy_kwargs.activation_fn must be one of {tuple(ACTIVATIONS)}, got {activation!r}")


def model_kwargs(kwargs: dict[str, Any]) -> dict[str, Any]:
    """
    Constructor kwargs from a budget's (or a variant's) ``kwargs``: ``activation_fn`` names become torch classes.

    :param kwargs: kwargs as written in a preset
    :return: a copy ready for the algorithm's constructor
    """
    result = copy.deepcopy(kwargs)
    policy_kwargs = result.get("policy_kwargs")
    if isinstance(policy_kwargs, dict) and isinstance(policy_kwargs.get("activation_fn"), str):
        policy_kwargs["activation_fn"] = ACTIVATIONS[policy_kwargs["activation_fn"]]
    return result


def check_preset(preset: str) -> int:
    """
    Load every entry of a preset (raising on the first invalid one).

    :param preset: preset name
    :return: the number of entries checked
    """
    count = 0
    for family, algos in preset_entries(preset).items():
        for algo in algos:
            load_budget(preset, family, algo)
            count += 1
    return count


__all__ = [
    "ENV_PRESET_FAMILY",
    "PRESETS",
    "check_preset",
    "load_budget",
    "model_kwargs",
    "preset_entries",
    "validate_entry",
]
