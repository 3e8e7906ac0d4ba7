# SPDX-License-Identifier: Apache-2.0
"""twin.simulation: the irreducible level of every random source (what no causal predictor
can beat) against hand-computed values, the expected reading of a quantised noisy joint,
and the error summary."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import batch_forward_kinematics
from lompr_predictor.twin import Simulation, irreducible_rmse, load_twin_parameters, simulate
from lompr_predictor.twin.simulation import error_summary, expected_reading

PARAMS = load_twin_parameters()
UM = 1e-6


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


def test_the_summary_is_the_peak_and_rms_per_axis_in_micrometres() -> None:
    error = np.array([[3e-6, -1e-6, 9.0], [-4e-6, 1e-6, 9.0]])
    summary = error_summary(error)
    assert summary['x'] == pytest.approx({'peak_um': 4.0, 'rms_um': np.sqrt(12.5)}, abs=1e-12)
    assert summary['y'] == pytest.approx({'peak_um': 1.0, 'rms_um': 1.0}, abs=1e-12)
    assert set(summary) == {'x', 'y'}  # z is no error the machine corrects


def test_a_horizon_beyond_the_run_is_refused(description: RobotDescription) -> None:
    sim = simulate(description, PARAMS.with_sources(), passes=1, seed=1)
    with pytest.raises(ValueError, match=f'horizon must be in \\[0, {len(sim.stamps) - 1}\\]'):
        irreducible_rmse(sim, len(sim.stamps))
