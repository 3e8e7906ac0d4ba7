# SPDX-License-Identifier: Apache-2.0
"""twin.plant: the twin's backlash, Stribeck friction and thermal growth and the machine seed,
against hand-computed values (the irreducible level of every random source:
test_simulation)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.twin import (
    DigitalTwin,
    load_twin_parameters,
)
from lompr_predictor.twin.plant import (
    friction_force,
    gravity_axial_forces,
    play_operator,
    thermal_growth,
)

PARAMS = load_twin_parameters()
UM = 1e-6


def test_play_holds_the_branch_for_exactly_the_play() -> None:
    up = np.arange(0.0, 11.0)  # motor side 0 .. 10 um, then back down to 0
    motor = np.concatenate([up, up[::-1][1:]])[:, None] * UM
    state = np.zeros(1)
    branch = play_operator(motor, np.array([4.0 * UM]), state)[:, 0] / UM
    # Centred at the start: the first 2 um take up half the play, then it lags by 2 um.
    np.testing.assert_allclose(branch[:11], [0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8], atol=1e-12)
    # Reversing at 10 um, the branch stands at 8 um while the motor travels the 4 um of
    # play (motor 9, 8, 7, 6), then follows 2 um above it.
    np.testing.assert_allclose(branch[11:], [8, 8, 8, 8, 7, 6, 5, 4, 3, 2], atol=1e-12)
    assert state[0] == pytest.approx(2.0 * UM)
    # The state carries over: two blocks give the same as one.
    state = np.zeros(1)
    halves = [play_operator(part, np.array([4.0 * UM]), state) for part in (motor[:13], motor[13:])]
    np.testing.assert_array_equal(np.vstack(halves)[:, 0] / UM, branch)


def test_backlash_in_the_plant_is_the_play_on_the_command(description: RobotDescription) -> None:
    params = PARAMS.with_sources('backlash')
    twin = DigitalTwin(description, params, seed=3)
    out = twin.step(len(twin.cycle))
    plays = twin.plant.branch_play
    assert np.ptp(plays) > 0 and np.all(np.abs(plays / params.backlash.play - 1) <= 0.3)
    lengths = out.joints.commanded[:, :3]
    expected = play_operator(lengths, plays, lengths[0].copy())
    np.testing.assert_allclose(out.joints.actual[:, :3], expected, rtol=0, atol=1e-15)
    lag = out.joints.actual[:, :3] - lengths
    assert np.all(np.abs(lag) <= plays / 2 + 1e-15)
    assert np.all(np.isclose(np.abs(lag), plays / 2, rtol=0, atol=1e-12).mean(0) > 0.9)


def test_stribeck_force_at_rest_at_the_stribeck_velocity_and_fast() -> None:
    force = friction_force(np.array([1e-4, -1e-4, 0.01, 1.0, 0.0]), coulomb=100.0,
                           static_ratio=1.5, stribeck_velocity=0.01, viscous=3000.0,
                           smoothing_velocity=1e-7)
    # v = 0+: the breakaway level Fs = 150 N (less the last bit of the Stribeck decay).
    assert force[0] == pytest.approx(150.0 * 0.9999 + 100 * 0.0001 + 0.3, rel=1e-5)
    assert force[1] == -force[0]
    # v = v_s: Fc + (Fs - Fc) / e + b v.
    assert force[2] == pytest.approx(100.0 + 50.0 / np.e + 30.0, rel=1e-12)
    # fast: the Coulomb level plus viscous.
    assert force[3] == pytest.approx(100.0 + 3000.0, rel=1e-12)
    assert force[4] == 0.0
    # static_ratio 1 is the plain smoothed Coulomb + viscous law of the nominal twin.
    plain = friction_force(np.array([0.001]), 80.0, 1.0, 0.005, 3000.0, 0.002)
    assert plain[0] == pytest.approx(80.0 * np.tanh(0.5) + 3.0, rel=1e-12)


def test_sharp_friction_switches_at_a_reversal(description: RobotDescription) -> None:
    params = load_twin_parameters(preset='sharp_friction').with_sources('friction')
    friction = params.friction
    out = DigitalTwin(description, params, seed=1).step(1100)
    lengths = out.joints.commanded[:, :3]
    shift = out.joints.actual[:, :3] - lengths  # -F / k; sample 0 has no velocity yet
    axial = gravity_axial_forces(description.geometry, out.joints.up,
                                 params.elastic.moving_mass * params.elastic.gravity,
                                 params.elastic.centre_of_mass_offset)
    coulomb = friction.coulomb_force + friction.load_coefficient * np.abs(axial)
    velocity = np.diff(lengths, axis=0)  # velocity[k - 1] is the one of sample k
    reversals = [(k, b) for k in range(2, 1099) for b in range(3)
                 if np.sign(velocity[k - 1, b]) != np.sign(velocity[k - 2, b])]
    assert len(reversals) > 10
    for k, b in reversals:
        # Over the reversal the shift flips from +-Fc / k to -+Fc / k (or more, the
        # Stribeck peak): within two samples, never more than the breakaway level's flip.
        flip = abs(shift[k + 1, b] - shift[k - 1, b]) * friction.servo_stiffness
        assert 1.9 * coulomb[k, b] < flip < 2 * friction.static_ratio * coulomb[k, b] + 10.0


def test_thermal_growth_is_first_order_towards_the_speed() -> None:
    speed = np.concatenate([np.full(5, 0.02), np.zeros(3)])[:, None]
    state = np.zeros(1)
    growth = thermal_growth(speed, np.array([10 * UM]), 0.02, 0.9, state)[:, 0] / UM
    heating = 10 * (1 - 0.9 ** np.arange(1, 6))
    cooling = heating[-1] * 0.9 ** np.arange(1, 4)
    np.testing.assert_allclose(growth, np.concatenate([heating, cooling]), rtol=1e-12)
    assert state[0] == pytest.approx(cooling[-1] * UM, rel=1e-12)


def test_every_source_on_one_sample_at_a_time_equals_one_block(
        description: RobotDescription) -> None:
    params = load_twin_parameters(preset='worn')
    assert set(params.enabled_sources) == set(dataclasses.asdict(params)) - {
        'sample_period', 'path'}
    block_twin, stream_twin = (DigitalTwin(description, params, seed=5) for _ in range(2))
    block = block_twin.step(150)
    stream = [stream_twin.step(1) for _ in range(150)]
    np.testing.assert_allclose(np.vstack([s.joints.actual for s in stream]),
                               block.joints.actual, rtol=0, atol=1e-12)
    measured = np.vstack([s.joints.measured for s in stream])
    steps = np.array([params.quantisation.length_step] * 3 + [params.quantisation.angle_step] * 2)
    assert (np.abs(measured - block.joints.measured) <= 1.01 * steps).all()
    assert (measured == block.joints.measured).mean() > 0.99


def test_machine_seed_fixes_the_machine_seed_the_run(description: RobotDescription) -> None:
    params = load_twin_parameters(preset='worn')
    first, second = (DigitalTwin(description, params, seed=s, machine_seed=7).plant
                     for s in (1, 2))
    for name in ('branch_gains', 'branch_time_constants', 'branch_play',
                 'branch_thermal_amplitudes'):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    tips = np.tile([0.05, -0.03, 1.097], (20, 1))
    assert not np.array_equal(first.advance(tips).measured, second.advance(tips).measured)
    default, same = (DigitalTwin(description, params, seed=2, machine_seed=m).plant
                     for m in (None, 2))
    np.testing.assert_array_equal(default.branch_play, same.branch_play)
    assert not np.array_equal(default.branch_play, first.branch_play)
