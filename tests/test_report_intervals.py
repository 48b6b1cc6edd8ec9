"""The reports' 95 % intervals (dexflow.stats): Wilson's for rates of sequences against published
values, Student's t for means, and the ``value [low, high]`` form the reports write."""

from __future__ import annotations

import math
import re

import pytest

from dexflow.stats import (
    Interval,
    mean_interval,
    rate_interval,
    rate_of_sequences,
    sequence_interval,
    wilson,
)


@pytest.mark.parametrize(
    ("successes", "n", "low", "high"),
    [  # Newcombe (1998), Statistics in Medicine 17:857, Table I, method 3 (score)
        (81, 263, 0.2553, 0.3662),
        (15, 148, 0.0624, 0.1605),
        (0, 20, 0.0, 0.1611),
        (1, 29, 0.0061, 0.1718),
    ],
)
def test_wilson_matches_published_intervals(successes, n, low, high):
    found = wilson(successes, n)
    assert found == pytest.approx((low, high), abs=1e-4)


def test_wilson_closed_forms_and_symmetry():
    z2 = 1.959963984540054**2
    for n in (1, 5, 24):
        assert wilson(0, n) == pytest.approx((0.0, z2 / (n + z2)))  # all failed
        assert wilson(n, n) == pytest.approx((n / (n + z2), 1.0))  # all held
        for k in range(n + 1):
            low, high = wilson(k, n)
            assert 0.0 <= low <= k / n <= high <= 1.0
            assert (low, high) == pytest.approx(tuple(1 - b for b in wilson(n - k, n)[::-1]))
    with pytest.raises(ValueError, match="7/5"):
        wilson(7, 5)


def test_the_rate_of_6_of_24_sequences():
    """The demo's refine SSR: 25.0 % of 24 sequences; one sequence less is 20.8 %, well inside
    the interval."""
    interval = rate_interval(6, 24)
    assert interval.text(1) == "25.0 [12.0, 44.9]"
    assert interval.low < 100 * 5 / 24 < interval.high
    assert rate_of_sequences(25.0, 24) == interval  # from a stage's rate and its count
    assert rate_of_sequences(100 * 5 / 24, 24).text(1) == "20.8 [9.2, 40.5]"
    assert rate_of_sequences(33.0, 24) is None  # no count of 24 sequences: a share of frames
    assert rate_of_sequences(None, 24) is None and rate_of_sequences(25.0, 0) is None


def test_the_mean_gets_students_t_interval():
    found = mean_interval([1.0, 2.0, 3.0, 4.0, 5.0])
    half = 2.7764451051977987 * math.sqrt(2.5) / math.sqrt(5)  # t(0.975, 4) s / sqrt(n)
    assert (found.value, found.n, found.method) == (3.0, 5, "t")
    assert (found.low, found.high) == pytest.approx((3.0 - half, 3.0 + half))
    assert mean_interval([0.0, 0.0, 0.0, 4.0], lower=0.0).low == 0.0  # a depth is never < 0
    assert mean_interval([0.0, 0.0, 0.0, 4.0]).low < 0.0
    one = mean_interval([2.0, float("nan")])  # NaN is left out; one value has no interval
    assert one.value == 2.0 and math.isnan(one.low) and one.text(2) == "2.00 [—, —]"
    assert mean_interval([]).text() == "—"


def test_a_per_sequence_column_picks_wilson_for_held_or_not_and_t_otherwise():
    held = sequence_interval([100.0, 0.0, 0.0, 0.0], rate=True)
    assert held == rate_interval(1, 4)
    shares = sequence_interval([50.0, 0.0, 25.0], rate=True)  # a rate of frames per sequence
    assert shares.method == "t" and shares.value == pytest.approx(25.0)
    assert sequence_interval([1.0, 3.0]).method == "t"


def test_intervals_are_written_so_that_a_reader_can_parse_them():
    text = Interval(25.0, 11.96, 44.9, 24, "wilson").text(1)
    value, low, high = map(float, re.fullmatch(r"(\S+) \[(\S+), (\S+)\]", text).groups())
    assert (value, low, high) == (25.0, 12.0, 44.9)
