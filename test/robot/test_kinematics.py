# SPDX-License-Identifier: Apache-2.0
"""Forward/inverse kinematics against the contract geometry, to 1e-9 m."""

from __future__ import annotations

import math
import re
from xml.etree import ElementTree

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lompr_predictor.errors import (
    ConvergenceError,
    JointLimitError,
    NameNotFoundError,
    RobotDescriptionError,
    StrokeLimitError,
    WorkspaceError,
)
from lompr_predictor.robot.description import (
    CELL_FRAME,
    ROBOT_FRAME,
    RobotDescription,
    default_description_path,
)
from lompr_predictor.robot.kinematics import (
    ForwardKinematics,
    NonFiniteJointError,
    batch_forward_kinematics,
    branch_lengths,
    inverse_kinematics,
)

MIRROR_Z = 1.097
MIRROR_RADIUS = 0.200


def spiral(samples: int = 251) -> np.ndarray:
    """The paper's Eq. 29 spiral, one pass."""
    t = np.linspace(0.0, 10.0, samples)
    angle = np.pi / 2 * t + np.pi / 2
    return np.stack([0.02 * t * np.cos(angle), 0.02 * t * np.sin(angle),
                     np.full_like(t, MIRROR_Z)], -1)


def grid(step: float = 0.02) -> np.ndarray:
    """A raster on the mirror, clipped to its disk, rows alternating direction."""
    points = []
    for row, y in enumerate(np.arange(-MIRROR_RADIUS, MIRROR_RADIUS + 1e-12, step)):
        xs = np.arange(-MIRROR_RADIUS, MIRROR_RADIUS + 1e-12, step / 4)
        xs = xs if row % 2 == 0 else xs[::-1]
        points += [(x, y, MIRROR_Z) for x in xs if math.hypot(x, y) <= MIRROR_RADIUS]
    return np.array(points)


def concentric(rings: int = 5, per_ring: int = 90) -> np.ndarray:
    """Concentric circles up to the mirror's radius."""
    angle = np.linspace(0, 2 * np.pi, per_ring, endpoint=False)
    return np.concatenate([
        np.stack([r * np.cos(angle), r * np.sin(angle), np.full_like(angle, MIRROR_Z)], -1)
        for r in np.linspace(MIRROR_RADIUS / rings, MIRROR_RADIUS, rings)])


def test_description_loads_contract_geometry(description: RobotDescription) -> None:
    geometry = description.geometry
    phi = np.deg2rad([90.0, 210.0, 330.0])
    ring = np.stack([np.cos(phi), np.sin(phi), np.zeros(3)], -1)
    np.testing.assert_allclose(geometry.base_anchors, 0.600 * ring, atol=1e-15)
    np.testing.assert_allclose(geometry.platform_anchors, 0.250 * ring, atol=1e-15)
    np.testing.assert_allclose(geometry.head_offset, [0, 0, 0.200])
    np.testing.assert_allclose(geometry.tool_offset, [0, 0, 0.150])
    assert len(description.sha256) == 64


def test_home_configuration_tip_is_d_plus_h1_h2(description: RobotDescription) -> None:
    for d in (0.70, 0.75, 0.80):
        lengths = branch_lengths(description.geometry, np.array([[0.0, 0.0, d]]))[0]
        pose = ForwardKinematics(description).solve([*lengths, 0.0, 0.0])
        np.testing.assert_allclose(pose.position, [0.0, 0.0, d + 0.35], atol=1e-12)
        np.testing.assert_allclose(pose.quaternion, [0, 0, 0, 1], atol=1e-12)


@pytest.mark.parametrize('path', [spiral(), grid(), concentric()],
                         ids=['spiral', 'grid', 'concentric'])
def test_fk_of_ik_along_paths(description: RobotDescription, path: np.ndarray) -> None:
    joints = inverse_kinematics(description.geometry, path).joints
    fk = ForwardKinematics(description)
    for row, tip in zip(joints, path, strict=False):
        pose = fk.solve(row)
        np.testing.assert_allclose(pose.position, tip, rtol=0, atol=1e-9)
        # The tool axis is vertical: R e_z = e_z.
        x, y, z, w = pose.quaternion
        np.testing.assert_allclose(
            [2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], [0, 0, 1],
            atol=1e-9)
    batch = batch_forward_kinematics(description.geometry, joints)
    assert batch.valid.all()
    np.testing.assert_allclose(batch.position, path, rtol=0, atol=1e-9)


@settings(max_examples=300, deadline=None)
@given(radius=st.floats(0.0, MIRROR_RADIUS), angle=st.floats(-np.pi, np.pi),
       z=st.floats(MIRROR_Z - 0.05, MIRROR_Z + 0.05), theta1_start=st.floats(-50.0, 50.0))
def test_fk_of_ik_anywhere_in_workspace(
        description: RobotDescription, radius: float, angle: float, z: float,
        theta1_start: float) -> None:
    tip = np.array([[radius * math.cos(angle), radius * math.sin(angle), z]])
    joints = inverse_kinematics(description.geometry, tip, theta1_start).joints
    assert abs(joints[0, 3] - theta1_start) <= math.pi / 2 + 1e-9
    pose = ForwardKinematics(description).solve(joints[0])  # cold start: no warm history
    np.testing.assert_allclose(pose.position, tip[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        batch_forward_kinematics(description.geometry, joints).position, tip, rtol=0, atol=1e-9)


def test_batch_equals_single_sample(description: RobotDescription) -> None:
    rng = np.random.default_rng(7)
    radius, angle = MIRROR_RADIUS * np.sqrt(rng.random(500)), rng.uniform(-np.pi, np.pi, 500)
    tips = np.stack([radius * np.cos(angle), radius * np.sin(angle),
                     MIRROR_Z + rng.uniform(-0.05, 0.05, 500)], -1)
    joints = inverse_kinematics(description.geometry, tips).joints
    joints[:, 3] += rng.uniform(-0.3, 0.3, 500)  # heads off vertical: a general pose
    joints[:, 4] += rng.uniform(-0.1, 0.1, 500)
    fk = ForwardKinematics(description)
    single = np.array([fk.solve(row).position for row in joints])
    batch = batch_forward_kinematics(description.geometry, joints)
    assert batch.valid.all()
    np.testing.assert_allclose(batch.position, single, rtol=0, atol=1e-10)


def test_theta1_continuous_along_spiral_and_theta2_flips_through_centre(
        description: RobotDescription) -> None:
    passes = np.concatenate([spiral(), spiral()[::-1], spiral()])  # out, back through 0, out
    head = inverse_kinematics(description.geometry, passes).head
    assert np.abs(np.diff(head[1:, 0])).max() < 0.2
    assert np.abs(head[:, 0]).max() > 2 * np.pi  # it winds
    tips = batch_forward_kinematics(
        description.geometry, inverse_kinematics(description.geometry, passes).joints).position
    np.testing.assert_allclose(tips, passes, atol=1e-9)


def test_out_of_stroke_raises_stroke_error(description: RobotDescription) -> None:
    fk = ForwardKinematics(description)
    with pytest.raises(StrokeLimitError, match=r'branch ups2 length 1\.200000 m is outside') as err:
        fk.solve([0.8, 1.2, 0.8, 0.0, 0.0])
    assert err.value.joint == 'ups2' and err.value.upper == pytest.approx(1.06)


def test_head_angle_out_of_range_raises(description: RobotDescription) -> None:
    with pytest.raises(JointLimitError, match='head_secondary'):
        ForwardKinematics(description).solve([0.8, 0.8, 0.8, 0.0, 0.9])


def test_non_finite_raises(description: RobotDescription) -> None:
    with pytest.raises(NonFiniteJointError, match='ups3'):
        ForwardKinematics(description).solve([0.8, 0.8, float('nan'), 0.0, 0.0])


def test_lengths_without_posture_in_limits_raise_workspace_error(
        description: RobotDescription) -> None:
    # Each length is within its stroke, but together they tilt the platform past the
    # UP-joint limits (or have no real solution at all).
    fk = ForwardKinematics(description)
    with pytest.raises((WorkspaceError, ConvergenceError)):
        fk.solve([0.63, 1.05, 1.05, 0.0, 0.0])
    # The stream recovers: the next good sample is answered.
    lengths = branch_lengths(description.geometry, np.array([[0.0, 0.0, 0.75]]))[0]
    np.testing.assert_allclose(fk.solve([*lengths, 0, 0]).position, [0, 0, 1.1], atol=1e-12)
    batch = batch_forward_kinematics(
        description.geometry, np.array([[0.63, 1.05, 1.05, 0.0, 0.0], [*lengths, 0, 0]]))
    assert batch.valid.tolist() == [False, True]
    assert np.isnan(batch.position[0]).all()


def test_batch_marks_bad_rows_invalid(description: RobotDescription) -> None:
    good = inverse_kinematics(description.geometry, spiral(10)).joints
    bad = good.copy()
    bad[1, 0] = np.nan
    bad[2, 1] = 2.0
    bad[3, 4] = 0.9
    bad[4, 3] = np.inf
    batch = batch_forward_kinematics(description.geometry, bad)
    assert batch.valid.tolist() == [True, False, False, False, False] + [True] * 5
    np.testing.assert_allclose(batch.position[batch.valid], spiral(10)[batch.valid], atol=1e-9)


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
