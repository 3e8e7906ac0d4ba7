# SPDX-License-Identifier: Apache-2.0
"""The overrun policy, on the node's clock (ROS-free, integer nanoseconds).

An output is for the instant stamp + lead (lead = horizon x sample period); it is late when,
on the node's clock, that instant has passed by more than a tolerance. How the instant is
read depends on where the stamps come from:

- stamps on the node's clock (a driver stamping with ROS time, a simulator's /clock): the
  smallest delay seen since the last restart lies between minus the tolerance and
  `SAME_CLOCK_NS`. The instant is then read as it is: every delay counts, a wait for the
  CPU before the callback ran included, so what the node counts late is what a receiver on
  the same clock sees late (less the transport after publishing);
- stamps on another clock (a bag replayed without /clock, a recording's epoch): judged
  against the best-case input delay, so that delay that builds up behind inferences counts
  and delay while the node waits for input does not (it cannot be told from a slow clock).

A sample whose output would be late gets no inference, so a backlog behind a slow model is
skipped to the newest sample; an inference that finishes late publishes nothing. A sample
that did not queue is always inferred, so one stall cannot stop the node. The estimate
restarts when a stamp or the clock goes backwards.
"""

from __future__ import annotations

#: The largest smallest delay [ns] still read as transport and scheduling on one clock:
#: far above a cell's (micro- to milliseconds), far below the offset of another clock.
SAME_CLOCK_NS = 1_000_000_000


class OverrunGuard:
    """Lateness of outputs on the node's clock (module docstring). All times in ns."""

    def __init__(self, lead_ns: int, tolerance_ns: int) -> None:
        self.lead_ns = lead_ns
        self.tolerance_ns = tolerance_ns
        self._offset: int | None = None  # best-case node time - stamp
        self._floor: int | None = None  # the smallest node time - stamp since the restart
        self._idle_since: int | None = None  # node time at which the last inference ended
        self._last_stamp: int | None = None
        self._inference_ns = 0  # the last inference's duration on the node's clock
        self.inference_skipped_late = 0
        self.late_outputs_dropped = 0
        self.outputs_in_time = 0  # published before their instant
        self.outputs_after_instant = 0  # published after it, within the tolerance

    def arrival(self, stamp_ns: int, now_ns: int) -> None:
        """A sample stamped `stamp_ns` arrived (its callback started) at `now_ns`."""
        idle_since = self._idle_since
        going_back = ((self._last_stamp is not None and stamp_ns < self._last_stamp)
                      or (idle_since is not None and now_ns < idle_since))
        if going_back:
            self.restart()
            idle_since = None
        self._last_stamp = stamp_ns
        delay = now_ns - stamp_ns
        self._floor = delay if self._floor is None else min(self._floor, delay)
        offset = self._offset
        if offset is None or idle_since is None:
            self._offset = delay
        else:
            self._offset = min(delay, offset + max(now_ns - idle_since, 0))

    @property
    def same_clock(self) -> bool | None:
        """Whether the stamps are read as on the node's clock (module docstring); None
        before any sample."""
        if self._floor is None:
            return None
        return -self.tolerance_ns <= self._floor <= SAME_CLOCK_NS

    def lateness_ns(self, stamp_ns: int, now_ns: int) -> int:
        """How far past its instant the output of the sample stamped `stamp_ns` would be if
        published at `now_ns` (negative: in time); 0 before any estimate."""
        if self._offset is None:
            return 0
        offset = 0 if self.same_clock else self._offset
        return now_ns - stamp_ns - offset - self.lead_ns

    def late(self, stamp_ns: int, now_ns: int) -> bool:
        """Whether the output of that sample, published at `now_ns`, would come after its
        instant by more than the tolerance."""
        return self.lateness_ns(stamp_ns, now_ns) > self.tolerance_ns

    def skip(self, stamp_ns: int, now_ns: int) -> bool:
        """Whether the sample is not worth an inference: its output is late already, or it
        queued (waited more than the tolerance) and an inference as long as the last one
        would finish late."""
        lateness = self.lateness_ns(stamp_ns, now_ns)
        if lateness > self.tolerance_ns:
            return True
        waited = lateness + self.lead_ns
        return waited > self.tolerance_ns and lateness + self._inference_ns > self.tolerance_ns

    def inference_took(self, start_ns: int, end_ns: int) -> None:
        """An inference ran from `start_ns` to `end_ns` (node clock): its duration, and
        the time from which the node is idle again."""
        self._inference_ns = max(end_ns - start_ns, 0)
        self._idle_since = end_ns

    def restart(self) -> None:
        """Forget the estimate (stamps or the clock went back)."""
        self._offset = None
        self._floor = None
        self._idle_since = None
        self._last_stamp = None
