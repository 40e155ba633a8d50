"""``train.py --budget PRESET``: a family's entry of a budget preset as the zoo's hyperparameters.

The presets (``sb3_pearl/config/presets/*.yml``, read by :func:`~sb3_pearl.budgets.load_budget`) are the one source
of the reproduction harness's budgets; ``--budget cpu`` trains with the same entry (sized for one run <= 45 minutes on
one core; the timings: docs/reproduce.md) instead of the paper-sized entry of ``zoo_hyperparams/<algo>.yml``. Env ids
map to the presets' family names through :data:`sb3_pearl.budgets.ENV_PRESET_FAMILY`.
"""

from __future__ import annotations

from typing import Any

from sb3_pearl.budgets import ENV_PRESET_FAMILY, PRESETS, load_budget, preset_entries
from sb3_pearl.zoo.usage import UsageError


def env_family(env_id: str) -> str | None:
    """
    The presets' family key that ``train.py --budget`` uses for ``env_id`` (None: no family trains on it).

    :param env_id: a registered env id
    :return: the family name, a top-level key of the presets
    """
    return ENV_PRESET_FAMILY.get(env_id)


def families_with(preset: str, algo: str) -> list[str]:
    """
    ``"<EnvId> (<family>)"`` for every family with an entry for ``algo`` in ``preset``.

    :param preset: ``smoke``, ``cpu`` or ``paper``
    :param algo: zoo algorithm name
    :return: one label per env id
    """
    entries = preset_entries(preset)
    return [f"{env_id} ({family})" for env_id, family in ENV_PRESET_FAMILY.items() if algo in entries.get(family, [])]


def budget_hyperparams(preset: str, env_id: str, algo: str) -> dict[str, Any]:
    """
    The zoo entry of ``env_id`` for ``algo`` taken from a budget preset.

    :param preset: ``smoke``, ``cpu`` or ``paper``
    :param env_id: the env id
    :param algo: zoo algorithm name
    :return: ``n_timesteps``, ``policy``, ``n_envs``, the constructor kwargs and ``meta_test``
    :raises UsageError: unknown preset, or no entry for this env and algorithm
    """
    if preset not in PRESETS:
        raise UsageError(f"--budget {preset}: unknown budget preset, choose among {', '.join(PRESETS)}")
    family = env_family(env_id)
    if family is None or algo not in preset_entries(preset).get(family, []):
        have = families_with(preset, algo)
        raise UsageError(
            f"--budget {preset}: the {preset} preset has no {algo} entry for {env_id}; it has one for "
            f"{', '.join(have) or 'no env'} (sb3_pearl/config/presets/{preset}.yml). Without --budget, "
            f"lower -n or the network sizes with -params"
        )
    budget = load_budget(preset, family, algo)
    kwargs = dict(budget["kwargs"])  # plain data as in the preset (activation by name): the run's config.yml stays so
    return {
        "n_timesteps": budget["n_timesteps"],
        "policy": budget["policy"],
        "n_envs": budget["n_envs"],
        **kwargs,
        "meta_test": dict(budget["meta_test"]),
    }


def faster_option(env_id: str, algo: str, budget: str | None, prog: str = "train.py") -> str:
    """
    What to run instead of a training run that takes more than a day on a CPU.

    :param env_id: the env id
    :param algo: zoo algorithm name
    :param budget: the ``--budget`` of the run (None: the YAML entry)
    :param prog: the command's name
    :return: the advice
    """
    if budget == "cpu":
        return "It already uses the cpu preset: lower -n, or train on a GPU (--device cuda)."
    try:
        entry = budget_hyperparams("cpu", env_id, algo)
    except UsageError:
        have = families_with("cpu", algo)
        return (
            f"No CPU-sized budget exists for {env_id} ({prog} --budget cpu has entries for {', '.join(have)}): "
            "lower -n or the network sizes (-params policy_kwargs:...), or train on a GPU."
        )
    return (
        f"Faster: {prog} --algo {algo} --env {env_id} --budget cpu trains with the reproduction harness's cpu preset "
        f"({entry['n_timesteps']:,} env steps, policy_kwargs {entry.get('policy_kwargs', 'default')}; "
        "PEARL / PEARL+ runs of it took 5-44 min on one core)."
    )


__all__ = ["budget_hyperparams", "env_family", "families_with", "faster_option"]
