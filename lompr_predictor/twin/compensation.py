# SPDX-License-Identifier: Apache-2.0
"""Compensation offsets waiting for their instant, as a real controller keeps them.

An offset is stamped with the sample instant it is for (docs/interface.md, the error). The
controller applies it when it executes that instant, and drops it, counting why, when it:

- `late`: arrives for an instant already executed (or being executed);
- `stale`: waited longer than the timeout between its arrival and its instant;
- `off_grid`: is stamped between two sample instants (more than a quarter period off);
- `non_finite`: holds a NaN or infinity;
- `too_large`: exceeds `max_offset` in any axis (a sane controller refuses a wild offset);
- `superseded`: is replaced by a newer offset for the same instant.

Time here is the sample index of the twin's simulated clock, so the rules hold at any speed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import StrEnum

import numpy as np

from lompr_predictor.monitoring import RejectionCounter


class OffsetDrop(StrEnum):
    """Why the controller dropped an offset (module docstring)."""

    LATE = 'late'
    STALE = 'stale'
    OFF_GRID = 'off_grid'
    NON_FINITE = 'non_finite'
    TOO_LARGE = 'too_large'
    SUPERSEDED = 'superseded'


class CompensationSchedule:
    """Offsets by sample index, applied at most once each."""

    def __init__(self, epoch_ns: int, period_ns: int, timeout_samples: int,
                 max_offset: float) -> None:
        self.epoch_ns = int(epoch_ns)
        self.period_ns = int(period_ns)
        self.timeout_samples = int(timeout_samples)
        self.max_offset = float(max_offset)
        self.rejected = RejectionCounter(OffsetDrop)
        self.applied = 0
        self.missing = 0
        self._pending: dict[int, tuple[np.ndarray, int]] = {}

    def offer(self, stamp_ns: int, offset: Sequence[float],
              next_index: int) -> OffsetDrop | None:
        """Queue an offset received while `next_index` is the next sample to execute.
        Returns the rejection reason, or None when it was queued."""
        index = round((int(stamp_ns) - self.epoch_ns) / self.period_ns)
        reason = None
        if not all(math.isfinite(v) for v in offset):
            reason = OffsetDrop.NON_FINITE
        elif abs(int(stamp_ns) - self.epoch_ns - index * self.period_ns) > self.period_ns // 4:
            reason = OffsetDrop.OFF_GRID
        elif index < next_index:
            reason = OffsetDrop.LATE
        elif max(abs(v) for v in offset) > self.max_offset:
            reason = OffsetDrop.TOO_LARGE
        if reason is not None:
            self.rejected.add(reason)
            return reason
        if index in self._pending:
            self.rejected.add(OffsetDrop.SUPERSEDED)
        self._pending[index] = (np.array(offset, dtype=float), next_index)
        return None

    def has(self, index: int) -> bool:
        """Whether an offset for sample `index` is waiting."""
        return index in self._pending

    def take(self, index: int) -> np.ndarray:
        """The offset to apply at sample `index` (zero if none or stale); forgets older ones."""
        for old in [i for i in self._pending if i < index]:
            del self._pending[old]
            self.rejected.add(OffsetDrop.LATE)
        entry = self._pending.pop(index, None)
        if entry is None:
            self.missing += 1
            return np.zeros(3)
        offset, received_at = entry
        if index - received_at > self.timeout_samples:
            self.rejected.add(OffsetDrop.STALE)
            return np.zeros(3)
        self.applied += 1
        return offset

    @property
    def pending(self) -> int:
        return len(self._pending)
