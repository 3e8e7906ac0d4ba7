# SPDX-License-Identifier: Apache-2.0
"""twin.compensation: offsets kept for their sample as a controller keeps them, applied at
most once, and every one it drops counted by why."""

from __future__ import annotations

import math

import numpy as np

from lompr_predictor.twin.compensation import CompensationSchedule, OffsetDrop

EPOCH = 1_700_000_000 * 10**9
PERIOD = 4_000_000


def at(index: int, off_ns: int = 0) -> int:
    return EPOCH + index * PERIOD + off_ns


def test_each_offset_is_applied_at_its_sample_or_dropped_with_its_reason() -> None:
    schedule = CompensationSchedule(EPOCH, PERIOD, timeout_samples=5, max_offset=1e-3)
    assert schedule.offer(at(3, PERIOD // 4), (1e-6, 2e-6, 0.0), next_index=2) is None
    assert schedule.offer(at(3), (3e-6, 4e-6, 0.0), next_index=2) is None  # supersedes
    assert schedule.offer(at(4, PERIOD // 4 + 1), (0.0, 0.0, 0.0), 2) == OffsetDrop.OFF_GRID
    assert schedule.offer(at(1), (0.0, 0.0, 0.0), next_index=2) == OffsetDrop.LATE
    assert schedule.offer(at(5), (math.nan, 0.0, 0.0), 2) == OffsetDrop.NON_FINITE
    assert schedule.offer(at(5), (0.0, -2e-3, 0.0), 2) == OffsetDrop.TOO_LARGE
    assert schedule.offer(at(12), (5e-6, 5e-6, 0.0), next_index=2) is None  # 10 ahead
    assert schedule.offer(at(4), (6e-6, 0.0, 0.0), next_index=2) is None
    assert schedule.has(3) and schedule.pending == 3
    np.testing.assert_array_equal(schedule.take(2), np.zeros(3))  # none came
    np.testing.assert_array_equal(schedule.take(3), [3e-6, 4e-6, 0.0])
    np.testing.assert_array_equal(schedule.take(3), np.zeros(3))  # at most once
    np.testing.assert_array_equal(schedule.take(5), np.zeros(3))  # 4's is forgotten: late
    np.testing.assert_array_equal(schedule.take(12), np.zeros(3))  # waited 10 > 5: stale
    assert (schedule.applied, schedule.missing, schedule.pending) == (1, 3, 0)
    assert schedule.rejected.counts() == {
        'late': 2, 'stale': 1, 'off_grid': 1, 'non_finite': 1, 'too_large': 1,
        'superseded': 1}
