# SPDX-License-Identifier: Apache-2.0
"""The twin's error physics, parameters and stepping (ROS-free)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.twin import (
    SOURCES,
    DigitalTwin,
    TwinParameterError,
    irreducible_rmse,
    load_twin_parameters,
    parse_twin_parameters,
    simulate,
)
from lompr_predictor.twin.plant import gravity_axial_forces

PARAMS = load_twin_parameters()


def _rms(error: np.ndarray) -> float:
    return float(np.sqrt(np.mean(error ** 2)))


def test_every_source_off_leaves_no_error(description: RobotDescription) -> None:
    sim = simulate(description, PARAMS.with_sources(), passes=1, seed=1)
    assert np.abs(sim.error_measured).max() < 1e-9
    assert np.abs(sim.error_true).max() < 1e-9
    np.testing.assert_array_equal(sim.joints_measured, sim.joints_commanded)


@pytest.mark.parametrize('source', SOURCES)
def test_each_source_alone_makes_an_error(description: RobotDescription, source: str) -> None:
    sim = simulate(description, PARAMS.with_sources(source), passes=1, seed=1)
    assert _rms(sim.error_measured[:, :2]) > 2e-8  # the smallest, quantisation, is ~5e-8 m


def test_servo_lag_grows_with_path_speed(description: RobotDescription) -> None:
    servo = PARAMS.with_sources('servo')
    rms = []
    for duration in (40.0, 20.0):  # the same spiral, at twice the speed
        params = dataclasses.replace(
            servo, path=dataclasses.replace(servo.path, spiral_duration=duration))
        sim = simulate(description, params, passes=1, seed=1)
        rms.append(_rms(sim.error_true[sim.in_pass, :2]))
    # Mostly velocity-proportional ((1 - kff) v / Kp), plus an acceleration term ~ v^2.
    assert 1.8 < rms[1] / rms[0] < 2.6


def test_servo_error_vanishes_at_rest(description: RobotDescription) -> None:
    twin = DigitalTwin(description, PARAMS.with_sources('servo'), seed=1)
    samples = twin.plant.advance(np.tile([0.05, -0.03, 1.097], (50, 1)))
    np.testing.assert_allclose(samples.actual, samples.commanded, atol=1e-12)


def test_spiral_error_grows_with_radius(description: RobotDescription) -> None:
    sim = simulate(description, PARAMS, passes=1, seed=3)
    error = sim.error_measured[sim.in_pass, :2]
    half = len(error) // 2
    assert _rms(error[half:]) > 1.5 * _rms(error[:half])
    assert 10e-6 < np.abs(error[half:]).max() < 200e-6  # tens of micrometres outside


def test_same_seed_same_run_other_seed_other_noise(description: RobotDescription) -> None:
    first, again = (simulate(description, PARAMS, passes=1, seed=7) for _ in range(2))
    other = simulate(description, PARAMS, passes=1, seed=8)
    np.testing.assert_array_equal(first.joints_measured, again.joints_measured)
    np.testing.assert_array_equal(first.error_true, again.error_true)
    assert not np.array_equal(first.joints_measured, other.joints_measured)


def test_one_sample_at_a_time_equals_one_block(description: RobotDescription) -> None:
    block_twin, stream_twin = (DigitalTwin(description, PARAMS, seed=5) for _ in range(2))
    block = block_twin.step(120)
    stream = [stream_twin.step(1) for _ in range(120)]
    np.testing.assert_allclose(np.vstack([s.joints.actual for s in stream]),
                               block.joints.actual, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.vstack([s.tip for s in stream]), block.tip, rtol=0, atol=1e-10)
    measured = np.vstack([s.joints.measured for s in stream])
    steps = np.array([PARAMS.quantisation.length_step] * 3 + [PARAMS.quantisation.angle_step] * 2)
    assert (np.abs(measured - block.joints.measured) <= 1.01 * steps).all()
    np.testing.assert_array_equal(np.concatenate([s.stamps for s in stream]), block.stamps)


def test_constant_compensation_shifts_the_tool(description: RobotDescription) -> None:
    params = PARAMS.with_sources('servo', 'friction', 'elastic', 'head')
    offset = np.array([20e-6, -15e-6, 0.0])
    plain = DigitalTwin(description, params, seed=2).step(400)
    shifted = DigitalTwin(description, params, seed=2).step(400, offset)
    np.testing.assert_array_equal(shifted.compensation, np.tile(offset, (400, 1)))
    # The tool moves by the offset; the plant's own error hardly changes (sub-micrometre).
    # Not at sample 0: at the spiral's centre the offset decides the primary head angle,
    # which turns the secondary head's offset error into another direction.
    np.testing.assert_allclose(shifted.tip[1:] - plain.tip[1:], np.tile(offset, (399, 1)),
                               atol=0.2e-6)
    np.testing.assert_allclose(shifted.plant_error_true[1:], plain.error_true[1:], atol=0.2e-6)


def test_gravity_load_is_shared_by_the_branches(description: RobotDescription) -> None:
    geometry = description.geometry
    weight = 1000.0
    level = np.array([[0.0, 0.0, 0.75]])
    tension = gravity_axial_forces(geometry, level, weight, 0.25)[0]
    np.testing.assert_allclose(tension, tension.mean(), rtol=1e-9)  # symmetric posture
    anchors = geometry.platform_anchors + np.array([0.0, 0.0, 0.75])
    directions = anchors - geometry.base_anchors
    vertical = directions[:, 2] / np.linalg.norm(directions, axis=1)
    assert tension @ vertical == pytest.approx(weight, rel=1e-9)  # they carry all of it
    tilted = gravity_axial_forces(geometry, np.array([[0.1, -0.05, 0.75]]), weight, 0.25)[0]
    assert np.ptp(tilted) > 0.01 * weight  # the share depends on the posture


def test_irreducible_is_the_noise_and_the_drift_innovation(description: RobotDescription) -> None:
    noise = simulate(description, PARAMS.with_sources('noise'), passes=1, seed=4)
    for horizon in (1, 25):  # white noise: nothing to predict, at any horizon
        np.testing.assert_allclose(
            irreducible_rmse(noise, horizon),
            np.sqrt(np.mean(noise.error_measured[horizon:, :2] ** 2, axis=0)), rtol=1e-6)
    drift = simulate(description, PARAMS.with_sources('drift'), passes=2, seed=4)
    np.testing.assert_allclose(irreducible_rmse(drift, 0), 0.0, atol=1e-15)
    levels = [irreducible_rmse(drift, h).mean() for h in (1, 10, 100)]
    assert 0.0 < levels[0] < levels[1] < levels[2]


def test_parameter_file_overrides_a_subset(tmp_path: Path) -> None:
    path = tmp_path / 'twin.yaml'
    path.write_text('servo:\n  velocity_feedforward: 0.9\nfriction:\n  servo_stiffness: 3.0e7\n')
    params = load_twin_parameters(path)
    assert params.servo.velocity_feedforward == 0.9
    assert params.friction.servo_stiffness == 3e7  # YAML 1.1 reads 3.0e7 as a string
    assert params.elastic == PARAMS.elastic


@pytest.mark.parametrize(('overrides', 'match'), [
    ({'servo': {'gain': 1.0}}, r"unknown key\(s\) \['gain'\] in servo"),
    ({'lubrication': {}}, r"unknown section\(s\) \['lubrication'\]"),
    ({'noise': {'length_std': -1.0}}, 'noise.length_std must be positive'),
    ({'friction': {'coulomb_force': -5.0}}, r'friction.coulomb_force must be >= 0'),
    ({'drift': {'enabled': 'yes'}}, 'drift.enabled must be true or false'),
])
def test_bad_parameters_are_named(overrides: dict, match: str) -> None:
    with pytest.raises(TwinParameterError, match=match):
        parse_twin_parameters(overrides)
