# SPDX-License-Identifier: Apache-2.0
"""The twin's programs: the paper's Eq. 29, continuity of the passes and their returns,
bounded accelerations and jerks, reachability; the random program's draws."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import inverse_kinematics
from lompr_predictor.robot.paths import (
    PATH_KINDS,
    PathConfig,
    PathCycle,
    build_cycle,
    random_feed_arc,
    speed_profile,
    spiral_pass,
)
from lompr_predictor.twin import load_twin_parameters
from lompr_predictor.twin.parameters import TwinParameterError, parse_twin_parameters

PARAMS = load_twin_parameters()
CONFIG = PARAMS.path
PERIOD = 0.04
#: The programs whose corners are rounded twice over the whole cycle (module docstring of
#: `robot/paths.py`): their acceleration and jerk have bounds from the parameters.
ROUNDED_TWICE = ('lissajous', 'radial', 'random')
#: The bound on the acceleration [m/s^2] of the other programs (corners rounded once, so
#: their acceleration steps at a corner and their jerk has no bound but 1 / sample period).
ROUNDED_ONCE_ACCELERATION = 0.5


def cycles(cycle: PathCycle, count: int = 3) -> np.ndarray:
    """(count M, 3) the first `count` passes and their returns, as the twin runs them."""
    return cycle.sample(0, count * len(cycle))


def differences(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Norms of the X/Y velocity, acceleration and jerk by differences [m/s, m/s^2, m/s^3]."""
    velocity = np.diff(positions[:, :2], axis=0) / PERIOD
    acceleration = np.diff(velocity, axis=0) / PERIOD
    jerk = np.diff(acceleration, axis=0) / PERIOD
    return tuple(np.linalg.norm(d, axis=1) for d in (velocity, acceleration, jerk))


def peak_raw_speed(kind: str, config: PathConfig) -> float:
    """The largest speed [m/s] of a twice-rounded program before rounding, from the
    parameters: its pass's (a Lissajous curve's bound below, `feed_speed` along the star,
    the random feed's largest) or its return's (a cubic from rest to rest over a distance d
    peaks at 1.5 d / return_duration; d at most the diameter, or the star's closing arc)."""
    def returning(distance: float) -> float:
        return 1.5 * distance / config.return_duration

    if kind == 'radial':  # the last stroke ends pi / strokes short of the first's start
        chord = 2.0 * config.radius * np.sin(0.5 * np.pi / config.radial_strokes)
        return max(config.feed_speed, returning(chord))
    if kind == 'random':
        return max(config.feed_speed * (1.0 + config.random_feed_variation),
                   returning(2.0 * config.radius))
    # (x g(y), y g(x)) R, x = sin(a theta + phase), y = sin(b theta), g(u) = sqrt(1 - u^2/2):
    # |g| <= 1 and |g'| <= 1/sqrt(2) on [-1, 1], so |d/dtheta| <= R (a + b/sqrt(2)) and
    # R (b + a/sqrt(2)) per axis; theta runs at most 2 pi / lissajous_duration.
    a, b = config.lissajous_x_cycles, config.lissajous_y_cycles
    rate = 2.0 * np.pi / config.lissajous_duration
    curve = config.radius * rate * np.hypot(a + b / np.sqrt(2.0), b + a / np.sqrt(2.0))
    return max(curve, returning(2.0 * config.radius))


def rounding_limits(kind: str, config: PathConfig) -> tuple[float, float]:
    """Bounds on the acceleration and jerk [m/s^2, m/s^3] of a twice-rounded program: a
    moving average over n samples of a path whose steps are at most V dt makes steps whose
    differences are at most 2 V dt / n; twice, differences of those at most 4 V dt / n^2."""
    window = (2 * round(0.5 * config.corner_time / PERIOD) + 1) * PERIOD  # n dt
    speed = peak_raw_speed(kind, config)
    return 2.0 * speed / window, 4.0 * speed / window ** 2


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
    cycle = build_cycle(kind, CONFIG, PERIOD)
    positions = cycles(cycle)  # endless: the steps from one cycle into the next included
    assert np.all(positions[:, 2] == CONFIG.height)
    # inside the disk to rounding (a moving average of points of a disk stays in it)
    assert np.linalg.norm(positions[:, :2], axis=1).max() <= CONFIG.radius + 1e-12
    speed, acceleration, _ = differences(positions)
    assert speed.max() < 0.2  # m/s
    assert acceleration.max() < ROUNDED_ONCE_ACCELERATION  # m/s^2: no jumps in velocity
    assert not cycle.in_pass(0, len(cycle))[-1] and cycle.in_pass(0, len(cycle))[0]
    np.testing.assert_array_equal(cycle.pass_index(len(cycle) - 1, 2), [0, 1])
    if kind != 'random':  # the others repeat
        np.testing.assert_array_equal(cycle.sample(len(cycle) + 3, 2), cycle.positions[3:5])


@pytest.mark.parametrize('kind', ROUNDED_TWICE)
def test_accelerations_and_jerks_stay_within_the_bounds_of_the_parameters(kind: str) -> None:
    limit_acceleration, limit_jerk = rounding_limits(kind, CONFIG)
    _, acceleration, jerk = differences(cycles(build_cycle(kind, CONFIG, PERIOD, seed=2)))
    assert acceleration.max() <= limit_acceleration
    assert jerk.max() <= limit_jerk
    # the bounds are not loose by orders of magnitude
    assert acceleration.max() > 0.1 * limit_acceleration and jerk.max() > 0.05 * limit_jerk


@pytest.mark.parametrize('kind', PATH_KINDS)
def test_the_velocity_is_continuous_where_a_pass_and_a_return_join(kind: str) -> None:
    """At each join (pass to return, return to the next pass) the velocity changes by no
    more in one sample than the program's acceleration bound allows."""
    cycle = build_cycle(kind, CONFIG, PERIOD, seed=5)
    n = len(cycle)
    velocity = np.diff(cycles(cycle)[:, :2], axis=0) / PERIOD
    limit = (rounding_limits(kind, CONFIG)[0] if kind in ROUNDED_TWICE
             else ROUNDED_ONCE_ACCELERATION)
    for first in (k * n + offset for k in range(3) for offset in (cycle.pass_samples, n)):
        if first < len(velocity):  # the velocity into and out of sample `first`
            jump = np.linalg.norm(velocity[first] - velocity[first - 1]) / PERIOD
            assert jump <= limit, f'{kind}: {jump:.3f} m/s^2 at sample {first}'


@pytest.mark.parametrize('kind', PATH_KINDS)
def test_every_path_is_reachable(description: RobotDescription, kind: str) -> None:
    """Inverse kinematics covers every sample of two passes, anywhere in the workspace the
    compensation may move the tool to: the disk at the mirror's height +- 0.05 m."""
    geometry = description.geometry
    positions = cycles(build_cycle(kind, CONFIG, PERIOD, seed=1), 2)
    for lift in (-0.05, 0.0, 0.05):
        joints = inverse_kinematics(geometry, positions + np.array([0.0, 0.0, lift])).joints
        assert np.isfinite(joints).all()
        assert (joints[:, :3] >= geometry.stroke_lower).all()
        assert (joints[:, :3] <= geometry.stroke_upper).all()
        assert (np.abs(joints[:, 4]) <= geometry.head_secondary_upper).all()


def test_grid_concentric_and_radial_run_at_the_feed_speed() -> None:
    for kind in ('grid', 'concentric', 'radial'):
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
    nominal = build_cycle(kind, CONFIG, seed=4)  # (random: the same passes' geometry)
    count, n = cycle.pass_samples, len(cycle)
    assert n == len(nominal)
    path, nominal_path = cycle.sample(0, 3 * n), nominal.sample(0, 3 * n)
    passes = [path[k * n:(k + 1) * n] for k in range(3)]
    for k, run in enumerate(passes):  # same ends, same return, the pass on its geometry
        base = nominal_path[k * n:(k + 1) * n]
        np.testing.assert_allclose(run[[0, count - 1]], base[[0, count - 1]], atol=1e-12)
        np.testing.assert_array_equal(run[count:], base[count:])
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


def test_random_passes_differ_by_pass_and_seed_and_repeat_for_the_same_ones() -> None:
    cycle = build_cycle('random', CONFIG, PERIOD, seed=7)
    n = len(cycle)
    assert cycle.pass_samples == round(CONFIG.random_duration / PERIOD) + 1  # a fixed duration
    passes = cycles(cycle, 4).reshape(4, n, 3)
    for k in range(3):
        assert np.abs(passes[k + 1] - passes[k]).max() > 0.05  # another path every pass
    other_seed = cycles(build_cycle('random', CONFIG, PERIOD, seed=8), 1)
    assert np.abs(other_seed - passes[0]).max() > 0.05
    # the same seed and pass number, the same samples: asked in another order, by a new cycle
    again = build_cycle('random', CONFIG, PERIOD, seed=7)
    np.testing.assert_array_equal(again.sample(2 * n + 10, 50), passes[2, 10:60])
    np.testing.assert_array_equal(again.sample(n - 20, 40),
                                  np.vstack([passes[0, -20:], passes[1, :20]]))
    np.testing.assert_array_equal(again.pass_positions(0), cycle.positions)


def test_a_random_pass_changes_its_feed_along_it() -> None:
    """The feed before rounding: `feed_speed` x g, g within 1 +- random_feed_variation,
    and g not constant; from rest to rest."""
    variation = CONFIG.random_feed_variation
    for number in range(5):
        arc = random_feed_arc(CONFIG, np.random.default_rng([3, number]), PERIOD)
        speed = np.diff(arc) / PERIOD
        ramp = round(CONFIG.ramp_time / PERIOD)
        cruise = speed[ramp:-ramp] / CONFIG.feed_speed
        assert len(arc) == round(CONFIG.random_duration / PERIOD) + 1
        assert speed[0] < 0.01 * CONFIG.feed_speed and speed[-1] < 0.01 * CONFIG.feed_speed
        assert 1.0 - variation <= cruise.min() and cruise.max() <= 1.0 + variation
        assert cruise.max() - cruise.min() > 0.5 * variation


def test_the_lissajous_curve_covers_the_mirror() -> None:
    """No point of the disk is farther from the curve than the raster's line spacing."""
    xy = build_cycle('lissajous', CONFIG, PERIOD).positions[:, :2]
    axis = np.arange(-CONFIG.radius, CONFIG.radius + 1e-9, 0.005)
    grid = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    grid = grid[np.linalg.norm(grid, axis=1) <= CONFIG.radius]
    farthest = max(np.linalg.norm(chunk[:, None] - xy[None], axis=2).min(axis=1).max()
                   for chunk in np.array_split(grid, 20))
    assert farthest <= CONFIG.grid_spacing


def test_the_radial_star_crosses_the_centre_in_every_direction_and_reverses() -> None:
    cycle = build_cycle('radial', CONFIG, PERIOD)
    xy = cycle.positions[:cycle.pass_samples, :2]
    velocity = np.diff(xy, axis=0)
    near = np.flatnonzero(np.linalg.norm(xy[:-1], axis=1) < 0.01)  # within 1 cm of it
    crossings = np.split(near, np.flatnonzero(np.diff(near) > 1) + 1)
    assert len(crossings) == CONFIG.radial_strokes
    headings = np.array([velocity[c].sum(axis=0) for c in crossings])
    # straight through the centre: every sample near it on the stroke's line
    for c, heading in zip(crossings, headings, strict=True):
        unit = heading / np.linalg.norm(heading)
        off_line = xy[c, 0] * unit[1] - xy[c, 1] * unit[0]
        assert np.abs(off_line).max() < 1e-12
    angle = np.arctan2(headings[:, 1], headings[:, 0])
    step = np.pi / CONFIG.radial_strokes
    np.testing.assert_allclose(np.sort(np.mod(angle, np.pi)), np.arange(CONFIG.radial_strokes)
                               * step, atol=1e-9)
    # each stroke runs back against the one before it (a reversal in its own direction)
    turn = np.einsum('ij,ij->i', headings[1:], headings[:-1]) / np.prod(
        np.linalg.norm([headings[1:], headings[:-1]], axis=2), axis=0)
    np.testing.assert_allclose(turn, -np.cos(step), atol=1e-9)


def test_the_new_programs_parameters_are_checked() -> None:
    with pytest.raises(TwinParameterError, match='random_feed_variation must be in'):
        parse_twin_parameters({'path': {'random_feed_variation': 1.0}})
    with pytest.raises(TwinParameterError, match='radial_strokes must be positive'):
        parse_twin_parameters({'path': {'radial_strokes': 0}})
    with pytest.raises(ValueError, match=r'lissajous_duration \(3 s\) must be longer'):
        build_cycle('lissajous', dataclasses.replace(CONFIG, lissajous_duration=3.0))
