# SPDX-License-Identifier: Apache-2.0
"""command_compensator_node on ROS: the twin arm's commands and the predictor's offsets in,
the compensated JointState and the forward controller's Float64MultiArray out; bad input
passed unchanged and counted on /diagnostics; the LOMPR refused at configure."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Vector3Stamped
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from ros_helpers import RosHarness, latest_status, set_stamp, stamp_ns
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from lompr_predictor.online.command_compensation import CommandPathError
from lompr_predictor.robot.chain import SerialChain, load_chain
from lompr_predictor.ros.command_compensator_node import CommandCompensatorNode
from lompr_predictor.twin.arm import arm_description_path, arm_spec

pytestmark = pytest.mark.ros

PERIOD_NS = 4_000_000
T0 = 1_700_000_000_000_000_000
Q = (2.90554713, -1.18873611, 1.90415391, -2.28621412, -1.57079633, -0.23604553)
#: The offset of each instant; instant 2 has none.
OFFSETS = {0: (1e-4, 0.0), 1: (0.0, -2e-4), 3: (-1.5e-4, 1e-4), 4: (2e-4, 2e-4)}


def node_parameters(**extra: Any) -> list[Parameter]:
    values = {'robot_description_file': str(arm_description_path()),
              'base_frame': 'arm_base', 'tip_frame': 'tool0', 'diagnostics_period': 0.1,
              **extra}
    return [Parameter(name, value=value) for name, value in values.items()]


def offset(k: int, xy: tuple[float, float], frame: str = 'arm_base') -> Vector3Stamped:
    msg = Vector3Stamped()
    msg.header.frame_id = frame
    msg.vector.x, msg.vector.y = xy
    set_stamp(msg, T0 + k * PERIOD_NS)
    return msg


def command(k: int, names: list[str], positions: list[float]) -> JointState:
    msg = JointState(name=names, position=positions, velocity=[0.5] * len(names))
    set_stamp(msg, T0 + k * PERIOD_NS)
    return msg


def inputs_of(ros: RosHarness) -> tuple[Publisher, Publisher]:
    """Publishers of the node's offsets and commands, each matched with the node."""
    offsets_out = ros.node.create_publisher(Vector3Stamped, '/lompr/compensation', 100)
    commands_out = ros.node.create_publisher(JointState, '/joint_commands', 100)
    for publisher in (offsets_out, commands_out):
        ros.wait_for_subscribers(publisher)
    return offsets_out, commands_out


def test_commands_come_out_compensated_on_both_topics(ros: RosHarness) -> None:
    chain = load_chain(arm_spec())
    assert isinstance(chain, SerialChain)
    order = list(reversed(chain.joint_names))
    node = ros.add(CommandCompensatorNode(context=ros.context, parameter_overrides=node_parameters(
        controller_joints=order)))
    assert node.lifecycle_state == 'active'
    states = ros.collect('/joint_commands_compensated', JointState, 100)
    arrays = ros.collect('/forward_position_controller/commands', Float64MultiArray, 100)
    diagnostics = ros.collect('/diagnostics', DiagnosticArray, 100)
    offsets_out, commands_out = inputs_of(ros)
    ros.wait_for_publishers('/forward_position_controller/commands')
    for k, xy in OFFSETS.items():
        offsets_out.publish(offset(k, xy))
    offsets_out.publish(offset(2, (1e-4, 0.0), frame='world'))  # dropped: not the arm's frame
    ros.spin_until(lambda: node.offset_rate.total == len(OFFSETS) + 1, what='the offsets')
    names = ['gripper', *chain.joint_names]
    for k in range(5):
        commands_out.publish(command(k, names, [0.04, *Q]))
    commands_out.publish(command(5, names, [0.04, *Q[:3], math.nan, *Q[4:]]))  # bad input
    ros.spin_until(lambda: len(states) == 6 and len(arrays) == 5, what='every answer')
    assert [stamp_ns(m) for m in states] == [T0 + k * PERIOD_NS for k in range(6)]
    assert all(list(m.name) == names and m.velocity[0] == 0.5 for m in states)
    base = chain.tool_positions(np.array([Q]))[0][0]
    for k in range(5):
        joints = np.array(states[k].position[1:])
        assert states[k].position[0] == 0.04
        np.testing.assert_array_equal(arrays[k].data, joints[::-1])  # the controller's order
        moved = chain.tool_positions(joints[None])[0][0] - base
        np.testing.assert_allclose(moved[:2], OFFSETS.get(k, (0.0, 0.0)), rtol=0, atol=1e-7)
    assert tuple(states[2].position[1:]) == Q  # no offset: the command, bit for bit
    assert math.isnan(states[5].position[4])  # bad: passed unchanged, not to the controller
    ros.spin_until(lambda: (latest_status(diagnostics, f'{node.get_name()}: command path')
                            or {}).get('passed_total') == '6', what='the counts')
    status = latest_status(diagnostics, f'{node.get_name()}: command path')
    assert status is not None
    assert {key: status[key] for key in ('commands.compensated', 'commands.no_offset',
                                         'commands.non_finite', 'bad_input_total', 'clamped',
                                         'offsets_dropped.wrong_frame')} == {
        'commands.compensated': '4', 'commands.no_offset': '1', 'commands.non_finite': '1',
        'bad_input_total': '1', 'clamped': '0', 'offsets_dropped.wrong_frame': '1'}
    assert status['last_problem'].endswith('passed unchanged: non-finite joint(s) '
                                           'wrist_1_joint')


def test_offsets_after_their_command_are_the_receivers_lateness_on_diagnostics(
        ros: RosHarness) -> None:
    """An offset that comes after the command of its instant is one the controller ran
    without: the status warns with how many since the last report, then is OK again."""
    chain = load_chain(arm_spec())
    node = ros.add(CommandCompensatorNode(context=ros.context,
                                          parameter_overrides=node_parameters()))
    states = ros.collect('/joint_commands_compensated', JointState, 100)
    diagnostics = ros.collect('/diagnostics', DiagnosticArray, 100)
    offsets_out, commands_out = inputs_of(ros)
    for k in range(3):
        commands_out.publish(command(k, list(chain.joint_names), list(Q)))
    ros.spin_until(lambda: len(states) == 3, what='the commands')
    for k in (0, 1):  # both instants already commanded
        offsets_out.publish(offset(k, (1e-4, 0.0)))
    ros.spin_until(lambda: node.offset_rate.total == 2, what='the late offsets')
    name = f'{node.get_name()}: command path'
    ros.spin_until(lambda: (latest_status(diagnostics, name) or {}).get(
        'offsets_dropped.late') == '2', what='the late count')
    warned = latest_status(diagnostics, name)
    assert warned is not None
    assert warned['_message'] == ('2 offset(s) came after their command since the last '
                                  'report: those commands ran without them')
    assert warned['_level'] == DiagnosticStatus.WARN and warned['commands.no_offset'] == '3'
    ros.spin_until(lambda: (latest_status(diagnostics, name) or {}).get('_level')
                   == DiagnosticStatus.OK, what='the next report')
    again = latest_status(diagnostics, name)
    assert again is not None and again['offsets_dropped.late'] == '2'


def test_a_command_ahead_of_its_offset_waits_for_it_but_never_for_a_stopped_predictor(
        ros: RosHarness) -> None:
    """Offsets and commands from two processes come in no set order: a command whose
    offset is due waits for it (up to offset_wait) and goes out compensated; one whose offset
    never comes goes out unchanged after the wait, and the next is not held."""
    chain = load_chain(arm_spec())
    node = ros.add(CommandCompensatorNode(context=ros.context,
                                          parameter_overrides=node_parameters(offset_wait=0.5)))
    states = ros.collect('/joint_commands_compensated', JointState, 100)
    diagnostics = ros.collect('/diagnostics', DiagnosticArray, 100)
    offsets_out, commands_out = inputs_of(ros)
    names, base = list(chain.joint_names), chain.tool_positions(np.array([Q]))[0][0]
    offsets_out.publish(offset(0, (1e-4, 0.0)))
    ros.spin_until(lambda: node.offset_rate.total == 1, what='the first offset')
    commands_out.publish(command(0, names, list(Q)))
    ros.spin_until(lambda: len(states) == 1, what='the first command')
    commands_out.publish(command(1, names, list(Q)))  # ahead of its offset
    ros.spin_until(lambda: node.held == 1, what='the command held')
    ros.spin_for(0.1)
    assert len(states) == 1
    offsets_out.publish(offset(1, (-2e-4, 1e-4)))
    ros.spin_until(lambda: len(states) == 2, what='the held command')
    moved = chain.tool_positions(np.array([states[1].position]))[0][0] - base
    np.testing.assert_allclose(moved[:2], (-2e-4, 1e-4), rtol=0, atol=1e-7)
    commands_out.publish(command(2, names, list(Q)))  # its offset never comes
    ros.spin_until(lambda: len(states) == 3, what='the command after its wait')
    assert tuple(states[2].position) == Q and node.held_in_vain == 1
    commands_out.publish(command(3, names, list(Q)))  # the offsets fell behind: no wait
    ros.spin_until(lambda: len(states) == 4, what='the next command')
    name = f'{node.get_name()}: command path'
    ros.spin_until(lambda: (latest_status(diagnostics, name) or {}).get('passed_total') == '4',
                   what='the counts')
    status = latest_status(diagnostics, name)
    assert status is not None
    assert {key: status[key] for key in ('commands_held', 'held_in_vain', 'commands.compensated',
                                         'commands.no_offset', 'offsets_dropped.late')} == {
        'commands_held': '2', 'held_in_vain': '1', 'commands.compensated': '2',
        'commands.no_offset': '2', 'offsets_dropped.late': '0'}


def test_the_lompr_is_refused_at_configure_in_one_line(ros: RosHarness) -> None:
    with pytest.raises(CommandPathError, match=r'^robot description .*lompr\.urdf is the LOMPR '
                                               'closed chain, commanded in tool tips'):
        CommandCompensatorNode(context=ros.context)


def test_unknown_controller_joints_are_refused_at_configure(ros: RosHarness) -> None:
    node = ros.add(CommandCompensatorNode(context=ros.context, parameter_overrides=(
        node_parameters(autostart=False, controller_joints=['gripper']))))
    assert node.lifecycle_state == 'unconfigured'
    node.trigger_configure()
    assert node.lifecycle_state == 'unconfigured'
    assert node.configure_error is not None
    assert node.configure_error.startswith('controller joint(s) gripper: each must be one of')


def test_the_arm_description_can_come_on_a_topic(ros: RosHarness) -> None:
    """With robot_description_topic and no file the node waits for the arm's URDF as
    robot_state_publisher shares it, then configures on it (the same chain as the file's)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = ros.node.create_publisher(String, '/robot_description', latched)
    publisher.publish(String(data=arm_description_path().read_text(encoding='utf-8')))
    parameters = [p for p in node_parameters(robot_description_topic='/robot_description')
                  if p.name != 'robot_description_file']
    node = ros.add(CommandCompensatorNode(context=ros.context, parameter_overrides=parameters))
    ros.spin_until(lambda: node.active, what='configured on the description received')
    assert node.core is not None
    assert node.core.chain.sha256 == load_chain(arm_spec()).sha256
