# SPDX-License-Identifier: Apache-2.0
"""Forward/inverse kinematics against the contract geometry, to 1e-9 m."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lompr_predictor.errors import (
    ConvergenceError,
    JointLimitError,
    StrokeLimitError,
    WorkspaceError,
)
from lompr_predictor.robot.description import (
    RobotDescription,
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
