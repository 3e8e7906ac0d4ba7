# SPDX-License-Identifier: Apache-2.0
"""online.faults alone: interval rules and staleness, on a fake clock."""

from __future__ import annotations

import pytest
from fake_clock import FakeClock

from lompr_predictor.online.faults import FaultReason, StaleWatch, StreamRules, StreamSettings

PERIOD = 0.04
PERIOD_NS = 40_000_000


def stream(sample_period: float = PERIOD, stale_min_time: float = 0.0) -> StreamSettings:
    return StreamSettings(sample_period=sample_period, gap_factor=2.5, min_interval_factor=0.5,
                          stale_periods=5.0, stale_min_time=stale_min_time,
                          accuracy_samples=100, max_future_stamp=1.0, late_tolerance=0.005,
                          preview_tolerance=1e-5)


@pytest.mark.parametrize(('interval_ns', 'fault'), [
    (40_000_000, None), (100_000_000, None), (100_000_001, FaultReason.GAP),
    (20_000_000, None), (19_999_999, FaultReason.OFF_RATE), (0, FaultReason.OFF_RATE)])
def test_interval_rules(interval_ns: int, fault: FaultReason | None) -> None:
    rules = StreamRules(stream(), PERIOD_NS)
    assert rules.interval_fault(1_000, 1_000 + interval_ns) == fault


def test_stale_after_has_a_floor_in_seconds() -> None:
    assert stream().stale_after == pytest.approx(0.2)
    assert stream(sample_period=1e-3, stale_min_time=0.05).stale_after == 0.05


def test_staleness_is_confirmed_by_a_second_idle_check() -> None:
    clock = FakeClock(50.0)
    watch = StaleWatch(0.2, clock.ns)
    clock.now += 0.19
    assert not watch.check()
    clock.now += 0.02
    assert not watch.check()  # idle once: maybe a busy executor
    assert watch.check()  # idle twice in a row: stale
    watch.used()
    clock.now += 0.1
    assert not watch.check()


def test_a_check_that_finds_a_recent_sample_clears_the_suspicion() -> None:
    clock = FakeClock(50.0)
    watch = StaleWatch(0.2, clock.ns)
    clock.now += 0.3
    assert not watch.check()  # suspected
    watch.used()
    assert not watch.check()  # not idle: the suspicion is gone
    clock.now += 0.25
    assert not watch.check()  # idle, suspected afresh
    assert watch.check()


def test_a_pose_waiting_for_its_reference_counts_as_no_sample() -> None:
    clock = FakeClock(50.0)
    watch = StaleWatch(0.2, clock.ns)
    waiting_since = clock.ns() + 100_000_000  # a pose arrived then, and still waits
    clock.now += 0.25
    assert not watch.check(waiting_since)  # idle 0.25 s since the last use, 0.15 s waiting...
    assert not watch.check(waiting_since)  # ...the newer of the two counts: not yet stale
    clock.now += 0.1
    assert not watch.check(waiting_since)
    assert watch.check(waiting_since)


def test_a_restart_counts_idle_time_from_the_jump() -> None:
    """A clock that jumps (its first /clock message, a simulator skipping ahead) is no idle
    input: the watch counts from the jump."""
    clock = FakeClock(50.0)
    watch = StaleWatch(0.2, clock.ns)
    clock.now += 1000.0
    assert not watch.check()  # suspected
    watch.restart()
    assert not watch.check()  # the suspicion is gone with the jump
    clock.now += 0.21
    assert not watch.check()
    assert watch.check()
