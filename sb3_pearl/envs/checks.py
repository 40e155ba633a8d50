"""Checks of the task families' constructor kwargs: each error names the kwarg, its range and the value.

Every family checks every kwarg of its own before building anything: a non-finite number or one out of its range
(a negative hazard radius, a nan goal radius, an infinite task range) would build an env that runs and reports
nonsense, e.g. a safety family on which no step is ever a violation. Kwargs passed through to a Gymnasium base env
(``frame_skip``, ``healthy_z_range``, ...) are that env's to check.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np


def is_real(value: Any) -> bool:
    """Whether ``value`` is a real number (Python or numpy int / float), not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def check_number(
    name: str,
    value: Any,
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    high_open: bool = False,
    hint: str = "",
) -> float:
    """
    Raise a ``ValueError`` unless ``value`` is a finite real number in the interval given by ``low`` / ``high``.

    :param name: the kwarg's name
    :param value: its value
    :param low: lower bound (None: none)
    :param high: upper bound (None: none)
    :param low_open: exclude ``low``
    :param high_open: exclude ``high``
    :param hint: what the kwarg does, for the message
    :return: the value as a float
    """
    ok = is_real(value) and math.isfinite(float(value))
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        if low is not None and high is not None:
            interval = f" in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
        elif low is not None:
            interval = f" {'>' if low_open else '>='} {low:g}"
        elif high is not None:
            interval = f" {'<' if high_open else '<='} {high:g}"
        else:
            interval = ""
        raise ValueError(f"{name} must be a finite number{interval}{f' ({hint})' if hint else ''}, got {value!r}")
    return float(value)


def check_count(name: str, value: Any, minimum: int = 1, hint: str = "") -> int:
    """
    Raise a ``ValueError`` unless ``value`` is an integer (not a bool, not a float) >= ``minimum``.

    :param name: the kwarg's name
    :param value: its value
    :param minimum: the smallest valid value
    :param hint: what the kwarg does, for the message
    :return: the value as an int
    """
    if not isinstance(value, (int, np.integer)) or isinstance(value, (bool, np.bool_)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}{f' ({hint})' if hint else ''}, got {value!r}")
    return int(value)


def check_range(name: str, low: Any, high: Any, *, allow_empty: bool = False, min_value: float | None = None) -> None:
    """
    Raise a clear ``ValueError`` unless ``[low, high]`` (the kwargs ``<name>_low`` / ``<name>_high``) is a valid,
    finite range.

    :param name: name of the range in the message (e.g. ``"velocity"``: kwargs ``velocity_low/high``)
    :param low: lower bound
    :param high: upper bound
    :param allow_empty: accept ``low == high`` (a single value)
    :param min_value: smallest allowed ``low``
    """
    if not (is_real(low) and is_real(high) and math.isfinite(low) and math.isfinite(high)):
        raise ValueError(f"{name}_low and {name}_high must be finite numbers, got [{low!r}, {high!r}]")
    if high < low or (high == low and not allow_empty):
        raise ValueError(f"{name}_low ({low}) must be {'<=' if allow_empty else '<'} {name}_high ({high})")
    if min_value is not None and low < min_value:
        raise ValueError(f"{name}_low ({low}) must be >= {min_value}")


def check_pair_range(name: str, pair: Any, *, min_value: float = 0.0, min_open: bool = False) -> tuple[float, float]:
    """
    Raise a ``ValueError`` unless ``pair`` is a range ``(low, high)`` of two finite numbers with
    ``min_value <= low <= high`` (``min_value < low`` with ``min_open``).

    :param name: the kwarg's name (e.g. ``"density_range"``)
    :param pair: its value
    :param min_value: the smallest allowed ``low``
    :param min_open: exclude ``min_value``
    :return: ``(low, high)`` as floats
    """
    bound = f"{min_value:g} {'<' if min_open else '<='} low <= high"
    values = list(pair) if isinstance(pair, (Sequence, np.ndarray)) and not isinstance(pair, str) else None
    if values is None or len(values) != 2 or not all(is_real(v) and math.isfinite(float(v)) for v in values):
        raise ValueError(f"{name} must be two finite numbers (low, high) with {bound}, got {pair!r}")
    low, high = float(values[0]), float(values[1])
    if not ((low > min_value if min_open else low >= min_value) and low <= high):
        raise ValueError(f"{name} must satisfy {bound}, got {(low, high)}")
    return low, high


__all__ = ["check_count", "check_number", "check_pair_range", "check_range", "is_real"]
