# SPDX-License-Identifier: Apache-2.0
"""Small ROS-free measuring pieces every node reports through /diagnostics.

- `RejectionCounter`: how many inputs were dropped, by reason.
- `RateMeter`: events per second over a sliding time window.
- `LatencyRecorder`: p50/p99/max of the last N durations.
- `LogThrottle`: lets one message per key and period through, counting the rest.
- `Status` / `Level`: one diagnostic status (OK/WARN/ERROR/STALE, message, key-values),
  the value a status provider returns; `nodes/common.py` turns it into a ROS message.

Time comes from an injectable clock (seconds, monotonic by default), so tests can drive
every piece with exact numbers; a node gives its own clock (ROS time, which follows /clock
under use_sim_time), so rates and throttles count the time the node runs on. Such a clock
can go backwards (a simulator reset): `RateMeter` then starts afresh and `LogThrottle` lets
the next message through. Durations (`LatencyRecorder.measure`) are wall time.
"""

from __future__ import annotations

import bisect
import itertools
import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import IntEnum
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

Clock = Callable[[], float]


class RejectionCounter:
    """Counts dropped inputs by reason (e.g. 'non_finite', 'missing_joint').

    Reasons given at construction are reported even while their count is zero, so a
    diagnostics reader sees every reason the node can drop for.
    """

    def __init__(self, reasons: Iterable[str] = ()) -> None:
        self._counts: dict[str, int] = dict.fromkeys(reasons, 0)
        self._total = 0

    def add(self, reason: str, count: int = 1) -> None:
        """Count `count` more inputs dropped for `reason`."""
        if count < 0:
            msg = f'a rejection count cannot be negative, got {count}'
            raise ValueError(msg)
        self._counts[reason] = self._counts.get(reason, 0) + count
        self._total += count

    def __getitem__(self, reason: str) -> int:
        return self._counts.get(reason, 0)

    @property
    def total(self) -> int:
        """Inputs dropped for any reason (kept as they come: a node reads it a sample)."""
        return self._total

    def counts(self) -> dict[str, int]:
        """A copy of the counts, reasons in first-seen order."""
        return dict(self._counts)


class RateMeter:
    """Events per second over the last `window` seconds.

    The rate is the number of events in (now - window, now] divided by the window, or by
    the time since the meter started while that is shorter, so the figure is right from
    the first second on and falls to zero when events stop.
    """

    def __init__(self, window: float = 5.0, clock: Clock = time.monotonic) -> None:
        if not window > 0.0:
            msg = f'rate window must be positive, got {window} s'
            raise ValueError(msg)
        self.window = window
        self._clock = clock
        self._started = clock()
        self._events: deque[float] = deque()
        self.total = 0

    def tick(self, now: float | None = None) -> None:
        """Record one event at `now` (the clock's reading of the caller; None: read it)."""
        now = self._now() if now is None else self._after_jumps(now)
        self._events.append(now)
        self.total += 1
        self._forget_before(now - self.window)

    def rate(self) -> float:
        """Events per second over the window ending now."""
        now = self._now()
        self._forget_before(now - self.window)
        span = min(self.window, now - self._started)
        return len(self._events) / span if span > 0.0 else 0.0

    def seconds_since_last(self) -> float | None:
        """Time since the last event still in the window, None if there is none."""
        now = self._now()
        self._forget_before(now - self.window)
        return now - self._events[-1] if self._events else None

    def _now(self) -> float:
        """The clock's time (`_after_jumps`)."""
        return self._after_jumps(self._clock())

    def _after_jumps(self, now: float) -> float:
        """`now`, the meter started afresh (the total kept) if it lies before the start or
        the newest event: the clock went back (a simulator reset)."""
        if now < self._started or (self._events and now < self._events[-1]):
            self._events.clear()
            self._started = now
        return now

    def _forget_before(self, cutoff: float) -> None:
        events = self._events
        while events and events[0] <= cutoff:
            events.popleft()


class LatencySummary(NamedTuple):
    """Percentiles of recorded durations [s]; NaN when nothing was recorded."""

    samples: int  # durations the percentiles are over (at most the recorder's capacity)
    p50: float
    p99: float
    max: float


class LatencyRecorder:
    """Keeps the last `capacity` durations [s] and gives their p50, p99 and max."""

    def __init__(self, capacity: int = 1000) -> None:
        if capacity < 1:
            msg = f'latency capacity must be at least 1, got {capacity}'
            raise ValueError(msg)
        self._samples = np.empty(capacity)
        self._sorted = np.empty(capacity)  # `summary`'s working copy, made once
        self._next = 0
        self._count = 0
        self.total = 0

    def record(self, seconds: float) -> None:
        """Add one duration, replacing the oldest once the buffer is full."""
        self._samples[self._next] = seconds
        self._next = (self._next + 1) % len(self._samples)
        self._count = min(self._count + 1, len(self._samples))
        self.total += 1

    @contextmanager
    def measure(self) -> Iterator[None]:
        """Record the wall time the `with` block takes (perf_counter), also when it raises."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.record(time.perf_counter() - start)

    def summary(self) -> LatencySummary:
        """p50, p99 and max of the durations held: `np.percentile`'s linear interpolation,
        to the bit, on a working copy sorted in place (a report per second must not cost
        the node's thread what `np.percentile`'s copies and checks do)."""
        count = self._count
        if count == 0:
            return LatencySummary(0, float('nan'), float('nan'), float('nan'))
        ordered = self._sorted[:count]
        ordered[:] = self._samples[:count]
        ordered.sort()
        return LatencySummary(count, _linear(ordered, 0.5), _linear(ordered, 0.99),
                              float(ordered[-1]))


def _linear(ordered: np.ndarray, q: float) -> float:
    """The `q` quantile (0..1) of sorted values as `np.percentile` interpolates it
    (method 'linear', its lerp from the nearer end)."""
    position = q * (len(ordered) - 1)
    below = math.floor(position)
    weight = position - below
    low = float(ordered[below])
    high = float(ordered[min(below + 1, len(ordered) - 1)])
    step = high - low
    return high - step * (1 - weight) if weight >= 0.5 else low + step * weight


class LogThrottle:
    """Lets one message per key through every `period` seconds and counts the others.

    `filter(key, text)` returns the text to log, with the number of messages of that key
    suppressed since the last one appended, or None while the key is throttled.
    """

    def __init__(self, period: float = 5.0, clock: Clock = time.monotonic) -> None:
        self.period = period
        self._clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def filter(self, key: str, text: str) -> str | None:
        now = self._clock()
        last = self._last.get(key)
        if last is not None and 0.0 <= now - last < self.period:  # a clock gone back: pass
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return None
        self._last[key] = now
        suppressed = self._suppressed.pop(key, 0)
        if suppressed and last is not None:
            span = now - last
            when = f'in the last {span:.1f} s' if span >= 0.0 else 'before the clock went back'
            return f'{text} ({suppressed} more like this {when})'
        return text


class Level(IntEnum):
    """Diagnostic levels, numbered as diagnostic_msgs/DiagnosticStatus."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True)
class Status:
    """One diagnostic status: a level, a one-line message and key-values."""

    level: Level
    message: str
    values: Mapping[str, object] = field(default_factory=lambda: MappingProxyType({}))


class HeldEvent:
    """A problem that happened once and is over by itself (a refused model change, a failed
    write, a failed adaptation attempt): its status shows it as a WARN for a hold time of
    the node's clock from when it first saw it, then in its values only. Without the hold a
    status would either miss a short problem between two reports or keep saying an old one
    until the next success, long after the node recovered."""

    def __init__(self) -> None:
        self._marker: object = None
        self._seen_ns = 0

    def shown(self, marker: object, now_ns: int, hold: float) -> bool:
        """Whether the problem `marker` names (None: there is none; another value: a new
        one) is still within `hold` seconds of when it was first seen; a clock that went
        back (a simulator reset) starts the hold again."""
        if marker is None:
            self._marker = None
            return False
        if marker != self._marker or now_ns < self._seen_ns:
            self._marker, self._seen_ns = marker, now_ns
        return now_ns - self._seen_ns < hold * 1e9


def latency_values(prefix: str, summary: LatencySummary) -> dict[str, object]:
    """Key-values `<prefix>_p50_us`, `_p99_us`, `_max_us`, `_samples` of a summary."""
    return {
        f'{prefix}_p50_us': round(summary.p50 * 1e6, 2),
        f'{prefix}_p99_us': round(summary.p99 * 1e6, 2),
        f'{prefix}_max_us': round(summary.max * 1e6, 2),
        f'{prefix}_samples': summary.samples,
    }


def rejection_values(counter: RejectionCounter) -> dict[str, object]:
    """Key-values `rejected_total` and `rejected.<reason>` of a counter."""
    values: dict[str, object] = {'rejected_total': counter.total}
    values.update({f'rejected.{reason}': n for reason, n in counter.counts().items()})
    return values


#: `DurationHistogram`'s bins: below `_FIRST_NS` one bin, then 4 per octave (the top two
#: bits after the leading one), up to `_OCTAVES` octaves; longer durations in the last bin.
_FIRST_NS = 256
_OCTAVES = 27  # 256 ns .. 34 s
_BINS = 1 + 4 * _OCTAVES + 1
#: The percentiles of a `CallbackTimes` row on /diagnostics.
_PERCENTILES = (50.0, 99.0, 99.9)


def bin_index(ns: int) -> int:
    """The `DurationHistogram` bin of a duration of `ns` nanoseconds (integer operations
    only: cheap enough for every sample)."""
    if ns < _FIRST_NS:
        return 0
    bits = ns.bit_length()
    return min((bits - 9) * 4 + ((ns >> (bits - 3)) & 3) + 1, _BINS - 1)


def bin_lower_ns(index: int) -> int:
    """The shortest duration [ns] that falls in bin `index`."""
    if index == 0:
        return 0
    octave, quarter = divmod(index - 1, 4)
    return (_FIRST_NS << octave) * (4 + quarter) // 4


class DurationHistogram:
    """Durations [ns] counted in fixed bins, 4 per octave (a quarter octave is 19 % wide at
    most), from 256 ns to 34 s: recording is a few integer operations on a list made once,
    so it can run for every sample; percentiles are read from the bins (their upper edge,
    conservative), the maximum exactly."""

    def __init__(self) -> None:
        self.counts = [0] * _BINS
        self.total = 0
        self.sum_ns = 0
        self.max_ns = 0

    def record(self, ns: int, runs: int = 1) -> None:
        """`runs` durations of `ns` each."""
        self.counts[bin_index(ns)] += runs
        self.total += runs
        self.sum_ns += ns * runs
        if ns > self.max_ns:
            self.max_ns = ns

    def percentiles_ns(self, *qs: float) -> list[int]:
        """For each `q` (0 < q <= 100) the upper edge of the bin that holds the `q` % point,
        or the max where that is smaller; 0 when empty."""
        if not self.total:
            return [0] * len(qs)
        cumulative = list(itertools.accumulate(self.counts))
        edges = []
        for q in qs:
            index = bisect.bisect_left(cumulative, q / 100.0 * self.total)
            upper = bin_lower_ns(index + 1) if index + 1 < _BINS else self.max_ns
            edges.append(min(upper, self.max_ns))
        return edges

    def text(self) -> str:
        """The non-empty bins as 'lower_ns:count' pairs, space separated
        (`parse_histogram` reads it back)."""
        return ' '.join(f'{bin_lower_ns(i)}:{n}' for i, n in enumerate(self.counts) if n)


def parse_histogram(text: str) -> dict[int, int]:
    """{bin's lower edge [ns]: count} of a `DurationHistogram.text`."""
    pairs = (item.split(':') for item in text.split())
    return {int(lower): int(count) for lower, count in pairs}


class CallbackTimes:
    """Where a node's thread spends its time: per kind of work (a named row: a callback,
    'logging', 'garbage collection', 'executor'), a `DurationHistogram` of the wall time of
    each run and the thread CPU time they used. Wall time well above CPU time is time the
    thread waited for the processor (other processes or threads ran); a sample that queued
    behind a row's long run waited as long. Rows are made on first use; recording one is
    cheap enough for every sample (`measure`: four clock readings)."""

    def __init__(self) -> None:
        self.rows: dict[str, DurationHistogram] = {}
        self.cpu_ns: dict[str, int] = {}
        #: CPU time of the outermost `measure`d runs [ns] (the executor's is the rest), how
        #: many they were, and how many runs it called `apart` (callbacks the executor did
        #: not dispatch: another node's, called from this node's).
        self.measured_cpu_ns = 0
        self.measured_runs = 0
        self.apart_runs = 0
        # wall and CPU time [ns] of the work run `apart` so far (taken out of the run
        # around it)
        self._apart_wall_ns = 0
        self._apart_cpu_ns = 0
        self._depth = 0  # `measure` calls running (a log call inside a callback: 2)
        self._gc_started = 0

    def record(self, row: str, wall_ns: int, cpu_ns: int | None = None, runs: int = 1) -> None:
        """`runs` runs of `row` that took `wall_ns` each (and `cpu_ns` of the thread's CPU
        together, if measured)."""
        histogram = self.rows.get(row)
        if histogram is None:
            histogram = self.rows[row] = DurationHistogram()
        histogram.record(wall_ns, runs)
        if cpu_ns is not None:
            self.cpu_ns[row] = self.cpu_ns.get(row, 0) + cpu_ns

    def measure(self, row: str, function: Callable[..., object], *args: object) -> None:
        """Run `function(*args)` and record it under `row`, also when it raises (without
        the work it ran `apart`)."""
        wall, cpu = time.perf_counter_ns(), time.thread_time_ns()
        apart_wall, apart_cpu = self._apart_wall_ns, self._apart_cpu_ns
        self._depth += 1
        try:
            function(*args)
        finally:
            used = time.thread_time_ns() - cpu - (self._apart_cpu_ns - apart_cpu)
            self.record(row, time.perf_counter_ns() - wall - (self._apart_wall_ns - apart_wall),
                        used)
            self._depth -= 1
            if not self._depth:
                self.measured_cpu_ns += used
                self.measured_runs += 1

    def apart(self, function: Callable[..., object], *args: object) -> None:
        """Run `function(*args)`, work that is not part of the run it is called from
        (another node's callback called from one of this node's, a status sent between two
        samples), outside that run's time; a run it `measure`s is an outermost one."""
        wall, cpu = time.perf_counter_ns(), time.thread_time_ns()
        self.apart_runs += 1
        depth, self._depth = self._depth, 0
        try:
            function(*args)
        finally:
            self._depth = depth
            self._apart_cpu_ns += time.thread_time_ns() - cpu
            self._apart_wall_ns += time.perf_counter_ns() - wall

    def on_gc(self, phase: str, info: dict[str, int]) -> None:
        """A `gc.callbacks` hook: each collection recorded by generation."""
        if phase == 'start':
            self._gc_started = time.perf_counter_ns()
        elif self._gc_started:
            self.record(f'garbage collection {info["generation"]}',
                        time.perf_counter_ns() - self._gc_started)
            self._gc_started = 0

    def values(self, histograms: bool = False) -> dict[str, object]:
        """Key-values of every row for a status: runs, mean wall and CPU, p50 / p99 / p99.9
        / max [us], and with `histograms` the histogram (`DurationHistogram.text`)."""
        values: dict[str, object] = {}
        for row, histogram in sorted(self.rows.items()):
            runs = histogram.total
            values[f'{row}.runs'] = runs
            values[f'{row}.mean_us'] = round(histogram.sum_ns / runs * 1e-3, 2)
            if row in self.cpu_ns:
                values[f'{row}.cpu_mean_us'] = round(self.cpu_ns[row] / runs * 1e-3, 2)
            for q, ns in zip(_PERCENTILES, histogram.percentiles_ns(*_PERCENTILES),
                             strict=True):
                values[f'{row}.p{q:g}_us'] = round(ns * 1e-3, 2)
            values[f'{row}.max_us'] = round(histogram.max_ns * 1e-3, 2)
            if histograms:
                values[f'{row}.histogram_ns'] = histogram.text()
        return values

    def status(self, histograms: bool = False) -> Status:
        """The 'callback timing' status: always OK, for reading (docs/speed.md); the
        histograms only with `histograms` (a bench's measurement, not an operator's)."""
        slowest = max(self.rows.items(), key=lambda item: item[1].max_ns, default=None)
        message = ('nothing timed yet' if slowest is None else
                   f'{len(self.rows)} kinds of work timed; longest run: {slowest[0]}, '
                   f'{slowest[1].max_ns * 1e-3:.0f} us')
        return Status(Level.OK, message, self.values(histograms))
