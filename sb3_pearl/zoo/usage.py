"""User errors of ``train.py`` / ``enjoy.py``: one line on stderr and exit status 2 (argparse's), no traceback.

:class:`UsageError` is what the zoo raises for a mistake in the command line or the hyperparameters (an unknown env,
a ``-params`` value that is not Python, a key the algorithm does not take, a value it refuses);
:func:`exit_on_usage_error` turns it into the one-line message. :class:`CheckedStoreDict` is rl_zoo3's
``StoreDict`` (``-params``, ``--env-kwargs``) with such an error instead of a traceback for a bad value.
"""

from __future__ import annotations

import argparse
import difflib
import os
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import gymnasium as gym
import yaml

from sb3_pearl.common.checks import output_folder_problem
from sb3_pearl.zoo.rl_zoo3_coupling import StoreDict

EXIT_USAGE = 2  # argparse's status for a bad command line


class UsageError(ValueError):
    """A mistake in the command line or the hyperparameters (the message says which and how to fix it)."""


class UsageExit(SystemExit):
    """``SystemExit`` with status 2 whose text is the error message (for callers that catch it, e.g. tests)."""

    def __init__(self, message: str) -> None:
        super().__init__(EXIT_USAGE)
        self.message = message

    def __str__(self) -> str:
        return self.message


def program_name() -> str:
    """The command's name for messages: ``train.py``, ``enjoy.py``, ``sb3-pearl-train``, ..."""
    return os.path.basename(sys.argv[0]) or "sb3_pearl"


@contextmanager
def exit_on_usage_error(prog: str | None = None) -> Iterator[None]:
    """
    Print a :class:`UsageError` raised inside as ``<prog>: error: <message>`` and exit with status 2 (:class:`UsageExit`).

    :param prog: the command's name (default: :func:`program_name`)
    """
    try:
        yield
    except UsageError as error:
        message = f"{prog or program_name()}: error: {error}"
        print(message, file=sys.stderr, flush=True)
        raise UsageExit(message) from None


def check_env_id(env_id: str) -> None:
    """
    Raise a :class:`UsageError` naming the closest registered id if ``env_id`` is not registered.

    :param env_id: the ``--env`` value
    """
    if env_id in gym.registry:
        return
    close = difflib.get_close_matches(env_id, list(gym.registry), n=1)
    raise UsageError(f"--env {env_id}: not found in gym registry" + (f", did you mean {close[0]}?" if close else ""))


class CheckedStoreDict(StoreDict):
    """rl_zoo3's ``StoreDict`` (``key:value`` pairs, values evaluated as Python) with a :class:`UsageError` for a bad pair."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        example = 'e.g. learning_rate:0.001 policy_kwargs:"dict(net_arch=[64, 64])"'
        for pair in values or []:
            key, sep, value = str(pair).partition(":")
            if not sep or not key:
                raise UsageError(f"{option_string} {pair}: expected key:value, {example}")
            try:  # what StoreDict does with it, in its module (rl_zoo3's convention: the values are Python expressions)
                eval(value, vars(sys.modules[StoreDict.__module__]))
            except Exception as error:
                raise UsageError(
                    f"{option_string} {pair}: the value {value!r} is not a Python expression ({type(error).__name__}: "
                    f"{error}); strings need quotes, {example}"
                ) from None
        super().__call__(parser, namespace, values, option_string)


__all__ = [
    "EXIT_USAGE",
    "CheckedStoreDict",
    "UsageError",
    "UsageExit",
    "check_conf_file",
    "check_env_id",
    "check_log_folder",
    "check_n_envs",
    "check_n_timesteps",
    "check_seed",
    "check_yaml_n_timesteps",
    "exit_on_usage_error",
    "flag_values",
    "program_name",
]


def flag_values(args: list[str], names: tuple[str, ...]) -> Iterator[tuple[str, str]]:
    """
    The values given to the flags ``names`` on the command line (``-n 5`` or ``-n=5``), as written.

    :param args: the command line
    :param names: the flag's spellings
    :return: (spelling, value) pairs
    """
    for index, arg in enumerate(args):
        name, _, value = arg.partition("=")
        if name in names:
            yield name, value or (args[index + 1] if index + 1 < len(args) else "")


MAX_SEED = 2**32 - 1  # numpy's and rl_zoo3's bound


def check_seed(args: list[str]) -> None:
    """
    Refuse a ``--seed`` outside [0, 2**32 - 1] at parse time (rl_zoo3 replaced a negative one by a random seed, and
    numpy refused a larger one with a traceback).

    :param args: the command line
    """
    for name, value in flag_values(args, ("--seed",)):
        try:
            seed = int(value)
        except ValueError:
            seed = None
        if seed is None or not 0 <= seed <= MAX_SEED:
            raise UsageError(f"{name} must be an integer in [0, {MAX_SEED}] (omit it for a random seed), got {value!r}")


def check_log_folder(args: list[str]) -> None:
    """
    Refuse a ``-f`` / ``--log-folder`` that is a file, lies under a file or cannot be written, before anything is built.

    :param args: the command line
    """
    for name, value in flag_values(args, ("-f", "--log-folder")):
        problem = output_folder_problem(value)
        if problem is not None:
            raise UsageError(f"{name} {value}: {problem}: give a folder for the run folders that you can write to")


def check_n_timesteps(args: list[str]) -> list[str]:
    """
    Check ``-n`` / ``--n-timesteps`` at parse time: a positive whole number of env steps, written as the YAML files write
    it (``2000``, ``2e3``, ``2_000``); refuse 0 or less (rl_zoo3 would train the YAML's budget instead).

    :param args: the command line (not changed)
    :return: the command line with the value as rl_zoo3's ``int`` parser takes it (``2e3`` -> ``2000``)
    """
    args = list(args)
    for index, arg in enumerate(args):
        name, sep, value = arg.partition("=")
        if name not in ("-n", "--n-timesteps"):
            continue
        value = value if sep else (args[index + 1] if index + 1 < len(args) else "")
        try:
            number = float(value.replace("_", ""))
        except ValueError:
            raise UsageError(f"{name} takes a number of env steps, got {value!r}") from None
        if not number.is_integer():
            raise UsageError(f"{name} takes a whole number of env steps, got {value!r}")
        steps = int(number)
        if steps <= 0:
            raise UsageError(
                f"{name} must be a positive number of env steps, got {steps} (omit it for the YAML's n_timesteps)"
            )
        if sep:
            args[index] = f"{name}={steps}"
        else:
            args[index + 1] = str(steps)
    return args


def check_yaml_n_timesteps(hyperparams: dict[str, Any], where: str) -> None:
    """
    Refuse a hyperparameter entry whose ``n_timesteps`` is not a positive number (it would train nothing, then meta-test).

    :param hyperparams: the entry
    :param where: the file and entry, for the message
    """
    steps = hyperparams.get("n_timesteps")
    if steps is not None and (not isinstance(steps, (int, float)) or isinstance(steps, bool) or steps < 1):
        raise UsageError(f"n_timesteps in {where} must be a positive number of env steps, got {steps!r}")


def check_n_envs(hyperparams: dict[str, Any], where: str) -> None:
    """
    Refuse an ``n_envs`` that is not a whole number >= 1 (0 divided the evaluation frequency by zero).

    :param hyperparams: the entry after ``-params`` overrides
    :param where: where the value was given, for the message
    """
    n_envs = hyperparams.get("n_envs")
    if n_envs is not None and (not isinstance(n_envs, int) or isinstance(n_envs, bool) or n_envs < 1):
        raise UsageError(f"n_envs must be an integer >= 1, got {n_envs!r} (in {where})")


def check_conf_file(path: str, env_id: str) -> None:
    """
    Refuse a ``-conf`` YAML file that is not valid YAML, or does not hold a mapping of env ids to hyperparameter entries
    (rl_zoo3 failed on it with a traceback).

    :param path: the file (a ``.yml`` / ``.yaml`` that exists)
    :param env_id: the env trained on (its entry, if the file has one, must be a mapping too)
    """
    expected = "a mapping of env ids to hyperparameter entries (see zoo_hyperparams/*.yml)"
    try:
        with open(path) as file:
            content = yaml.safe_load(file)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(error, "problem", None) or type(error).__name__
        raise UsageError(f"-conf {path} is not valid YAML ({problem}{where}): it must hold {expected}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise UsageError(f"-conf {path} cannot be read ({error}): give a YAML file holding {expected}") from None
    if not isinstance(content, dict):
        got = "nothing (the file is empty)" if content is None else f"a {type(content).__name__}"
        raise UsageError(f"-conf {path} holds {got}: it must hold {expected}")
    entry = content.get(env_id)
    if env_id in content and not isinstance(entry, dict):
        raise UsageError(f"-conf {path}: the entry {env_id} must be a mapping of hyperparameters, got {entry!r}")
