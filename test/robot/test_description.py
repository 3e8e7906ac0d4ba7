# SPDX-License-Identifier: Apache-2.0
"""robot.description, the LOMPR's URDF: the contract geometry read from it (a calibrated one
moves the tip), its frames under a Z-up cell frame, its name, and every description that
cannot be read or used refused in one line."""

from __future__ import annotations

import math
import re
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest
from test_kinematics import grid, spiral

from lompr_predictor.errors import NameNotFoundError, RobotDescriptionError
from lompr_predictor.robot.description import (
    CELL_FRAME,
    MEASURED_JOINTS,
    ROBOT_FRAME,
    RobotDescription,
    default_description_path,
    joint_names_problem,
    read_urdf,
    robot_name,
)
from lompr_predictor.robot.kinematics import (
    ForwardKinematics,
    batch_forward_kinematics,
    inverse_kinematics,
)


def test_description_loads_contract_geometry(description: RobotDescription) -> None:
    geometry = description.geometry
    phi = np.deg2rad([90.0, 210.0, 330.0])
    ring = np.stack([np.cos(phi), np.sin(phi), np.zeros(3)], -1)
    np.testing.assert_allclose(geometry.base_anchors, 0.600 * ring, atol=1e-15)
    np.testing.assert_allclose(geometry.platform_anchors, 0.250 * ring, atol=1e-15)
    np.testing.assert_allclose(geometry.head_offset, [0, 0, 0.200])
    np.testing.assert_allclose(geometry.tool_offset, [0, 0, 0.150])
    assert len(description.sha256) == 64


def test_unknown_frame_lists_valid_names(description: RobotDescription) -> None:
    with pytest.raises(NameNotFoundError, match='tool_tip') as err:
        description.frame_id('tool_tipp')
    assert 'tool_tip' in err.value.available


def test_description_without_a_branch_is_refused() -> None:
    xml = default_description_path().read_text()
    broken = xml.replace('name="ups3"', 'name="ups3_renamed"')
    with pytest.raises(RobotDescriptionError, match="'ups3'"):
        RobotDescription(broken, 'broken.urdf')


def test_calibrated_description_moves_the_tip(description: RobotDescription) -> None:
    """Geometry comes from the URDF: moving an anchor changes the answer."""
    xml = default_description_path().read_text().replace(
        '<origin xyz="0.0 0.6 0.0" rpy="0 0 0"/>', '<origin xyz="0.0 0.601 0.0" rpy="0 0 0"/>')
    calibrated = RobotDescription(xml, 'calibrated.urdf')
    assert calibrated.sha256 != description.sha256
    joints = inverse_kinematics(description.geometry, spiral(5)).joints
    nominal = batch_forward_kinematics(description.geometry, joints).position
    moved = batch_forward_kinematics(calibrated.geometry, joints).position
    assert np.abs(moved - nominal).max() > 1e-4


def test_the_packaged_description_hangs_the_robot_frame_under_a_z_up_world(
        description: RobotDescription) -> None:
    """REP 103: the URDF's root is the Z-up cell frame `world`; the robot frame lompr_base
    (Z down) hangs from it by a fixed joint rotated by pi about X, so a tool tip at z below
    the fixed platform in lompr_base is at -z in world (TF and RViz show it the right way up)."""
    import pinocchio as pin

    root = ElementTree.parse(default_description_path()).getroot()
    children = {joint.find('child').get('link') for joint in root.iter('joint')}  # type: ignore[union-attr]
    roots = [link.get('name') for link in root.iter('link') if link.get('name') not in children]
    assert roots == [CELL_FRAME]
    (placing,) = [joint for joint in root.iter('joint')
                  if joint.find('child').get('link') == ROBOT_FRAME]  # type: ignore[union-attr]
    assert placing.get('type') == 'fixed'
    assert placing.find('parent').get('link') == CELL_FRAME  # type: ignore[union-attr]
    assert description.base_frame == ROBOT_FRAME
    joints = inverse_kinematics(description.geometry, spiral(7)).joints
    tips = batch_forward_kinematics(description.geometry, joints).position
    cell = pin.buildModelFromXML(description.urdf_xml)  # the whole tree, rooted at world
    data = cell.createData()
    tool = cell.getFrameId('tool_tip')
    for joint_row, tip in zip(joints, tips, strict=True):
        fk = ForwardKinematics(description)
        fk.solve(joint_row)
        q = pin.neutral(cell)
        for name, value in zip(('up_alpha', 'up_beta', 'up_d'), fk.last_up, strict=True):
            q[cell.joints[cell.getJointId(name)].idx_q] = value
        primary = cell.joints[cell.getJointId('head_primary')].idx_q
        q[primary:primary + 2] = math.cos(joint_row[3]), math.sin(joint_row[3])
        q[cell.joints[cell.getJointId('head_secondary')].idx_q] = joint_row[4]
        pin.framesForwardKinematics(cell, data, q)
        np.testing.assert_allclose(data.oMf[tool].translation, tip * [1.0, -1.0, -1.0],
                                   rtol=0, atol=1e-12)
    assert tips[:, 2].min() > 1.0  # the mirror lies below the platform in lompr_base


def test_a_description_rooted_at_the_robot_frame_gives_the_same_numbers(
        description: RobotDescription) -> None:
    """The kinematics reads the tree below the robot frame only: the same robot without a
    cell frame above it (as descriptions were before one was added, robot frame `world`)
    gives bit-identical geometry and forward kinematics."""
    xml = default_description_path().read_text()
    bare = re.sub(r'\s*<link name="world"/>|\s*<joint name="world_to_lompr_base".*?</joint>', '',
                  xml, flags=re.DOTALL).replace('"lompr_base"', '"world"')
    older = RobotDescription(bare, 'older.urdf')
    assert older.base_frame == 'world' and older.sha256 != description.sha256
    for field in ('base_anchors', 'platform_anchors', 'head_offset', 'tool_offset',
                  'stroke_lower', 'stroke_upper', 'up_lower', 'up_upper'):
        np.testing.assert_array_equal(getattr(older.geometry, field),
                                      getattr(description.geometry, field))
    joints = inverse_kinematics(description.geometry, grid(0.05)).joints
    assert np.array_equal(batch_forward_kinematics(older.geometry, joints).position,
                          batch_forward_kinematics(description.geometry, joints).position)
    now, before = ForwardKinematics(description), ForwardKinematics(older)
    for row in joints[:50]:
        assert np.array_equal(now.solve(row).position, before.solve(row).position)


def test_its_name_and_an_unreadable_description_in_one_line(tmp_path: Path) -> None:
    assert robot_name() == robot_name(default_description_path()) == 'lompr'
    (tmp_path / 'other.urdf').write_text('<robot name="cell7_arm"><link name="a"/></robot>')
    assert robot_name(tmp_path / 'other.urdf') == 'cell7_arm'
    (tmp_path / 'no_name.urdf').write_text('<robot><link name="a"/></robot>')
    with pytest.raises(RobotDescriptionError, match=r'the root element is not a <robot '):
        robot_name(tmp_path / 'no_name.urdf')
    (tmp_path / 'broken.urdf').write_text('<robot name="r">')
    with pytest.raises(RobotDescriptionError, match='is not a URDF \\(XML\\)'):
        robot_name(tmp_path / 'broken.urdf')
    (tmp_path / 'latin1.urdf').write_bytes(b'<robot name="r\xe9"/>')
    with pytest.raises(RobotDescriptionError, match='byte 14 is not UTF-8'):
        read_urdf(tmp_path / 'latin1.urdf')
    with pytest.raises(RobotDescriptionError, match=r'^cannot read robot description .*: No '):
        read_urdf(tmp_path / 'missing.urdf')


def test_measured_joint_names_are_five_distinct_in_order() -> None:
    assert joint_names_problem(list(MEASURED_JOINTS)) is None
    assert joint_names_problem(('b1', 'b2', 'b3', 'c', 'a')) is None
    why = ('needs 5 distinct names, for ups1, ups2, ups3, head_primary, head_secondary in '
           'this order')
    assert [joint_names_problem(names) for names in (
        ('b1', 'b2', 'b3', 'c'), ('b1', 'b1', 'b3', 'c', 'a'), ('b1', '', 'b3', 'c', 'a'))] == [
        why] * 3
