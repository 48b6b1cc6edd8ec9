"""95 % intervals of the rates and means that the reports give over sequences.

Every report number that is a rate or a mean over sequences carries its interval, written
``value [low, high]`` (:meth:`Interval.text`), e.g. ``25.0 [12.0, 44.9]`` for 6 of 24 sequences.
Two intervals, one per kind of number; both deterministic (no resampling):

- A rate of sequences (SSR: the share of sequences whose grasp holds, in %) is a binomial
  proportion ``p = k / n``. Its interval is Wilson's score interval (Newcombe 1998, method 3)::

      centre = (p + z² / 2n) / (1 + z² / n)
      half   = z / (1 + z² / n) · sqrt(p (1 − p) / n + z² / 4n²)

  with ``z`` the standard normal quantile (1.96 at 95 %). Unlike ``p ± z sqrt(p (1 − p) / n)``
  it stays within [0, 1] and does not collapse to a point at 0 or n successes.
- A mean over sequences of a per-sequence value (PD in mm) gets Student's t interval
  ``mean ± t(0.975, n − 1) · s / sqrt(n)``, ``s`` the sample standard deviation; none for n < 2.
  For a quantity that cannot be negative (a depth, a share) the lower bound is clipped at 0.

Both treat sequences as independent; sequences of the same object are not fully so, which makes
the intervals, if anything, too narrow.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from statistics import NormalDist

__all__ = [
    "CONFIDENCE",
    "Interval",
    "mean_interval",
    "rate_interval",
    "rate_of_sequences",
    "sequence_interval",
    "wilson",
]

CONFIDENCE = 0.95


@dataclass(frozen=True)
class Interval:
    """A value with its interval (NaN bounds: none).

    Attributes:
        value: The rate (%) or the mean.
        low, high: The interval's bounds, in the value's unit.
        n: The sequences it is over.
        method: ``wilson`` or ``t``.
    """

    value: float
    low: float
    high: float
    n: int
    method: str

    def text(self, digits: int = 1) -> str:
        """``value [low, high]``; ``—`` for a missing value or bound."""

        def number(x: float) -> str:
            return f"{x:.{digits}f}" if math.isfinite(x) else "—"

        if not math.isfinite(self.value):
            return "—"
        return f"{number(self.value)} [{number(self.low)}, {number(self.high)}]"


def wilson(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson's score interval of the proportion ``successes / n`` (bounds in [0, 1]).

    Raises:
        ValueError: ``n < 1`` or ``successes`` outside ``[0, n]``.
    """
    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"wilson: expected 0 <= successes <= n and n >= 1, got {successes}/{n}")
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    p = successes / n
    scale = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / scale
    half = z / scale * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return max(0.0, centre - half), min(1.0, centre + half)


def rate_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> Interval:
    """The rate ``100 successes / n`` (%) with its Wilson interval."""
    low, high = wilson(successes, n, confidence)
    return Interval(100 * successes / n, 100 * low, 100 * high, n, "wilson")


def rate_of_sequences(
    rate_percent: float | None, n: int | None, confidence: float = CONFIDENCE
) -> Interval | None:
    """:func:`rate_interval` of a rate a stage reports (%) over ``n`` sequences: the count of
    successes is ``rate · n / 100``. None when either is missing or the rate is no count of
    ``n`` (a share of frames, say)."""
    if rate_percent is None or not n or not math.isfinite(rate_percent):
        return None
    count = rate_percent * n / 100
    if abs(count - round(count)) > 1e-6 * max(1, n) or not 0 <= round(count) <= n:
        return None
    return rate_interval(round(count), n, confidence)


def mean_interval(
    values: Iterable[float], confidence: float = CONFIDENCE, lower: float | None = None
) -> Interval:
    """The mean of the finite ``values`` with Student's t interval (NaN bounds for n < 2, NaN
    everywhere for none); ``lower``: the smallest value the quantity can take (the lower
    bound is clipped there)."""
    finite = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    n = len(finite)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0, "t")
    mean = math.fsum(finite) / n
    if n < 2:
        return Interval(mean, math.nan, math.nan, n, "t")
    from scipy.stats import t as student

    sd = math.sqrt(math.fsum((v - mean) ** 2 for v in finite) / (n - 1))
    half = float(student.ppf(0.5 + confidence / 2, n - 1)) * sd / math.sqrt(n)
    low = mean - half if lower is None else max(lower, mean - half)
    return Interval(mean, low, mean + half, n, "t")


def sequence_interval(
    values: Iterable[float], rate: bool = False, lower: float | None = None
) -> Interval:
    """The interval of a per-sequence column: Wilson's for a rate whose every value is 0 or
    100 (% of one sequence: it held or not), Student's t otherwise (a mean, or a rate of
    frames per sequence), its lower bound clipped at ``lower``."""
    finite = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if rate and finite and all(v in (0.0, 100.0) for v in finite):
        return rate_interval(sum(v == 100.0 for v in finite), len(finite))
    return mean_interval(finite, lower=lower)
