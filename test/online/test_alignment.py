# SPDX-License-Identifier: Apache-2.0
"""online.alignment alone: poses aligned with the reference by stamp, faults in their place."""

from __future__ import annotations

import math

import pytest
from fake_clock import FakeClock

from lompr_predictor.online.alignment import (
    MAX_PENDING_POSES,
    AlignedSample,
    DropReason,
    Event,
    ReferenceTrack,
    StampAlignment,
)

PERIOD_NS = 40_000_000
T0 = 1_700_000_000_000_000_000


def at(k: float) -> int:
    """The stamp k periods after T0 [ns]."""
    return T0 + round(k * PERIOD_NS)


def aligned(clock: FakeClock | None = None) -> StampAlignment:
    return StampAlignment(2.5, PERIOD_NS, (clock or FakeClock(10.0)).ns)


def samples_of(events: list[Event]) -> list[AlignedSample]:
    """The events, which must all be samples."""
    assert all(isinstance(event, AlignedSample) for event in events), events
    return [event for event in events if isinstance(event, AlignedSample)]


def test_a_pose_gets_the_reference_interpolated_to_its_stamp() -> None:
    alignment = aligned()
    assert alignment.add_reference(at(0), 0.010, 0.020, 1.097) == []
    assert alignment.add_reference(at(1), 0.014, 0.012, 1.097) == []
    (sample,) = samples_of(alignment.add_pose(at(0.25), 0.0105, 0.0181))
    assert sample[:3] == (at(0.25), 0.0105, 0.0181)
    assert (sample.reference_x, sample.reference_y) == pytest.approx((0.011, 0.018))
    (exact,) = samples_of(alignment.add_pose(at(1), 0.0141, 0.0119))
    assert (exact.reference_x, exact.reference_y) == (0.014, 0.012)  # no interpolation


def test_a_pose_waits_for_a_reference_at_or_after_its_stamp() -> None:
    alignment = aligned()
    alignment.add_reference(at(0), 0.0, 0.0, 1.097)
    assert alignment.add_pose(at(0.5), 1e-5, 0.0) == []  # the reference is not there yet
    assert alignment.add_pose(at(1), 2e-5, 0.0) == []
    assert alignment.waiting
    # the reference for both arrives: both are used, in order, with their own references
    samples = samples_of(alignment.add_reference(at(1), 0.004, -0.002, 1.097))
    assert [(s.stamp_ns, s.reference_x, s.reference_y) for s in samples] == [
        (at(0.5), 0.002, -0.001), (at(1), 0.004, -0.002)]
    assert not alignment.waiting and alignment.dropped.total == 0


def test_a_slower_reference_widens_the_bracket_to_its_own_period() -> None:
    alignment = aligned()
    for k in range(0, 20, 4):  # a reference every 4 pose periods, x = k mm
        alignment.add_reference(at(k), k * 1e-3, 0.0, 1.097)
    # 4 periods exceed gap_factor 2.5 pose periods, but not 2.5 reference periods
    assert alignment.references.max_bracket_ns == 2.5 * 4 * PERIOD_NS
    (sample,) = samples_of(alignment.add_pose(at(13), 0.0, 0.0))
    assert sample.reference_x == pytest.approx(13e-3)


def test_an_unbracketed_pose_is_a_fault_in_its_place() -> None:
    alignment = aligned()
    alignment.add_reference(at(10), 0.0, 0.0, 1.097)
    assert alignment.add_pose(at(9), 0.0, 0.0) == ['no_reference']  # before the first one
    for k in (11, 12, 13, 16):  # a reference every period, then a 3-period step
        alignment.add_reference(at(k), 0.0, 0.0, 1.097)
    assert alignment.add_pose(at(15), 0.0, 0.0) == ['no_reference']  # 3 > 2.5 periods
    assert alignment.dropped['no_reference'] == 2


def test_a_non_finite_pose_is_a_fault_after_the_poses_before_it() -> None:
    alignment = aligned()
    alignment.add_reference(at(0), 0.0, 0.0, 1.097)
    alignment.add_pose(at(1), 1e-5, 0.0)
    assert alignment.add_pose(at(2), math.nan, 0.0) == []  # waits behind sample 1
    events = alignment.add_reference(at(2), 0.0, 0.0, 1.097)
    assert [e if isinstance(e, str) else e.stamp_ns for e in events] == [at(1), 'non_finite']
    assert alignment.dropped['non_finite'] == 1


def test_duplicates_are_dropped_and_a_stamp_going_back_drops_the_waiting_poses() -> None:
    alignment = aligned()
    alignment.add_reference(at(0), 0.0, 0.0, 1.097)
    alignment.add_pose(at(1), 0.0, 0.0)
    alignment.add_pose(at(2), 0.0, 0.0)
    assert alignment.add_pose(at(2), 5.0, 5.0) == []  # repeated stamp: dropped, no fault
    assert alignment.add_pose(at(0.5), 0.0, 0.0) == ['out_of_order']
    assert alignment.newest_pose_ns == at(0.5) and not alignment.waiting
    assert alignment.dropped.counts()['duplicate'] == 1
    assert alignment.dropped['out_of_order'] == 3  # the pose itself and the two waiting


@pytest.mark.faults
def test_bad_references() -> None:
    alignment = aligned()
    alignment.add_reference(at(5), 0.0, 0.0, 1.097)
    assert alignment.add_reference(at(5), 1.0, 1.0, 1.097) == []
    assert alignment.add_reference(at(6), math.inf, 0.0, 1.097) == ['reference_non_finite']
    # the reference stream went back: a fault, and the track restarts from it
    assert alignment.add_reference(at(2), 0.002, 0.0, 1.097) == ['reference_out_of_order']
    assert alignment.references.newest == at(2)
    assert alignment.dropped.counts() | {} == {
        'non_finite': 0, 'duplicate': 0, 'out_of_order': 0, 'no_reference': 0,
        'reference_duplicate': 1, 'reference_non_finite': 1, 'reference_out_of_order': 1,
        'stale': 0, 'clock_jump': 0, 'inactive': 0, 'internal': 0, 'bad_stamp': 0,
        'future_stamp': 0, 'reference_bad_stamp': 0, 'reference_future_stamp': 0,
        'wrong_frame': 0, 'reference_wrong_frame': 0}


def test_too_many_waiting_poses_drop_the_oldest_as_a_fault() -> None:
    alignment = aligned()
    for k in range(MAX_PENDING_POSES):
        assert alignment.add_pose(at(k), 0.0, 0.0) == []
    assert alignment.add_pose(at(MAX_PENDING_POSES), 0.0, 0.0) == ['no_reference']


def test_waiting_poses_keep_their_arrival_and_clear_counts_them() -> None:
    clock = FakeClock(10.0)
    alignment = aligned(clock)
    assert alignment.oldest_waiting_arrival() is None
    alignment.add_pose(at(0), 0.0, 0.0)
    clock.now += 0.04
    alignment.add_pose(at(1), 0.0, 0.0)
    assert alignment.oldest_waiting_arrival() == 10_000_000_000
    alignment.clear(DropReason.STALE)
    assert alignment.dropped['stale'] == 2 and alignment.oldest_waiting_arrival() is None


def test_reference_track_forgets_what_no_pose_can_need() -> None:
    track = ReferenceTrack(2.5, PERIOD_NS)
    for k in range(10):
        track.add(at(k), k * 1e-3, 0.0, 1.097)
    assert track.at(at(8.5)) == pytest.approx((8.5e-3, 0.0, 1.097))
    # poses come in order: the references far before that one are gone
    assert track.at(at(2)) == 'no_reference'
    assert track.at(at(10)) is None  # not arrived yet


@pytest.mark.parametrize('reference_first', [False, True])
def test_a_rewind_takes_the_restarted_streams_without_a_fault(reference_first: bool) -> None:
    """A simulator reset: its clock goes back to the start and the streams start again. The
    reference of the new run may come before the clock's jump (another topic): it is kept."""
    alignment = aligned()
    for k in range(10):
        alignment.add_reference(at(k), k * 1e-3, 0.0, 1.097)
        samples_of(alignment.add_pose(at(k), k * 1e-3, 0.0))
    alignment.add_pose(at(10), 0.0, 0.0)  # waits for its reference
    if reference_first:
        assert alignment.add_reference(at(0), 0.5, 0.0, 1.097) == ['reference_out_of_order']
    alignment.rewind(at(0), DropReason.CLOCK_JUMP)
    assert alignment.dropped['clock_jump'] == 1 and not alignment.waiting
    assert alignment.newest_pose_ns is None
    if not reference_first:
        assert alignment.references.newest is None  # every reference was after the reset
        assert alignment.add_reference(at(0), 0.5, 0.0, 1.097) == []
    (sample,) = samples_of(alignment.add_pose(at(0), 0.5, 0.0))
    assert (sample.stamp_ns, sample.reference_x) == (at(0), 0.5)
    assert alignment.dropped['out_of_order'] == 0
    alignment.rewind(None, DropReason.INACTIVE)
    assert alignment.references.newest is None
