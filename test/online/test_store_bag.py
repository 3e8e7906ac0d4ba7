# SPDX-License-Identifier: Apache-2.0
"""online.store_bag: the node's sample store as a bag, read back as the plant error it
holds, and what `lompr train` learns from it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_predictor import PERIOD_NS
from test_sample_store import fill

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.data.bags import bag_sha256, read_recording, write_recording
from lompr_predictor.data.cleaning import CleaningConfig
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.sample_store import COPY_MARGIN, SampleStore
from lompr_predictor.online.store_bag import INFO_JSON, write_store_bag
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import batch_forward_kinematics
from lompr_predictor.twin.parameters import load_twin_parameters
from lompr_predictor.twin.recording import to_recording
from lompr_predictor.twin.simulation import simulate


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
