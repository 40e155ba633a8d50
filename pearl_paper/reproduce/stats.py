"""Statistics of the reproduction report: t intervals over seeds, paired differences and the verdict rule.

The unit of replication is the model seed: every seed of a variant is one independent training run,
and its meta-test gives one violation rate and one mean return per k. Intervals over seeds are
Student t intervals. Comparisons between two variants are *paired* over seeds: seed s of both
variants is meta-tested on the same test tasks with the same env seeds and prior draws (common
random numbers, ``crn_seed``), so the per-seed difference removes the test-set noise they share.

The verdict rule (docs/reproduce.md, written before any run), on the 95% t interval [lo, hi] of the
mean paired difference d = variant - reference, with the claim's margin m > 0:

- fewer than 2 seeds in common, or no interval: **inconclusive**;
- ``lower``: **reproduced** if hi < 0 and lo <= -m (below zero, and not confined to a negligible
  effect); **not reproduced** if lo > 0 (the other direction) or -m < lo and hi < m (any effect is
  smaller than the margin); otherwise **inconclusive**;
- ``higher``: the mirror image;
- ``equal``: **reproduced** if -m < lo and hi < m; **not reproduced** if lo >= m or hi <= -m;
  otherwise **inconclusive**;
- ``not_lower`` (non-inferiority): **reproduced** if lo > -m; **not reproduced** if hi < -m;
  otherwise **inconclusive**; ``not_higher``: the mirror image.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

REPRODUCED = "reproduced"
NOT_REPRODUCED = "not reproduced"
INCONCLUSIVE = "inconclusive"
VERDICTS = (REPRODUCED, NOT_REPRODUCED, INCONCLUSIVE)


class Interval(NamedTuple):
    """A mean with its confidence interval over ``n`` values (``low`` / ``high`` nan when ``n < 2``)."""

    mean: float
    low: float
    high: float
    n: int


def clip_interval(interval: Interval, low: float = 0.0, high: float = 1.0) -> Interval:
    """``interval`` with its bounds clipped to ``[low, high]``: a rate's t interval can reach below 0 or above 1 at few
    seeds, which no rate can; missing (nan) bounds stay missing."""
    return interval._replace(
        low=min(max(interval.low, low), high) if math.isfinite(interval.low) else interval.low,
        high=max(min(interval.high, high), low) if math.isfinite(interval.high) else interval.high,
    )


def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 500):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-15:
            break
    return h


def incomplete_beta(a: float, b: float, x: float) -> float:
    """
    Regularised incomplete beta function I_x(a, b).

    :param a: first shape (> 0)
    :param b: second shape (> 0)
    :param x: in [0, 1]
    :return: I_x(a, b)
    """
    if not 0.0 <= x <= 1.0:
        raise ValueError(f"incomplete_beta: x must be in [0, 1], got {x}")
    if x in (0.0, 1.0):
        return x
    log_front = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(log_front) * _betacf(a, b, x) / a
    return 1.0 - math.exp(log_front) * _betacf(b, a, 1.0 - x) / b


def t_cdf(t: float, df: float) -> float:
    """
    Cumulative distribution function of Student's t.

    :param t: the value
    :param df: degrees of freedom (> 0)
    :return: P(T <= t)
    """
    if df <= 0:
        raise ValueError(f"t_cdf: df must be > 0, got {df}")
    tail = 0.5 * incomplete_beta(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t > 0 else tail


def t_quantile(p: float, df: float) -> float:
    """
    Quantile of Student's t (bisection on :func:`t_cdf`).

    :param p: probability in (0, 1)
    :param df: degrees of freedom (> 0)
    :return: t with P(T <= t) = p
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"t_quantile: p must be in (0, 1), got {p}")
    if p < 0.5:
        return -t_quantile(1.0 - p, df)
    low, high = 0.0, 1.0
    while t_cdf(high, df) < p:
        high *= 2.0
    for _ in range(200):
        mid = 0.5 * (low + high)
        if t_cdf(mid, df) < p:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)


def mean_finite(values: Sequence[float]) -> float:
    """The mean of the finite values (nan / inf left out), nan when none is finite."""
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def median_finite(values: Sequence[float]) -> float:
    """The median of the finite values (nan / inf left out), nan when none is finite."""
    finite = [v for v in values if math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def t_interval(values: Sequence[float] | np.ndarray, confidence: float = 0.95) -> Interval:
    """
    Student t interval of the mean of ``values`` (independent replications, e.g. one per seed).

    :param values: the values (nan values are an error: drop them first)
    :param confidence: coverage of the interval
    :return: mean, low, high, n; the bounds are nan for fewer than 2 values
    """
    array = np.asarray(values, dtype=np.float64)
    if np.isnan(array).any():
        raise ValueError("t_interval: nan among the values")
    n = int(array.size)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    mean = float(array.mean())
    if n < 2:
        return Interval(mean, math.nan, math.nan, n)
    half = t_quantile(0.5 + confidence / 2.0, n - 1) * float(array.std(ddof=1)) / math.sqrt(n)
    return Interval(mean, mean - half, mean + half, n)


def sign_flip_p_value(differences: np.ndarray, shift: float = 0.0, max_exact: int = 16, draws: int = 100_000) -> float:
    """
    Two-sided p-value of the paired sign-flip permutation test of "the mean difference is ``shift``".

    Under that hypothesis, with differences symmetric around ``shift``, every sign pattern of ``d - shift`` is equally
    likely; the p-value is the share of patterns whose mean is at least as far from 0 as the observed one. Every one of
    the 2^n patterns up to ``max_exact`` values (exact), else ``draws`` patterns drawn with a fixed seed.

    :param differences: the paired differences (one per seed)
    :param shift: the hypothesised mean difference
    :param max_exact: enumerate every pattern up to this many values
    :param draws: patterns drawn above it
    :return: the p-value, in (0, 1]
    """
    centred = np.asarray(differences, dtype=np.float64) - shift
    n = centred.size
    if n == 0:
        return math.nan
    signs = sign_patterns(n, max_exact, draws)
    observed = abs(float(centred.mean()))
    # ties within rounding, relative to the values' own scale (an absolute tolerance would tie a flip of a value 1e-9
    # from the shift with the identity when every difference is small, and never reject)
    tolerance = 1e-12 * float(np.abs(centred).max())
    extreme = int(np.count_nonzero(np.abs(signs @ centred) / n >= observed - tolerance))
    if n <= max_exact:
        return extreme / len(signs)  # exact: the identity pattern is among them
    return (extreme + 1) / (len(signs) + 1)  # drawn patterns: the observed one counted too, so p > 0


@functools.cache
def sign_patterns(n: int, max_exact: int = 16, draws: int = 100_000) -> np.ndarray:
    """Every sign pattern of ``n`` values (up to ``max_exact``; the identity first), else ``draws`` drawn with seed 0."""
    if n <= max_exact:
        return 1.0 - 2.0 * ((np.arange(2**n)[:, None] >> np.arange(n)) & 1)
    return np.random.default_rng(0).choice([-1.0, 1.0], size=(draws, n))


def sign_flip_interval(
    values: Sequence[float] | np.ndarray, confidence: float = 0.95, bounds: tuple[float, float] = (-math.inf, math.inf)
) -> Interval:
    """
    The paired sign-flip permutation interval of the mean difference: every shift the test of
    :func:`sign_flip_p_value` does not reject at ``1 - confidence``, clipped to ``bounds``.

    Why beside the t interval: it assumes only that the per-seed differences are symmetric about their mean, not that
    they are normal, so it stays valid at 4-10 seeds and for bounded, skewed rates; and it never leaves the range the
    quantity can take (``bounds``: (-1, 1) for a difference of two rates), where a t interval at few seeds can. At few
    seeds it is honest about what they can show: with n values the smallest p-value is 2 / 2^n, so at n <= 5 no shift
    is rejected at 5% and the interval is the whole range.

    :param values: the paired differences (one per seed)
    :param confidence: coverage
    :param bounds: the range the mean difference can take
    :return: mean, low, high, n (bounds nan for fewer than 2 values)
    """
    array = np.asarray(values, dtype=np.float64)
    if np.isnan(array).any():
        raise ValueError("sign_flip_interval: nan among the values")
    n = int(array.size)
    if n < 2:
        return Interval(float(array.mean()) if n else math.nan, math.nan, math.nan, n)
    mean, alpha = float(array.mean()), 1.0 - confidence
    spread = float(array.max() - array.min()) or 1.0

    def bound(direction: float) -> float:
        # the p-value falls from 1 at the mean to 2 / 2^n beyond the extreme value on this side: bisect the crossing
        inner, outer = mean, (array.max() if direction > 0 else array.min()) + direction * 1e-9 * spread
        if sign_flip_p_value(array, outer) > alpha:
            return math.inf * direction
        for _ in range(60):
            middle = 0.5 * (inner + outer)
            if sign_flip_p_value(array, middle) > alpha:
                inner = middle
            else:
                outer = middle
        return float(inner)

    low, high = max(bound(-1.0), float(bounds[0])), min(bound(1.0), float(bounds[1]))
    return Interval(mean, low, high, n)


def sign_flip_can_reject(n: int, confidence: float = 0.95) -> bool:
    """
    Whether the sign-flip test of :func:`sign_flip_p_value` on ``n`` values can reject anything at ``1 - confidence``:
    its smallest p-value is 2 / 2^n (the identity pattern and its mirror), so below that count
    :func:`sign_flip_interval` is the whole range whatever the values.

    :param n: the number of paired differences
    :param confidence: coverage
    """
    return 2.0 / 2.0**n <= 1.0 - confidence


def paired_differences(variant: Mapping[int, float], reference: Mapping[int, float]) -> dict[int, float]:
    """
    Per-seed differences ``variant - reference`` over the seeds both have.

    :param variant: value per seed
    :param reference: value per seed
    :return: difference per common seed, in seed order
    """
    return {seed: float(variant[seed]) - float(reference[seed]) for seed in sorted(set(variant) & set(reference))}


def verdict(interval: Interval, direction: str, margin: float) -> str:
    """
    The verdict of a claim from the interval of the paired difference (module docstring).

    :param interval: 95% t interval of the mean difference variant - reference
    :param direction: ``lower``, ``higher``, ``equal``, ``not_lower`` or ``not_higher``
    :param margin: equivalence margin (> 0), in the metric's units
    :return: ``"reproduced"``, ``"not reproduced"`` or ``"inconclusive"``
    """
    if margin <= 0:
        raise ValueError(f"verdict: margin must be > 0, got {margin}")
    if direction in ("higher", "not_higher"):  # mirror onto lower / not_lower
        interval = Interval(-interval.mean, -interval.high, -interval.low, interval.n)
        direction = {"higher": "lower", "not_higher": "not_lower"}[direction]
    lo, hi = interval.low, interval.high
    if interval.n < 2 or not (math.isfinite(lo) and math.isfinite(hi)):
        return INCONCLUSIVE
    if direction == "lower":
        if hi < 0 and lo <= -margin:
            return REPRODUCED
        if lo > 0 or (-margin < lo and hi < margin):
            return NOT_REPRODUCED
        return INCONCLUSIVE
    if direction == "equal":
        if -margin < lo and hi < margin:
            return REPRODUCED
        if lo >= margin or hi <= -margin:
            return NOT_REPRODUCED
        return INCONCLUSIVE
    if direction == "not_lower":
        if lo > -margin:
            return REPRODUCED
        if hi < -margin:
            return NOT_REPRODUCED
        return INCONCLUSIVE
    raise ValueError(f"verdict: unknown direction {direction!r}")


__all__ = [
    "INCONCLUSIVE",
    "NOT_REPRODUCED",
    "REPRODUCED",
    "VERDICTS",
    "Interval",
    "incomplete_beta",
    "paired_differences",
    "t_cdf",
    "t_interval",
    "t_quantile",
    "verdict",
]
