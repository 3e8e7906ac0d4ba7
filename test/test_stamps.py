# SPDX-License-Identifier: Apache-2.0
"""stamps: integer nanoseconds round-trip through (sec, nanosec) exactly, a stamp that is no
time or too far ahead is named, and differences keep the nanosecond a float64 second loses."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from lompr_predictor.stamps import (
    NOT_A_TIME,
    Stamp,
    StampReason,
    instants_ns,
    ns_to_sec_nanosec,
    period_ns,
    seconds_since,
    set_stamp,
    stamp_problem,
    stamp_to_ns,
)

PRESENT = 1_796_000_000_123_456_789  # a present-day stamp [ns]


@given(st.integers(min_value=0, max_value=2**62))
def test_nanoseconds_round_trip_through_sec_and_nanosec(ns: int) -> None:
    sec, nanosec = ns_to_sec_nanosec(ns)
    assert 0 <= nanosec < 1_000_000_000
    assert stamp_to_ns(Stamp(sec, nanosec)) == ns
    message = SimpleNamespace(sec=0, nanosec=0)
    set_stamp(message, ns)
    assert stamp_to_ns(message) == ns


def test_a_stamp_that_is_no_time_or_too_far_ahead_is_named() -> None:
    now = PRESENT
    sec, nanosec = ns_to_sec_nanosec(now)
    assert stamp_problem(sec, nanosec, now, 0) is None
    assert stamp_problem(sec + 1, nanosec, now, 1_000_000_000) is None  # exactly the limit
    ahead = stamp_problem(sec + 2, nanosec, now, 1_000_000_000)
    assert ahead is not None and ahead.reason == StampReason.FUTURE_STAMP
    assert ahead.explanation == (f'stamp {sec + 2}.{nanosec:09d} is 2.000 s ahead of this '
                                 "node's clock (more than 1 s)")
    assert stamp_problem(sec + 2, nanosec, 0, 1_000_000_000) is None  # no /clock yet
    assert stamp_problem(sec + 2, nanosec, now, None) is None  # not checked
    for bad in ((-1, 0), (sec, 1_000_000_000), (sec, -1)):
        problem = stamp_problem(*bad, now, None)
        assert problem is not None and problem.reason == StampReason.BAD_STAMP
    assert instants_ns([1, 2, -1], [5, 1_000_000_000, 0]) == [
        1_000_000_005, NOT_A_TIME, -1_000_000_000]


def test_differences_keep_the_nanosecond_of_a_present_day_stamp() -> None:
    stamps = np.array([PRESENT, PRESENT + 1, PRESENT + 4_000_001], dtype=np.int64)
    np.testing.assert_array_equal(seconds_since(stamps), [0.0, 1e-9, 0.004000001])
    np.testing.assert_array_equal(seconds_since(stamps, PRESENT - 1), [1e-9, 2e-9, 0.004000002])
    assert float(PRESENT) * 1e-9 + 1e-9 == float(PRESENT) * 1e-9  # what floats would lose
    assert (period_ns(0.004), period_ns(0.001), period_ns(1 / 3)) == (4_000_000, 1_000_000,
                                                                       333_333_333)
