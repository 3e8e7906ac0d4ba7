# SPDX-License-Identifier: Apache-2.0
"""The predictor node's sample store, ROS-free: the ring (its order, window, restarts and a
reader racing its writer) and the store as a unit of the core (the bag it is written as:
test_store_bag; the child process that writes it: test_store_export)."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_clock import FakeClock
from model_helpers import save_constant
from test_predictor import HORIZON, NEEDED, PERIOD_NS, WINDOW, feed, limits, spiral, stream

from lompr_predictor.learning.model_file import load_model
from lompr_predictor.online import sample_store
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.sample_store import (
    COPY_MARGIN,
    SampleStore,
    SampleStoreError,
    StoredSamples,
    capacity_for,
    ring_bytes,
)

T0 = 1_000_000_000_000


def sample(k: int) -> tuple[AlignedSample, tuple[float, float]]:
    """Sample `k` (one period apart) and its plant error: distinct values in every field."""
    return (AlignedSample(T0 + k * PERIOD_NS, 0.1 + 1e-6 * k, -0.05 - 2e-6 * k, 0.1 + 1e-7 * k,
                          -0.05, 1.097 + 1e-9 * k), (3e-6 * np.sin(k), -2e-6 * np.cos(k)))


def fill(store: SampleStore, ks: range) -> None:
    for k in ks:
        store.observe(*sample(k), None)


def expected(ks: Iterable[int]) -> StoredSamples:
    samples = [sample(k) for k in ks]
    return StoredSamples(
        stamps=np.array([s.stamp_ns for s, _ in samples], dtype=np.int64),
        measured=np.array([(s.x, s.y) for s, _ in samples]),
        reference=np.array([(s.reference_x, s.reference_y, s.reference_z) for s, _ in samples]),
        error=np.array([e for _, e in samples]))


def assert_same(found: StoredSamples, wanted: StoredSamples) -> None:
    np.testing.assert_array_equal(found.stamps, wanted.stamps)
    for name in ('measured', 'reference', 'error'):
        np.testing.assert_array_equal(getattr(found, name), getattr(wanted, name))


def test_the_ring_keeps_the_newest_samples_exactly_and_in_stamp_order() -> None:
    store = SampleStore(capacity=50, window_ns=10**15)
    fill(store, range(30))
    assert store.held == 30 and store.held_seconds == pytest.approx(29 * PERIOD_NS * 1e-9)
    assert_same(store.snapshot(), expected(range(30)))
    fill(store, range(30, 130))  # around the ring twice
    assert store.held == 50 and store.held_seconds == pytest.approx(49 * PERIOD_NS * 1e-9)
    # a full ring: the oldest records, which a writer overwrites next, are left out
    snapshot = store.snapshot()
    assert_same(snapshot, expected(range(80 + COPY_MARGIN, 130)))
    tip, reference, error = snapshot.measured, snapshot.reference[:, :2], snapshot.error
    np.testing.assert_allclose(snapshot.compensation, tip - reference - error, rtol=0,
                               atol=1e-18)
    assert store.size_bytes == ring_bytes(50) == 64 + 50 * 64
    store.close()


def test_its_memory_is_allocated_when_it_is_made(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every byte of the ring is allocated up front (not a sparse file whose pages a sample
    first touches); memory that cannot be had is one clear error when the store is made."""
    store = SampleStore.for_minutes(1.0, 1e-3)
    assert store.capacity == 60_000 and store.size_bytes == 64 + 60_000 * 64
    assert os.fstat(store.fd).st_blocks * 512 >= store.size_bytes
    store.close()

    def no_memory(fd: int, offset: int, length: int) -> None:
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(sample_store.os, 'posix_fallocate', no_memory)
    with pytest.raises(SampleStoreError, match=r'^a sample store of 60000 samples \(3.8 MB\) '
                       'cannot be allocated: No space left on device$'):
        SampleStore.for_minutes(1.0, 1e-3)


def test_the_default_window_at_1_khz_is_under_64_mb() -> None:
    assert capacity_for(10.0, 1e-3) == 600_000
    assert ring_bytes(capacity_for(10.0, 1e-3)) == 64 + 600_000 * 64  # 38.4 MB


def test_its_window_is_sample_time() -> None:
    store = SampleStore(capacity=100, window_ns=10 * PERIOD_NS)
    fill(store, range(40))
    assert_same(store.snapshot(), expected(range(29, 40)))  # the newest and 10 periods back
    fill(store, range(45, 47))  # after a gap of 5 samples
    assert_same(store.snapshot(), expected([*range(36, 40), 45, 46]))
    store.close()


def test_sample_time_going_back_starts_afresh_and_a_fault_keeps_the_store() -> None:
    store = SampleStore(capacity=100, window_ns=10**15)
    fill(store, range(20))
    store.clear()  # a fault: the samples stay, the gap splits the trainer's segments
    fill(store, range(25, 30))
    assert store.held == 25 and store.restarts == 0
    fill(store, range(3, 8))  # a simulator reset: the clock went back
    assert store.restarts == 1 and store.held == 5
    assert_same(store.snapshot(), expected(range(3, 8)))
    store.observe(*sample(7), None)  # the same stamp again is no later either
    assert store.restarts == 2 and store.held == 1
    store.close()


def test_a_reader_leaves_out_what_the_writer_wrote_while_it_copied(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Ten records written between the reader's two looks at the count: their slots held
    the oldest records of its copy, which it drops (and the margin)."""
    store = SampleStore(capacity=50, window_ns=10**15)
    fill(store, range(60))
    header = sample_store.HEADER
    looks: list[int] = []

    class WriterMeanwhile:
        def unpack_from(self, buffer: Any, offset: int = 0) -> tuple[Any, ...]:
            looks.append(offset)
            if len(looks) == 2:  # the copy is made: the writer writes on
                fill(store, range(60, 70))
            return header.unpack_from(buffer, offset)

    monkeypatch.setattr(sample_store, 'HEADER', WriterMeanwhile())
    snapshot = store.snapshot()
    assert len(looks) == 2
    # the copy held records 10..59; 60..69 overwrote 10..19 meanwhile
    assert_same(snapshot, expected(range(20 + COPY_MARGIN, 60)))
    store.close()


def test_in_the_core_it_holds_the_plant_error_and_the_offset_in_force(tmp_path: Path) -> None:
    """A constant model compensating: every stored sample's compensation is the offset the
    core published for its instant (zero before the first), its error measured -
    reference - that offset."""
    model = load_model(save_constant(tmp_path / 'c.pt', (-12e-6, 7e-6), window=WINDOW,
                                     horizon=HORIZON))
    store = SampleStore(capacity=1000, window_ns=10**15)
    core = OnlinePredictor(model, stream(), limits(max_step=4e-6), clock=FakeClock().ns,
                           units=(store,))
    stamps, reference, tips = spiral(40)
    outputs = feed(core, stamps, reference, tips)
    in_force = {output.instant_ns: output.compensation for output in outputs}
    snapshot = store.snapshot()
    np.testing.assert_array_equal(snapshot.stamps, stamps)
    offsets = np.array([in_force.get(int(stamp), (0.0, 0.0)) for stamp in stamps])
    assert np.abs(offsets).max() == pytest.approx(12e-6)  # clamped by no limit, stepped up
    assert (np.abs(offsets[:NEEDED + HORIZON - 1]) == 0).all()
    np.testing.assert_allclose(snapshot.compensation, offsets, rtol=0, atol=1e-17)
    np.testing.assert_allclose(snapshot.error, tips - reference[:, :2] - offsets, rtol=0,
                               atol=1e-17)
    np.testing.assert_array_equal(snapshot.reference, reference)
    store.close()
