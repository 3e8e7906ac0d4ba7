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

    def add(self, reason: str, count: int = 1) -> None:
        """Count `count` more inputs dropped for `reason`."""
        if count < 0:
            msg = f'a rejection count cannot be negative, got {count}'
            raise ValueError(msg)
        self._counts[reason] = self._counts.get(reason, 0) + count

    def __getitem__(self, reason: str) -> int:
        return self._counts.get(reason, 0)

    @property
    def total(self) -> int:
        """Inputs dropped for any reason."""
        return sum(self._counts.values())

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
        """p50, p99 (linear interpolation) and max of the durations held."""
        if self._count == 0:
            return LatencySummary(0, float('nan'), float('nan'), float('nan'))
        held = self._samples[:self._count]
        p50, p99 = np.percentile(held, [50.0, 99.0])
        return LatencySummary(self._count, float(p50), float(p99), float(held.max()))


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
            return f'{text} ({suppressed} more like this in the last {now - last:.1f} s)'
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
