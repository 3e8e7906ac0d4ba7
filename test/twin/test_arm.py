# SPDX-License-Identifier: Apache-2.0
"""The serial arm's twin: its URDF against the UR5e's DH kinematics, the programs' IK, each
error source against its hand-computed value, block invariance, seeds, the error's size."""

from __future__ import annotations

import dataclasses
import fnmatch
import itertools
import math
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from lompr_predictor.twin.arm import (
    ArmRun,
    arm_description_path,
    load_arm_model,
    simulate_arm,
    tool_positions,
)
from lompr_predictor.twin.arm_plant import (
    ARM_SOURCES,
    ArmBacklash,
    ArmParameters,
    ArmPlant,
    ArmServo,
)
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
from lompr_predictor.twin.digital_twin import EPOCH_NS

UR_JOINTS = ('shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint',
             'wrist_2_joint', 'wrist_3_joint')
# UR5e standard DH parameters, as published by Universal Robots
DH_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
DH_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
PERIOD = 0.004
#: The documented band of a default run's tool-tip error RMS [m].
RMS_BAND = (60e-6, 250e-6)


def dh_forward(q: np.ndarray) -> np.ndarray:
    """4x4 pose of the flange: the product of Rz(theta) Tz(d) Tx(a) Rx(alpha), by hand."""
    pose = np.eye(4)
    for theta, d, a, alpha in zip(q, DH_D, DH_A, DH_ALPHA, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        pose = pose @ np.array([[ct, -st * ca, st * sa, a * ct],
                                [st, ct * ca, -ct * sa, a * st],
                                [0.0, sa, ca, d],
                                [0.0, 0.0, 0.0, 1.0]])
    return pose


@pytest.fixture(scope='module')
def model() -> pin.Model:
    return load_arm_model()


@pytest.fixture(scope='module')
def circle(model: pin.Model) -> np.ndarray:
    """The commanded joints of one circle pass at 250 Hz."""
    return program_joints(model, 'circle', 1, PERIOD)[1]


def plant(model: pin.Model, *sources: str) -> ArmPlant:
    """The default arm with only `sources` on, at 250 Hz."""
    return ArmPlant(model, ArmParameters().only(*sources), PERIOD, seed=3, machine_seed=11)


def ramp(speed: float, count: int = 300) -> np.ndarray:
    """(count, 6) joints moving at `speed` [rad/s] from the start posture, all at once."""
    start = np.array([3.0, -1.4, 2.0, -2.2, -1.57, -0.3])
    return start + speed * PERIOD * np.arange(count)[:, None] * np.ones(6)


# --- the description ---------------------------------------------------------------------

def test_the_urdf_is_a_six_joint_arm_from_arm_base_to_tool0(model: pin.Model) -> None:
    text = arm_description_path().read_text()
    assert re.search(r'<robot name="arm6">', text)
    assert model.nq == 6 and model.nv == 6
    assert tuple(model.names)[1:] == UR_JOINTS
    assert model.existFrame('arm_base') and model.existFrame('tool0')
    np.testing.assert_allclose(model.upperPositionLimit, [2 * math.pi] * 2 + [math.pi]
                               + [2 * math.pi] * 3)
    np.testing.assert_allclose(model.lowerPositionLimit, -model.upperPositionLimit)
    masses = [model.inertias[j].mass for j in range(1, 7)]
    np.testing.assert_allclose(masses, [3.761, 8.058, 2.846, 1.37, 1.3, 0.365])


def test_the_urdf_is_packaged_by_setup_py() -> None:
    path = arm_description_path()
    assert path.is_file()
    setup = (Path(__file__).resolve().parents[2] / 'setup.py').read_text()
    assert "'description/*.urdf'" in setup
    assert fnmatch.fnmatch(f'description/{path.name}', 'description/*.urdf')


@pytest.mark.parametrize('q', [
    np.zeros(6),
    np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4]),
    np.array([-2.5, 0.7, -2.9, 1.1, 2.3, -5.8]),
])
def test_forward_kinematics_of_tool0_is_the_ur5e_dh_chain(model: pin.Model,
                                                          q: np.ndarray) -> None:
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    pose = data.oMf[model.getFrameId('tool0')]
    expected = dh_forward(q)
    np.testing.assert_allclose(pose.translation, expected[:3, 3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(pose.rotation, expected[:3, :3], rtol=0, atol=1e-12)


def test_at_zero_the_arm_stretches_along_minus_x(model: pin.Model) -> None:
    tip = tool_positions(model, np.zeros((1, 6)))[0]
    np.testing.assert_allclose(tip, [-0.425 - 0.3922, -0.1333 - 0.0996, 0.1625 - 0.0997],
                               atol=1e-12)


# --- the programs ------------------------------------------------------------------------

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
def test_the_ik_reaches_every_tip_and_the_joints_are_continuous(model: pin.Model,
                                                                name: str) -> None:
    stamps, tips = program_tips(name, 2, PERIOD)
    stamps_q, joints = program_joints(model, name, 2, PERIOD)
    np.testing.assert_array_equal(stamps, stamps_q)
    np.testing.assert_allclose(np.diff(stamps), PERIOD)
    data, frame = model.createData(), model.getFrameId('tool0')
    worst_position = worst_rotation = 0.0
    for q, tip in zip(joints, tips, strict=True):
        pin.framesForwardKinematics(model, data, q)
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
        pin.framesForwardKinematics(model, data, q)
        for link, values in heights.items():
            values.append(float(data.oMf[model.getFrameId(link)].translation[2]))
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


def test_a_program_out_of_reach_is_a_clear_error(model: pin.Model) -> None:
    with pytest.raises(ValueError, match='IK missed'):
        program_joints(model, 'circle', 1, 0.02, ArmWorkspace(centre=(1.5, 0.0)))
    with pytest.raises(ValueError, match='unknown arm program'):
        program_tips('spiral')
    with pytest.raises(ValueError, match='not continuous'):
        # the same tips at a sample period far too short for the joints to follow
        solve_tip_path(model, program_tips('circle', 1, 0.04)[1], 1e-4)


# --- each error source alone -------------------------------------------------------------

def test_servo_lags_a_ramp_by_its_analytic_steady_state_error(model: pin.Model) -> None:
    speed = 0.2
    arm = plant(model, 'servo')
    command = ramp(speed)
    out = arm.advance(command)
    kff = ArmServo().velocity_feedforward
    expected = (1.0 - kff) * speed / arm.position_gains
    np.testing.assert_allclose(command[-1] - out.actual[-1], expected, rtol=1e-9)
    # at rest on the first command: no start-up step
    np.testing.assert_allclose(out.actual[0], command[0], atol=1e-15)


def test_friction_holds_the_joint_back_by_coulomb_over_stiffness(model: pin.Model) -> None:
    for speed in (0.2, -0.2):
        arm = plant(model, 'friction')
        command = ramp(speed, 50)
        error = arm.advance(command).actual - command
        np.testing.assert_array_equal(error[0], 0.0)  # at rest on the first sample
        expected = -np.sign(speed) * arm.coulomb_torques / np.array(
            ArmParameters().friction.servo_stiffness)
        np.testing.assert_allclose(error[1:], np.tile(expected, (49, 1)), rtol=0, atol=1e-15)


def test_backlash_stands_still_through_the_play_at_a_reversal(model: pin.Model) -> None:
    arm = plant(model, 'backlash')
    half = arm.play / 2
    speed = 0.002
    up = ramp(speed, 101)  # a step far below the play, so the play shows over many samples
    command = np.vstack([up, up[-2::-1]])  # out and back
    actual = arm.advance(command).actual
    peak = up[-1]
    np.testing.assert_allclose(actual[:101], np.maximum(up[0], up - half), rtol=0, atol=1e-15)
    np.testing.assert_allclose(actual[101:], np.minimum(peak - half, command[101:] + half),
                               rtol=0, atol=1e-15)
    # after the reversal the joint stands while the motor side crosses the play
    stands = np.sum(np.abs(actual[101:] - actual[100]) < 1e-15, axis=0)
    np.testing.assert_array_equal(stands, np.floor(arm.play / (speed * PERIOD)))


def test_gravity_sags_each_joint_by_its_load_over_its_stiffness(model: pin.Model,
                                                                circle: np.ndarray) -> None:
    arm = plant(model, 'gravity')
    command = circle[::50]
    out = arm.advance(command)
    data = model.createData()
    load = np.array([pin.computeGeneralizedGravity(model, data, q) for q in command])
    np.testing.assert_allclose(out.actual - command, -load / arm.joint_stiffness,
                               rtol=0, atol=1e-15)
    assert np.abs(load[:, 0]).max() < 1e-12  # the pan axis is vertical
    # the sag moves the tool down, never up
    drop = tool_positions(model, out.actual)[:, 2] - tool_positions(model, command)[:, 2]
    assert np.all(drop < -1e-6)


def test_thermal_offset_grows_first_order_towards_its_speed_share(model: pin.Model) -> None:
    speed = 0.1
    arm = plant(model, 'thermal')
    command = ramp(speed, 500)
    error = arm.advance(command).actual - command
    thermal = ArmParameters().thermal
    k = np.arange(500)[:, None]
    steady = arm.thermal_amplitudes * speed / thermal.reference_speed
    expected = steady * (1.0 - arm.thermal_decay ** k)  # cold start, at rest on sample 0
    np.testing.assert_allclose(error, expected, rtol=0, atol=1e-15)
    assert arm.thermal_decay == pytest.approx(math.exp(-PERIOD / thermal.time_constant))


def test_drift_is_the_only_random_part_of_the_actual_joints(model: pin.Model,
                                                            circle: np.ndarray) -> None:
    arm = plant(model, 'drift')
    out = arm.advance(circle)
    np.testing.assert_allclose(out.actual - circle, out.drift, rtol=0, atol=1e-15)
    sigma = ArmParameters().drift.standard_deviation
    assert 0.0 < np.abs(out.drift).max() < 6 * sigma
    # first-order Gauss-Markov: what the decay leaves unexplained is white, of the
    # innovation's size
    innovation = out.drift[1:] - arm.drift_decay * out.drift[:-1]
    assert innovation.std() == pytest.approx(sigma * math.sqrt(1 - arm.drift_decay ** 2),
                                             rel=0.05)
    assert abs(np.corrcoef(innovation[1:, 0], innovation[:-1, 0])[0, 1]) < 0.1


def test_noise_and_quantisation_touch_only_the_measured_joints(model: pin.Model,
                                                               circle: np.ndarray) -> None:
    out = plant(model, 'noise', 'quantisation').advance(circle)
    np.testing.assert_array_equal(out.actual, circle)
    step = ArmParameters().quantisation.step
    np.testing.assert_allclose(out.measured / step, np.round(out.measured / step), atol=1e-6)
    residual = out.measured - out.actual
    assert np.abs(residual).max() < 6 * 2e-6 + step
    assert residual.std() == pytest.approx(math.sqrt(2e-6 ** 2 + step ** 2 / 12), rel=0.1)


# --- blocks, seeds, parameters -----------------------------------------------------------

def test_one_sample_at_a_time_gives_the_numbers_of_one_block(model: pin.Model,
                                                             circle: np.ndarray) -> None:
    command = circle[:400]
    whole = plant(model, *ARM_SOURCES).advance(command)
    arm = plant(model, *ARM_SOURCES)
    steps = [arm.advance(q[None]) for q in command]
    arm = plant(model, *ARM_SOURCES)
    cuts = [0, 1, 7, 100, 101, 333, 400]
    blocks = [arm.advance(command[a:b]) for a, b in itertools.pairwise(cuts)]
    for field in ('actual', 'measured', 'drift'):
        np.testing.assert_array_equal(np.vstack([getattr(s, field) for s in steps]),
                                      getattr(whole, field))
        np.testing.assert_array_equal(np.vstack([getattr(b, field) for b in blocks]),
                                      getattr(whole, field))


def test_same_seeds_same_run_other_run_seed_only_drift_and_noise(model: pin.Model) -> None:
    first = simulate_arm('figure8', 1, seed=5, machine_seed=9, model=model)
    again = simulate_arm('figure8', 1, seed=5, machine_seed=9, model=model)
    for field in dataclasses.fields(ArmRun):
        value = getattr(first, field.name)
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, getattr(again, field.name))
    other = simulate_arm('figure8', 1, seed=6, machine_seed=9, model=model)
    np.testing.assert_allclose(first.actual - first.drift, other.actual - other.drift,
                               rtol=0, atol=1e-15)
    assert not np.array_equal(first.drift, other.drift)
    assert not np.array_equal(first.measured, other.measured)
    machine = simulate_arm('figure8', 1, seed=5, machine_seed=10, model=model)
    assert np.abs((machine.actual - machine.drift) - (first.actual - first.drift)).max() > 1e-6


def test_a_run_has_stamps_joints_and_tool_tips(model: pin.Model) -> None:
    run = simulate_arm('circle', 2, seed=1, model=model)
    count = len(run.stamps)
    assert run.stamps.dtype == np.int64 and run.stamps[0] == EPOCH_NS
    np.testing.assert_array_equal(np.diff(run.stamps), 4_000_000)
    assert run.joint_names == UR_JOINTS
    for joints in (run.commanded, run.measured, run.actual, run.drift):
        assert joints.shape == (count, 6)
    np.testing.assert_allclose(run.tool_commanded, program_tips('circle', 2, PERIOD)[1],
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(run.tool_actual, tool_positions(model, run.actual))


@pytest.mark.parametrize('name', PROGRAMS)
def test_a_default_run_misses_by_a_real_arms_tracking_error(model: pin.Model,
                                                            name: str) -> None:
    rms = [simulate_arm(name, 1, seed=0, machine_seed=m, model=model).tool_error_rms()
           for m in (0, 1)]
    assert all(RMS_BAND[0] < value < RMS_BAND[1] for value in rms), rms


def test_bad_parameters_are_clear_errors() -> None:
    with pytest.raises(ValueError, match='unknown arm error sources'):
        ArmParameters().only('servo', 'magic')
    with pytest.raises(ValueError, match='backlash play needs 6 positive values'):
        ArmBacklash(play=(1e-5,))
    with pytest.raises(ValueError, match='servo tolerance'):
        ArmServo(tolerance=1.5)
    params = ArmParameters().only('servo', 'gravity')
    assert [getattr(params, s).enabled for s in ARM_SOURCES] == [
        s in ('servo', 'gravity') for s in ARM_SOURCES]
