# SPDX-License-Identifier: Apache-2.0
"""The predictor node's sample store over ROS: off by default, the `~/write_samples` service
writing what the node saw (with the offsets it had in force) as a bag, its status on
/diagnostics, the write when the node shuts down, and a store that cannot be allocated."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from model_helpers import save_constant
from rclpy.parameter import Parameter
from ros_helpers import RosHarness, stamp_ns, xy
from std_srvs.srv import Trigger
from test_predictor_node import HORIZON, PERIOD_NS, T0, WINDOW, Wiring

from lompr_predictor.data.bags import read_recording
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.online import sample_store
from lompr_predictor.online.sample_store import SampleStoreError
from lompr_predictor.online.store_bag import INFO_JSON
from lompr_predictor.ros.predictor_node import PredictorNode

pytestmark = pytest.mark.ros

SERVICE = '/predictor_node/write_samples'
ERROR = (1e-5, -1e-5)  # Wiring.run's measured tool tip - reference


def constant_model(tmp_path: Path) -> Path:
    return save_constant(tmp_path / 'c.pt', (-10e-6, 5e-6), window=WINDOW, horizon=HORIZON)


def test_the_store_is_off_by_default(ros: RosHarness, tmp_path: Path) -> None:
    wiring = Wiring(ros, constant_model(tmp_path))
    wiring.run(0, 3)
    ros.spin_until(lambda: wiring.status('sample store') is not None, what='store status')
    status = wiring.latest('sample store')
    assert status['_message'] == 'off (store_minutes 0)' and status['_level'] == DiagnosticStatus.OK
    assert SERVICE not in dict(ros.node.get_service_names_and_types())
    assert wiring.node.runtime.store is None


def test_the_service_writes_what_the_node_saw_and_had_in_force(
        ros: RosHarness, tmp_path: Path) -> None:
    model = constant_model(tmp_path)
    wiring = Wiring(ros, model, store_minutes=1.0, store_folder=str(tmp_path / 'bags'),
                    max_compensation_step=4e-6)
    samples = 30
    wiring.run(0, samples)
    client = ros.node.create_client(Trigger, SERVICE)
    response = ros.call(client, Trigger.Request(), 'write_samples')
    assert response.success, response.message
    bag = Path(response.message)
    assert bag.parent == tmp_path / 'bags'
    ros.spin_until(lambda: (wiring.status('sample store') or {}).get('last_bag') == str(bag),
                   timeout=60.0, what='the bag written')
    status = wiring.latest('sample store')
    assert status['samples'] == str(samples) and status['capacity'] == str(60 * 25)
    assert status['size_mb'] == str(round((64 + 1500 * 64) / 1e6, 3))
    assert status['bags_written'] == '1' and status['_level'] == DiagnosticStatus.OK
    recording = read_recording(bag)
    assert recording.end_pose is not None and recording.compensation is not None
    stamps = T0 + PERIOD_NS * np.arange(samples)
    np.testing.assert_array_equal(recording.end_pose.stamps, stamps)
    reference = 0.01 + 1e-3 * np.arange(samples)[:, None] + np.array([0.0, 0.01])
    np.testing.assert_allclose(recording.reference.positions[:, :2], reference, atol=1e-15)
    np.testing.assert_allclose(recording.end_pose.positions[:, :2], reference + ERROR,
                               atol=1e-15)
    # the offset in force at each sample: the newest the node published for its instant
    in_force = {stamp_ns(m): tuple(v) for m, v in zip(wiring.compensations,
                                                     xy(wiring.compensations), strict=True)}
    expected = np.array([in_force.get(int(stamp), (0.0, 0.0)) for stamp in stamps])
    assert np.abs(expected).max() == pytest.approx(10e-6)
    np.testing.assert_allclose(recording.compensation.offsets, expected, rtol=0, atol=1e-15)
    info = json.loads((bag / INFO_JSON).read_text())
    assert info['node'] == '/predictor_node' and info['samples'] == samples
    assert info['model_sha256'] == load_model(model).sha256


def test_a_node_that_shuts_down_writes_its_store_when_asked(
        ros: RosHarness, tmp_path: Path) -> None:
    folder = tmp_path / 'bags'
    wiring = Wiring(ros, constant_model(tmp_path), store_minutes=0.5,
                    store_folder=str(folder), store_write_at_shutdown=True)
    wiring.run(0, 12)
    wiring.node.trigger_shutdown()
    assert wiring.node.lifecycle_state == 'finalized'
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and not any(
            p.name.startswith('samples-') for p in (folder.iterdir() if folder.is_dir() else ())):
        time.sleep(0.1)
    (bag,) = (p for p in folder.iterdir() if p.name.startswith('samples-'))
    recording = read_recording(bag)
    assert recording.end_pose is not None and len(recording.end_pose.stamps) == 12


def test_a_store_that_cannot_be_allocated_refuses_the_configure_in_one_line(
        ros: RosHarness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def no_memory(fd: int, offset: int, length: int) -> None:
        raise OSError(12, 'Cannot allocate memory')

    monkeypatch.setattr(sample_store.os, 'posix_fallocate', no_memory)
    with pytest.raises(SampleStoreError, match=r'^a sample store of 1500 samples \(0.1 MB\) '
                       'cannot be allocated: Cannot allocate memory$'):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(constant_model(tmp_path))),
            Parameter('store_minutes', value=1.0)])
