# SPDX-License-Identifier: Apache-2.0
"""Alignment by stamp: each pose gets the reference interpolated to its own stamp.

The measured tool tip and the reference may come at different instants and rates, and in
any arrival order (docs/interface.md, topics); a consumer aligns them by time, never by
arrival. `StampAlignment` keeps the poses that wait for a reference at or after their stamp, in
arrival order, and the reference track (`ReferenceTrack`) they are interpolated on. Each
input returns what became ready, in order: an `AlignedSample` or the `FaultReason` of a
fault the caller must handle there, between the samples. Every input not used is counted by
reason in `dropped`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from enum import StrEnum
from typing import NamedTuple

from lompr_predictor.monitoring import RejectionCounter
from lompr_predictor.online.faults import FaultReason


class DropReason(StrEnum):
    """Why an input sample was not used; each is counted (`StampAlignment.dropped`) and the
    value is the key on /diagnostics (`rejected.<value>`)."""

    NON_FINITE = 'non_finite'
    DUPLICATE = 'duplicate'
    OUT_OF_ORDER = 'out_of_order'
    NO_REFERENCE = 'no_reference'
    REFERENCE_DUPLICATE = 'reference_duplicate'
    REFERENCE_NON_FINITE = 'reference_non_finite'
    REFERENCE_OUT_OF_ORDER = 'reference_out_of_order'
    STALE = 'stale'
    CLOCK_JUMP = 'clock_jump'
    INACTIVE = 'inactive'
    INTERNAL = 'internal'
    BAD_STAMP = 'bad_stamp'
    FUTURE_STAMP = 'future_stamp'
    REFERENCE_BAD_STAMP = 'reference_bad_stamp'
    REFERENCE_FUTURE_STAMP = 'reference_future_stamp'
    WRONG_FRAME = 'wrong_frame'
    REFERENCE_WRONG_FRAME = 'reference_wrong_frame'

#: Drops that say a sender is wrong (another frame, stamps on another clock), not that a
#: stream hiccuped: each raises the inputs status, as a fault does.
SENDER_ERRORS = frozenset({DropReason.WRONG_FRAME, DropReason.REFERENCE_WRONG_FRAME,
                           DropReason.BAD_STAMP, DropReason.REFERENCE_BAD_STAMP,
                           DropReason.FUTURE_STAMP, DropReason.REFERENCE_FUTURE_STAMP})

#: Poses kept waiting for a reference at or after their stamp; beyond, the oldest is dropped.
MAX_PENDING_POSES = 1000
#: References kept before the oldest pose that may still need one.
REFERENCE_MARGIN = 4
#: References kept at most (while no pose comes to use them, the oldest go).
MAX_REFERENCES = 10_000
#: Reference steps whose median is the reference's own period.
REFERENCE_STEPS = 15


class ReferenceTrack:
    """The reference stream, linearly interpolated to pose stamps across short brackets.

    A bracket is short when it spans at most `gap_factor` periods of the poses or of the
    reference itself (its median step over the last `REFERENCE_STEPS`), whichever is
    longer: the reference may come slower than the poses (docs/interface.md, topics).
    """

    def __init__(self, gap_factor: float, period_ns: int) -> None:
        self.gap_factor = gap_factor
        self.max_bracket_ns = gap_factor * period_ns
        self._pose_period_ns = period_ns
        self._stamps: deque[int] = deque(maxlen=MAX_REFERENCES)
        self._positions: deque[tuple[float, float, float]] = deque(maxlen=MAX_REFERENCES)
        self._steps: deque[int] = deque(maxlen=REFERENCE_STEPS)

    @property
    def newest(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_ns: int, x: float, y: float, z: float) -> DropReason | None:
        """Keep one reference tool tip; None, or the reason it was not kept."""
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            return DropReason.REFERENCE_NON_FINITE
        newest = self.newest
        if newest is not None and stamp_ns <= newest:
            return (DropReason.REFERENCE_DUPLICATE if stamp_ns == newest
                    else DropReason.REFERENCE_OUT_OF_ORDER)
        if newest is not None:
            steps, step = self._steps, stamp_ns - newest
            # a step equal to the one it pushes out leaves the median as it is: a regular
            # stream sorts nothing
            unchanged = len(steps) == steps.maxlen and steps[0] == step
            steps.append(step)
            if not unchanged:
                typical = sorted(steps)[len(steps) // 2]
                self.max_bracket_ns = self.gap_factor * max(self._pose_period_ns, typical)
        self._stamps.append(stamp_ns)
        self._positions.append((x, y, z))
        return None

    def restart(self, stamp_ns: int, x: float, y: float, z: float) -> None:
        """Forget the history and start again from one reference (the stream went back)."""
        self.clear()
        self._stamps.append(stamp_ns)
        self._positions.append((x, y, z))

    def clear(self) -> None:
        self._stamps.clear()
        self._positions.clear()

    def drop_after(self, stamp_ns: int | None) -> None:
        """Forget the references stamped after `stamp_ns` (all of them if None)."""
        if stamp_ns is None:
            self.clear()
            return
        while self._stamps and self._stamps[-1] > stamp_ns:
            self._stamps.pop()
            self._positions.pop()

    def at(self, stamp_ns: int) -> tuple[float, float, float] | FaultReason | None:
        """The reference at `stamp_ns`; None while no reference at or after it has arrived;
        a no_reference fault when the history does not bracket it within `max_bracket_ns`."""
        stamps, positions = self._stamps, self._positions
        if not stamps or stamp_ns > stamps[-1]:
            return None
        while len(stamps) > REFERENCE_MARGIN and stamps[1] <= stamp_ns:
            stamps.popleft()
            positions.popleft()
        if stamp_ns < stamps[0]:
            return FaultReason.NO_REFERENCE
        right = 0
        while stamps[right] < stamp_ns:
            right += 1
        if stamps[right] == stamp_ns:
            return positions[right]
        left = right - 1
        span = stamps[right] - stamps[left]
        if span > self.max_bracket_ns:
            return FaultReason.NO_REFERENCE
        weight = (stamp_ns - stamps[left]) / span
        (x0, y0, z0), (x1, y1, z1) = positions[left], positions[right]
        return x0 + weight * (x1 - x0), y0 + weight * (y1 - y0), z0 + weight * (z1 - z0)


class AlignedSample(NamedTuple):
    """A pose with the reference at its stamp (SI units)."""

    stamp_ns: int
    x: float  # measured tool tip X [m]
    y: float  # measured tool tip Y [m]
    reference_x: float  # reference tool tip at the stamp [m]
    reference_y: float
    reference_z: float


class _Pose(NamedTuple):
    stamp_ns: int
    x: float
    y: float
    arrival_ns: int  # clock() when it arrived


#: What an input made ready, in order: a sample to use, or the reason of a fault.
Event = AlignedSample | FaultReason


class StampAlignment:
    """Poses waiting for their reference, and the reference track (module docstring).

    `clock` (integer nanoseconds) stamps each pose's arrival, so that a pose waiting too
    long for its reference can be told from a stream that stopped
    (`oldest_waiting_arrival`).
    A non-finite pose is a fault, raised in its place among the waiting poses (the poses
    before it are still used first); a pose with a stamp going backwards is a fault at once
    (the waiting poses are dropped); a repeated stamp is dropped without a fault.
    """

    def __init__(self, gap_factor: float, period_ns: int, clock: Callable[[], int]) -> None:
        self.references = ReferenceTrack(gap_factor, period_ns)
        self._clock = clock
        self._pending: deque[_Pose | FaultReason] = deque()
        #: Stamp of the newest pose taken (the last one, if a stamp went backwards) [ns].
        self.newest_pose_ns: int | None = None
        self.dropped = RejectionCounter(DropReason)

    @property
    def waiting(self) -> bool:
        """Whether any pose (or a fault in its place) waits for a reference."""
        return bool(self._pending)

    def oldest_waiting_arrival(self) -> int | None:
        """clock() at the arrival of the oldest pose still waiting, None if none waits."""
        for item in self._pending:
            if isinstance(item, _Pose):
                return item.arrival_ns
        return None

    def add_reference(self, stamp_ns: int, x: float, y: float, z: float) -> list[Event]:
        """Take one reference sample (the commanded tool tip); returns what became ready."""
        reason = self.references.add(stamp_ns, x, y, z)
        if reason is None:
            return self._drain([])
        self.dropped.add(reason)
        if reason == DropReason.REFERENCE_OUT_OF_ORDER:
            self.references.restart(stamp_ns, x, y, z)
            return [FaultReason.REFERENCE_OUT_OF_ORDER]
        if reason == DropReason.REFERENCE_NON_FINITE:
            return [FaultReason.REFERENCE_NON_FINITE]
        return []

    def add_pose(self, stamp_ns: int, x: float, y: float,
                 arrival_ns: int | None = None) -> list[Event]:
        """Take one measured tool-tip sample arrived at `arrival_ns` (the clock's reading of
        the caller's callback; None: read it); returns what became ready."""
        if not (math.isfinite(x) and math.isfinite(y)):
            self.dropped.add(DropReason.NON_FINITE)
            self._pending.append(FaultReason.NON_FINITE)
            return self._drain([])
        newest = self.newest_pose_ns
        if newest is not None and stamp_ns == newest:
            self.dropped.add(DropReason.DUPLICATE)
            return []
        if newest is not None and stamp_ns < newest:
            self.dropped.add(DropReason.OUT_OF_ORDER)
            self.newest_pose_ns = stamp_ns
            self.clear(DropReason.OUT_OF_ORDER)
            return [FaultReason.OUT_OF_ORDER]
        self.newest_pose_ns = stamp_ns
        self._pending.append(_Pose(stamp_ns, x, y,
                                   self._clock() if arrival_ns is None else arrival_ns))
        events: list[Event] = []
        if len(self._pending) > MAX_PENDING_POSES:
            self._pending.popleft()
            self.dropped.add(DropReason.NO_REFERENCE)
            events.append(FaultReason.NO_REFERENCE)
        return self._drain(events)

    def clear(self, reason: DropReason) -> None:
        """Drop the poses waiting for a reference, counted under `reason`."""
        self.dropped.add(reason, sum(isinstance(p, _Pose) for p in self._pending))
        self._pending.clear()

    def rewind(self, stamp_ns: int | None, reason: DropReason) -> None:
        """Take the streams as starting afresh at `stamp_ns` (a clock gone back to it, a
        simulator reset) or anew (None: a node reactivated): drop the waiting poses
        (counted under `reason`) and the references stamped after `stamp_ns` (all if None),
        and forget the newest pose stamp, so that the restarted streams are no out-of-order
        fault. A reference of the new run that came before the clock's jump is kept."""
        self.clear(reason)
        self.references.drop_after(stamp_ns)
        self.newest_pose_ns = None

    def _drain(self, events: list[Event]) -> list[Event]:
        """Append to `events` every waiting pose whose reference has arrived, in order."""
        pending = self._pending
        while pending:
            head = pending[0]
            if isinstance(head, FaultReason):
                pending.popleft()
                events.append(head)
                continue
            reference = self.references.at(head.stamp_ns)
            if reference is None:
                break
            pending.popleft()
            if isinstance(reference, FaultReason):
                self.dropped.add(DropReason.NO_REFERENCE)
                events.append(reference)
                continue
            events.append(AlignedSample(head.stamp_ns, head.x, head.y, *reference))
        return events
