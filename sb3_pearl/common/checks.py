"""Argument checks shared by the algorithms: each error names the argument, the value and what to pass instead.

The constructors call these before building anything (no env is created for a bad argument), so a
typo in a YAML entry fails at once instead of training a silently wrong model.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable
from typing import Any

import numpy as np

from sb3_pearl.envs.checks import check_number, is_real


def is_integer(value: Any) -> bool:
    """Whether ``value`` is an integer (Python or numpy), not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _hint(hint: str) -> str:
    return f" ({hint})" if hint else ""


def check_int(name: str, value: Any, minimum: int, hint: str = "") -> None:
    """
    Raise unless ``value`` is an integer >= ``minimum``.

    :param name: the argument's name
    :param value: its value
    :param minimum: the smallest valid value
    :param hint: what the argument does, for the message
    """
    if not is_integer(value) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}{_hint(hint)}, got {value!r}")


def check_real(
    name: str,
    value: Any,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    hint: str = "",
) -> None:
    """
    Raise unless ``value`` is a finite real number in the interval given by ``low`` / ``high``.

    :param name: the argument's name
    :param value: its value
    :param low: lower bound (None: none)
    :param high: upper bound (None: none)
    :param low_open: exclude ``low``
    :param high_open: exclude ``high``
    :param hint: what the argument does, for the message
    """
    check_number(name, value, low, high, low_open=low_open, high_open=high_open, hint=hint)


def check_gamma(gamma: Any) -> None:
    """Raise unless the discount factor is in (0, 1]."""
    check_real("gamma", gamma, 0.0, 1.0, low_open=True, hint="the discount factor, e.g. 0.99")


def check_tau(tau: Any) -> None:
    """Raise unless the Polyak coefficient is in [0, 1]."""
    check_real("tau", tau, 0.0, 1.0, hint="the Polyak coefficient of the target critics, e.g. 0.005")


def check_learning_rate(name: str, learning_rate: float | Callable[[float], float]) -> None:
    """Raise unless ``learning_rate`` is a schedule (callable) or a finite number >= 0."""
    if not callable(learning_rate):
        check_real(name, learning_rate, 0.0, hint="e.g. 3e-4, or a schedule: a function of the remaining progress")


def check_ent_coef(ent_coef: Any) -> None:
    """Raise unless ``ent_coef`` is ``"auto"`` / ``"auto_<init>"`` with init > 0, or a finite number >= 0."""
    if isinstance(ent_coef, str):
        init = ent_coef.split("_", 1)[1] if ent_coef.startswith("auto_") else "1.0"
        try:
            valid = ent_coef == "auto" or (ent_coef.startswith("auto_") and float(init) > 0 and math.isfinite(float(init)))
        except ValueError:
            valid = False
        if not valid:
            raise ValueError(
                f"ent_coef must be a number >= 0, 'auto' or 'auto_<init>' with init > 0 (e.g. 'auto_0.1'), got {ent_coef!r}"
            )
        return
    check_real("ent_coef", ent_coef, 0.0, hint="the entropy coefficient; 'auto' learns it")


def check_arch(name: str, arch: Any) -> None:
    """
    Raise unless ``arch`` is a list of hidden-layer sizes, each an integer >= 1 (an empty list: no hidden layer),
    or SB3's dict of such lists (``dict(pi=[64], qf=[64])``).
    """
    if arch is None:
        return
    if isinstance(arch, dict):
        for key, value in arch.items():
            check_arch(f"{name}[{key!r}]", value)
        return
    if not isinstance(arch, (list, tuple)) or not all(is_integer(size) and size >= 1 for size in arch):
        raise ValueError(f"{name} must be a list of hidden-layer sizes, each an integer >= 1 (e.g. [256, 256]), got {arch!r}")


def check_task_counts(n_train_tasks: Any, n_test_tasks: Any) -> None:
    """Raise unless ``n_train_tasks >= 1`` and ``n_test_tasks >= 0``."""
    check_int("n_train_tasks", n_train_tasks, 1, hint="training tasks drawn from the env")
    check_int("n_test_tasks", n_test_tasks, 0, hint="held-out test tasks drawn with them; 0 for none")


__all__ = [
    "check_arch",
    "check_ent_coef",
    "check_gamma",
    "check_int",
    "check_learning_rate",
    "check_real",
    "check_task_counts",
    "check_tau",
    "is_integer",
    "is_real",
    "output_folder_problem",
]


def output_folder_problem(path: str) -> str | None:
    """
    Why ``path`` cannot be an output folder (it or the nearest existing folder above it is a file, or not writable),
    or None when it can: the check of a results or log folder before any run starts.

    Writability is asked (``os.access``), then tried: a folder is created in the nearest existing one and removed at
    once (``os.access`` says yes to root for a read-only file system or a pseudo file system such as /sys).

    :param path: the folder (it need not exist)
    :return: the problem, or None
    """
    existing = os.path.abspath(path or ".")
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        return f"{existing} is a file, not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{existing} is not writable"
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".write-probe-", dir=existing))
    except OSError as error:
        return f"{existing} is not writable ({error.strerror or error})"
    return None


def positive_int(text: str) -> int:
    """argparse ``type``: an integer >= 1 (the parser's one-line error names the flag otherwise)."""
    return _bounded_int(text, 1)


def non_negative_int(text: str) -> int:
    """argparse ``type``: an integer >= 0 (seeds)."""
    return _bounded_int(text, 0)


def _bounded_int(text: str, low: int) -> int:
    import argparse

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {value}")
    return value
