# SPDX-License-Identifier: Apache-2.0
"""The planned reference of the coming instants (docs/interface.md, topics, reference preview).

`PlannedPath` keeps the newest planned tool-tip position per instant, aligned by stamp and
linearly interpolated like the reference (`at`), never by arrival order: a newer preview
replaces an older one for the instants both cover. A preview is refused whole, with its
reason counted, when a pose is not finite, its stamps do not increase or it plans nothing
after the newest reference. The reference actually commanded is checked against the plan
(`check`): a plan that contradicts it (the path changed, e.g. the program was stopped) is
dropped, since the instants it covered were predicted from a path that will not happen.

The plan is bounded: it reaches at most `PLAN_REACH` beyond the instant the model reads
ahead of the newest reference, and `PLAN_REACH` before that reference, since the poses come
later than the reference (through the kinematics node); what the samples have read and the
references have checked is let go. It starts again (`restart`) when the streams do: a
clock gone back, a node reactivated, a reference going back.

The plan is a few dozen instants, merged with every preview and searched several times a
sample: it is kept in Python lists searched by `bisect`, since NumPy's per-call overhead on
arrays that small is many times the work (a preview given as arrays is taken as lists).
"""

from __future__ import annotations

import math
import operator
from bisect import bisect_left, bisect_right
from collections.abc import Sequence
from enum import StrEnum
from typing import Any

import numpy as np

from lompr_predictor.monitoring import RejectionCounter
from lompr_predictor.stamps import period_ns

XYZ = tuple[float, float, float]
#: Planned instants [ns], or their positions [m] (rows of x, y, z): lists or arrays.
Planned = Sequence[Any] | np.ndarray

#: How far [s] the plan reaches beyond the instant a model reads ahead of the newest
#: reference, and before that reference. A look-ahead plans the coming samples, a fraction
#: of a second of motion: instants further out are planned again by a later preview before
#: any sample reads them, and a preview that starts beyond comes from a path generator whose
#: clock runs ahead of the reference's (refused, 'ahead'); a pose that lags the reference by
#: more is stale. Either way the plan, which every preview copies, stays small.
PLAN_REACH = 1.0


class PreviewDrop(StrEnum):
    """Why a preview (or the plan it built) was not used; each is counted
    (`PlannedPath.dropped`), the value is the key on /diagnostics."""

    UNREADABLE = 'unreadable'
    WRONG_FRAME = 'wrong_frame'
    EMPTY = 'empty'
    NON_FINITE = 'non_finite'
    OUT_OF_ORDER = 'out_of_order'
    PAST = 'past'
    #: a stamp that is no time (negative, or `nanosec` of 1e9 or more: `stamps.instants_ns`)
    BAD_STAMP = 'bad_stamp'
    #: planned to start beyond `PLAN_REACH` after the newest reference
    AHEAD = 'ahead'
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
        #: [ns] how far after the newest reference the plan reaches at most (`read_ahead`)
        self.max_ahead_ns = period_ns(PLAN_REACH)
        self._stamps: list[int] = []  # increasing
        self._positions: list[Sequence[float]] = []  # (x, y, z) at each of `_stamps`
        self._newest_reference_ns = -1
        self.dropped = RejectionCounter(PreviewDrop)
        self.previews_used = 0

    @property
    def horizon_ns(self) -> int | None:
        """The last planned instant [ns], None without a plan."""
        return self._stamps[-1] if self._stamps else None

    def add(self, stamps: Planned, positions: Planned) -> PreviewDrop | None:
        """Take one preview: n instants [ns] and n planned positions (x, y, z) [m]; the
        reason it was refused (counted), or None."""
        stamps, positions = _listed(stamps), _listed(positions)
        reason = self._problem(stamps, positions)
        if reason is not None:
            self.dropped.add(reason)
            return reason
        old = self._stamps  # sorted: what the new plan does not cover is before or after it
        before = bisect_left(old, stamps[0])
        after = bisect_right(old, stamps[-1])
        # before the first reference nothing lets go of the plan's past: the newest alone
        keep = 0 if self._newest_reference_ns >= 0 else before
        self._stamps = old[keep:before] + stamps + old[after:]
        self._positions = self._positions[keep:before] + positions + self._positions[after:]
        self.previews_used += 1
        return None

    def at(self, stamp_ns: int) -> XYZ | None:
        """The planned position at `stamp_ns`, interpolated between the planned instants
        around it (at most `max_step_ns` apart), or None where the plan does not cover it."""
        stamps = self._stamps
        index = bisect_left(stamps, stamp_ns)
        if index < len(stamps) and stamps[index] == stamp_ns:
            x, y, z = self._positions[index]
            return x, y, z
        if index == 0 or index == len(stamps):
            return None
        before, after = stamps[index - 1], stamps[index]
        if after - before > self.max_step_ns:
            return None
        weight = (stamp_ns - before) / (after - before)
        x0, y0, z0 = self._positions[index - 1]
        x1, y1, z1 = self._positions[index]
        return (x0 + weight * (x1 - x0), y0 + weight * (y1 - y0), z0 + weight * (z1 - z0))

    def check(self, stamp_ns: int, x: float, y: float, z: float) -> bool:
        """The reference commanded at `stamp_ns`: False (and the plan dropped, counted as
        contradicted) if the plan covers that instant elsewhere than `tolerance` allows;
        the plan more than `PLAN_REACH` before it, and beyond its reach (`max_ahead_ns`), is
        let go. A reference before the newest one starts the plan again (`restart`): the
        reference stream restarted."""
        if stamp_ns < self._newest_reference_ns:
            self.restart()
        self._newest_reference_ns = stamp_ns
        planned = self.at(stamp_ns)
        self._keep(stamp_ns - period_ns(PLAN_REACH), stamp_ns + self.max_ahead_ns)
        if planned is None:
            return True
        px, py, pz = planned
        if max(abs(px - x), abs(py - y), abs(pz - z)) <= self.tolerance:
            return True
        self.dropped.add(PreviewDrop.CONTRADICTED)
        self.clear()
        return False

    def read(self, instant_ns: int) -> None:
        """A sample read the plan at `instant_ns` (the samples come in stamp order): the plan
        before it is let go, but not the instants the references still check it at."""
        self._keep(min(instant_ns, self._newest_reference_ns))

    def _keep(self, first_ns: int, last_ns: int | None = None) -> None:
        """Let go of the plan before `first_ns` (but the instant before it, which brackets
        it) and after `last_ns` (None: nothing after)."""
        stamps = self._stamps
        cut = max(bisect_left(stamps, first_ns) - 1, 0)
        end = len(stamps) if last_ns is None else bisect_right(stamps, last_ns)
        if cut > 0 or end < len(stamps):
            self._stamps, self._positions = stamps[cut:end], self._positions[cut:end]

    def clear(self) -> None:
        """Forget the plan (the next preview starts a new one)."""
        self._stamps = []
        self._positions = []

    def read_ahead(self, lead_ns: int) -> None:
        """The plan is read `lead_ns` after each sample (`PlanReader`): it reaches
        `PLAN_REACH` beyond that."""
        self.max_ahead_ns = lead_ns + period_ns(PLAN_REACH)

    def restart(self) -> None:
        """Forget the plan and the newest reference: the streams start again, from any
        stamps (a clock gone back, a node reactivated)."""
        self.clear()
        self._newest_reference_ns = -1

    def _problem(self, stamps: list[int],
                 positions: list[Sequence[float]]) -> PreviewDrop | None:
        if not stamps:
            return PreviewDrop.EMPTY
        # sums instead of a test per value: NaN and infinity carry through them (a sum that
        # overflows holds positions no robot has, refused alike)
        if not math.isfinite(sum(map(sum, positions))):
            return PreviewDrop.NON_FINITE
        # increasing stamps are all valid if the first is; a bad stamp (negative, and
        # `NOT_A_TIME`) is named as such wherever it is
        if not all(map(operator.lt, stamps, stamps[1:])):
            return PreviewDrop.BAD_STAMP if min(stamps) < 0 else PreviewDrop.OUT_OF_ORDER
        if stamps[0] < 0:
            return PreviewDrop.BAD_STAMP
        newest = self._newest_reference_ns
        if stamps[-1] <= newest:
            return PreviewDrop.PAST
        if newest >= 0 and stamps[0] > newest + self.max_ahead_ns:
            return PreviewDrop.AHEAD
        return None


def _listed(values: Planned) -> list[Any]:
    """`values` as a list: an array's `tolist` (Python numbers, rows as lists)."""
    return values.tolist() if isinstance(values, np.ndarray) else list(values)


class PlanReader:
    """What a preview model reads with each sample: the plan `lead_ns` after the sample's
    stamp (`at_sample`), counted missing where the plan does not reach it, and `stale` once
    no sample had one for `stale_after_ns` of the caller's clock [ns]."""

    def __init__(self, plan: PlannedPath, lead_ns: int, stale_after_ns: int) -> None:
        self.plan = plan
        plan.read_ahead(lead_ns)
        self.lead_ns = lead_ns
        self.stale_after_ns = stale_after_ns
        self.stale = False
        self._planned_ns: int | None = None  # when a sample last had a plan

    def restart(self) -> None:
        """The streams start again (`PlannedPath.restart`): no plan, not stale."""
        self.plan.restart()
        self.stale = False
        self._planned_ns = None

    def at_sample(self, stamp_ns: int, now_ns: int) -> tuple[int, float, float, float] | None:
        """(instant [ns], planned x, y, z [m]) `lead_ns` after the sample at `stamp_ns`,
        used at `now_ns`; None (counted) where the plan does not reach it."""
        instant_ns = stamp_ns + self.lead_ns
        position = self.plan.at(instant_ns)
        self.plan.read(instant_ns)
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


class ReferencePreview:
    """The plan a model of `steps` samples of preview reads (none if 0): the previews taken
    (`PlannedPath`), read with each sample (`PlanReader`) and checked against the reference
    as it comes; for the core, one object that answers the same whether the model reads a
    plan or not."""

    def __init__(self, steps: int, sample_period_ns: int, max_step_ns: float,
                 tolerance: float, stale_after_ns: int) -> None:
        self.steps = steps
        self.plan = PlannedPath(max_step_ns, tolerance)
        self.reader = PlanReader(self.plan, steps * sample_period_ns, stale_after_ns)

    def contradicts(self, stamp_ns: int, x: float, y: float, z: float) -> bool:
        """Whether the reference commanded at `stamp_ns` contradicts the plan (which is then
        dropped: `PlannedPath.check`); never without a preview."""
        return bool(self.steps) and not self.plan.check(stamp_ns, x, y, z)

    def at_sample(self, stamp_ns: int,
                  now_ns: int) -> tuple[tuple[int, float, float, float] | None, bool]:
        """What the sample at `stamp_ns` reads (`PlanReader.at_sample`; None without a
        preview) and whether the plan went stale with it (what was predicted from the plan
        is then to be cancelled)."""
        if not self.steps:
            return None, False
        was_stale = self.reader.stale
        planned = self.reader.at_sample(stamp_ns, now_ns)
        return planned, self.reader.stale and not was_stale

    @property
    def stale(self) -> bool:
        """No plan for the stale time: a preview model cannot predict."""
        return self.reader.stale

    def restart(self) -> None:
        """The streams start again: no plan, not stale."""
        self.reader.restart()
