# SPDX-License-Identifier: Apache-2.0
"""The predictor node's sample store, ROS-free: the ring (its order, window, restarts and a
reader racing its writer), the store as a unit of the core, the bag it is written as and the
child process that writes it."""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_clock import FakeClock
from model_helpers import save_constant
from test_predictor import HORIZON, NEEDED, PERIOD_NS, WINDOW, feed, limits, spiral, stream

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.data.bags import bag_sha256, read_recording, write_recording
from lompr_predictor.data.cleaning import CleaningConfig
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.monitoring import Level
from lompr_predictor.online import sample_store
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.predictor_status import Lifecycle, store_status
from lompr_predictor.online.sample_store import (
    COPY_MARGIN,
    SampleStore,
    SampleStoreError,
    StoredSamples,
    capacity_for,
    ring_bytes,
)
from lompr_predictor.online.store_bag import INFO_JSON, write_store_bag
from lompr_predictor.online.store_export import StoreExport, StoreExportError
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import batch_forward_kinematics
from lompr_predictor.twin.parameters import load_twin_parameters
from lompr_predictor.twin.recording import to_recording
from lompr_predictor.twin.simulation import simulate

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


def test_a_store_bag_is_read_back_as_the_plant_error_it_holds(
        tmp_path: Path, description: RobotDescription) -> None:
    store = SampleStore(capacity=1000, window_ns=10**15)
    fill(store, range(300))
    stored = store.snapshot()
    bag = write_store_bag(tmp_path / 'samples', stored, {'node': '/predictor_node'})
    recording = read_recording(bag)
    assert len(recording.joints.stamps) == 0 and recording.end_pose is not None
    assert recording.compensation is not None
    np.testing.assert_array_equal(recording.end_pose.positions[:, :2], stored.measured)
    np.testing.assert_array_equal(recording.end_pose.positions[:, 2], stored.reference[:, 2])
    np.testing.assert_array_equal(recording.reference.positions, stored.reference)
    np.testing.assert_array_equal(recording.compensation.offsets, stored.compensation)
    info = json.loads((bag / INFO_JSON).read_text())
    assert info['node'] == '/predictor_node' and info['samples'] == 300
    assert info['span_seconds'] == pytest.approx(299 * PERIOD_NS * 1e-9)
    # what the trainer reads: the plant error the core computed, the offset in force
    data, _ = load_clean_data(BagInputs((str(bag),), cleaning=CleaningConfig(
        hampel_threshold=1e12)), LomprChain(description))
    assert data.counts['end_pose_read'] == 300 and data.counts['compensated'] == 300
    np.testing.assert_array_equal(data.stamps, stored.stamps)
    np.testing.assert_allclose(data.error, stored.error, rtol=0, atol=1e-15)
    np.testing.assert_allclose(data.tool_error, stored.measured - stored.reference[:, :2],
                               rtol=0, atol=1e-15)
    store.close()


def test_a_child_writes_the_store_one_write_at_a_time(tmp_path: Path) -> None:
    store = SampleStore(capacity=500, window_ns=10**15)
    export = StoreExport(tmp_path / 'bags', 'lompr_base')
    with pytest.raises(StoreExportError, match='holds no sample'):
        export.start(store, {})
    fill(store, range(200))
    path = export.start(store, {'node': '/n'})
    assert path.parent == tmp_path / 'bags' and path.name.startswith('samples-')
    with pytest.raises(StoreExportError, match='is running'):  # the child takes a second
        export.start(store, {})
    fill(store, range(200, 260))  # the node writes on meanwhile
    assert export.wait(60.0)
    assert export.state.last_bag == str(path) and export.state.written == 1, export.state
    recording = read_recording(path)
    assert recording.end_pose is not None and len(recording.end_pose.stamps) >= 200
    second = export.start(store, {})
    assert second != path and export.wait(60.0) and export.state.written == 2
    store.close()


@pytest.mark.faults
def test_a_write_that_fails_says_why(tmp_path: Path) -> None:
    store = SampleStore(capacity=100, window_ns=10**15)
    fill(store, range(10))
    (tmp_path / 'file').write_text('')
    unmade = StoreExport(tmp_path / 'file' / 'bags', 'lompr_base')
    with pytest.raises(OSError):  # the folder cannot be made
        unmade.start(store, {})
    assert unmade.state.failed == 1 and 'Not a directory' in unmade.state.last_error
    status = store_status(Lifecycle('active', True, None), 1.0, store, unmade,
                          failure_shown=True)
    assert status.level == Level.WARN and 'the last write failed' in status.message
    held_over = store_status(Lifecycle('active', True, None), 1.0, store, unmade,
                             failure_shown=False)  # past its hold: the store holds samples
    assert held_over.level == Level.OK and 'Not a directory' in str(held_over.values['last_error'])
    export = StoreExport(tmp_path / 'bags', 'lompr_base')
    os.ftruncate(store.fd, 32)  # the child finds no ring behind the descriptor
    export.start(store, {})
    assert export.wait(60.0)
    assert export.state.failed == 1 and export.state.written == 0
    assert 'no sample store' in export.state.last_error, export.state
    assert not any((tmp_path / 'bags').iterdir())  # nothing half-written
    store.close()


@pytest.mark.slow
def test_lompr_train_learns_from_a_store_bag_what_the_joint_bag_holds(
        tmp_path: Path, description: RobotDescription) -> None:
    """A twin run stored as the node stores it (the end pose, the kinematics node's forward
    kinematics of the measured joints; no compensation) reads as the twin's joint bag of the
    same run, and `lompr train` trains on it."""
    sim = simulate(description, load_twin_parameters(), passes=2, seed=1)
    tips = batch_forward_kinematics(description.geometry, sim.joints_measured).position
    store = SampleStore(capacity=len(sim.stamps) + COPY_MARGIN, window_ns=10**15)
    for stamp, tip, reference in zip(sim.stamps, tips, sim.reference, strict=True):
        store.observe(AlignedSample(int(stamp), tip[0], tip[1], *reference),
                      (tip[0] - reference[0], tip[1] - reference[1]), None)
    bag = write_store_bag(tmp_path / 'store', store.snapshot(), {})
    store.close()
    joints = write_recording(tmp_path / 'joints', to_recording(sim)[0])
    (stored, _), (recorded, _) = (load_clean_data(BagInputs((str(b),)), LomprChain(description))
                                  for b in (bag, joints))
    np.testing.assert_array_equal(stored.stamps, recorded.stamps)
    np.testing.assert_allclose(stored.error, recorded.error, rtol=0, atol=1e-12)
    assert stored.counts['end_pose_read'] == len(sim.stamps) and stored.counts['joint_read'] == 0
    np.testing.assert_array_equal(stored.compensation, 0.0)
    model = tmp_path / 'model.pt'
    assert lompr_main(['train', str(bag), '--out', str(model), '--report', str(tmp_path / 'r'),
                       '--trials', '1', '--restarts', '0', '--max-epochs', '2', '--window', '8',
                       '--horizon', '2', '--workers', '1', '--quiet']) == 0
    (trained_on,) = load_model(model).metadata.training_bags
    assert trained_on['sha256'] == bag_sha256(bag)
