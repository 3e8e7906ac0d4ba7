# SPDX-License-Identifier: Apache-2.0
"""Machines other than the LOMPR, end to end: a serial arm and a one-joint axis, recorded as a
robot commanded in joints records (measured and commanded JointState), cleaned, trained,
scored, and run through kinematics_node -> predictor_node against the offline model."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from model_helpers import LinearWindowModel, metadata
from robots import ARM_URDF, AXIS_URDF, arm_joints, arm_tip, write_urdf
from ros_helpers import RosHarness, set_stamp, stamp_ns, xy
from sensor_msgs.msg import JointState
from trainer_data import FAST, run_cli

from lompr_predictor.data.bags import (
    COMMAND_TOPIC,
    BagError,
    BagTopics,
    JointSamples,
    Recording,
    no_reference,
    read_recording,
    write_recording,
)
from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.features import HISTORY, TOOL_FEATURES, feature_names
from lompr_predictor.learning.model_file import load_model, save_model
from lompr_predictor.learning.models import predict_rows
from lompr_predictor.robot.chain import RobotSpec, load_chain

PERIOD = 0.004
T0 = 1_700_000_000 * 10**9
ARM_JOINTS = ('yaw', 'shoulder', 'elbow')
LAG = 0.012  # [s] the arm's joints trail their command


def arm_recording(samples: int, noise: float = 0.0) -> Recording:
    """The planar arm's measured joints `LAG` behind its commanded ones, both at every
    sample instant (4 ms)."""
    stamps = T0 + np.round(np.arange(samples) * PERIOD * 1e9).astype(np.int64)
    measured = arm_joints(samples, PERIOD, LAG)
    measured += noise * np.random.default_rng(0).standard_normal(measured.shape)
    return Recording(joints=JointSamples(stamps, measured, ARM_JOINTS), reference=no_reference(),
                     commands=JointSamples(stamps, arm_joints(samples, PERIOD), ARM_JOINTS))


@pytest.fixture(scope='module')
def arm_urdf(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_urdf(tmp_path_factory.mktemp('arm'), 'arm.urdf', ARM_URDF)


def test_commanded_joints_round_trip_and_their_kinematics_are_the_reference(
        tmp_path: Path, arm_urdf: Path) -> None:
    bag = write_recording(tmp_path / 'arm', arm_recording(300))
    recording = read_recording(bag, topics=BagTopics(commands=COMMAND_TOPIC),
                               joint_names=ARM_JOINTS)
    assert recording.commands is not None and len(recording.reference.stamps) == 0
    np.testing.assert_array_equal(recording.commands.positions, arm_joints(300, PERIOD))
    chain = load_chain(RobotSpec(arm_urdf, 'base', 'flange'))
    data = clean_recordings([recording], chain)
    assert data.counts['kept'] == 300 and data.counts['command_fk_invalid'] == 0
    np.testing.assert_allclose(data.reference, arm_tip(arm_joints(300, PERIOD)), atol=1e-9)
    expected = arm_tip(arm_joints(300, PERIOD, LAG)) - arm_tip(arm_joints(300, PERIOD))
    np.testing.assert_allclose(data.error, expected[:, :2], rtol=0, atol=1e-9)
    # a serial chain's rows are the tool's columns: its map works in the tool's axes
    assert data.features().shape == (300, len(TOOL_FEATURES))


def test_commands_that_lack_a_measured_joint_are_refused_naming_it(tmp_path: Path) -> None:
    recording = arm_recording(20)
    commands = recording.commands
    assert commands is not None
    partial = Recording(joints=recording.joints, reference=no_reference(),
                        commands=JointSamples(commands.stamps, commands.positions[:, :2],
                                              ARM_JOINTS[:2]))
    bag = write_recording(tmp_path / 'partial', partial)
    with pytest.raises(BagError, match=r'no joint\(s\) elbow on /joint_commands; its joints '
                                       'are shoulder, yaw'):
        read_recording(bag, topics=BagTopics(commands=COMMAND_TOPIC), joint_names=ARM_JOINTS)


def test_a_joint_beyond_its_limit_in_a_command_is_counted_not_used(
        tmp_path: Path, arm_urdf: Path) -> None:
    recording = arm_recording(100)
    assert recording.commands is not None
    recording.commands.positions[40, 2] = 3.0  # the elbow's limit is 2.5 rad
    data = clean_recordings([recording], load_chain(RobotSpec(arm_urdf, 'base', 'flange')))
    assert data.counts['command_fk_invalid'] == 1
    assert data.counts['kept'] == 100  # the reference is interpolated over the one missing


def test_a_one_joint_axis_trains_and_predicts_its_y_as_zero(tmp_path: Path) -> None:
    """X alone moves; the error on Y is identically zero: the trainer, the report and the
    model predict it as zero, the X error is learned."""
    urdf = write_urdf(tmp_path, 'axis.urdf', AXIS_URDF)
    samples = 3000
    t = np.arange(samples) * PERIOD
    stamps = T0 + np.round(t * 1e9).astype(np.int64)
    command = 0.2 * np.sin(2 * np.pi * t / 3.0)
    measured = 0.2 * np.sin(2 * np.pi * (t - 0.01) / 3.0)
    measured += 1e-6 * np.random.default_rng(1).standard_normal(samples)
    bags = [write_recording(tmp_path / name, Recording(
        joints=JointSamples(stamps[part], measured[part, None], ('x',)),
        reference=no_reference(),
        commands=JointSamples(stamps[part], command[part, None], ('x',))))
        for name, part in (('first', slice(0, 2400)), ('second', slice(2400, None)))]
    robot = ['--robot-description', str(urdf), '--tip-frame', 'tool',
             '--command-topic', COMMAND_TOPIC]
    model_path, report = tmp_path / 'axis.pt', tmp_path / 'report'
    assert run_cli(['train', str(bags[0]), '--out', str(model_path), '--report', str(report),
                    *robot, *FAST]) == 0
    document = json.loads((report / 'report.json').read_text())
    for name, entry in document['models'].items():
        assert entry['metrics']['y']['rmse_um'] == 0.0, name
        assert entry['metrics']['x']['rmse_um'] > 0.1, name
    assert '| RMSE (um) | 0 |' in (report / 'report.md').read_text()
    model = load_model(model_path)
    assert model.metadata.robot['joints'] == ['x'] and model.metadata.robot['tip_frame'] == 'tool'
    data = clean_recordings([read_recording(bags[1], topics=BagTopics(commands=COMMAND_TOPIC),
                                            joint_names=('x',))],
                            load_chain(RobotSpec(urdf, tip_frame='tool')))
    ends = np.arange(8 + HISTORY, len(data) - 2)
    predicted = predict_rows(model.module, data.features(), ends, 8)
    assert np.isfinite(predicted).all() and not predicted[:, 1].any()
    # the frames and joints come from the model file: evaluate needs the URDF alone
    assert run_cli(['evaluate', str(model_path), str(bags[1]), '--report',
                    str(tmp_path / 'evaluation'), '--robot-description', str(urdf),
                    '--command-topic', COMMAND_TOPIC]) == 0
    evaluated = json.loads((tmp_path / 'evaluation' / 'report.json').read_text())
    assert evaluated['models']['model']['metrics']['y']['rmse_um'] == 0.0


def serial_model(path: Path, urdf: Path, window: int = 4, horizon: int = 3, *,
                 base: str = 'base', tip: str = 'flange') -> Path:
    """A linear model of a serial chain's rows (the tool's columns): the last error plus
    1 ms of the reference's velocity, bound to `urdf`'s chain from `base` to `tip`."""
    chain = load_chain(RobotSpec(urdf, base, tip))
    features = feature_names(0, chain.actuators)
    weight = np.zeros((window, len(features), 2))
    weight[-1, 0, 0] = weight[-1, 1, 1] = 1.0
    weight[-1, features.index('ref_vx'), 0] = 1e-3
    weight[-1, features.index('ref_vy'), 1] = -1e-3
    info = metadata(features=features, window=window, horizon=horizon, sample_period=PERIOD,
                    robot_sha256=chain.sha256, robot=chain.metadata())
    save_model(path, LinearWindowModel(weight.reshape(-1, 2), np.zeros(2)), info)
    return path


@dataclass(frozen=True)
class Machine:
    """A test machine: its URDF, frames, recording and tool tips by hand."""

    urdf: str
    base: str
    tip: str
    recording: Callable[[int, float], Recording]
    tip_of: Callable[[np.ndarray], np.ndarray]


def axis_recording(samples: int, noise: float = 0.0) -> Recording:
    """The one-joint axis's carriage `LAG` behind its command."""
    stamps = T0 + np.round(np.arange(samples) * PERIOD * 1e9).astype(np.int64)
    t = np.arange(samples) * PERIOD
    command = 0.2 * np.sin(2 * np.pi * t / 3.0)
    measured = 0.2 * np.sin(2 * np.pi * (t - LAG) / 3.0)
    measured += noise * np.random.default_rng(0).standard_normal(samples)
    return Recording(joints=JointSamples(stamps, measured[:, None], ('x',)),
                     reference=no_reference(),
                     commands=JointSamples(stamps, command[:, None], ('x',)))


def axis_tip(joints: np.ndarray) -> np.ndarray:
    """(N, 3) the axis's tool: x along the bed, 0.15 m above it."""
    x = np.asarray(joints, dtype=float)[:, 0]
    return np.column_stack([x, np.zeros(len(x)), np.full(len(x), 0.15)])


MACHINES = {'arm': Machine(ARM_URDF, 'base', 'flange', arm_recording, arm_tip),
            'axis': Machine(AXIS_URDF, 'bed', 'tool', axis_recording, axis_tip)}


@pytest.mark.ros
@pytest.mark.parametrize('name', sorted(MACHINES))
def test_a_machine_through_both_nodes_gives_the_offline_predictions(
        ros: RosHarness, tmp_path: Path, name: str) -> None:
    """kinematics_node solves the measured and the commanded joints of an arm and of a
    single axis (poses to 1e-9 m against the kinematics by hand), predictor_node answers
    every sample as the offline model does on the trainer's rows (to 1e-9 m)."""
    from rclpy.parameter import Parameter

    from lompr_predictor.ros.kinematics_node import KinematicsNode
    from lompr_predictor.ros.predictor_node import PredictorNode

    machine = MACHINES[name]
    urdf = write_urdf(tmp_path, f'{name}.urdf', machine.urdf)
    model_path = serial_model(tmp_path / 'model.pt', urdf, base=machine.base, tip=machine.tip)
    robot = {'robot_description_file': str(urdf), 'base_frame': machine.base,
             'tip_frame': machine.tip, 'frame_id': machine.base}
    kinematics = ros.add(KinematicsNode(context=ros.context, parameter_overrides=[
        Parameter(name, value=value) for name, value in
        {**robot, 'command_topic': 'joint_commands', 'diagnostics_period': 0.1}.items()]))
    predictor = ros.add(PredictorNode(context=ros.context, parameter_overrides=[
        Parameter(name, value=value) for name, value in
        {'model_path': str(model_path), 'robot_description_file': str(urdf),
         'frame_id': machine.base, 'compensation_enabled': False, 'guard_enabled': False,
         'stale_periods': 1e6, 'late_tolerance': 60.0}.items()]))
    poses = ros.collect('/lompr/end_pose', PoseStamped, 1000)
    references = ros.collect('/lompr/reference', PoseStamped, 1000)
    predictions = ros.collect('/lompr/predicted_error', Vector3Stamped, 1000)
    measured_out = ros.node.create_publisher(JointState, '/joint_states', 100)
    commanded_out = ros.node.create_publisher(JointState, '/joint_commands', 100)
    for publisher in (measured_out, commanded_out):
        ros.wait_for_subscribers(publisher)
    ros.wait_for_publishers('/lompr/predicted_error')
    recording = machine.recording(40, 1e-6)
    assert recording.commands is not None
    names = ['other', *reversed(recording.joints.names)]  # matched by name, others ignored
    for k, stamp in enumerate(recording.joints.stamps):
        for publisher, joints in ((commanded_out, recording.commands),
                                  (measured_out, recording.joints)):
            message = JointState(name=names,
                                 position=[7.0, *joints.positions[k][::-1].tolist()])
            set_stamp(message, int(stamp))
            publisher.publish(message)
        answered = k + 1
        ros.spin_until(lambda: min(len(poses), len(references),
                                   predictor.inputs.pose_rate.total) >= answered,  # noqa: B023
                       what=f'sample {k}')
    assert kinematics.rejected.total == 0 and kinematics.commands.rejected.total == 0
    assert {message.header.frame_id for message in poses + references} == {machine.base}
    np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                                for p in poses], machine.tip_of(recording.joints.positions),
                               atol=1e-9)
    np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                                for p in references],
                               machine.tip_of(recording.commands.positions), atol=1e-9)
    data = clean_recordings([recording],
                            load_chain(RobotSpec(urdf, machine.base, machine.tip)))
    ends = np.arange(4 + HISTORY - 1, len(data))
    offline = predict_rows(load_model(model_path).module, data.features(), ends, 4)
    ros.spin_until(lambda: len(predictions) >= len(ends), what='every prediction')
    assert [stamp_ns(m) for m in predictions] == (data.stamps[ends]
                                                 + round(3 * PERIOD * 1e9)).tolist()
    np.testing.assert_allclose(xy(predictions), offline, rtol=0, atol=1e-9)


def test_a_model_of_another_tip_frame_is_refused_by_the_core(
        tmp_path: Path, arm_urdf: Path) -> None:
    from lompr_predictor.learning.model_file import MetadataMismatchError
    from lompr_predictor.online.model_slot import check_model

    model = load_model(serial_model(tmp_path / 'arm.pt', arm_urdf))
    other_tip = load_chain(RobotSpec(arm_urdf, 'base', 'fore'))
    with pytest.raises(MetadataMismatchError, match=r"'robot\.tip_frame' is 'flange', this "
                                                    r"configuration needs 'fore'"):
        check_model(model, other_tip)
    with pytest.raises(MetadataMismatchError, match=r"'features' is .*'ref_ay'\), this "
                                                    r"configuration needs .*'ups3_a'"):
        check_model(model, load_chain())


def test_lompr_simulate_records_the_twin_arm_as_a_robot_commanded_in_joints(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lompr_predictor.cli import main as lompr_main
    from lompr_predictor.twin.arm import arm_spec, simulate_arm

    out = tmp_path / 'arm'
    assert lompr_main(['simulate', '--robot', 'arm', '--path', 'figure8', '--passes', '1',
                       '--seed', '3', '--out', str(out)]) == 0
    truth = json.loads((out / 'arm_ground_truth.json').read_text())
    assert (truth['base_frame'], truth['tip_frame']) == ('arm_base', 'tool0')
    chain = load_chain(arm_spec())
    recording = read_recording(out, topics=BagTopics(commands=COMMAND_TOPIC),
                               joint_names=chain.joint_names)
    run = simulate_arm('figure8', passes=1, seed=3)
    assert recording.commands is not None
    np.testing.assert_array_equal(recording.commands.positions, run.commanded)
    np.testing.assert_array_equal(recording.joints.positions, run.measured)
    data = clean_recordings([recording], chain)
    assert data.counts['kept'] == len(run.stamps)
    np.testing.assert_allclose(data.reference, run.tool_commanded, rtol=0, atol=1e-12)
    # the error the trainer learns is the true one but for the encoders' noise (microns)
    rms = np.sqrt(np.mean(data.error ** 2, axis=0)) * 1e6
    np.testing.assert_allclose(rms, [truth['tool_error_rms_um'][axis] for axis in 'xy'],
                               rtol=0.05)
    # a program of the other machine is refused in one line
    assert lompr_main(['simulate', '--robot', 'arm', '--path', 'spiral', '--out',
                       str(tmp_path / 'refused')]) == 2
    assert ('--path spiral is not a program of the arm: one of circle, raster, figure8'
            in capsys.readouterr().err)
    assert not (tmp_path / 'refused').exists()
    # the LOMPR twin's options are refused with the arm, not left unapplied
    assert lompr_main(['simulate', '--robot', 'arm', '--gaps', '3', '--preset', 'worn',
                       '--out', str(tmp_path / 'refused')]) == 2
    assert ("--preset, --gaps: the LOMPR twin's, not the arm's"
            in capsys.readouterr().err)
    assert not (tmp_path / 'refused').exists()


@pytest.mark.parametrize(('robot', 'message'), [
    (['--tip-frame', 'hand'], "tip frame 'hand' is not in robot description"),
    (['--tip-frame', 'flange', '--joint-names', 'yaw,shoulder'],
     r'moves joint\(s\) elbow that the joint names lack'),
    (['--tip-frame', 'flange', '--joint-names', 'yaw,shoulder,elbow,grip'],
     r'joint\(s\) grip not on the chain'),
])
def test_lompr_train_refuses_a_robot_named_wrong_in_one_line_writing_nothing(
        tmp_path: Path, arm_urdf: Path, capsys: pytest.CaptureFixture[str],
        robot: list[str], message: str) -> None:
    from lompr_predictor.cli import main as lompr_main

    bag = write_recording(tmp_path / 'arm', arm_recording(100))
    model, report = tmp_path / 'm.pt', tmp_path / 'report'
    assert lompr_main(['train', str(bag), '--out', str(model), '--report', str(report),
                       '--robot-description', str(arm_urdf), '--command-topic', COMMAND_TOPIC,
                       *robot, '--quiet']) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1
    assert re.search(message, error), error
    assert not model.exists() and not report.exists()


def test_runs_too_short_for_the_maps_horizon_are_a_one_line_data_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Runs of 50 samples hold windows of 8 with a horizon of 25, but no pair of window ends
    25 samples apart: the machine map cannot be fitted, and the trainer says so in one line
    (exit 2), naming the way out, before anything is written."""
    from lompr_predictor.cli import main as lompr_main

    urdf = write_urdf(tmp_path, 'axis.urdf', AXIS_URDF)
    full = axis_recording(4000)
    keep = (np.arange(4000) % 60) < 50  # a gap of 10 samples after every 50
    assert full.commands is not None
    bag = write_recording(tmp_path / 'short', Recording(
        joints=JointSamples(full.joints.stamps[keep], full.joints.positions[keep], ('x',)),
        reference=no_reference(),
        commands=JointSamples(full.commands.stamps[keep], full.commands.positions[keep],
                              ('x',))))
    at = FAST.index('--horizon')
    fast = FAST[:at] + FAST[at + 2:]
    assert lompr_main(['train', str(bag), '--out', str(tmp_path / 'm.pt'), '--report',
                       str(tmp_path / 'r'), '--robot-description', str(urdf), '--tip-frame',
                       'tool', '--command-topic', COMMAND_TOPIC, '--horizon', '25',
                       *fast]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1, error
    assert 'the machine map needs at least' in error and '--no-machine-map' in error
    assert not (tmp_path / 'm.pt').exists()
