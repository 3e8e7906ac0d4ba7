# SPDX-License-Identifier: Apache-2.0
"""kinematics_node's statuses read directly (no /diagnostics round trip): a rejection is
said once, in the report after it; the unconfigured node says what it waits for; the
commanded joints have a status only with `command_topic`."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from ros_helpers import RosHarness
from sensor_msgs.msg import JointState

from lompr_predictor.monitoring import Level
from lompr_predictor.robot.description import MEASURED_JOINTS, RobotDescription
from lompr_predictor.robot.kinematics import inverse_kinematics
from lompr_predictor.ros.kinematics_node import KinematicsNode

pytestmark = pytest.mark.ros


def joint_state(stamp_s: float, positions: list[float]) -> bytes:
    msg = JointState(name=list(MEASURED_JOINTS), position=positions)
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(stamp_s), round(stamp_s % 1 * 1e9)
    return serialize_message(msg)


def node(ros: RosHarness, name: str, **values: object) -> KinematicsNode:
    return ros.add(KinematicsNode(name, context=ros.context, parameter_overrides=[
        Parameter(key, value=value) for key, value in values.items()]))


def test_a_rejection_is_said_once_then_the_rate_again(
        ros: RosHarness, description: RobotDescription) -> None:
    kinematics = node(ros, 'diagnosed_kinematics')
    centre = np.array([[0.0, 0.0, 1.097]])
    joints = inverse_kinematics(description.geometry, centre).joints[0].tolist()
    kinematics.on_joint_state(joint_state(5.0, joints))
    kinematics.on_joint_state(joint_state(5.04, [math.nan, *joints[1:]]))
    statuses = kinematics.statuses
    first = statuses.input_status()
    assert (first.level, first.message) == (
        Level.WARN, '1 joint states rejected since the last report (totals non_finite: 1)')
    assert (first.values['received_total'], first.values['rejected.non_finite']) == (2, 1)
    kinematics.on_joint_state(joint_state(5.08, joints))
    second = statuses.input_status()
    assert second.level == Level.OK and second.message.endswith(' Hz')
    assert second.values['received_total'] == 3 and second.values['rejected.non_finite'] == 1
    solved = statuses.kinematics_status()
    assert kinematics.chain is not None and solved.values['published_total'] == 2
    assert solved.values['robot_description_sha256'] == kinematics.chain.sha256


def test_an_unconfigured_node_says_what_it_waits_for(ros: RosHarness) -> None:
    waiting = node(ros, 'waiting_kinematics', autostart=False, command_topic='joint_commands')
    statuses = waiting.statuses
    assert statuses.input_status().message == 'unconfigured: joint states not answered'
    kinematics = statuses.kinematics_status()
    assert (kinematics.level, kinematics.message) == (Level.WARN,
                                                      'unconfigured: waiting for configure')
    commands = statuses.commands_status()
    assert (commands.level, commands.message) == (
        Level.WARN, 'unconfigured: commanded joints not answered')
    described = node(ros, 'described_kinematics', autostart=False,
                     robot_description_topic='robot_description')
    assert described.statuses.kinematics_status().message == (
        'unconfigured: waiting for the robot description on /robot_description')
