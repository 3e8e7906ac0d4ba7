# SPDX-License-Identifier: Apache-2.0
"""twin.arm_programs: the programs' smooth progress, their inverse kinematics, passes inside
the disk, the raster's lines, and a program out of reach refused."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from lompr_predictor.twin.arm_programs import (
    PROGRAMS,
    TOOL_DOWN,
    ArmWorkspace,
    program_duration,
    program_joints,
    program_tips,
    raster_waypoints,
    smooth_progress,
    solve_tip_path,
)

PERIOD = 0.004


def test_smooth_progress_starts_and_ends_at_rest() -> None:
    duration, ramp_time = 4.0, 0.5
    t = np.linspace(0.0, duration, 40001)
    s = smooth_progress(t, duration, ramp_time)
    assert s[0] == 0.0 and s[-1] == pytest.approx(1.0, abs=1e-15)
    speed = np.gradient(s, t)
    assert np.all(np.diff(s) >= 0.0)
    assert abs(speed[0]) < 1e-6 and abs(speed[-1]) < 1e-6
    assert speed.max() == pytest.approx(1.0 / (duration - ramp_time), rel=1e-6)
    assert np.abs(np.diff(np.gradient(speed, t))).max() < 1e-3  # acceleration continuous


@pytest.mark.parametrize('name', PROGRAMS)
def test_the_ik_reaches_every_tip_and_the_joints_are_continuous(arm_model: pin.Model,
                                                                name: str) -> None:
    stamps, tips = program_tips(name, 2, PERIOD)
    stamps_q, joints = program_joints(arm_model, name, 2, PERIOD)
    np.testing.assert_array_equal(stamps, stamps_q)
    np.testing.assert_allclose(np.diff(stamps), PERIOD)
    data, frame = arm_model.createData(), arm_model.getFrameId('tool0')
    worst_position = worst_rotation = 0.0
    for q, tip in zip(joints, tips, strict=True):
        pin.framesForwardKinematics(arm_model, data, q)
        pose = data.oMf[frame]
        worst_position = max(worst_position, float(np.linalg.norm(pose.translation - tip)))
        worst_rotation = max(worst_rotation, float(np.abs(pose.rotation - TOOL_DOWN).max()))
    assert worst_position < 1e-9 and worst_rotation < 1e-9
    # continuous across the samples and the wrap from one pass to the next
    assert np.abs(np.diff(joints, axis=0)).max() < 0.5 * PERIOD
    # elbow up: the elbow above the shoulder and the wrist all along
    heights: dict[str, list[float]] = {
        link: [] for link in ('upper_arm_link', 'forearm_link', 'wrist_1_link')}
    for q in joints[::25]:
        pin.framesForwardKinematics(arm_model, data, q)
        for link, values in heights.items():
            values.append(float(data.oMf[arm_model.getFrameId(link)].translation[2]))
    elbow = np.array(heights['forearm_link'])
    assert np.all(elbow > np.array(heights['upper_arm_link']))
    assert np.all(elbow > np.array(heights['wrist_1_link']))


@pytest.mark.parametrize('name', PROGRAMS)
def test_a_pass_stays_in_the_disk_and_starts_and_ends_at_rest(name: str) -> None:
    workspace = ArmWorkspace()
    stamps, tips = program_tips(name, 1, PERIOD)
    assert 4.0 < stamps[-1] < 60.0
    # a whole number of samples, the nominal duration stretched by less than one
    assert 0.0 <= len(stamps) * PERIOD - program_duration(name) < PERIOD
    radial = np.linalg.norm(tips[:, :2] - np.array(workspace.centre), axis=1)
    assert radial.max() <= workspace.radius + 1e-12
    np.testing.assert_allclose(tips[:, 2], workspace.height)
    speed = np.linalg.norm(np.diff(tips, axis=0), axis=1) / PERIOD
    assert speed[0] < 1e-3 and speed[-1] < 1e-3
    # the cruise speed; the figure eight's angle runs evenly, so faster through the centre
    top = 1.5 if name == 'figure8' else 1.0 + 1e-6
    assert workspace.feed_speed * 0.99 < speed.max() < workspace.feed_speed * top


def test_the_raster_is_a_grid_of_lines_clipped_to_the_disk() -> None:
    workspace = ArmWorkspace(radius=0.1, raster_spacing=0.04)
    corners = raster_waypoints(workspace)
    # five lines at y = -0.08 .. 0.08, each from rim to rim, alternating direction
    np.testing.assert_allclose(corners[:, 1], np.repeat([-0.08, -0.04, 0.0, 0.04, 0.08], 2))
    np.testing.assert_allclose(np.hypot(corners[:, 0], corners[:, 1]), 0.1)
    assert corners[0, 0] < 0 < corners[1, 0] and corners[2, 0] > 0 > corners[3, 0]


def test_a_program_out_of_reach_is_a_clear_error(arm_model: pin.Model) -> None:
    with pytest.raises(ValueError, match='IK missed'):
        program_joints(arm_model, 'circle', 1, 0.02, ArmWorkspace(centre=(1.5, 0.0)))
    with pytest.raises(ValueError, match='unknown arm program'):
        program_tips('spiral')
    with pytest.raises(ValueError, match='not continuous'):
        # the same tips at a sample period far too short for the joints to follow
        solve_tip_path(arm_model, program_tips('circle', 1, 0.04)[1], 1e-4)
