# SPDX-License-Identifier: Apache-2.0
"""Counters, rate meter, latency percentiles and log throttle, driven by a fake clock."""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from fake_clock import FakeClock

from lompr_predictor import monitoring
from lompr_predictor.monitoring import (
    CallbackTimes,
    DurationHistogram,
    HeldEvent,
    LatencyRecorder,
    LatencySummary,
    Level,
    LogThrottle,
    RateMeter,
    RejectionCounter,
    Status,
    bin_lower_ns,
    latency_values,
    parse_histogram,
    rejection_values,
)


def test_rejection_counter_counts_by_reason_and_keeps_declared_zeros() -> None:
    counter = RejectionCounter(['non_finite', 'missing_joint'])
    counter.add('non_finite')
    counter.add('non_finite', 2)
    counter.add('stroke_limit')
    assert counter['non_finite'] == 3
    assert counter['missing_joint'] == 0
    assert counter['never_seen'] == 0
    assert counter.total == 4
    assert counter.counts() == {'non_finite': 3, 'missing_joint': 0, 'stroke_limit': 1}
    assert rejection_values(counter) == {
        'rejected_total': 4, 'rejected.non_finite': 3, 'rejected.missing_joint': 0,
        'rejected.stroke_limit': 1}
    with pytest.raises(ValueError, match='negative'):
        counter.add('non_finite', -1)


def test_rate_meter_is_exact_from_start_and_over_the_window() -> None:
    clock = FakeClock()
    meter = RateMeter(window=2.0, clock=clock)
    assert meter.rate() == 0.0
    assert meter.seconds_since_last() is None
    # 100 Hz for 0.5 s: 50 events in 0.5 s since start.
    for _ in range(50):
        clock.now += 0.01
        meter.tick()
    assert meter.rate() == pytest.approx(100.0)
    # Then 25 Hz for 3 s: the 2 s window holds only 25 Hz events.
    for _ in range(75):
        clock.now += 0.04
        meter.tick()
    assert meter.rate() == pytest.approx(25.0)
    assert meter.total == 125
    # Silence: one second later half the window is empty, after the window all of it.
    clock.now += 1.0
    assert meter.rate() == pytest.approx(12.5)
    assert meter.seconds_since_last() == pytest.approx(1.0)
    clock.now += 1.0
    assert meter.rate() == 0.0
    assert meter.seconds_since_last() is None
    with pytest.raises(ValueError, match='positive'):
        RateMeter(window=0.0)


def test_rate_meter_starts_afresh_when_the_clock_goes_back() -> None:
    """A simulator reset sets the node's clock back: the events of the abandoned timeline
    would otherwise sit in the window as events from the future."""
    clock = FakeClock()
    meter = RateMeter(window=2.0, clock=clock)
    for _ in range(50):
        clock.now += 0.04
        meter.tick()
    assert meter.rate() == pytest.approx(25.0)
    clock.now -= 10.0  # reset
    assert meter.rate() == 0.0 and meter.seconds_since_last() is None
    for _ in range(10):
        clock.now += 0.1
        meter.tick()
    assert meter.rate() == pytest.approx(10.0)  # exact from the reset on
    assert meter.total == 60


@pytest.mark.faults
def test_rate_meter_told_the_time_starts_afresh_when_it_goes_back() -> None:
    """The caller passes its own clock reading (`tick(now)`, as kinematics_node does): a time
    before the newest event starts the meter afresh too, instead of keeping every event of
    the restarted run behind those of the abandoned one (a deque growing by one a sample
    until the simulated time catches up)."""
    clock = FakeClock()
    meter = RateMeter(window=2.0, clock=clock)
    for _ in range(50):
        clock.now += 0.04
        meter.tick(clock.now)
    clock.now -= 10.0  # reset
    for _ in range(100):
        clock.now += 0.04
        meter.tick(clock.now)
    # the window's 2 s of events: 25 Hz, not the 150 events of both runs over 2 s
    assert meter.rate() == pytest.approx(25.0) and meter.total == 150


def test_latency_recorder_percentiles_over_last_samples() -> None:
    recorder = LatencyRecorder(capacity=100)
    summary = recorder.summary()
    assert summary.samples == 0 and math.isnan(summary.p50) and math.isnan(summary.p99)
    # 1..100 microseconds: p50 = 50.5 us, p99 = 99.01 us (linear interpolation).
    for us in range(1, 101):
        recorder.record(us * 1e-6)
    summary = recorder.summary()
    assert summary.samples == 100
    assert summary.p50 == pytest.approx(50.5e-6)
    assert summary.p99 == pytest.approx(99.01e-6)
    assert summary.max == pytest.approx(100e-6)
    # 100 more of 1 ms push all the old ones out.
    for _ in range(100):
        recorder.record(1e-3)
    assert recorder.summary() == pytest.approx(LatencySummary(100, 1e-3, 1e-3, 1e-3))
    assert recorder.total == 200
    assert latency_values('solve', LatencySummary(10, 35e-6, 80.5e-6, 1e-4)) == {
        'solve_p50_us': 35.0, 'solve_p99_us': 80.5, 'solve_max_us': 100.0, 'solve_samples': 10}
    with pytest.raises(ValueError, match='at least 1'):
        LatencyRecorder(capacity=0)


def test_latency_recorder_partial_buffer_matches_numpy() -> None:
    rng = np.random.default_rng(3)
    values = rng.exponential(40e-6, size=37)
    recorder = LatencyRecorder(capacity=1000)
    for value in values:
        recorder.record(float(value))
    summary = recorder.summary()
    assert summary.samples == 37
    assert summary.p50 == pytest.approx(np.median(values))
    assert summary.p99 == pytest.approx(np.percentile(values, 99))


def test_latency_measure_records_even_when_block_raises() -> None:
    recorder = LatencyRecorder(capacity=4)
    with recorder.measure():
        sum(range(1000))
    with pytest.raises(RuntimeError), recorder.measure():
        raise RuntimeError('boom')
    summary = recorder.summary()
    assert summary.samples == 2
    assert 0.0 < summary.max < 1.0


def test_log_throttle_passes_one_per_period_and_counts_the_rest() -> None:
    clock = FakeClock()
    throttle = LogThrottle(period=5.0, clock=clock)
    assert throttle.filter('nan', 'NaN in ups1') == 'NaN in ups1'
    clock.now += 1.0
    assert throttle.filter('nan', 'NaN in ups2') is None
    assert throttle.filter('missing', 'no ups3') == 'no ups3'  # other keys are independent
    clock.now += 1.0
    assert throttle.filter('nan', 'NaN in ups1') is None
    clock.now += 3.0
    assert throttle.filter('nan', 'NaN in ups3') == (
        'NaN in ups3 (2 more like this in the last 5.0 s)')
    clock.now += 5.0
    assert throttle.filter('nan', 'NaN in ups1') == 'NaN in ups1'
    clock.now -= 100.0  # the clock went back (a simulator reset): the next one passes
    assert throttle.filter('nan', 'NaN in ups2') == 'NaN in ups2'
    clock.now += 1.0
    assert throttle.filter('nan', 'NaN in ups2') is None


def test_log_throttle_says_when_the_suppressed_came_before_the_clock_went_back() -> None:
    clock = FakeClock()
    throttle = LogThrottle(period=5.0, clock=clock)
    assert throttle.filter('frame', 'wrong frame') == 'wrong frame'
    clock.now += 1.0
    assert throttle.filter('frame', 'wrong frame') is None
    clock.now -= 30.0  # a simulator reset: no negative span in the summary
    assert throttle.filter('frame', 'wrong frame') == (
        'wrong frame (1 more like this before the clock went back)')


def test_status_defaults_and_levels_match_diagnostic_msgs() -> None:
    status = Status(Level.WARN, 'slow')
    assert dict(status.values) == {}
    assert [int(level) for level in Level] == [0, 1, 2, 3]


def test_duration_histogram_bins_are_quarter_octaves_and_percentiles_bound_the_data() -> None:
    # the bin edges: 0, then 256, 320, 384, 448, 512, 640, ... (4 per octave)
    assert [bin_lower_ns(i) for i in range(7)] == [0, 256, 320, 384, 448, 512, 640]
    histogram = DurationHistogram()
    durations = [100, 300, 1000, 1000, 1000, 5000, 70_000, 2_000_000]
    for ns in durations * 100:
        histogram.record(ns)
    assert histogram.total == 800 and histogram.max_ns == 2_000_000
    assert histogram.sum_ns == 100 * sum(durations)
    # 1000 ns falls in [896, 1024): p50 (rank 400, inside the 1000s) reads its upper edge
    assert histogram.percentiles_ns(50) == [1024]
    assert histogram.percentiles_ns(70) == [5120]  # 5000 in [4608, 5120)
    assert histogram.percentiles_ns(80) == [81920]  # 70 us in [65536, 81920)
    assert histogram.percentiles_ns(99, 100) == [2_000_000] * 2  # the max, below its bin's edge
    for q, exact in ((50, 1000), (70, 5000), (80, 70_000)):
        assert exact <= histogram.percentiles_ns(q)[0] <= exact * 1.25
    assert DurationHistogram().percentiles_ns(50, 99) == [0, 0]
    # a duration beyond the last bin is counted there, the max exact
    histogram.record(10**12)
    assert histogram.counts[-1] == 1 and histogram.max_ns == 10**12
    assert parse_histogram(histogram.text())[256] == 100  # 300 ns in [256, 320)


def test_callback_times_rows_measure_wall_and_cpu_and_nested_runs_count_once() -> None:
    times = CallbackTimes()

    def busy(seconds: float) -> None:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            pass

    times.measure('work', busy, 0.002)
    times.measure('idle', time.sleep, 0.002)
    times.measure('outer', lambda: times.measure('logging', busy, 0.001))
    with pytest.raises(ZeroDivisionError):
        times.measure('failing', lambda: 1 / 0)
    values: dict[str, Any] = times.values()
    assert values['work.runs'] == 1 and values['failing.runs'] == 1
    assert 2000 <= values['work.mean_us'] < 50_000
    assert values['work.cpu_mean_us'] > 1000  # busy: CPU
    assert values['idle.mean_us'] >= 2000 and values['idle.cpu_mean_us'] < 1000  # asleep
    # the log call inside 'outer' is its own row, and the CPU of outermost runs counts once
    assert values['logging.runs'] == 1
    assert times.measured_cpu_ns == sum(times.cpu_ns[row]
                                        for row in ('work', 'idle', 'outer', 'failing'))
    assert values['outer.cpu_mean_us'] >= values['logging.cpu_mean_us']
    assert 'work.histogram_ns' not in values  # an operator's status: percentiles only
    with_histograms = times.values(histograms=True)  # a bench's
    assert parse_histogram(str(with_histograms['work.histogram_ns'])) != {}
    assert with_histograms['work.p99_us'] == values['work.p99_us']


@pytest.fixture
def take(monkeypatch: pytest.MonkeyPatch) -> Callable[[int], None]:
    """`take(ns)`: work of `ns` nanoseconds, the only thing that advances monitoring's
    wall and CPU clocks."""
    now = [0]

    class FakeTime:
        perf_counter_ns = thread_time_ns = staticmethod(lambda: now[0])

    monkeypatch.setattr(monitoring, 'time', FakeTime)

    def work(ns: int) -> None:
        now[0] += ns
    return work


def test_work_run_apart_is_out_of_the_run_it_is_called_from(
        take: Callable[[int], None]) -> None:
    """Another node's callback called from one of this node's (the pipeline's end pose) is
    not this node's time: the run around it is recorded without it, also when it raises,
    and the measured CPU counts only the run's own."""
    times = CallbackTimes()

    def failing() -> None:
        take(4_000)
        raise ZeroDivisionError

    def callback() -> None:
        take(100_000)
        times.apart(take, 700_000)
        take(20_000)
        with pytest.raises(ZeroDivisionError):
            times.apart(failing)

    times.measure('joint states', callback)
    times.measure('joint states', take, 50_000)  # the next run: nothing taken out
    row = times.rows['joint states']
    assert (row.total, row.sum_ns, row.max_ns) == (2, 170_000, 120_000)
    assert times.cpu_ns['joint states'] == times.measured_cpu_ns == 170_000
    assert times.measured_runs == 2 and times.apart_runs == 2


def test_a_run_measured_apart_inside_another_counts_as_an_outermost_run(
        take: Callable[[int], None]) -> None:
    """A status sent between two samples from within the sample's callback is a run of its
    own: its row has its time, the callback's has not, and the CPU the executor's row is
    reckoned from has both."""
    times = CallbackTimes()

    def end_pose() -> None:
        take(100_000)
        times.apart(times.measure, 'diagnostics', take, 300_000)

    times.measure('end pose', end_pose)
    assert times.rows['end pose'].sum_ns == 100_000
    assert times.rows['diagnostics'].sum_ns == 300_000
    assert times.measured_cpu_ns == 400_000
    assert (times.measured_runs, times.apart_runs) == (2, 1)  # one callback dispatched


def test_callback_times_records_garbage_collections_by_generation() -> None:
    times = CallbackTimes()
    gc.callbacks.append(times.on_gc)
    try:
        gc.collect(0)
        gc.collect(2)
    finally:
        gc.callbacks.remove(times.on_gc)
    assert times.rows['garbage collection 0'].total >= 1
    assert times.rows['garbage collection 2'].total >= 1
    status = times.status()
    assert status.level == Level.OK
    assert int(str(status.values['garbage collection 2.runs'])) >= 1


def test_latency_percentiles_are_numpys_to_the_bit() -> None:
    """The summary sorts a working copy in place instead of calling `np.percentile`; the
    figures are the same floats, full buffer or not, ties and all."""
    rng = np.random.default_rng(7)
    for trial in range(400):
        capacity = int(rng.integers(1, 200))
        recorder = LatencyRecorder(capacity)
        values = (rng.lognormal(-9.0, 1.5, int(rng.integers(1, 2 * capacity + 1)))
                  if trial % 2 else np.round(rng.random(int(rng.integers(1, 50))) * 9) * 1e-6)
        for value in values:
            recorder.record(float(value))
        held = values[-capacity:]
        p50, p99 = np.percentile(held, [50.0, 99.0])
        assert recorder.summary() == (len(held), float(p50), float(p99), float(held.max()))


def test_a_held_event_is_shown_for_its_hold_from_when_it_was_first_seen() -> None:
    event, second = HeldEvent(), 1_000_000_000
    assert not event.shown(None, 5 * second, hold=10.0)  # nothing happened
    assert event.shown(1, 5 * second, hold=10.0)  # the first refusal, seen at 5 s
    assert event.shown(1, 14 * second, hold=10.0)
    assert not event.shown(1, 15 * second, hold=10.0)  # held 10 s: a value only now
    assert event.shown(2, 16 * second, hold=10.0)  # another one: held again
    assert event.shown(2, 3 * second, hold=10.0)  # the clock went back: held from there
    assert not event.shown(2, 13 * second, hold=10.0)
    assert not event.shown(None, 14 * second, hold=10.0)  # a success ended it
    assert event.shown(2, 14 * second, hold=10.0)  # the same marker after it: a new one
