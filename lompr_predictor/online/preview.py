"""The planned reference of the coming instants (docs/interface.md, topics, reference preview).

`PlannedPath` keeps the newest planned tool-tip position per instant, aligned by stamp and
linearly interpolated like the reference (`at`), never by arrival order: a newer preview
replaces an older one for the instants both cover. A preview is refused whole, with its
reason counted, when a pose is not finite, its stamps do not increase or it plans nothing
after the newest reference. The reference actually commanded is checked against the plan
(`check`): a plan that contradicts it (the path changed, e.g. the program was stopped) is
dropped, since the instants it covered were predicted from a path that will not happen.
"""

from __future__ import annotations

import math
from enum import StrEnum

import numpy as np

from lompr_predictor.monitoring import RejectionCounter

XYZ = tuple[float, float, float]


class PreviewDrop(StrEnum):
    """Why a preview (or the plan it built) was not used; each is counted
    (`PlannedPath.dropped`), the value is the key on /diagnostics."""

    UNREADABLE = 'unreadable'
    WRONG_FRAME = 'wrong_frame'
    EMPTY = 'empty'
    NON_FINITE = 'non_finite'
    OUT_OF_ORDER = 'out_of_order'
    PAST = 'past'
    CONTRADICTED = 'contradicted'
    #: a sample used while the plan did not cover the instant its model reads ahead
    MISSING = 'missing'


class PlannedPath:
    """The planned positions of the coming instants, from the previews received.

    `max_step_ns`: planned poses further apart than this are not interpolated between (a gap
    in the plan); `tolerance`: how far [m] the commanded reference may lie from the plan
    before the plan counts as contradicted."""

    def __init__(self, max_step_ns: float, tolerance: float) -> None:
        self.max_step_ns = max_step_ns
        self.tolerance = tolerance
        self._stamps = np.zeros(0, dtype=np.int64)
        self._positions = np.zeros((0, 3))
        self._newest_reference_ns = -1
        self.dropped = RejectionCounter(PreviewDrop)
        self.previews_used = 0

    @property
    def horizon_ns(self) -> int | None:
        """The last planned instant [ns], None without a plan."""
        return int(self._stamps[-1]) if len(self._stamps) else None

    def add(self, stamps: np.ndarray, positions: np.ndarray) -> PreviewDrop | None:
        """Take one preview: (n,) int64 instants [ns] and (n, 3) planned positions [m]; the
        reason it was refused (counted), or None."""
        reason = self._problem(stamps, positions)
        if reason is not None:
            self.dropped.add(reason)
            return reason
        old = self._stamps  # sorted: what the new plan does not cover is before or after it
        before = int(np.searchsorted(old, stamps[0]))
        after = int(np.searchsorted(old, stamps[-1], side='right'))
        self._stamps = np.concatenate([old[:before], stamps, old[after:]])
        self._positions = np.concatenate([self._positions[:before], positions,
                                          self._positions[after:]])
        self.previews_used += 1
        return None

    def at(self, stamp_ns: int) -> XYZ | None:
        """The planned position at `stamp_ns`, interpolated between the planned instants
        around it (at most `max_step_ns` apart), or None where the plan does not cover it."""
        stamps = self._stamps
        index = int(np.searchsorted(stamps, stamp_ns))
        if index < len(stamps) and stamps[index] == stamp_ns:
            x, y, z = self._positions[index].tolist()
            return x, y, z
        if index == 0 or index == len(stamps):
            return None
        before, after = int(stamps[index - 1]), int(stamps[index])
        if after - before > self.max_step_ns:
            return None
        weight = (stamp_ns - before) / (after - before)
        x0, y0, z0 = self._positions[index - 1].tolist()
        x1, y1, z1 = self._positions[index].tolist()
        return (x0 + weight * (x1 - x0), y0 + weight * (y1 - y0), z0 + weight * (z1 - z0))

    def check(self, stamp_ns: int, x: float, y: float, z: float) -> bool:
        """The reference commanded at `stamp_ns`: False (and the plan dropped, counted as
        contradicted) if the plan covers that instant elsewhere than `tolerance` allows;
        the plan before it is let go."""
        self._newest_reference_ns = max(self._newest_reference_ns, stamp_ns)
        planned = self.at(stamp_ns)
        # keep the instant before: it brackets instants after the reference
        cut = int(np.searchsorted(self._stamps, stamp_ns)) - 1
        if cut > 0:
            self._stamps, self._positions = self._stamps[cut:], self._positions[cut:]
        if planned is None:
            return True
        px, py, pz = planned
        if max(abs(px - x), abs(py - y), abs(pz - z)) <= self.tolerance:
            return True
        self.dropped.add(PreviewDrop.CONTRADICTED)
        self.clear()
        return False

    def clear(self) -> None:
        """Forget the plan (the next preview starts a new one)."""
        self._stamps = self._stamps[:0]
        self._positions = self._positions[:0]

    def _problem(self, stamps: np.ndarray, positions: np.ndarray) -> PreviewDrop | None:
        if len(stamps) == 0:
            return PreviewDrop.EMPTY
        # one sum instead of a mask: NaN and infinity carry through it (a sum that overflows
        # holds positions no robot has, refused alike)
        if not math.isfinite(float(positions.sum())):
            return PreviewDrop.NON_FINITE
        if not (stamps[1:] > stamps[:-1]).all():
            return PreviewDrop.OUT_OF_ORDER
        if stamps[-1] <= self._newest_reference_ns:
            return PreviewDrop.PAST
        return None


class PlanReader:
    """What a preview model reads with each sample: the plan `lead_ns` after the sample's
    stamp (`at_sample`), counted missing where the plan does not reach it, and `stale` once
    no sample had one for `stale_after_ns` of the caller's clock [ns]."""

    def __init__(self, plan: PlannedPath, lead_ns: int, stale_after_ns: int) -> None:
        self.plan = plan
        self.lead_ns = lead_ns
        self.stale_after_ns = stale_after_ns
        self.stale = False
        self._planned_ns: int | None = None  # when a sample last had a plan

    def at_sample(self, stamp_ns: int, now_ns: int) -> tuple[int, float, float, float] | None:
        """(instant [ns], planned x, y, z [m]) `lead_ns` after the sample at `stamp_ns`,
        used at `now_ns`; None (counted) where the plan does not reach it."""
        instant_ns = stamp_ns + self.lead_ns
        position = self.plan.at(instant_ns)
        if position is not None:
            self._planned_ns = now_ns
            self.stale = False
            return (instant_ns, *position)
        self.plan.dropped.add(PreviewDrop.MISSING)
        if self._planned_ns is None:
            self._planned_ns = now_ns
        if now_ns - self._planned_ns >= self.stale_after_ns:
            self.stale = True
        return None
