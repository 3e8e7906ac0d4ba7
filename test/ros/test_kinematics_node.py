# SPDX-License-Identifier: Apache-2.0
"""kinematics_node in the test process: IK joints in, the same poses out to 1e-9 m; bad
inputs dropped, counted by reason in /diagnostics, and the node keeps answering."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.exceptions import InvalidParameterValueException
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter
from ros_helpers import RosHarness, latest_status
from sensor_msgs.msg import JointState

from lompr_predictor.errors import RobotDescriptionError
from lompr_predictor.robot.description import MEASURED_JOINTS, ROBOT_FRAME, RobotDescription
from lompr_predictor.robot.kinematics import inverse_kinematics
from lompr_predictor.ros.kinematics_node import JointStateDrop, KinematicsNode

pytestmark = pytest.mark.ros

MIRROR_Z = 1.097
#: Known tool-tip poses: centre, the spiral's start, the mirror's rim, z at both ends of
#: the +-0.05 m band.
KNOWN_TIPS = np.array([
    [0.0, 0.0, MIRROR_Z],
    [0.0, 0.02, MIRROR_Z],
    [0.2, 0.0, MIRROR_Z],
    [-0.1, 0.15, MIRROR_Z + 0.05],
    [0.12, -0.16, MIRROR_Z - 0.05],
    [-0.2 / math.sqrt(2), -0.2 / math.sqrt(2), MIRROR_Z],
])


def joint_state(stamp_s: float, positions: Sequence[float],
                names: Sequence[str] = MEASURED_JOINTS) -> JointState:
    msg = JointState(name=list(names), position=[float(p) for p in positions])
    msg.header.stamp.sec = int(stamp_s)
    msg.header.stamp.nanosec = round((stamp_s - int(stamp_s)) * 1e9)
    return msg


def stamp_of(msg: JointState | PoseStamped) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


class Wiring:
    """A kinematics node plus the test's publisher and collectors, discovery done."""

    def __init__(self, ros: RosHarness, name: str = 'kinematics_node',
                 **overrides: object) -> None:
        parameters = {'diagnostics_period': 0.1, **overrides}
        self.ros, self.name = ros, name
        self.node = ros.add(KinematicsNode(name, context=ros.context, parameter_overrides=[
            Parameter(key, value=value) for key, value in parameters.items()]))
        self.poses: list[PoseStamped] = ros.collect('/lompr/end_pose', PoseStamped, 100)
        self.diagnostics: list[DiagnosticArray] = ros.collect('/diagnostics', DiagnosticArray)
        self.publisher = ros.node.create_publisher(JointState, '/joint_states', 100)
        if self.node.active:  # else its endpoints come with configure
            self.discover()

    def discover(self) -> None:
        self.ros.wait_for_subscribers(self.publisher)
        self.ros.wait_for_publishers('/lompr/end_pose')

    def publish(self, messages: Sequence[JointState]) -> None:
        for msg in messages:
            self.publisher.publish(msg)

    def status(self, name: str) -> dict[str, Any] | None:
        """Key-values of the latest status `<node>: <name>`, or None yet."""
        return latest_status(self.diagnostics, f'{self.name}: {name}')


def test_known_poses_round_trip_with_same_stamp(
        ros: RosHarness, description: RobotDescription) -> None:
    wiring = Wiring(ros, solve_time_warn=10.0)  # the level must not depend on the load
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS).joints
    sent = [joint_state(1000.0 + 0.04 * i, row) for i, row in enumerate(joints)]
    wiring.publish(sent)
    ros.spin_until(lambda: len(wiring.poses) == len(sent), what='an end pose per joint state')
    for msg, pose, tip in zip(sent, wiring.poses, KNOWN_TIPS, strict=False):
        assert stamp_of(pose) == stamp_of(msg)
        assert pose.header.frame_id == ROBOT_FRAME
        position = pose.pose.position
        np.testing.assert_allclose([position.x, position.y, position.z], tip, rtol=0, atol=1e-9)
        q = pose.pose.orientation
        # The tool axis (rotated z) is vertical: R[2, 2] = 1 - 2 (x^2 + y^2).
        assert 1.0 - 2.0 * (q.x ** 2 + q.y ** 2) == pytest.approx(1.0, abs=1e-9)
    ros.spin_until(lambda: (wiring.status('forward kinematics') or {}).get(
        'published_total') == str(len(sent)), what='diagnostics counting the poses')
    kinematics = wiring.status('forward kinematics')
    assert kinematics is not None and kinematics['_level'] == DiagnosticStatus.OK
    assert 0.0 < float(kinematics['solve_time_p50_us']) <= float(kinematics['solve_time_p99_us'])
    assert kinematics['robot_description_sha256'] == description.sha256


def test_a_frame_prefix_keeps_a_cells_frames_apart(
        ros: RosHarness, description: RobotDescription) -> None:
    """As robot_state_publisher's frame_prefix: the end pose is in <prefix>lompr_base."""
    wiring = Wiring(ros, frame_prefix='cell1/')
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS[:1]).joints
    wiring.publish([joint_state(3.0, joints[0])])
    ros.spin_until(lambda: len(wiring.poses) == 1, what='the end pose')
    assert wiring.poses[0].header.frame_id == f'cell1/{ROBOT_FRAME}'
    assert wiring.node.settings.frame == f'cell1/{ROBOT_FRAME}'


def test_bad_inputs_are_dropped_counted_and_next_good_answered(
        ros: RosHarness, description: RobotDescription) -> None:
    wiring = Wiring(ros)
    geometry = description.geometry
    good = inverse_kinematics(geometry, KNOWN_TIPS[[1, 3, 4]]).joints
    names = list(MEASURED_JOINTS)
    shuffled_order = [4, 2, 0, 3, 1]
    too_long = good[0].copy()
    too_long[1] = geometry.stroke_upper[1] + 0.01
    nan = good[0].copy()
    nan[3] = math.nan
    unstamped = joint_state(0.0, good[0])
    sent = [
        joint_state(10.00, good[0]),                                       # answered
        joint_state(10.04, nan),                                           # non_finite
        joint_state(10.08, good[0][:4], names[:4]),                        # missing_joint
        joint_state(10.12, [*good[1][shuffled_order], 0.3],                # answered
                    [names[i] for i in shuffled_order] + ['spindle']),
        joint_state(10.16, too_long),                                      # stroke_limit
        joint_state(10.20, good[1][:3], names),                            # malformed
        unstamped,                                                         # unstamped
        joint_state(12.00, [math.inf, *good[2][1:]]),                      # non_finite
        joint_state(12.04, good[2]),                                       # answered
    ]
    wiring.publish(sent)
    ros.spin_until(lambda: len(wiring.poses) == 3, what='the three good samples answered')
    assert [stamp_of(p) for p in wiring.poses] == [stamp_of(sent[i]) for i in (0, 3, 8)]
    for pose, tip in zip(wiring.poses, KNOWN_TIPS[[1, 3, 4]], strict=False):
        position = pose.pose.position
        np.testing.assert_allclose([position.x, position.y, position.z], tip, rtol=0, atol=1e-9)

    expected = {'non_finite': 2, 'missing_joint': 1, 'stroke_limit': 1, 'malformed': 1,
                'unstamped': 1}
    ros.spin_until(lambda: (wiring.status('joint states') or {}).get('received_total')
                   == str(len(sent)), what='diagnostics of all joint states')
    inputs = wiring.status('joint states')
    assert inputs is not None
    assert inputs['rejected_total'] == str(sum(expected.values()))
    assert {reason: int(inputs[f'rejected.{reason}']) for reason in JointStateDrop} == {
        reason: expected.get(reason, 0) for reason in JointStateDrop}
    assert wiring.node.rejected.counts() == {r: expected.get(r, 0) for r in JointStateDrop}
    # The 1.84 s gap between 10.16 and 12.00 restarted the warm start once (each status
    # comes in its own array: the next forward kinematics status after the last sample).
    ros.spin_until(lambda: (wiring.status('forward kinematics') or {}).get(
        'published_total') == '3', what='diagnostics of the three solves')
    kinematics = wiring.status('forward kinematics')
    assert kinematics is not None and kinematics['warm_start_resets'] == '1'


def test_a_dropped_joint_state_brings_its_status_out_of_its_turn(
        ros: RosHarness, description: RobotDescription) -> None:
    """With a round of 50 s no status is read in its turn here: the drop asks for the
    'joint states' status, which goes once the next good sample is answered."""
    wiring = Wiring(ros, diagnostics_period=50.0)
    good = inverse_kinematics(description.geometry, KNOWN_TIPS[:2]).joints
    nan = good[0].copy()
    nan[2] = math.nan
    ros.spin_for(0.3)  # the statuses sent at the start
    first = len(wiring.diagnostics)
    wiring.publish([joint_state(20.00, good[0]), joint_state(20.04, nan),
                    joint_state(20.08, good[1])])
    ros.spin_until(lambda: len(wiring.poses) == 2, what='the two good samples answered')
    ros.spin_until(lambda: len(wiring.diagnostics) > first, what='a status out of turn')
    ros.spin_for(0.2)
    sent = [array.status[0] for array in wiring.diagnostics[first:]]
    assert [status.name for status in sent] == ['kinematics_node: joint states']
    assert sent[0].level == DiagnosticStatus.WARN


def test_unreadable_bytes_are_malformed_and_next_good_answered(
        ros: RosHarness, description: RobotDescription) -> None:
    """The node takes joint states raw (`ros.wire`): bytes that are no JointState are
    rejected as malformed, the stream goes on."""
    wiring = Wiring(ros)
    good = inverse_kinematics(description.geometry, KNOWN_TIPS[:1]).joints[0]
    wiring.publisher.publish(b'\x00\x01\x00\x00' + b'\xff' * 40)  # a name 4 GB long
    wiring.publish([joint_state(5.0, good)])
    ros.spin_until(lambda: len(wiring.poses) == 1, what='the good sample answered')
    assert stamp_of(wiring.poses[0]) == (5, 0)
    assert wiring.node.rejected.counts()['malformed'] == 1


def test_solve_times_over_the_threshold_warn(
        ros: RosHarness, description: RobotDescription) -> None:
    wiring = Wiring(ros, solve_time_warn=1e-6)  # no solve takes under a microsecond
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS[:2]).joints
    wiring.publish([joint_state(3.0 + 0.04 * i, row) for i, row in enumerate(joints)])
    ros.spin_until(lambda: (wiring.status('forward kinematics') or {}).get(
        'published_total') == '2', what='diagnostics of both solves')
    kinematics = wiring.status('forward kinematics')
    assert kinematics is not None and kinematics['_level'] == DiagnosticStatus.WARN
    assert str(kinematics['_message']).endswith('(over 1 us)')


def test_renamed_joints_and_bad_joint_names_parameter(
        ros: RosHarness, description: RobotDescription) -> None:
    renamed = ['l1', 'l2', 'l3', 'c_axis', 'a_axis']
    wiring = Wiring(ros, joint_names=renamed)
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS[:2]).joints
    wiring.publish([joint_state(5.0, joints[0], renamed),
                    joint_state(5.04, joints[1], MEASURED_JOINTS)])  # default names: missing
    ros.spin_until(lambda: wiring.node.input_rate.total == 2, what='both joint states')
    ros.spin_until(lambda: len(wiring.poses) == 1, what='the renamed sample answered')
    np.testing.assert_allclose(
        [wiring.poses[0].pose.position.x, wiring.poses[0].pose.position.y], KNOWN_TIPS[0, :2],
        atol=1e-9)
    assert wiring.node.rejected['missing_joint'] == 1
    # Runtime-changeable parameters reach the settings snapshot; read-only ones are refused.
    node = wiring.node
    assert node.set_parameters([Parameter('warm_start_max_gap', value=2.0)])[0].successful
    assert node.settings.warm_start_max_gap == 2.0
    assert node.limits.warm_start_max_gap == 2.0  # what each sample is judged by, taken
    assert not node.set_parameters([Parameter('frame_id', value='base')])[0].successful
    assert node.settings.frame_id == ROBOT_FRAME
    with pytest.raises(InvalidParameterValueException, match='needs distinct, non-empty'):
        KinematicsNode(node_name='bad_names', context=ros.context, parameter_overrides=[
            Parameter('joint_names', value=['a', 'a', 'b', 'c', 'd'])])
    # how many the robot's chain says: the LOMPR measures five
    with pytest.raises(RobotDescriptionError, match='a,b,c,d: needs 5 distinct names'):
        KinematicsNode(node_name='four_names', context=ros.context, parameter_overrides=[
            Parameter('joint_names', value=['a', 'b', 'c', 'd'])])


def test_a_sensor_data_publisher_is_heard_by_default(
        ros: RosHarness, description: RobotDescription) -> None:
    """A robot driver may publish joint states best-effort (sensor-data QoS), which a
    reliable subscription never hears: the default input QoS hears it."""
    from rclpy.qos import qos_profile_sensor_data

    node = ros.add(KinematicsNode(context=ros.context))
    poses: list[PoseStamped] = ros.collect('/lompr/end_pose', PoseStamped, 100)
    publisher = ros.node.create_publisher(JointState, '/joint_states', qos_profile_sensor_data)
    ros.wait_for_subscribers(publisher)
    ros.wait_for_publishers('/lompr/end_pose')
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS[:2]).joints
    for i, row in enumerate(joints):
        publisher.publish(joint_state(2000.0 + 0.04 * i, row))
    ros.spin_until(lambda: len(poses) == 2, what='end poses of best-effort joint states')
    assert node.rejected.total == 0


def test_input_qos_is_overridable_by_parameters(ros: RosHarness) -> None:
    """QoS comes from rclpy's QoSOverridingOptions: `qos_overrides.<topic>.<kind>.<policy>`,
    read-only parameters, reach the middleware (the graph reports the endpoint's QoS)."""
    from rclpy.qos import ReliabilityPolicy

    node = ros.add(KinematicsNode(context=ros.context, parameter_overrides=[
        Parameter('qos_overrides./joint_states.subscription.reliability', value='reliable'),
        Parameter('qos_overrides./joint_states.subscription.depth', value=5),
        Parameter('qos_overrides./lompr/end_pose.publisher.reliability',
                  value='best_effort')]))

    def graph(kind: str, topic: str) -> list[ReliabilityPolicy]:
        infos = (node.get_subscriptions_info_by_topic(topic) if kind == 'subscription'
                 else node.get_publishers_info_by_topic(topic))
        return [info.qos_profile.reliability for info in infos
                if info.node_name == 'kinematics_node']

    ros.spin_until(lambda: graph('subscription', '/joint_states') == [
        ReliabilityPolicy.RELIABLE], what='a reliable joint state subscription in the graph')
    assert graph('publisher', '/lompr/end_pose') == [ReliabilityPolicy.BEST_EFFORT]
    assert node._subscription is not None and node._subscription.qos_profile.depth == 5
    assert not node.set_parameters([Parameter(
        'qos_overrides./joint_states.subscription.depth', value=50)])[0].successful


# -- faults: duplicate joints and impossible stamps -----------------------------------------

@pytest.mark.faults
def test_duplicate_joint_names_and_impossible_stamps_are_rejected_and_counted(
        ros: Any, description: RobotDescription) -> None:
    from test_kinematics_node import KNOWN_TIPS, Wiring, joint_state

    from lompr_predictor.robot.description import MEASURED_JOINTS
    from lompr_predictor.robot.kinematics import inverse_kinematics

    wiring = Wiring(ros)
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS[:1]).joints[0]
    now = wiring.node.clock_ns() * 1e-9
    twice = joint_state(now, [*joints, 0.7], [*MEASURED_JOINTS, MEASURED_JOINTS[0]])
    future = joint_state(now + 3600.0, joints)
    negative = joint_state(now, joints)
    negative.header.stamp.sec = -3
    unnormalised = joint_state(now, joints)
    unnormalised.header.stamp.nanosec = 1_500_000_000
    wiring.publish([twice, future, negative, unnormalised, joint_state(now, joints)])
    ros.spin_until(lambda: len(wiring.poses) == 1 and wiring.node.rejected.total == 4,
                   what='one pose, four rejections')
    counts = wiring.node.rejected.counts()
    assert (counts['duplicate_joint'], counts['future_stamp'], counts['bad_stamp']) == (1, 1, 2)


def test_a_lifecycle_manager_brings_it_up_and_down(
        ros: RosHarness, description: RobotDescription, tmp_path: Path) -> None:
    """With autostart false the node waits unconfigured (no endpoints, a WARN status);
    configured but inactive its joint states are counted as dropped; activated it answers;
    deactivated it drops again; cleaned up it lets the robot go; a robot that cannot be
    loaded leaves it unconfigured with the reason at ERROR."""
    wiring = Wiring(ros, autostart=False)
    node = wiring.node
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS[:2]).joints
    assert node.lifecycle_state == 'unconfigured' and node.chain is None
    ros.spin_until(lambda: (wiring.status('joint states') or {}).get('_message')
                   == 'unconfigured: joint states not answered', what='the unconfigured status')
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    wiring.discover()
    wiring.publish([joint_state(20.0, joints[0])])
    ros.spin_until(lambda: node.dropped_inactive == 1, what='a joint state dropped')
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    wiring.publish([joint_state(20.04, joints[1])])
    ros.spin_until(lambda: len(wiring.poses) == 1, what='the end pose once active')
    position = wiring.poses[0].pose.position
    np.testing.assert_allclose([position.x, position.y, position.z], KNOWN_TIPS[1], atol=1e-9)
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    wiring.publish([joint_state(20.08, joints[0])])
    ros.spin_until(lambda: node.dropped_inactive == 2, what='a joint state dropped again')
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert node.chain is None and node.measured is None and len(wiring.poses) == 1

    broken = tmp_path / 'broken.urdf'
    broken.write_text('<robot name="broken"><link name="a"/>')
    refused = Wiring(ros, 'refused_kinematics', autostart=False,
                     robot_description_file=str(broken))
    assert refused.node.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert refused.node.lifecycle_state == 'unconfigured'
    assert 'cannot parse robot description' in (refused.node.configure_error or '')
    ros.spin_until(lambda: (refused.status('forward kinematics') or {}).get('_level')
                   == DiagnosticStatus.ERROR, what='the configure error on /diagnostics')


def test_the_robot_description_can_come_on_a_topic(
        ros: RosHarness, description: RobotDescription) -> None:
    """With robot_description_topic and no file the node waits unconfigured for the URDF
    robot_state_publisher shares (transient local), then configures on it and answers: the
    same text as the packaged file, the same sha256."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from lompr_predictor.robot.description import default_description_path

    wiring = Wiring(ros, robot_description_topic='robot_description')
    node = wiring.node
    assert node.lifecycle_state == 'unconfigured'
    ros.spin_until(lambda: (wiring.status('forward kinematics') or {}).get('_message')
                   == 'unconfigured: waiting for the robot description on /robot_description',
                   what='the node waiting for its description')
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = ros.node.create_publisher(String, 'robot_description', latched)
    publisher.publish(String(data=default_description_path().read_text(encoding='utf-8')))
    ros.spin_until(lambda: node.active, what='configured and active on the description')
    assert node.chain is not None and node.chain.sha256 == description.sha256
    assert node.chain.source == 'topic /robot_description'
    wiring.discover()
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS[:1]).joints
    wiring.publish([joint_state(30.0, joints[0])])
    ros.spin_until(lambda: len(wiring.poses) == 1, what='an end pose')
    position = wiring.poses[0].pose.position
    np.testing.assert_allclose([position.x, position.y, position.z], KNOWN_TIPS[0], atol=1e-9)
