# SPDX-License-Identifier: Apache-2.0
"""Every joint of the URDF for robot_state_publisher: the passive joints from the forward
kinematics close each UPS branch (its rod end meets its platform anchor), and
kinematics_node publishes them only when asked to."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from rclpy.parameter import Parameter
from ros_helpers import RosHarness, set_stamp
from sensor_msgs.msg import JointState

from lompr_predictor.robot.description import (
    BRANCH_JOINTS,
    MEASURED_JOINTS,
    RobotDescription,
    load_robot_description,
)
from lompr_predictor.robot.kinematics import AllJoints, ForwardKinematics, inverse_kinematics
from lompr_predictor.ros.kinematics_node import KinematicsNode

TIPS = np.array([[0.0, 0.0, 1.097], [0.15, -0.1, 1.06], [-0.12, 0.14, 1.14]])


def configuration(description: RobotDescription, names: tuple[str, ...],
                  positions: list[float]) -> np.ndarray:
    """A Pinocchio configuration from joint positions by name (continuous joints as cos/sin)."""
    model = description.model
    q = pin.neutral(model)
    for name, value in zip(names, positions, strict=True):
        joint = model.joints[model.getJointId(name)]
        if joint.nq == 2:
            q[joint.idx_q:joint.idx_q + 2] = np.cos(value), np.sin(value)
        else:
            q[joint.idx_q] = value
    return q


def test_the_passive_joints_close_every_branch(description: RobotDescription) -> None:
    fk, all_joints = ForwardKinematics(description), AllJoints(description)
    model = description.model
    data = model.createData()
    assert set(all_joints.names) == set(model.names[1:]) and set(MEASURED_JOINTS) <= set(
        all_joints.names)
    for joints in inverse_kinematics(description.geometry, TIPS).joints:
        pose = fk.solve(joints)
        positions = all_joints.positions(fk.last_up, joints)
        pin.framesForwardKinematics(model, data, configuration(
            description, all_joints.names, positions))
        for branch in BRANCH_JOINTS:
            rod_end = data.oMi[model.getJointId(branch)].translation
            anchor = data.oMf[model.getFrameId(f'{branch}_platform_anchor')].translation
            np.testing.assert_allclose(rod_end, anchor, atol=1e-9)
        tool = data.oMf[model.getFrameId('tool_tip')].translation
        np.testing.assert_allclose(tool, pose.position, atol=1e-12)


@pytest.mark.ros
def test_kinematics_node_publishes_every_joint_only_when_asked(ros: RosHarness) -> None:
    plain = ros.add(KinematicsNode('plain_kinematics', context=ros.context,
                                   namespace='plain'))
    assert '/plain/lompr/full_joint_states' not in {
        name for name, _ in plain.get_publisher_names_and_types_by_node(
            'plain_kinematics', '/plain')}
    ros.add(KinematicsNode(context=ros.context, parameter_overrides=[
        Parameter('publish_full_joint_state', value=True)]))
    received = ros.collect('/lompr/full_joint_states', JointState)
    joints = ros.node.create_publisher(JointState, '/joint_states', 10)
    ros.wait_for_subscribers(joints)
    ros.wait_for_publishers('/lompr/full_joint_states')
    measured = [float(v) for v in inverse_kinematics(
        load_robot_description().geometry, TIPS[1:2]).joints[0]]
    message = JointState(name=list(MEASURED_JOINTS), position=measured)
    set_stamp(message, 1_700_000_000 * 10**9)
    joints.publish(message)
    ros.spin_until(lambda: len(received) == 1, what='a full joint state')
    full = dict(zip(received[0].name, received[0].position, strict=True))
    assert len(full) == len(load_robot_description().model.names) - 1
    assert [full[name] for name in MEASURED_JOINTS] == pytest.approx(measured)
    assert received[0].header.stamp.sec == 1_700_000_000
