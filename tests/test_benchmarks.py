"""The statistics of the benchmark scripts that compute more than a ratio, on hand-computed cases."""

from __future__ import annotations

import math

import pytest

from benchmarks.merge_math_check import welch


def test_welch_interval_on_a_hand_computed_case() -> None:
    """after = [1, 3], before = [4, 6]: each side's variance of the mean is 1, so df = (1 + 1)^2 / (1 + 1) = 2 and the
    half-width is t(0.975, 2) * sqrt(2) = 4.302653 * 1.414214 = 6.084870 around -3."""
    interval = welch([1.0, 3.0], [4.0, 6.0])
    assert interval.mean == pytest.approx(-3.0)
    assert (interval.low, interval.high) == pytest.approx((-9.084870, 3.084870), abs=1e-5)
    assert interval.n == 4


def test_welch_interval_without_spread_or_seeds() -> None:
    """No spread on either side: the difference itself; one seed on a side: no interval."""
    assert welch([2.0, 2.0], [1.0, 1.0])[:3] == (1.0, 1.0, 1.0)
    one = welch([2.0], [1.0, 3.0])
    assert one.mean == 0.0 and math.isnan(one.low) and math.isnan(one.high)


def test_holds_says_when_there_is_no_interval() -> None:
    from benchmarks.merge_math_check import holds
    from pearl_paper.reproduce.stats import Interval

    assert holds(Interval(0.0, -1.0, 1.0, 3), 0.0) == "yes" and holds(Interval(2.0, 1.0, 3.0, 3), 0.0) == "NO"
    assert holds(welch([2.0], [1.0, 3.0]), 0.0) == "-"  # one seed on a side: no interval, no verdict
