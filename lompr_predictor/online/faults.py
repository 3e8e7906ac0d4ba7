# SPDX-License-Identifier: Apache-2.0
"""When the input stream is not what the model was trained on: the fault rules.

A fault empties the window and cancels the offset in force (`offset.OffsetGate.cancel`);
output resumes once the window has refilled with good samples. The rules here decide what
is a fault, apart from the alignment's own (`alignment.StampAlignment`: non-finite values,
stamps going backwards, poses the reference does not bracket) and a failing inference:

- `StreamRules`: the interval between two used samples must be near the model's sample
  period, as in the trainer: above `gap_factor` periods it is a gap (the trainer splits its
  data there), below `min_interval_factor` periods the input is not at the model's rate.
- `StaleWatch`: no usable sample for `StreamSettings.stale_after` seconds of `clock`
  (integer nanoseconds), found by two checks in a row. The clock is the caller's: the
  predictor node gives its ROS clock,
  so under simulated time a simulator slower than real time is not stale, and one that
  stands still (waiting for an answer in lockstep) never is.
- `clock_jump`: the clock went backwards (a simulator reset); the caller reports it
  (`OnlinePredictor.clock_jumped_back`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import TypeGuard

from lompr_predictor.stamps import period_ns


class FaultReason(StrEnum):
    """Why the window was emptied (and an offset in force cancelled by a zero); the value
    is the key on /diagnostics (`faults.<value>`)."""

    NON_FINITE = 'non_finite'
    OUT_OF_ORDER = 'out_of_order'
    GAP = 'gap'
    OFF_RATE = 'off_rate'
    NO_REFERENCE = 'no_reference'
    REFERENCE_NON_FINITE = 'reference_non_finite'
    REFERENCE_OUT_OF_ORDER = 'reference_out_of_order'
    INFERENCE = 'inference'
    STALE = 'stale'
    CLOCK_JUMP = 'clock_jump'
    INTERNAL = 'internal'


_FAULT_VALUES = frozenset(FaultReason)


def is_fault(reason: StrEnum | None) -> TypeGuard[FaultReason]:
    """Whether an output's reason is a fault (not a prediction, nor a cancel by the
    caller such as 'inactive')."""
    return reason in _FAULT_VALUES


@dataclass(frozen=True, kw_only=True)
class StreamSettings:
    """How the input stream must look for the model (SI units). No defaults: the node
    builds it by keyword from its declared parameters (`ros.predictor_settings`), the one
    declaration of each; a test states the values it runs on."""

    sample_period: float  # [s] the model's; also the spacing the stamps must have
    gap_factor: float  # an interval above gap_factor * sample_period is a gap
    min_interval_factor: float  # one below min_interval_factor * sample_period is off-rate
    stale_periods: float  # no sample for this many periods (of the clock): input is stale
    # ... and for at least this long [s]: a process on a general-purpose OS can stall for
    # milliseconds (scheduler, garbage collector), which at kHz rates is many periods
    stale_min_time: float
    accuracy_samples: int  # residuals the live RMS is over
    #: [s] A message stamp further than this ahead of the clock is dropped.
    max_future_stamp: float
    #: [s] An output may come this much after its instant before it counts as late
    #: (`timing.OverrunGuard`).
    late_tolerance: float
    #: [m] How far the commanded reference may lie from the preview's plan for the same
    #: instant before the plan counts as contradicted (`preview.PlannedPath.check`).
    preview_tolerance: float

    @property
    def stale_after(self) -> float:
        """Seconds of the clock without a usable sample after which the input is stale."""
        return max(self.stale_periods * self.sample_period, self.stale_min_time)


class StreamRules:
    """The interval rules between two used samples (module docstring)."""

    def __init__(self, stream: StreamSettings, period_ns: int) -> None:
        self.max_interval_ns = stream.gap_factor * period_ns
        self.min_interval_ns = stream.min_interval_factor * period_ns

    def interval_fault(self, previous_ns: int, stamp_ns: int) -> FaultReason | None:
        """The fault of an interval the model was not trained on, None for one it was."""
        interval = stamp_ns - previous_ns
        if interval > self.max_interval_ns:
            return FaultReason.GAP
        if interval < self.min_interval_ns:
            return FaultReason.OFF_RATE
        return None


class StaleWatch:
    """Input gone stale: no usable sample for `stale_after` seconds of `clock` (which reads
    integer nanoseconds).

    `used()` marks a sample used now. `check(oldest_waiting)` is called periodically, with
    the arrival time of the oldest pose still waiting for its reference (a pose waiting
    that long counts as no sample); it is True when this call and the previous one both
    found the input idle that long. One idle check alone proves nothing: an executor that
    was busy runs its timer before the samples that queued meanwhile.
    """

    def __init__(self, stale_after: float, clock: Callable[[], int]) -> None:
        self.stale_after_ns = period_ns(stale_after)
        self._clock = clock
        self._last_used = clock()
        self._suspected = False

    def used(self, now_ns: int | None = None) -> None:
        """A sample was used at `now_ns` (the clock's reading of the caller's callback;
        None: read it)."""
        self._last_used = self._clock() if now_ns is None else now_ns

    def restart(self) -> None:
        """Count idle time from now on, and forget a suspicion: the clock jumped (it
        started, a simulator skipped ahead or was reset), so time read before says nothing
        about the input."""
        self._last_used = self._clock()
        self._suspected = False

    def check(self, oldest_waiting_ns: int | None = None) -> bool:
        """True when this check and the previous one both found the input idle."""
        since = self._last_used if oldest_waiting_ns is None else max(self._last_used,
                                                                      oldest_waiting_ns)
        idle = self._clock() - since >= self.stale_after_ns
        confirmed, self._suspected = self._suspected and idle, idle
        return confirmed
