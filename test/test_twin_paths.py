"""The paper's paths: Eq. 29, continuity of the passes and their returns, reachability."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import inverse_kinematics
from lompr_predictor.robot.paths import PATH_KINDS, build_cycle, speed_profile, spiral_pass
from lompr_predictor.twin import load_twin_parameters

PARAMS = load_twin_parameters()
CONFIG = PARAMS.path


def test_spiral_is_eq_29() -> None:
    xy = spiral_pass(CONFIG, 0.04)
    assert len(xy) == 1001  # 40 s at 25 Hz, both ends included
    t_h = np.arange(1001) * 0.04 / 4.0  # t_h from 0 to 10 over 40 s
    phase = np.pi / 2 * t_h + np.pi / 2
    np.testing.assert_allclose(xy[:, 0], 0.020 * t_h * np.cos(phase), atol=1e-15)
    np.testing.assert_allclose(xy[:, 1], 0.020 * t_h * np.sin(phase), atol=1e-15)
    assert np.linalg.norm(xy[-1]) == pytest.approx(0.200)


@pytest.mark.parametrize('kind', PATH_KINDS)
def test_cycle_is_smooth_and_on_the_mirror(kind: str) -> None:
    cycle = build_cycle(kind, CONFIG, 0.04)
    positions = cycle.positions
    assert np.all(positions[:, 2] == CONFIG.height)
    assert np.linalg.norm(positions[:, :2], axis=1).max() <= CONFIG.radius + 1e-12
    # Endless: the step from the last sample to the first is like any other.
    wrapped = np.vstack([positions, positions[:2]])
    velocity = np.diff(wrapped[:, :2], axis=0) / 0.04
    acceleration = np.diff(velocity, axis=0) / 0.04
    assert np.linalg.norm(velocity, axis=1).max() < 0.2  # m/s
    assert np.linalg.norm(acceleration, axis=1).max() < 0.5  # m/s^2: no jumps in velocity
    assert not cycle.in_pass(0, len(cycle))[-1] and cycle.in_pass(0, len(cycle))[0]
    np.testing.assert_array_equal(cycle.sample(len(cycle) + 3, 2), positions[3:5])
    np.testing.assert_array_equal(cycle.pass_index(len(cycle) - 1, 2), [0, 1])


@pytest.mark.parametrize('kind', PATH_KINDS)
def test_every_path_is_reachable(description: RobotDescription, kind: str) -> None:
    geometry = description.geometry
    joints = inverse_kinematics(geometry, build_cycle(kind, CONFIG, 0.04).positions).joints
    assert (joints[:, :3] >= geometry.stroke_lower).all()
    assert (joints[:, :3] <= geometry.stroke_upper).all()
    assert (np.abs(joints[:, 4]) <= geometry.head_secondary_upper).all()


def test_grid_and_concentric_run_at_the_feed_speed() -> None:
    for kind in ('grid', 'concentric'):
        xy = build_cycle(kind, CONFIG, 0.04).positions[:, :2]
        speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.04
        assert np.median(speed) == pytest.approx(CONFIG.feed_speed, rel=0.02)


def test_speed_profile_runs_from_rest_to_rest() -> None:
    arc = speed_profile(1.0, 0.05, 1.0, 0.04)
    speed = np.diff(arc) / 0.04
    assert arc[0] == 0.0 and arc[-1] == pytest.approx(1.0)
    assert speed[0] < 0.001 and speed[-1] < 0.001  # starts and stops at rest
    assert np.median(speed) == pytest.approx(0.05, rel=1e-3)
    assert len(arc) == pytest.approx((1.0 / 0.05 + 1.0) / 0.04, abs=2)  # ramps cost ramp_time
    assert np.abs(np.diff(speed)).max() / 0.04 < 1.6 * 0.05 / 1.0  # smoothstep peak 1.5 v/T


@pytest.mark.parametrize('kind', PATH_KINDS)
def test_a_varied_feed_runs_each_pass_on_the_same_geometry_at_another_speed(kind: str) -> None:
    variation = 0.5
    config = dataclasses.replace(CONFIG, feed_variation=variation)
    cycle = build_cycle(kind, config, seed=4)
    nominal = build_cycle(kind, CONFIG)
    count, n = cycle.pass_samples, len(cycle)
    assert n == len(nominal)
    path = cycle.sample(0, 3 * n)
    passes = [path[k * n:(k + 1) * n] for k in range(3)]
    for run in passes:  # same ends, same return, the pass on the nominal geometry
        np.testing.assert_allclose(run[[0, count - 1]], nominal.positions[[0, count - 1]],
                                   atol=1e-12)
        np.testing.assert_array_equal(run[count:], nominal.positions[count:])
        assert np.linalg.norm(run[:, :2], axis=1).max() <= CONFIG.radius + 1e-9
    assert np.abs(passes[0] - passes[1]).max() > 1e-3  # the passes differ
    np.testing.assert_array_equal(cycle.sample(n + 5, 7), passes[1][5:12])  # by pass number
    np.testing.assert_array_equal(build_cycle(kind, config, seed=4).sample(0, n), passes[0])
    # the speed along the pass: the nominal one times g in [1 - variation, 1 + variation]
    if kind == 'spiral':  # (the others start and end at rest: ratios of tiny speeds there)
        speed = np.linalg.norm(np.diff(passes[0][:count, :2], axis=0), axis=1)
        base = np.linalg.norm(np.diff(nominal.positions[:count, :2], axis=0), axis=1)
        ratio = speed / base
        assert 1 - variation - 0.02 <= ratio.min() < 0.9 and 1.1 < ratio.max() <= (
            1 + variation + 0.02)
    with pytest.raises(ValueError, match='feed_variation'):
        build_cycle(kind, dataclasses.replace(CONFIG, feed_variation=1.0))
