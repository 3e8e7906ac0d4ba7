# SPDX-License-Identifier: Apache-2.0
"""The robot as a chain (`robot.chain`): the LOMPR's closed chain chosen from its
description, any serial chain solved by Pinocchio against kinematics by hand, and every way a
user's robot can be named wrong refused in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from robots import ARM_URDF, AXIS_URDF, arm_joints, arm_tip, write_urdf

from lompr_predictor.errors import JointLimitError, RobotDescriptionError
from lompr_predictor.robot.chain import (
    LOMPR_KIND,
    SERIAL_KIND,
    LomprChain,
    RobotSpec,
    description_sha256,
    load_chain,
    spec_with_model,
)
from lompr_predictor.robot.description import MEASURED_JOINTS, RobotDescription
from lompr_predictor.robot.kinematics import NonFiniteJointError, inverse_kinematics


@pytest.fixture(scope='module')
def arm_urdf(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_urdf(tmp_path_factory.mktemp('arm'), 'arm.urdf', ARM_URDF)


def test_the_packaged_description_is_the_lompr_closed_chain(
        description: RobotDescription) -> None:
    chain = load_chain()
    assert isinstance(chain, LomprChain)
    assert (chain.kind, chain.base_frame, chain.tip_frame) == (LOMPR_KIND, 'lompr_base',
                                                              'tool_tip')
    assert chain.joints == chain.joint_names == MEASURED_JOINTS
    assert chain.sha256 == description.sha256 == description_sha256()
    assert chain.actuators == ('ups1', 'ups2', 'ups3')
    # its solver is the LOMPR's: the tips of known postures come back to 1e-9 m
    tips = np.array([[0.1, -0.05, 1.097], [-0.15, 0.12, 1.12]])
    joints = inverse_kinematics(description.geometry, tips).joints
    positions, valid = chain.tool_positions(joints)
    assert valid.all()
    np.testing.assert_allclose(positions, tips, rtol=0, atol=1e-9)
    np.testing.assert_allclose(chain.solver().solve(joints[1]).position, tips[1], atol=1e-9)


def test_a_renamed_lompr_keeps_its_joints_and_refuses_other_frames() -> None:
    names = ('b1', 'b2', 'b3', 'c', 'a')
    chain = load_chain(RobotSpec(joint_names=names))
    assert chain.joint_names == names and chain.joints == MEASURED_JOINTS
    with pytest.raises(RobotDescriptionError, match="tip frame is 'tool_tip'; got 'flange'"):
        load_chain(RobotSpec(tip_frame='flange'))
    with pytest.raises(RobotDescriptionError, match='b1,b2: needs 5 distinct names'):
        load_chain(RobotSpec(joint_names=('b1', 'b2')))


def test_a_serial_arm_is_solved_as_by_hand(arm_urdf: Path) -> None:
    chain = load_chain(RobotSpec(arm_urdf, base_frame='base', tip_frame='flange'))
    assert (chain.kind, chain.name, chain.joints) == (SERIAL_KIND, 'planar_arm',
                                                     ('yaw', 'shoulder', 'elbow'))
    assert chain.actuators == () and chain.map_jacobian(np.zeros((1, 3))) is None
    joints = arm_joints(200, 0.05)
    joints[:, 0] += 3 * np.pi  # a continuous joint may wind past a turn
    positions, valid = chain.tool_positions(joints)
    assert valid.all()
    np.testing.assert_allclose(positions, arm_tip(joints), rtol=0, atol=1e-9)
    solver = chain.solver()
    for row in (0, 77, 199):
        pose = solver.solve(joints[row])
        np.testing.assert_allclose(pose.position, arm_tip(joints[row:row + 1])[0], atol=1e-9)
    # the default base is the URDF's root: here the world, 1 m, 2 m away from the base
    rooted = load_chain(RobotSpec(arm_urdf, tip_frame='flange'))
    assert rooted.base_frame == 'world'
    np.testing.assert_allclose(rooted.tool_positions(joints[:5])[0],
                               arm_tip(joints[:5]) + np.array([1.0, 2.0, 0.0]), atol=1e-9)


def test_a_one_joint_axis_moves_its_tool_along_x_only(tmp_path: Path) -> None:
    urdf = write_urdf(tmp_path, 'axis.urdf', AXIS_URDF)
    chain = load_chain(RobotSpec(urdf, tip_frame='tool'))
    assert chain.joints == ('x',) and chain.base_frame == 'bed'
    x = np.linspace(-0.4, 0.4, 9)[:, None]
    positions, valid = chain.tool_positions(x)
    assert valid.all()
    np.testing.assert_allclose(positions, np.column_stack([x[:, 0], np.zeros(9),
                                                           np.full(9, 0.15)]), atol=1e-12)


def test_joints_out_of_their_limits_or_not_finite_are_refused(arm_urdf: Path) -> None:
    chain = load_chain(RobotSpec(arm_urdf, tip_frame='flange'))
    with pytest.raises(JointLimitError, match=r'joint elbow value 2.600000 is outside its '
                                              r'limits \[-2.500000, 2.500000\]'):
        chain.solver().solve([0.0, 0.0, 2.6])
    with pytest.raises(NonFiniteJointError, match='joint shoulder value is not finite'):
        chain.solver().solve([0.0, float('nan'), 0.0])
    positions, valid = chain.tool_positions(np.array([[0.0, 0.0, 2.6], [0.0, 0.1, 0.2],
                                                      [np.nan, 0.0, 0.0]]))
    assert valid.tolist() == [False, True, False] and np.isnan(positions[[0, 2]]).all()


@pytest.mark.parametrize(('spec', 'message'), [
    ({'tip_frame': 'hand'}, "tip frame 'hand' is not in robot description .*; frames: "
                            'universe, world'),
    ({'base_frame': 'nowhere', 'tip_frame': 'flange'}, "base frame 'nowhere' is not in"),
    ({}, 'is not the LOMPR: name its tool frame'),
    ({'base_frame': 'finger', 'tip_frame': 'flange'}, "'finger' is not above 'flange', so "
                                                      'no serial chain'),
    ({'tip_frame': 'flange', 'joint_names': ('yaw', 'shoulder', 'wrist_roll')},
     r'joint\(s\) wrist_roll not in robot description .*; its joints: yaw, shoulder, elbow, '
     'grip'),
    ({'tip_frame': 'flange', 'joint_names': ('yaw', 'shoulder', 'elbow', 'grip')},
     r"joint\(s\) grip not on the chain from 'world' to 'flange' \(yaw, shoulder, elbow\): "
     "a closed chain other than the LOMPR's"),
    ({'tip_frame': 'flange', 'joint_names': ('yaw', 'elbow')},
     r'moves joint\(s\) shoulder that the joint names lack'),
])
def test_a_robot_named_wrong_is_refused_in_one_line(arm_urdf: Path, spec: dict[str, object],
                                                    message: str) -> None:
    with pytest.raises(RobotDescriptionError, match=message) as caught:
        load_chain(RobotSpec(arm_urdf, **spec))  # type: ignore[arg-type]
    assert '\n' not in str(caught.value)


def test_a_chain_through_a_joint_of_several_coordinates_is_refused(tmp_path: Path) -> None:
    urdf = write_urdf(tmp_path, 'planar.urdf', AXIS_URDF.replace(
        'type="prismatic"', 'type="planar"').replace('<axis xyz="1 0 0"/>', '<axis xyz="0 0 1"/>'))
    with pytest.raises(RobotDescriptionError, match="joint 'x' on the chain is JointModelPlanar; "
                                                    'a serial chain here has revolute'):
        load_chain(RobotSpec(urdf, tip_frame='tool'))


def test_a_model_file_fills_in_the_frames_and_joints_a_spec_leaves_open(arm_urdf: Path) -> None:
    chain = load_chain(RobotSpec(arm_urdf, base_frame='base', tip_frame='flange'))
    spec = spec_with_model(RobotSpec(arm_urdf), chain.metadata())
    assert spec == RobotSpec(arm_urdf, 'base', 'flange', ('yaw', 'shoulder', 'elbow'))
    assert spec_with_model(RobotSpec(arm_urdf, tip_frame='fore'), chain.metadata()).tip_frame \
        == 'fore'
    assert spec_with_model(RobotSpec(), {}) == RobotSpec()


def test_every_urdf_joint_of_a_serial_chain_for_robot_state_publisher(arm_urdf: Path) -> None:
    chain = load_chain(RobotSpec(arm_urdf, tip_frame='flange'))
    names, positions = chain.all_joints(chain.solver(), [0.1, 0.2, 0.3])
    assert names == ('yaw', 'shoulder', 'elbow', 'grip')
    assert positions == [0.1, 0.2, 0.3, 0.0]
