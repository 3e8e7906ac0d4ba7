# SPDX-License-Identifier: Apache-2.0
"""online.input_stamps: a trusted integer passes as it is, a message stamp is read in
integers, and one that cannot be a sample instant is dropped under its stream's reason and
named for /diagnostics."""

from __future__ import annotations

from lompr_predictor.monitoring import RejectionCounter
from lompr_predictor.online.alignment import DropReason
from lompr_predictor.online.input_stamps import InputStamps
from lompr_predictor.stamps import Stamp

NOW = 1_700_000_010_000_000_000


def test_stamps_are_read_dropped_under_their_streams_reason_and_named() -> None:
    dropped = RejectionCounter(DropReason)
    stamps = InputStamps(dropped, max_future_stamp=1.0)
    assert stamps.pose_ns(NOW + 5 * 10**9, NOW) == NOW + 5 * 10**9  # trusted
    assert stamps.pose_ns(Stamp(1_700_000_010, 40_000_001), NOW) == NOW + 40_000_001
    assert stamps.reference_ns(Stamp(1_700_000_011, 0), NOW) == NOW + 10**9  # the limit
    assert stamps.last_bad is None and dropped.total == 0
    assert stamps.pose_ns(Stamp(1_700_000_012, 0), NOW) is None
    assert stamps.last_bad == ("pose_future_stamp: stamp 1700000012.000000000 is 2.000 s "
                               "ahead of this node's clock (more than 1 s)")
    assert stamps.reference_ns(Stamp(-3, 0), NOW) is None
    assert stamps.last_bad is not None and stamps.last_bad.startswith(
        'reference_bad_stamp: stamp -3 s 0 ns is not a time')
    assert stamps.pose_ns(Stamp(1_700_000_012, 0), 0) == NOW + 2 * 10**9  # no clock yet
    counts = dropped.counts()
    assert (counts[DropReason.FUTURE_STAMP], counts[DropReason.REFERENCE_BAD_STAMP],
            dropped.total) == (1, 1, 2)
