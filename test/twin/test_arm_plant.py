# SPDX-License-Identifier: Apache-2.0
"""twin.arm_plant: each error source of the arm against its hand-computed value, block
invariance and bad parameters refused."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pinocchio as pin
import pytest

from lompr_predictor.twin.arm import (
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
    program_joints,
)

PERIOD = 0.004


@pytest.fixture(scope='module')
def circle(arm_model: pin.Model) -> np.ndarray:
    """The commanded joints of one circle pass at 250 Hz."""
    return program_joints(arm_model, 'circle', 1, PERIOD)[1]


def plant(arm_model: pin.Model, *sources: str) -> ArmPlant:
    """The default arm with only `sources` on, at 250 Hz."""
    return ArmPlant(arm_model, ArmParameters().only(*sources), PERIOD, seed=3, machine_seed=11)


def ramp(speed: float, count: int = 300) -> np.ndarray:
    """(count, 6) joints moving at `speed` [rad/s] from the start posture, all at once."""
    start = np.array([3.0, -1.4, 2.0, -2.2, -1.57, -0.3])
    return start + speed * PERIOD * np.arange(count)[:, None] * np.ones(6)


def test_servo_lags_a_ramp_by_its_analytic_steady_state_error(arm_model: pin.Model) -> None:
    speed = 0.2
    arm = plant(arm_model, 'servo')
    command = ramp(speed)
    out = arm.advance(command)
    kff = ArmServo().velocity_feedforward
    expected = (1.0 - kff) * speed / arm.position_gains
    np.testing.assert_allclose(command[-1] - out.actual[-1], expected, rtol=1e-9)
    # at rest on the first command: no start-up step
    np.testing.assert_allclose(out.actual[0], command[0], atol=1e-15)


def test_friction_holds_the_joint_back_by_coulomb_over_stiffness(arm_model: pin.Model) -> None:
    for speed in (0.2, -0.2):
        arm = plant(arm_model, 'friction')
        command = ramp(speed, 50)
        error = arm.advance(command).actual - command
        np.testing.assert_array_equal(error[0], 0.0)  # at rest on the first sample
        expected = -np.sign(speed) * arm.coulomb_torques / np.array(
            ArmParameters().friction.servo_stiffness)
        np.testing.assert_allclose(error[1:], np.tile(expected, (49, 1)), rtol=0, atol=1e-15)


def test_backlash_stands_still_through_the_play_at_a_reversal(arm_model: pin.Model) -> None:
    arm = plant(arm_model, 'backlash')
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


def test_gravity_sags_each_joint_by_its_load_over_its_stiffness(arm_model: pin.Model,
                                                                circle: np.ndarray) -> None:
    arm = plant(arm_model, 'gravity')
    command = circle[::50]
    out = arm.advance(command)
    data = arm_model.createData()
    load = np.array([pin.computeGeneralizedGravity(arm_model, data, q) for q in command])
    np.testing.assert_allclose(out.actual - command, -load / arm.joint_stiffness,
                               rtol=0, atol=1e-15)
    assert np.abs(load[:, 0]).max() < 1e-12  # the pan axis is vertical
    # the sag moves the tool down, never up
    drop = tool_positions(arm_model, out.actual)[:, 2] - tool_positions(arm_model, command)[:, 2]
    assert np.all(drop < -1e-6)


def test_thermal_offset_grows_first_order_towards_its_speed_share(arm_model: pin.Model) -> None:
    speed = 0.1
    arm = plant(arm_model, 'thermal')
    command = ramp(speed, 500)
    error = arm.advance(command).actual - command
    thermal = ArmParameters().thermal
    k = np.arange(500)[:, None]
    steady = arm.thermal_amplitudes * speed / thermal.reference_speed
    expected = steady * (1.0 - arm.thermal_decay ** k)  # cold start, at rest on sample 0
    np.testing.assert_allclose(error, expected, rtol=0, atol=1e-15)
    assert arm.thermal_decay == pytest.approx(math.exp(-PERIOD / thermal.time_constant))


def test_drift_is_the_only_random_part_of_the_actual_joints(arm_model: pin.Model,
                                                            circle: np.ndarray) -> None:
    arm = plant(arm_model, 'drift')
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


def test_noise_and_quantisation_touch_only_the_measured_joints(arm_model: pin.Model,
                                                               circle: np.ndarray) -> None:
    out = plant(arm_model, 'noise', 'quantisation').advance(circle)
    np.testing.assert_array_equal(out.actual, circle)
    step = ArmParameters().quantisation.step
    np.testing.assert_allclose(out.measured / step, np.round(out.measured / step), atol=1e-6)
    residual = out.measured - out.actual
    assert np.abs(residual).max() < 6 * 2e-6 + step
    assert residual.std() == pytest.approx(math.sqrt(2e-6 ** 2 + step ** 2 / 12), rel=0.1)


def test_one_sample_at_a_time_gives_the_numbers_of_one_block(arm_model: pin.Model,
                                                             circle: np.ndarray) -> None:
    command = circle[:400]
    whole = plant(arm_model, *ARM_SOURCES).advance(command)
    arm = plant(arm_model, *ARM_SOURCES)
    steps = [arm.advance(q[None]) for q in command]
    arm = plant(arm_model, *ARM_SOURCES)
    cuts = [0, 1, 7, 100, 101, 333, 400]
    blocks = [arm.advance(command[a:b]) for a, b in itertools.pairwise(cuts)]
    for field in ('actual', 'measured', 'drift'):
        np.testing.assert_array_equal(np.vstack([getattr(s, field) for s in steps]),
                                      getattr(whole, field))
        np.testing.assert_array_equal(np.vstack([getattr(b, field) for b in blocks]),
                                      getattr(whole, field))


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
