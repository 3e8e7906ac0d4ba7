# SPDX-License-Identifier: Apache-2.0
"""The twin's backlash, Stribeck friction and thermal growth, the machine seed, and the
irreducible level of every random source, against hand-computed values."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import batch_forward_kinematics
from lompr_predictor.twin import (
    DigitalTwin,
    Simulation,
    irreducible_rmse,
    load_twin_parameters,
    simulate,
)
from lompr_predictor.twin.plant import (
    friction_force,
    gravity_axial_forces,
    play_operator,
    thermal_growth,
)
from lompr_predictor.twin.simulation import expected_reading

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


@pytest.mark.parametrize('ratio', [0.0, 0.1, 0.2, 0.3, 1.5])
def test_expected_reading_is_the_mean_of_the_quantised_reading(ratio: float) -> None:
    rng = np.random.default_rng(0)
    step = 1e-6
    mean = np.array([0.0, 0.3, 0.5, 1.7, -2.45]) * step
    draws = mean + ratio * step * rng.standard_normal((200_000, 1))
    sampled = (np.round(draws / step) * step).mean(0)
    np.testing.assert_allclose(expected_reading(mean, ratio * step, step), sampled,
                               rtol=0, atol=0.01 * step)
    np.testing.assert_array_equal(expected_reading(mean, ratio * step, None), mean)


def _fk_noise_rms(sim: Simulation, std: np.ndarray) -> np.ndarray:
    """X/Y RMS of joint noise of `std` (5,) through the FK's Jacobian along the run."""
    joints = sim.joints_commanded
    base = batch_forward_kinematics(sim.geometry, joints).position[:, :2]
    variance = np.zeros_like(base)
    for j in range(5):
        delta = np.zeros(5)
        delta[j] = 1e-7
        column = (batch_forward_kinematics(sim.geometry, joints + delta).position[:, :2]
                  - base) / 1e-7
        variance += (column * std[j]) ** 2
    return np.sqrt(variance.mean(0))


def test_irreducible_of_a_noise_only_twin_is_the_noise_through_fk(
        description: RobotDescription) -> None:
    sim = simulate(description, PARAMS.with_sources('noise'), passes=6, seed=4)
    std = np.array([PARAMS.noise.length_std] * 3 + [PARAMS.noise.angle_std] * 2)
    expected = _fk_noise_rms(sim, std)
    # 6600 draws: the sampled RMS scatters by ~2 % about the expected one (seeds 4-9).
    for horizon in (1, 25):
        np.testing.assert_allclose(irreducible_rmse(sim, horizon), expected, rtol=0.05)


def test_a_coarse_encoder_without_noise_is_predictable(description: RobotDescription) -> None:
    coarse = dataclasses.replace(PARAMS, quantisation=dataclasses.replace(
        PARAMS.quantisation, length_step=1e-6))
    sim = simulate(description, coarse.with_sources('quantisation'), passes=1, seed=4)
    measured_rms = np.sqrt(np.mean(sim.error_measured[:, :2] ** 2, axis=0))
    assert np.all(measured_rms > 0.15 * UM)  # the rounding error is there ...
    np.testing.assert_allclose(irreducible_rmse(sim, 1), 0.0, atol=1e-11)  # ... but known
    # With noise well above the step the rounding adds its step^2 / 12, unpredictable.
    noisy = simulate(description, coarse.with_sources('quantisation', 'noise'), passes=6, seed=4)
    std = np.array([np.hypot(PARAMS.noise.length_std, 1e-6 / np.sqrt(12))] * 3
                   + [np.hypot(PARAMS.noise.angle_std, PARAMS.quantisation.angle_step
                               / np.sqrt(12))] * 2)
    np.testing.assert_allclose(irreducible_rmse(noisy, 1), _fk_noise_rms(noisy, std), rtol=0.05)


def test_irreducible_of_the_drift_is_its_innovation_over_the_horizon(
        description: RobotDescription) -> None:
    sim = simulate(description, PARAMS.with_sources('drift'), passes=2, seed=4)
    decay = np.exp(-PARAMS.sample_period / PARAMS.drift.time_constant)
    for horizon in (1, 25, 100):
        innovation = PARAMS.drift.standard_deviation * np.sqrt(1 - decay ** (2 * horizon))
        expected = _fk_noise_rms(sim, np.array([innovation] * 3 + [0.0] * 2))
        # 2200 samples of a correlated process: the sampled RMS is within ~10 %.
        np.testing.assert_allclose(irreducible_rmse(sim, horizon), expected, rtol=0.12)
        np.testing.assert_allclose(irreducible_rmse(sim, horizon, measured=False),
                                   irreducible_rmse(sim, horizon), rtol=1e-9)


def test_deterministic_physics_adds_nothing_irreducible(description: RobotDescription) -> None:
    worn = load_twin_parameters(preset='worn')
    random_only = worn.with_sources('noise', 'quantisation')
    every = dataclasses.replace(worn, drift=dataclasses.replace(worn.drift, enabled=False))
    levels = [irreducible_rmse(simulate(description, p, passes=1, seed=6), 1)
              for p in (random_only, every)]
    np.testing.assert_allclose(levels[1], levels[0], rtol=0.03)
    assert np.all(levels[0] > 0.5 * UM)
