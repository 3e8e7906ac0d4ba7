# SPDX-License-Identifier: Apache-2.0
"""predictor_node in the test process: bag replay parity with the offline pipeline, safety
over the topics, model refusal and run-time swaps, diagnostics."""

from __future__ import annotations

import dataclasses
import hashlib
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import torch
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from model_helpers import save_constant, save_linear, write_sidecar
from nav_msgs.msg import Path as NavPath
from rclpy.parameter import Parameter
from ros_helpers import (
    RosHarness,
    latest_status,
    set_stamp,
    stamp_ns,
    start_executable,
    stop_process,
    xy,
)
from sensor_msgs.msg import JointState

from lompr_predictor.data.bags import (
    JointSamples,
    Recording,
    ReferenceSamples,
    read_recording,
    write_recording,
)
from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.features import FEATURES, HISTORY, feature_names
from lompr_predictor.learning.model_file import (
    ExportedModule,
    MetadataMismatchError,
    ModelTrustError,
    load_model,
)
from lompr_predictor.learning.models import predict_rows
from lompr_predictor.monitoring import Level
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import (
    MEASURED_JOINTS,
    ROBOT_FRAME,
    RobotDescription,
    load_robot_description,
)
from lompr_predictor.robot.kinematics import inverse_kinematics
from lompr_predictor.ros.kinematics_node import KinematicsNode
from lompr_predictor.ros.pipeline import build_pipeline
from lompr_predictor.ros.predictor_node import PredictorNode

pytestmark = pytest.mark.ros

PERIOD_NS = 40_000_000
T0 = 1_000_000_000_000
WINDOW, HORIZON = 4, 3
NEEDED = WINDOW + HISTORY
PARAMS_FILE = Path(__file__).parents[2] / 'lompr_predictor' / 'config' / 'predictor_node.yaml'


def spiral_recording(description: RobotDescription, samples: int,
                     reference_shift_ns: int = 0) -> Recording:
    """Joints by IK of (spiral + a smooth synthetic error); the reference is the spiral,
    sampled `reference_shift_ns` after the joints (so it must be interpolated)."""
    k = np.arange(samples + 1)
    t_h = 10.0 * k / 1000.0

    def spiral(t: np.ndarray) -> np.ndarray:
        angle = np.pi / 2 * t + np.pi / 2
        return np.stack([0.02 * t * np.cos(angle), 0.02 * t * np.sin(angle),
                         np.full(len(t), 1.097)], -1)

    error = np.stack([25e-6 * np.sin(0.05 * k), 18e-6 * np.cos(0.07 * k), 0 * k], -1)
    joints = inverse_kinematics(description.geometry, spiral(t_h) + error).joints[:samples]
    shift = reference_shift_ns / PERIOD_NS * 10.0 / 1000.0
    reference = spiral(t_h + shift)
    return Recording(
        joints=JointSamples(T0 + k[:samples] * PERIOD_NS, joints, MEASURED_JOINTS),
        reference=ReferenceSamples(T0 + k * PERIOD_NS + reference_shift_ns, reference,
                                   np.tile([0.0, 0.0, 0.0, 1.0], (len(k), 1))))


class Wiring:
    """A predictor node (optionally behind a kinematics node), the test's publishers and
    collectors, discovery done."""

    def __init__(self, ros: RosHarness, model: Path, *, kinematics: bool = False,
                 **overrides: object) -> None:
        # staleness counts wall time: 40 s, unless a test is about it, so that a stall of
        # the loaded machine between two samples is no fault; for the same reason an output
        # is late (overrun, dropped) only after a minute, unless a test is about that
        # the guard off unless a test is about it: with it on persistence answers until the
        # model earns control, and the tests of everything else read the model's output;
        # the offset's low-pass off too: they check the offset against the clamp and the
        # step limit alone (the low-pass has its own tests, online/test_offset.py)
        parameters = {'model_path': str(model), 'diagnostics_period': 0.1,
                      'stale_periods': 1000.0, 'late_tolerance': 60.0,
                      'compensation_enabled': True, 'guard_enabled': False,
                      'compensation_bandwidth': 0.0, **overrides}
        self.ros = ros
        self.node: PredictorNode = ros.add(PredictorNode(
            context=ros.context,
            parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()]))
        self.predictions: list[Vector3Stamped] = ros.collect(
            '/lompr/predicted_error', Vector3Stamped, 1000)
        self.compensations: list[Vector3Stamped] = ros.collect(
            '/lompr/compensation', Vector3Stamped, 1000)
        self.diagnostics: list[DiagnosticArray] = ros.collect('/diagnostics', DiagnosticArray)
        self.reference = ros.node.create_publisher(PoseStamped, '/lompr/reference', 100)
        if kinematics:
            kinematics_node = ros.add(KinematicsNode(context=ros.context))
            self.joints = ros.node.create_publisher(JointState, '/joint_states', 100)
            ros.wait_for_subscribers(self.joints)
            ros.wait_for_subscribers(kinematics_node._publisher)
        else:
            self.poses = ros.node.create_publisher(PoseStamped, '/lompr/end_pose', 100)
            ros.wait_for_subscribers(self.poses)
        ros.wait_for_subscribers(self.reference)
        ros.wait_for_publishers('/lompr/compensation')
        ros.wait_for_publishers('/lompr/predicted_error')

    def publish_sample(self, ns: int, reference_xy: np.ndarray, tip_xy: np.ndarray,
                       frames: tuple[str, str] = (ROBOT_FRAME, ROBOT_FRAME)) -> None:
        """A reference and an end pose at `ns`, in `frames` (reference's, pose's)."""
        reference = PoseStamped()
        reference.header.frame_id = frames[0]
        set_stamp(reference, ns)
        reference.pose.position.x, reference.pose.position.y = map(float, reference_xy)
        self.reference.publish(reference)
        pose = PoseStamped()
        pose.header.frame_id = frames[1]
        set_stamp(pose, ns)
        pose.pose.position.x, pose.pose.position.y = map(float, tip_xy)
        self.poses.publish(pose)

    def received(self) -> int:
        """Messages the node has taken (end poses and references)."""
        return int(self.node.inputs.pose_rate.total + self.node.inputs.reference_rate.total)

    def wait_received(self, total: int, what: str) -> None:
        self.ros.spin_until(lambda: self.received() >= total, what=what)

    def run(self, first: int, count: int, reference_xy: tuple[float, float] = (0.01, 0.02),
            error: tuple[float, float] = (1e-5, -1e-5),
            frames: tuple[str, str] = (ROBOT_FRAME, ROBOT_FRAME)) -> None:
        """Publish samples first..first+count-1 (stamps every period), each answered or not
        before the next, as a controller's cycle would."""
        for k in range(first, first + count):
            received = self.received()
            xy = np.asarray(reference_xy) + 1e-3 * k
            self.publish_sample(T0 + k * PERIOD_NS, xy, xy + np.asarray(error), frames)
            self.wait_received(received + 2, f'sample {k}')

    def latest(self, name: str) -> dict[str, Any]:
        """The latest status `name`, which must have arrived."""
        status = self.status(name)
        assert status is not None, f'no status {name} yet'
        return status

    def status(self, name: str) -> dict[str, Any] | None:
        return latest_status(self.diagnostics, f'predictor_node: {name}')


def test_bag_replay_matches_offline_predictions(
        ros: RosHarness, description: RobotDescription, tmp_path: Path) -> None:
    bag = write_recording(tmp_path / 'spiral', spiral_recording(description, 120, 13_000_000))
    recording = read_recording(bag)
    model_path = save_linear(tmp_path / 'model.pt', window=WINDOW, horizon=HORIZON)
    # the guard off (Wiring's default): the model's own predictions, whatever persistence
    # would have done
    wiring = Wiring(ros, model_path, kinematics=True, compensation_enabled=False,
                    stale_periods=1000.0)
    joints, reference = recording.joints, recording.reference
    order = np.argsort(np.concatenate([joints.stamps, reference.stamps]), kind='stable')
    for index in order:  # the bag's time order, each message answered before the next
        if index < len(joints.stamps):
            msg = JointState(name=list(joints.names), position=joints.positions[index].tolist())
            set_stamp(msg, joints.stamps[index])
            received = wiring.received()
            wiring.joints.publish(msg)
            wiring.wait_received(received + 1, 'end pose')
        else:
            i = index - len(joints.stamps)
            msg = PoseStamped()
            msg.header.frame_id = ROBOT_FRAME
            set_stamp(msg, reference.stamps[i])
            p = reference.positions[i]
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, p)
            received = wiring.received()
            wiring.reference.publish(msg)
            wiring.wait_received(received + 1, 'reference')
    # offline: the trainer's cleaning (interpolation, batch FK, error) and feature rows
    data = clean_recordings([recording], LomprChain(description))
    assert data.counts['spike'] == 0 and len(data.segments) == 1
    ends = np.arange(NEEDED - 1, len(data))
    offline = predict_rows(load_model(model_path).module, data.features(), ends, WINDOW)
    expected_instants = data.stamps[ends] + HORIZON * PERIOD_NS
    ros.spin_until(lambda: min(len(wiring.predictions), len(wiring.compensations)) >= len(ends),
                   what='all predictions and offsets')
    assert [stamp_ns(m) for m in wiring.predictions] == expected_instants.tolist()
    np.testing.assert_allclose(xy(wiring.predictions), offline, rtol=0, atol=1e-9)
    assert all(m.vector.z == 0.0 for m in wiring.predictions)
    assert not xy(wiring.compensations).any()  # shadow mode: offsets all zero
    assert len(wiring.compensations) == len(ends)


def test_outputs_start_with_a_full_window_clamped_and_step_limited(
        ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'c.pt', (-0.6e-3, 0.8e-3), window=WINDOW, horizon=HORIZON)
    wiring = Wiring(ros, model, max_compensation=0.5e-3, max_compensation_step=0.2e-3)
    wiring.run(0, NEEDED - 1)
    ros.spin_for(0.2)
    assert wiring.compensations == [] and wiring.predictions == []
    wiring.run(NEEDED - 1, 4)
    ros.spin_until(lambda: len(wiring.compensations) == 4, what='4 offsets')
    np.testing.assert_allclose(xy(wiring.predictions), [[-0.6e-3, 0.8e-3]] * 4)
    # clamped to 0.5 mm along (0.6, -0.8), reached in steps of at most 0.2 mm
    np.testing.assert_allclose(xy(wiring.compensations)[:, 0],
                               [0.12e-3, 0.24e-3, 0.3e-3, 0.3e-3], atol=1e-12)
    np.testing.assert_allclose(xy(wiring.compensations)[:, 1],
                               [-0.16e-3, -0.32e-3, -0.4e-3, -0.4e-3], atol=1e-12)
    assert [stamp_ns(m) for m in wiring.compensations] == [
        T0 + (k + HORIZON) * PERIOD_NS for k in range(NEEDED - 1, NEEDED + 3)]


def test_shadow_mode_switched_at_run_time(ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 0.0), window=WINDOW, horizon=HORIZON)
    wiring = Wiring(ros, model)
    wiring.run(0, NEEDED)
    ros.spin_until(lambda: len(wiring.compensations) == 1, what='first offset')
    (result,) = wiring.node.set_parameters([Parameter('compensation_enabled', value=False)])
    assert result.successful
    # switching off cancels the offset already published for a future instant at once
    ros.spin_until(lambda: len(wiring.compensations) == 2, what='cancelling zero')
    assert stamp_ns(wiring.compensations[1]) == stamp_ns(wiring.compensations[0])
    wiring.run(NEEDED, 3)
    ros.spin_until(lambda: len(wiring.compensations) == 5, what='shadow offsets')
    np.testing.assert_allclose(xy(wiring.compensations)[:, 0], [20e-6, 0, 0, 0, 0])
    np.testing.assert_allclose(xy(wiring.predictions)[:, 0], [-20e-6] * 4)
    assert wiring.node.core.faults.total == 0


def test_gap_and_staleness_zero_once(ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 0.0), window=WINDOW, horizon=HORIZON)
    wiring = Wiring(ros, model, stale_periods=25.0)  # 1 s of wall time
    wiring.run(0, NEEDED)
    ros.spin_until(lambda: len(wiring.compensations) == 1, what='first offset')
    wiring.run(NEEDED + 3, 1)  # three samples missing: a gap
    ros.spin_until(lambda: len(wiring.compensations) == 2, what='zero after the gap')
    assert xy(wiring.compensations)[1].tolist() == [0.0, 0.0]
    assert stamp_ns(wiring.compensations[1]) >= T0 + (NEEDED + 3) * PERIOD_NS
    wiring.run(NEEDED + 4, NEEDED - 1)  # refilled (the gap sample was the first): resumes
    ros.spin_until(lambda: len(wiring.compensations) == 3, what='resumed offset')
    ros.spin_until(lambda: len(wiring.compensations) == 4, what='stale zero')
    ros.spin_for(0.5)
    assert len(wiring.compensations) == 4 and not xy(wiring.compensations)[3].any()
    assert len(wiring.predictions) == 2
    ros.spin_until(lambda: (wiring.status('inputs') or {}).get('faults.stale') == '1',
                   what='stale fault in /diagnostics')
    status = wiring.latest('inputs')
    assert status['faults.gap'] == '1' and status['last_fault'] == 'stale'


@pytest.mark.faults
def test_mismatched_model_is_refused_naming_the_field(ros: RosHarness, tmp_path: Path) -> None:
    model = save_linear(tmp_path / 'm.pt', window=WINDOW, horizon=HORIZON, sample_period=0.004)
    with pytest.raises(MetadataMismatchError, match=r"'sample_period' is 0\.004"):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(model)), Parameter('sample_period', value=0.04)])
    # A recorded clock's median step is not the nominal period to the last bit: 2 % passes.
    jittered = save_linear(tmp_path / 'j.pt', window=WINDOW, horizon=HORIZON,
                           sample_period=0.0401)
    node = PredictorNode(context=ros.context, parameter_overrides=[
        Parameter('model_path', value=str(jittered)), Parameter('sample_period', value=0.04)])
    assert node.runtime.sample_period == 0.04
    node.destroy_node()
    other_robot = save_linear(tmp_path / 'r.pt', robot_sha256='0' * 64)
    with pytest.raises(MetadataMismatchError, match="'robot_description_sha256'"):
        PredictorNode(context=ros.context,
                      parameter_overrides=[Parameter('model_path', value=str(other_robot))])
    # the node runs a calibrated URDF (robot_description_file), the model was trained for
    # the packaged one
    packaged = load_robot_description()
    calibrated = tmp_path / 'calibrated.urdf'
    calibrated.write_text(packaged.urdf_xml + '<!-- calibrated -->\n', encoding='utf-8')
    with pytest.raises(MetadataMismatchError, match=f"'robot_description_sha256' is "
                                                    f"'{packaged.sha256}'"):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(jittered)),
            Parameter('robot_description_file', value=str(calibrated))])
    # a model file from before the branch features reads other columns
    old = save_linear(tmp_path / 'o.pt', weight=np.zeros((WINDOW * 8, 2)), window=WINDOW,
                      horizon=HORIZON, features=FEATURES[:8])
    with pytest.raises(MetadataMismatchError, match=r"'features' is \('error_x', .*'ref_ay'\), "
                                                    r"this configuration needs .*'ups3_a'"):
        PredictorNode(context=ros.context,
                      parameter_overrides=[Parameter('model_path', value=str(old))])
    good = save_linear(tmp_path / 'g.pt', window=WINDOW, horizon=HORIZON)
    with pytest.raises(MetadataMismatchError,
                       match=r"'horizon' is 3, this configuration needs 5"):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(good)), Parameter('horizon', value=5)])
    with pytest.raises(ModelTrustError, match='the pinned sha256 is abab'):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(good)), Parameter('model_sha256', value='ab' * 32)])


@pytest.mark.faults
def test_bad_reload_keeps_the_old_model_and_good_reload_swaps_without_a_gap(
        ros: RosHarness, tmp_path: Path) -> None:
    old = save_constant(tmp_path / 'old.pt', (1e-6, 0.0), window=WINDOW, horizon=HORIZON)
    new = save_constant(tmp_path / 'new.pt', (2e-6, 0.0), window=WINDOW, horizon=HORIZON)
    longer = save_constant(tmp_path / 'longer.pt', (3e-6, 0.0), window=WINDOW + 1,
                           horizon=HORIZON)
    corrupt = tmp_path / 'corrupt.pt'
    corrupt.write_bytes(old.read_bytes()[:200])
    write_sidecar(corrupt)  # its hash checks out: the format is what is wrong
    unhashed = tmp_path / 'unhashed.pt'
    unhashed.write_bytes(new.read_bytes())  # no unhashed.pt.sha256
    wiring = Wiring(ros, old)
    wiring.run(0, NEEDED + 2)
    for bad, why in ((corrupt, 'not a TorchScript file'), (longer, "'window' is 5"),
                     (tmp_path / 'missing.pt', 'no such file'),
                     (unhashed, 'no hash to check it against')):
        (result,) = wiring.node.set_parameters([Parameter('model_path', value=str(bad))])
        assert not result.successful and why in result.reason
        assert f'still running {old}' in result.reason
    assert wiring.node.get_parameter('model_path').value == str(old)
    wiring.run(NEEDED + 2, 2)
    (result,) = wiring.node.set_parameters([Parameter('model_path', value=str(new))])
    assert result.successful
    wiring.run(NEEDED + 4, 3)
    ros.spin_until(lambda: len(wiring.predictions) == 8, what='8 predictions')
    instants = [stamp_ns(m) for m in wiring.predictions]
    assert instants == [T0 + (k + HORIZON) * PERIOD_NS for k in range(NEEDED - 1, NEEDED + 7)]
    np.testing.assert_allclose(xy(wiring.predictions)[:, 0], [1e-6] * 5 + [2e-6] * 3)
    ros.spin_until(lambda: (wiring.status('model') or {}).get('swaps') == '1',
                   what='swap in /diagnostics')
    assert wiring.latest('model')['sha256'] == load_model(new).sha256


def test_a_pose_or_reference_in_another_frame_is_dropped_and_counted(
        ros: RosHarness, tmp_path: Path) -> None:
    """Never used as if it were in the robot frame, and no fault: the stream goes on as if
    it had not come (the same instant in the robot frame is then used, no duplicate)."""
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 0.0), window=WINDOW, horizon=HORIZON)
    wiring = Wiring(ros, model)
    wiring.run(0, NEEDED)
    wiring.run(NEEDED, 1, frames=('world', 'map'))  # an old recording's frame; another one
    wiring.run(NEEDED, 2)
    ros.spin_until(lambda: len(wiring.compensations) == 3, what='three offsets')
    assert [stamp_ns(m) for m in wiring.compensations] == [
        T0 + (k + HORIZON) * PERIOD_NS for k in range(NEEDED - 1, NEEDED + 2)]
    assert xy(wiring.compensations)[:, 0].tolist() == [20e-6] * 3
    ros.spin_until(lambda: (wiring.status('inputs') or {}).get('rejected.wrong_frame') == '1',
                   what='the drops on /diagnostics')
    inputs = wiring.latest('inputs')
    assert (inputs['rejected.reference_wrong_frame'], inputs['rejected.duplicate'],
            inputs['faults_total']) == ('1', '0', '0')


def test_a_frame_prefix_is_the_frame_of_the_inputs_and_the_outputs(
        ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 0.0), window=WINDOW, horizon=HORIZON)
    wiring = Wiring(ros, model, frame_prefix='cell1/')
    prefixed = f'cell1/{ROBOT_FRAME}'
    wiring.run(0, NEEDED, frames=(prefixed, prefixed))
    wiring.run(NEEDED, 1)  # the bare robot frame is another cell's
    ros.spin_until(lambda: len(wiring.compensations) == 1, what='one offset')
    assert {m.header.frame_id for m in wiring.compensations + wiring.predictions} == {prefixed}
    assert wiring.node.core.dropped['wrong_frame'] == 1


def test_bad_messages_never_stop_the_node_and_are_counted(ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 0.0), window=WINDOW, horizon=HORIZON)
    wiring = Wiring(ros, model)
    wiring.run(0, NEEDED)
    wiring.run(NEEDED, 1, error=(float('nan'), 0.0))
    wiring.run(NEEDED, 1)  # a good sample at the NaN one's stamp is used
    wiring.run(NEEDED, 1)  # and its duplicate dropped
    wiring.run(2, 1)  # out of order
    wiring.run(NEEDED + 1, NEEDED)
    ros.spin_until(lambda: len(wiring.compensations) == 3, what='offset, zero, offset')
    assert xy(wiring.compensations)[:, 0].tolist() == [20e-6, 0.0, 20e-6]
    ros.spin_until(lambda: (wiring.status('prediction') or {}).get('predictions_total') == '2',
                   what='diagnostics')
    inputs = wiring.latest('inputs')
    assert (inputs['rejected.non_finite'], inputs['rejected.duplicate'],
            inputs['rejected.out_of_order']) == ('1', '1', '1')
    prediction = wiring.latest('prediction')
    assert float(prediction['inference_p99_us']) > 0.0
    assert float(prediction['input_to_output_p50_us']) > 0.0


def test_a_failing_callback_aborts_the_core_with_one_zero(
        ros: RosHarness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The node base's callback-exception policy: counted, logged, and the predictor's hook
    empties the window and cancels the offset in force; the node goes on."""
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 0.0), window=WINDOW, horizon=HORIZON)
    wiring = Wiring(ros, model)
    wiring.run(0, NEEDED)
    ros.spin_until(lambda: len(wiring.compensations) == 1, what='first offset')
    core = wiring.node.core
    add_pose = core.add_pose

    def broken(stamp_ns: int, x: float, y: float) -> list[Any]:
        raise RuntimeError('broken on purpose')

    monkeypatch.setattr(core, 'add_pose', broken)
    wiring.run(NEEDED, 1)
    ros.spin_until(lambda: len(wiring.compensations) == 2, what='the cancelling zero')
    assert not xy(wiring.compensations)[1].any()
    assert stamp_ns(wiring.compensations[1]) == stamp_ns(wiring.compensations[0])
    assert core.faults['internal'] == 1 and core.primary.window.fill == 0
    monkeypatch.setattr(core, 'add_pose', add_pose)
    wiring.run(NEEDED + 1, NEEDED)  # refilled: output resumes
    ros.spin_until(lambda: len(wiring.compensations) == 3, what='resumed offset')
    ros.spin_until(lambda: (wiring.status('inputs') or {}).get('callback_failures') == '1',
                   what='the failure in /diagnostics')
    assert 'end pose: RuntimeError: broken on purpose' in wiring.latest('inputs')[
        'last_callback_failure']


def test_torch_threads_are_set_by_the_entry_point_not_the_node(
        ros: RosHarness, tmp_path: Path) -> None:
    import torch

    from lompr_predictor.ros.predictor_node import build_entry_point
    from lompr_predictor.threads import set_torch_threads

    model = save_constant(tmp_path / 'c.pt', window=WINDOW, horizon=HORIZON)
    before = torch.get_num_threads()
    threads = 2 if before != 2 else 3
    parameters = [Parameter('model_path', value=str(model)),
                  Parameter('inference_threads', value=threads)]
    node = ros.add(PredictorNode(context=ros.context, parameter_overrides=parameters))
    assert node.settings.inference_threads == threads
    assert torch.get_num_threads() == before  # building a node leaves the process alone
    try:  # the executables' main() builds this way
        ros.add(build_entry_point(ros.context, node_name='entry', parameter_overrides=[
            Parameter('model_path', value=str(model))]))
        assert torch.get_num_threads() == 1  # the default inference_threads
    finally:
        set_torch_threads(before)


def test_executable_with_params_file_refuses_a_mismatched_model_in_one_line(tmp_path: Path) -> None:
    model = save_linear(tmp_path / 'm.pt', window=WINDOW, horizon=HORIZON)
    process = start_executable('predictor_node', '--params-file', str(PARAMS_FILE),
                               '-p', f'model_path:={model}', '-p', 'horizon:=7')
    try:
        code = process.wait(timeout=60)
    finally:
        _, stderr = stop_process(process)
    assert code == 2
    errors = [line for line in stderr.splitlines() if 'error' in line.lower()]
    assert len(errors) == 1 and "metadata field 'horizon' is 3" in errors[0], stderr


def test_one_process_pipeline_answers_joint_states(
        ros: RosHarness, description: RobotDescription, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'c.pt', (-7e-6, 3e-6), window=WINDOW, horizon=HORIZON)
    # the guard off: the constant model's offsets, not persistence's while it is unproven;
    # the low-pass off: the offset is the constant at once
    process = start_executable('pipeline', '-p', f'predictor_node:model_path:={model}',
                               '-p', 'predictor_node:compensation_enabled:=true',
                               '-p', 'predictor_node:guard_enabled:=false',
                               '-p', 'predictor_node:compensation_bandwidth:=0.0')
    try:
        compensations = ros.collect('/lompr/compensation', Vector3Stamped, 100)
        joints = ros.node.create_publisher(JointState, '/joint_states', 100)
        reference = ros.node.create_publisher(PoseStamped, '/lompr/reference', 100)
        ros.wait_for_subscribers(joints, timeout=60.0)
        ros.wait_for_subscribers(reference, timeout=60.0)
        ros.wait_for_publishers('/lompr/compensation', timeout=60.0)
        recording = spiral_recording(description, NEEDED + 1)

        def publish_stream(shift_ns: int) -> None:
            for k in range(NEEDED + 1):
                ref = PoseStamped()
                ref.header.frame_id = ROBOT_FRAME
                set_stamp(ref, recording.reference.stamps[k] + shift_ns)
                ref.pose.position.x, ref.pose.position.y = map(
                    float, recording.reference.positions[k, :2])
                reference.publish(ref)
                msg = JointState(name=list(MEASURED_JOINTS),
                                 position=recording.joints.positions[k].tolist())
                set_stamp(msg, recording.joints.stamps[k] + shift_ns)
                joints.publish(msg)
                ros.spin_for(0.01)

        # The graph shows the pipeline's inner end-pose link before its reader and writer
        # have surely matched: a warm-up stream 100 s earlier, repeated until it comes back.
        deadline = time.monotonic() + 30.0
        while not compensations and time.monotonic() < deadline:
            publish_stream(-100 * 10**9)
            ros.spin_for(0.2)
        assert compensations, 'the pipeline never answered the warm-up stream'
        publish_stream(0)
        first = recording.joints.stamps[NEEDED - 1] + HORIZON * PERIOD_NS

        def answers() -> list[Vector3Stamped]:
            return [c for c in compensations if stamp_ns(c) >= first]

        ros.spin_until(lambda: len(answers()) == 2, what='two offsets from the pipeline')
        np.testing.assert_allclose(xy(answers()), [[7e-6, -3e-6]] * 2)
        assert stamp_ns(answers()[-1]) == recording.joints.stamps[NEEDED] + HORIZON * PERIOD_NS
    finally:
        stop_process(process)


def pipeline_parameters(model: Path, **overrides: object) -> dict[str, list[Parameter]]:
    """The predictor's parameters of an in-process pipeline test (as `Wiring`'s: staleness
    and lateness out of a loaded machine's way, the guard and the low-pass off)."""
    values = {'model_path': str(model), 'compensation_enabled': True, 'guard_enabled': False,
              'compensation_bandwidth': 0.0, 'stale_periods': 1000.0, 'late_tolerance': 60.0,
              **overrides}
    return {'predictor_node': [Parameter(k, value=v) for k, v in values.items()]}


def test_the_pipeline_hands_its_end_poses_over_in_process(
        ros: RosHarness, description: RobotDescription, tmp_path: Path) -> None:
    """In one process the predictor takes the kinematics node's end poses by a call, not
    back from the topic they are still published on (no subscription of its own): every
    sample is answered as through the topic, and both nodes time their own callbacks."""
    model = save_constant(tmp_path / 'c.pt', (-7e-6, 3e-6), window=WINDOW, horizon=HORIZON)
    kinematics, predictor = (ros.add(node) for node in
                             build_pipeline(ros.context, pipeline_parameters(model)))
    assert predictor.end_pose_in_process
    assert kinematics.end_pose_readers == [predictor.read_end_pose]
    assert '/lompr/end_pose' not in {s.topic_name for s in predictor.subscriptions}
    end_poses = ros.collect('/lompr/end_pose', PoseStamped, 100)
    compensations = ros.collect('/lompr/compensation', Vector3Stamped, 100)
    joints = ros.node.create_publisher(JointState, '/joint_states', 100)
    reference = ros.node.create_publisher(PoseStamped, '/lompr/reference', 100)
    ros.wait_for_subscribers(joints)
    ros.wait_for_subscribers(reference)
    ros.wait_for_subscribers(kinematics._publisher)  # the test's reader, not the predictor
    ros.wait_for_publishers('/lompr/compensation')
    recording = spiral_recording(description, NEEDED + 1)
    for k in range(NEEDED + 1):
        ref = PoseStamped()
        ref.header.frame_id = ROBOT_FRAME
        set_stamp(ref, recording.reference.stamps[k])
        ref.pose.position.x, ref.pose.position.y = map(float,
                                                       recording.reference.positions[k, :2])
        reference.publish(ref)
        ros.spin_until(lambda: predictor.inputs.reference_rate.total > k,  # noqa: B023
                       what=f'reference {k}')
        msg = JointState(name=list(MEASURED_JOINTS),
                         position=recording.joints.positions[k].tolist())
        set_stamp(msg, recording.joints.stamps[k])
        joints.publish(msg)
        ros.spin_until(lambda: len(end_poses) > k, what=f'end pose {k}')  # noqa: B023
    ros.spin_until(lambda: len(compensations) == 2, what='two offsets')
    np.testing.assert_allclose(xy(compensations), [[7e-6, -3e-6]] * 2)
    assert [stamp_ns(c) for c in compensations] == [
        recording.joints.stamps[k] + HORIZON * PERIOD_NS for k in (NEEDED - 1, NEEDED)]
    assert predictor.inputs.pose_rate.total == NEEDED + 1  # each end pose once, by the call
    # each node's callbacks in its own rows (the time apart: test_monitoring)
    assert predictor.callback_times.rows['end pose'].total == NEEDED + 1
    assert kinematics.callback_times.rows['joint states'].total == NEEDED + 1


def test_a_pipeline_predictor_on_another_topic_subscribes_to_it(
        ros: RosHarness, tmp_path: Path) -> None:
    """The handover is for the topic the kinematics node publishes on: a predictor told to
    read another one subscribes to that one as on its own."""
    model = save_constant(tmp_path / 'c.pt', window=WINDOW, horizon=HORIZON)
    kinematics, predictor = (ros.add(node) for node in build_pipeline(
        ros.context, pipeline_parameters(model, end_pose_topic='/cell2/end_pose')))
    assert not predictor.end_pose_in_process and not kinematics.end_pose_readers
    assert '/cell2/end_pose' in {s.topic_name for s in predictor.subscriptions}


# -- faults: refusals, the trust chain, overruns --------------------------------------------

@pytest.mark.faults
@pytest.mark.parametrize(('argument', 'expected'), [
    ('model_path:=', "Couldn't parse parameter override rule: '-p model_path:='"),
    ("model_path:=''", 'parameter model_path is empty'),
])
def test_predictor_node_refuses_an_empty_model_path_in_one_line(
        argument: str, expected: str) -> None:
    command = [str(Path(sys.executable).parent / 'predictor_node'), '--ros-args', '-p', argument]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    lines = [line for line in result.stderr.splitlines() if '[WARN]' not in line]
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith('predictor_node: error: ') and expected in lines[0]


@pytest.mark.faults
def test_the_node_refuses_an_unverified_model_at_start_and_reports_the_hash(
        ros: Any, tmp_path: Path) -> None:

    model = save_constant(tmp_path / 'model.pt', window=WINDOW, horizon=HORIZON)
    bare = tmp_path / 'bare.pt'
    bare.write_bytes(model.read_bytes())  # no bare.pt.sha256
    with pytest.raises(ModelTrustError, match='no hash to check it against'):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(bare))])
    ros.spin_until(lambda: 'predictor_node' not in ros.node.get_node_names(),
                   what='the refused node gone (no output)')
    node = ros.add(PredictorNode(context=ros.context, parameter_overrides=[
        Parameter('model_path', value=str(model))]))
    status = node.diagnostics.model_status()
    digest = hashlib.sha256(model.read_bytes()).hexdigest()
    assert status.level == Level.OK
    assert (status.values['sha256'], status.values['sha256_verified_by']) == (digest, 'sidecar')
    # a hot swap to a file whose hash does not check out keeps the running model
    (result,) = node.set_parameters([Parameter('model_path', value=str(bare))])
    assert not result.successful and 'no hash to check it against' in result.reason
    assert node.core.model.sha256 == digest and node.runtime.models.history.swaps == 0
    node.destroy_node()
    loose = ros.add(PredictorNode(context=ros.context, node_name='loose', parameter_overrides=[
        Parameter('model_path', value=str(bare)), Parameter('verify_model_hash', value=False)]))
    status = loose.diagnostics.model_status()
    assert status.level == Level.WARN and 'NOT verified' in status.message


@pytest.mark.faults
def test_overruns_are_counted_on_diagnostics(ros: Any, tmp_path: Path) -> None:
    import time


    wiring = Wiring(ros, save_constant(tmp_path / 'model.pt', (1e-5, 0.0), window=WINDOW,
                                       horizon=HORIZON), late_tolerance=0.005)
    core = wiring.node.core
    module = core.model.module

    def slow_module(windows: torch.Tensor) -> torch.Tensor:
        time.sleep(0.2)  # longer than the lead, 3 x 40 ms
        return cast(torch.Tensor, module(windows))

    core.replace_model(dataclasses.replace(core.model,
                                           compiled=cast(ExportedModule, slow_module)))
    wiring.run(0, NEEDED + 3)
    overrun = core.overrun
    assert overrun.late_outputs_dropped + overrun.inference_skipped_late >= 3
    assert not [m for m in wiring.compensations if m.vector.x or m.vector.y]  # none late
    status = wiring.node.diagnostics.prediction_status()
    assert status.level == Level.WARN and 'after their instant or skipped' in status.message
    assert status.values['late_outputs_dropped'] == overrun.late_outputs_dropped


def test_a_preview_model_reads_the_planned_path_and_counts_a_bad_one(
        ros: RosHarness, tmp_path: Path) -> None:
    preview = 2
    model = save_constant(tmp_path / 'p.pt', (-20e-6, 5e-6), window=WINDOW, horizon=HORIZON,
                          features=feature_names(preview), preview=preview)
    wiring = Wiring(ros, model)
    plans = ros.node.create_publisher(NavPath, '/lompr/reference_preview', 100)
    ros.wait_for_subscribers(plans)

    def plan(k: int, frame: str = ROBOT_FRAME) -> None:
        """The next preview + 2 samples of `Wiring.run`'s path, planned at sample k."""
        msg = NavPath()
        msg.header.frame_id = frame
        for j in range(k + 1, k + preview + 3):
            pose = PoseStamped()
            set_stamp(pose, T0 + j * PERIOD_NS)
            pose.pose.position.x, pose.pose.position.y = 0.01 + 1e-3 * j, 0.02 + 1e-3 * j
            msg.poses.append(pose)
        received = wiring.node.inputs.preview_rate.total
        plans.publish(msg)
        ros.spin_until(lambda: wiring.node.inputs.preview_rate.total > received, what='a preview')

    for k in range(NEEDED + 2):
        plan(k)
        wiring.run(k, 1)
    ros.spin_until(lambda: len(wiring.predictions) == 3, what='3 predictions')
    np.testing.assert_allclose(xy(wiring.predictions), [[-20e-6, 5e-6]] * 3)
    plan(NEEDED + 2, frame='map')  # refused whole: the plan stops two samples later
    wiring.run(NEEDED + 2, 4)
    ros.spin_until(lambda: (wiring.status('reference preview') or {}).get(
        'rejected.missing') == '2', what='the samples without a plan on /diagnostics')
    status = wiring.latest('reference preview')
    assert status['rejected.wrong_frame'] == '1' and status['previews_used'] == str(NEEDED + 2)
    warnings = [s.message for array in wiring.diagnostics for s in array.status
                if s.name == 'predictor_node: reference preview' and s.level == b'\x01']
    assert warnings and 'without a plan' in warnings[0]
    assert len(wiring.predictions) == 3 + 2


def test_without_a_preview_the_fallback_model_answers(ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'p.pt', (-20e-6, 5e-6), window=WINDOW, horizon=HORIZON,
                          features=feature_names(2), preview=2)
    fallback = save_constant(tmp_path / 'f.pt', (4e-6, -1e-6), window=2, horizon=HORIZON)
    wiring = Wiring(ros, model, fallback_model_path=str(fallback))
    wiring.run(0, 8)  # no preview ever: the fallback answers once its window of 2 has filled
    ros.spin_until(lambda: len(wiring.predictions) == 8 - 2 - HISTORY + 1, what='fallback')
    np.testing.assert_allclose(xy(wiring.predictions), [[4e-6, -1e-6]] * 5)
    ros.spin_until(lambda: (wiring.status('reference preview') or {}).get(
        'fallback_answers') == '5', what='the fallback on /diagnostics')
    assert wiring.latest('reference preview')['fallback_model'] == str(fallback)
    # a fallback for another instant is refused at configure, naming the field
    other = save_constant(tmp_path / 'h.pt', window=2, horizon=HORIZON + 1)
    with pytest.raises(MetadataMismatchError, match=r"'horizon' is 4, this configuration "
                                                    r'needs 3'):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(model)),
            Parameter('fallback_model_path', value=str(other))])


def test_the_guard_holds_back_an_axis_where_the_model_is_worse_and_says_so(
        ros: RosHarness, tmp_path: Path) -> None:
    """The plant error holds at (10, -10) um: persistence is exact. A model that predicts
    (50, -10) um misses X by 40 um: persistence answers from the first prediction (the model
    has not earned control) and X stays with it after `guard_min_scored` scored instants;
    the 'guard' status is OK while the model is unproven, then WARN naming X and the reason
    (Y, as exact as persistence, stays unproven). The guard switched off at run time: the
    model's X."""
    model = save_constant(tmp_path / 'biased.pt', (5e-5, -1e-5), window=WINDOW,
                          horizon=HORIZON)
    wiring = Wiring(ros, model, compensation_enabled=False, guard_enabled=True,
                    guard_min_scored=10, guard_min_dwell=5 * PERIOD_NS * 1e-9,
                    guard_window=10 * PERIOD_NS * 1e-9)
    wiring.run(0, NEEDED)
    ros.spin_until(lambda: len(wiring.predictions) == 1, what='the first prediction')
    ros.spin_until(lambda: (wiring.status('guard') or {}).get('reason_x') == 'unproven',
                   what='the guard status')
    status = wiring.latest('guard')
    assert status['_level'] == DiagnosticStatus.OK
    assert 'persistence answers on X until the model is better by the margin' in (
        status['_message'])
    wiring.run(NEEDED, 30)
    ros.spin_until(lambda: len(wiring.predictions) == 31, what='31 predictions')
    published = xy(wiring.predictions)
    np.testing.assert_allclose(published[:, 0], 1e-5, atol=1e-12)
    np.testing.assert_allclose(published[:, 1], -1e-5, atol=1e-12)
    ros.spin_until(lambda: (wiring.status('guard') or {}).get('reason_x')
                   == 'worse_than_persistence', what='the guard status')
    status = wiring.latest('guard')
    assert status['_level'] == DiagnosticStatus.WARN
    assert 'persistence answers on X (worse_than_persistence' in status['_message']
    assert status['state_x'] == status['state_y'] == 'persistence'
    assert status['reason_y'] == 'unproven'
    assert float(status['model_rms_x_um']) == pytest.approx(40.0, rel=1e-6)
    assert float(status['persistence_rms_x_um']) == 0.0
    assert status['hand_overs_x'] == status['hand_backs_x'] == '0'
    wiring.node.set_parameters([Parameter('guard_enabled', value=False)])
    wiring.run(NEEDED + 30, 3)
    ros.spin_until(lambda: len(wiring.predictions) == 34, what='3 more predictions')
    np.testing.assert_allclose(xy(wiring.predictions)[-3:, 0], 5e-5, rtol=1e-12)


@pytest.mark.faults
def test_a_refused_fallback_names_how_to_verify_the_fallback(ros: Any, tmp_path: Path) -> None:
    """The fallback model is checked against its own sidecar: a fallback without one is
    refused with a hint naming that file, not `model_sha256`, which pins model_path."""
    model = save_constant(tmp_path / 'p.pt', window=WINDOW, horizon=HORIZON,
                          features=feature_names(2), preview=2)
    digest = hashlib.sha256(model.read_bytes()).hexdigest()
    fallback = tmp_path / 'f.pt'
    fallback.write_bytes(save_constant(tmp_path / 'made.pt', window=2,
                                       horizon=HORIZON).read_bytes())  # no f.pt.sha256
    with pytest.raises(ModelTrustError, match='no hash to check it against') as refused:
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(model)), Parameter('model_sha256', value=digest),
            Parameter('fallback_model_path', value=str(fallback))])
    message = str(refused.value)
    assert message.startswith(f'model {fallback}: ') and 'f.pt.sha256' in message
    assert 'model_sha256 pins model_path, not the fallback' in message
    assert 'model_sha256:=' not in message and 'pin its sha256' not in message
