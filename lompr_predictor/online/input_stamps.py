# SPDX-License-Identifier: Apache-2.0
"""The stamps of the predictor core's inputs as integer nanoseconds (ROS-free).

An input's stamp is an integer (ns, trusted: the caller made it) or a message stamp,
which is checked (`stamps.stamp_problem`) against the caller's clock: one that cannot be a
sample instant is dropped, counted under the reason of its stream (`alignment.DropReason`),
and the last such stamp is kept for /diagnostics.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from lompr_predictor.monitoring import RejectionCounter
from lompr_predictor.online.alignment import DropReason
from lompr_predictor.stamps import NS_PER_SECOND, StampLike, StampReason, period_ns, stamp_problem

#: The drop reason of a pose's and of a reference's stamp, by what is wrong with it.
POSE_DROPS: Mapping[StampReason, DropReason] = {
    StampReason.BAD_STAMP: DropReason.BAD_STAMP,
    StampReason.FUTURE_STAMP: DropReason.FUTURE_STAMP}
REFERENCE_DROPS: Mapping[StampReason, DropReason] = {
    StampReason.BAD_STAMP: DropReason.REFERENCE_BAD_STAMP,
    StampReason.FUTURE_STAMP: DropReason.REFERENCE_FUTURE_STAMP}


class InputStamps:
    """Reads the stamps of poses and references (module docstring); drops are counted in
    `dropped`. `max_future_stamp` [s]: how far a message stamp may lie ahead of the clock."""

    def __init__(self, dropped: RejectionCounter, max_future_stamp: float) -> None:
        self._dropped = dropped
        self._max_future_ns = period_ns(max_future_stamp)
        #: The last message stamp dropped, as '<stream>_<reason>: <what was wrong>' (None:
        #: none yet).
        self.last_bad: str | None = None

    def pose_ns(self, stamp: int | StampLike, now_ns: int) -> int | None:
        """The stamp of a pose in ns; None (counted) if it is no sample instant."""
        if isinstance(stamp, (int, np.integer)):
            return int(stamp)
        return self._read(stamp, now_ns, 'pose', POSE_DROPS)

    def reference_ns(self, stamp: int | StampLike, now_ns: int) -> int | None:
        """The stamp of a reference in ns; None (counted) if it is no sample instant."""
        if isinstance(stamp, (int, np.integer)):
            return int(stamp)
        return self._read(stamp, now_ns, 'reference', REFERENCE_DROPS)

    def _read(self, stamp: StampLike, now_ns: int, stream: str,
              drops: Mapping[StampReason, DropReason]) -> int | None:
        sec, nanosec = stamp.sec, stamp.nanosec
        problem = stamp_problem(sec, nanosec, now_ns, self._max_future_ns)
        if problem is None:
            return sec * NS_PER_SECOND + nanosec
        self._dropped.add(drops[problem.reason])
        self.last_bad = f'{stream}_{problem.reason}: {problem.explanation}'
        return None
