"""Numbers and intervals as the report's markdown tables print them.

Its own module so that every section of the report (``report``, ``remeasured_tables``) formats a cell the same way
without importing each other.
"""

from __future__ import annotations

import math

from pearl_paper.reproduce.stats import Interval


def format_number(value: float, digits: int = 1, scale: float = 1.0, missing: str = "-") -> str:
    """``scale * value`` to ``digits`` decimals, or ``missing`` when it is missing or not finite."""
    return missing if value is None or not math.isfinite(value) else f"{scale * value:.{digits}f}"


def format_interval(interval: Interval, digits: int = 1, scale: float = 1.0) -> str:
    """``mean [low, high]``, or the mean alone when there is no interval."""
    mean = format_number(interval.mean, digits, scale)
    if not (math.isfinite(interval.low) and math.isfinite(interval.high)):
        return mean
    return f"{mean} [{format_number(interval.low, digits, scale)}, {format_number(interval.high, digits, scale)}]"


def seed_count(n: int) -> str:
    """``1 seed``, ``4 seeds``: a count of seeds as the report's tables and figure legends print it."""
    return f"{n} seed{'' if n == 1 else 's'}"
