# SPDX-License-Identifier: Apache-2.0
"""The offset gate: the one place the published offset is bounded, scheduled and cancelled.

Safety rules (docs/safety.md, docs/nodes.md):

- The offset for an instant is minus the prediction for it, clamped to `max_compensation`
  (XY norm, direction kept), low-passed (first order, cutoff `bandwidth`, 0: none: above a
  servo's bandwidth the plant error echoes the offset back into the prediction, docs/nodes.md)
  and limited to `max_step` change from the previous offset (XY norm), so it never jumps,
  also when it starts or resumes. The clamp is last: every offset published satisfies the
  clamp in force when it is published.
- Limits changed at run time hold from the very next output: a lowered `max_compensation`
  re-issues, clamped, every offset already published for an instant still to come (reason
  'clamp_lowered') and clamps the offset the step limit starts from. That is the one case
  where consecutive offsets may differ by more than `max_step`: a lowered clamp is only
  respected at once by a larger step (a cancel to zero is the other).
- An instant left without an offset (`missed`: the overrun policy skipped its inference or
  dropped its late output) gets zero from the controller, so the step limit starts again
  from zero: the offset ramps back in.
- What was published is kept by the instant it is for (`InstantSchedule`), offsets and
  predictions apart: the plant error of a sample subtracts the offset published for its
  instant (docs/interface.md, the error) and the live accuracy compares the prediction for it
  (`sample_units.LiveAccuracy`).
- Cancelling (a fault, or compensation switched off): if an offset is in force, a zero
  `Output` for every instant after the newest pose for which an offset was already
  published, or for the next instant if there is none; nothing if no offset was published
  since the last cancel. A controller applies each offset at its instant, the newest
  message for an instant winning, and nothing where it has none, so no offset computed
  before the cancel is applied after it; the plant error is computed with the same rule.
- Shadow mode (`enabled` false): every offset is zero; predictions go on.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

import numpy as np


@dataclass(frozen=True)
class CompensationLimits:
    """Bounds of the published offset [m]."""

    max_compensation: float  # XY norm of the offset
    max_step: float  # XY norm of its change from one sample to the next
    enabled: bool  # False: shadow mode, predictions go on, every offset is zero
    bandwidth: float = 0.0  # [Hz] cutoff of the offset's low-pass; 0: none


#: An X/Y pair [m], on Python floats: the per-sample path builds no arrays.
XY = tuple[float, float]
ZERO: XY = (0.0, 0.0)


class GateReason(StrEnum):
    """Why the gate itself re-issued offsets already published."""

    COMPENSATION_DISABLED = 'compensation_disabled'  # cancelled to zero
    CLAMP_LOWERED = 'clamp_lowered'  # clamped to a lowered `max_compensation`


class Output(NamedTuple):
    """What to publish for one instant."""

    instant_ns: int  # the instant both values are for [ns]
    prediction: XY | None  # predicted plant X/Y error [m]; None for a zero
    compensation: XY  # X/Y offset [m]
    # None for a prediction; else why the offset was re-issued: a `GateReason`, or the
    # caller's (a `faults.FaultReason`, an `alignment.DropReason`) for a cancel
    reason: StrEnum | None
    sample_stamp_ns: int  # stamp of the newest sample the output was made from [ns]


class InstantSchedule:
    """Values by the instant they are for, in increasing instants; found within a tolerance.

    `take(stamp)` returns the value for the instant nearest `stamp` (within the tolerance)
    and forgets every earlier one; stamps asked for must increase, as the poses do.
    """

    def __init__(self, tolerance_ns: int, capacity: int = 100_000) -> None:
        self.tolerance_ns = tolerance_ns
        self._items: deque[tuple[int, XY]] = deque(maxlen=capacity)

    def add(self, instant_ns: int, value: XY) -> None:
        self.cancel_from(instant_ns)
        self._items.append((instant_ns, value))

    def clamp_after(self, stamp_ns: int, limit: float) -> list[tuple[int, XY]]:
        """Clamp to `limit` (XY norm, direction kept) the values held for instants after
        `stamp_ns`; returns the (instant, new value) pairs that changed."""
        changed: list[tuple[int, XY]] = []
        items = self._items
        for i, (instant, value) in enumerate(items):
            if instant <= stamp_ns + self.tolerance_ns:
                continue
            x, y = value
            norm = math.hypot(x, y)
            if norm > limit:
                scale = limit / norm
                clamped = (x * scale, y * scale)
                items[i] = (instant, clamped)
                changed.append((instant, clamped))
        return changed

    def instants_after(self, stamp_ns: int) -> list[int]:
        """Instants held that lie after `stamp_ns` (beyond the tolerance)."""
        return [instant for instant, _ in self._items if instant > stamp_ns + self.tolerance_ns]

    def cancel_from(self, instant_ns: int) -> None:
        """Forget values for instants from `instant_ns` on (a later message supersedes)."""
        items = self._items
        while items and items[-1][0] >= instant_ns - self.tolerance_ns:
            items.pop()

    def take(self, stamp_ns: int) -> XY | None:
        items = self._items
        while items and items[0][0] < stamp_ns - self.tolerance_ns:
            items.popleft()
        if items and items[0][0] <= stamp_ns + self.tolerance_ns:
            return items.popleft()[1]
        return None


class OffsetGate:
    """Bounds, schedules and cancels the offsets (module docstring), on a grid of instants
    `period_ns` apart (an instant is found within half a period)."""

    def __init__(self, limits: CompensationLimits, period_ns: int) -> None:
        self.limits = limits
        self._period_ns = period_ns
        self._smoothing = smoothing_factor(limits.bandwidth, period_ns)
        self._compensations = InstantSchedule(period_ns // 2)
        self._predictions = InstantSchedule(period_ns // 2)
        self._offset = ZERO
        self._in_force = False
        self.clamped = 0  # offsets clamped to max_compensation
        self.step_limited = 0  # offsets limited to max_step from the previous one
        self.zeros_published = 0  # zero outputs of cancels
        self.reclamped = 0  # offsets re-issued clamped after max_compensation was lowered

    @property
    def in_force(self) -> bool:
        """Whether an offset was published since the last cancel (in shadow mode a zero)."""
        return self._in_force

    @property
    def offset_in_force(self) -> np.ndarray:
        """(2,) the last offset published (zero after a cancel or in shadow mode)."""
        return np.array(self._offset)

    def offset_for(self, stamp_ns: int) -> XY | None:
        """The offset published for the instant of `stamp_ns`, None where none was; it is
        forgotten with every earlier one. Stamps asked for must increase."""
        return self._compensations.take(stamp_ns)

    def prediction_for(self, stamp_ns: int) -> XY | None:
        """The prediction published for the instant of `stamp_ns` (as `offset_for`)."""
        return self._predictions.take(stamp_ns)

    def publish(self, instant_ns: int, prediction: XY, sample_stamp_ns: int) -> Output:
        """The bounded offset for `prediction` (the plant error predicted for `instant_ns`),
        scheduled with it."""
        compensation = self._bounded(-prediction[0], -prediction[1])
        self._predictions.add(instant_ns, prediction)
        self._compensations.add(instant_ns, compensation)
        self._offset = compensation
        self._in_force = True
        return Output(instant_ns, prediction, compensation, None, sample_stamp_ns)

    def cancel(self, reason: StrEnum, newest_pose_ns: int | None) -> list[Output]:
        """Zero outputs for the instants after `newest_pose_ns` that already have an offset,
        or for the next instant; none if no offset was published since the last cancel."""
        if not self._in_force:
            return []
        newest = newest_pose_ns or 0
        instants = (self._compensations.instants_after(newest)
                    or [newest + self._period_ns])
        for instant in instants:
            self._compensations.add(instant, ZERO)
        self._offset = ZERO
        self._in_force = False
        self.zeros_published += len(instants)
        return [Output(instant, None, ZERO, reason, newest) for instant in instants]

    def set_limits(self, limits: CompensationLimits, newest_pose_ns: int | None) -> list[Output]:
        """New bounds from the next output on. Disabling compensation cancels the offsets
        already published (reason 'compensation_disabled'); a lowered `max_compensation`
        re-issues, clamped, those above it (reason 'clamp_lowered') and clamps the offset
        the step limit starts from."""
        disabled = self.limits.enabled and not limits.enabled
        self.limits = limits
        self._smoothing = smoothing_factor(limits.bandwidth, self._period_ns)
        if disabled:
            return self.cancel(GateReason.COMPENSATION_DISABLED, newest_pose_ns)
        limit = limits.max_compensation
        self._offset = _clamped(*self._offset, limit)
        newest = newest_pose_ns or 0
        outputs = [Output(instant, None, value, GateReason.CLAMP_LOWERED, newest)
                   for instant, value in self._compensations.clamp_after(newest, limit)]
        self.reclamped += len(outputs)
        return outputs

    def missed(self) -> None:
        """An instant got no offset (the controller applies zero there): the next offset
        ramps in from zero."""
        self._offset = ZERO

    def _bounded(self, x: float, y: float) -> XY:
        """The offset for the wanted offset (x, y): clamped, low-passed, step-limited,
        clamped."""
        limits = self.limits
        if not limits.enabled:
            return ZERO
        norm = math.hypot(x, y)
        if norm > limits.max_compensation:
            scale = limits.max_compensation / norm
            x, y = x * scale, y * scale
            self.clamped += 1
        offset_x, offset_y = self._offset
        if self._smoothing < 1.0:
            x = offset_x + (x - offset_x) * self._smoothing
            y = offset_y + (y - offset_y) * self._smoothing
        change_x, change_y = x - offset_x, y - offset_y
        step = math.hypot(change_x, change_y)
        if step > limits.max_step:
            scale = limits.max_step / step
            x, y = offset_x + change_x * scale, offset_y + change_y * scale
            self.step_limited += 1
        # The clamp is the last operation, whatever the offset the step started from.
        return _clamped(x, y, limits.max_compensation)


def smoothing_factor(bandwidth: float, period_ns: int) -> float:
    """The share of the way to the wanted offset the offset goes per instant: a first-order
    low-pass of cutoff `bandwidth` [Hz] sampled every `period_ns` (its step response exact at
    the instants); 1 (none) for a bandwidth of 0."""
    if bandwidth <= 0.0:
        return 1.0
    return 1.0 - math.exp(-2.0 * math.pi * bandwidth * period_ns * 1e-9)


def _clamped(x: float, y: float, limit: float) -> XY:
    """(x, y) scaled to XY norm `limit` (direction kept) if it is longer."""
    norm = math.hypot(x, y)
    if norm > limit:
        scale = limit / norm
        return x * scale, y * scale
    return x, y

