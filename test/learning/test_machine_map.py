# SPDX-License-Identifier: Apache-2.0
"""The machine map: its kinematics, its least squares, its place in the model, and that what
it learns on one program holds on another (the twin's spiral -> grid)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.features import FEATURES, base_features, feature_names
from lompr_predictor.data.problem import build_problem, train_test_problem
from lompr_predictor.learning.machine_map import (
    FRICTION_SCALES,
    LEVEL_WINDOW_SECONDS,
    MachineMap,
    fit_machine_map,
    motion_columns,
    speed_scales,
)
from lompr_predictor.learning.map_fit import POSTURE_TERMS
from lompr_predictor.learning.model_file import script_module
from lompr_predictor.learning.models import NoChangeNet, PredictorModule, predict_rows
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import (
    batch_forward_kinematics,
    inverse_kinematics,
    tool_branch_jacobian,
)
from lompr_predictor.twin import load_twin_parameters, simulate
from lompr_predictor.twin.recording import to_recording

JACOBIAN = np.array([[0.0, 1.2, -1.1], [-1.4, 0.7, 0.6]])


def test_jacobian_is_the_forward_kinematics_slope(description: RobotDescription) -> None:
    """A branch longer by dl moves the tool tip by J dl, the head angles held: the columns
    equal central differences of the forward kinematics to 1e-8 (per unit length)."""
    geometry = description.geometry
    tips = np.array([[0.12, -0.07, 1.097], [0.0, 1e-4, 1.05], [-0.18, 0.05, 1.14]])
    jacobian = tool_branch_jacobian(geometry, tips)
    joints = inverse_kinematics(geometry, tips).joints
    for branch in range(3):
        step = np.zeros(5)
        step[branch] = 1e-7
        moved = (batch_forward_kinematics(geometry, joints + step).position
                 - batch_forward_kinematics(geometry, joints - step).position)[:, :2] / 2e-7
        np.testing.assert_allclose(jacobian[:, :, branch], moved, atol=1e-8)


def _rows(count: int, seed: int = 0, preview: int = 0) -> np.ndarray:
    """Random feature rows over the mirror: positions within 0.2 m, branch speeds up to
    0.04 m/s, accelerations up to 0.2 m/s^2 (the plan block as a second such row)."""
    rng = np.random.default_rng(seed)
    names = feature_names(preview)
    rows = np.zeros((count, len(names)))
    for prefix in ('', 'plan_') if preview else ('',):
        for name, scale in (('ref_x', 0.2), ('ref_y', 0.2), ('ref_vx', 0.05), ('ref_vy', 0.05),
                            *((f'ups{i}_v', 0.04) for i in (1, 2, 3)),
                            *((f'ups{i}_a', 0.2) for i in (1, 2, 3))):
            column = prefix + name
            if column in names:
                rows[:, names.index(column)] = rng.uniform(-scale, scale, count)
    if preview:
        for axis in 'xy':
            rows[:, names.index(f'plan_d{axis}')] = rng.uniform(-0.01, 0.01, count)
    return rows


def _known_map(features: tuple[str, ...], horizon: int = 1, preview: int = 0) -> MachineMap:
    return _with_random_coefficients(
        MachineMap(features, horizon, preview, 0.04, JACOBIAN, 0.02 * np.asarray(FRICTION_SCALES)),
        seed=7)


def _with_random_coefficients(machine_map: MachineMap, seed: int) -> MachineMap:
    """`machine_map` with every coefficient of both fits drawn at random (1e-5 m scale)."""
    rng = np.random.default_rng(seed)
    with torch.no_grad():
        for coefficients in (machine_map.branch_coefficients,
                             machine_map.posture_coefficients,
                             machine_map.level_branch_coefficients,
                             machine_map.level_posture_coefficients):
            coefficients.copy_(torch.from_numpy(rng.normal(0.0, 1e-5, coefficients.shape)))
    return machine_map


def _no_change_module(machine_map: MachineMap) -> PredictorModule:
    """A model on `machine_map` whose network predicts no change: its prediction is the
    map prior."""
    n = len(FEATURES)
    return PredictorModule(NoChangeNet(), np.zeros(n + 2), np.ones(n + 2), -np.ones(2),
                           np.ones(2), residual=True, relative_errors=True,
                           machine_map=machine_map)


def _rows_with_errors(seed: int) -> np.ndarray:
    """40 feature rows (`_rows`) with plant errors of a few micrometres."""
    rows = _rows(40, seed=seed)
    rows[:, :2] = np.random.default_rng(seed).normal(0.0, 1e-5, (40, 2))
    return rows


def test_map_is_each_branch_error_through_the_jacobian_plus_the_posture() -> None:
    """g = J (c_v v + c_a a + sum c_k tanh(v / s_k)) + P(x, y), by hand for one row; the
    residual map the same form with its own coefficients."""
    machine_map = _known_map(FEATURES)
    row = _rows(1, seed=3)[0]
    value = lambda name: row[FEATURES.index(name)]  # noqa: E731
    v = np.array([value(f'ups{i}_v') for i in (1, 2, 3)])
    a = np.array([value(f'ups{i}_a') for i in (1, 2, 3)])
    scales = machine_map.scales.numpy()
    x, y = value('ref_x'), value('ref_y')
    terms = np.array([1.0, x, y, x * x, x * y, y * y])

    def by_hand(branch: torch.Tensor, posture: torch.Tensor) -> np.ndarray:
        c = branch.numpy()
        branch_error = c[0] * v + c[1] * a + sum(c[2 + k] * np.tanh(v / s)
                                                 for k, s in enumerate(scales))
        return JACOBIAN @ branch_error + terms @ posture.numpy()

    with torch.no_grad():
        got = machine_map.rows(torch.from_numpy(row[None, None]))[0, 0].numpy()
        levels = machine_map.levels_and_change(torch.from_numpy(row[None, None]))[0][0, 0]
    np.testing.assert_allclose(got, by_hand(machine_map.branch_coefficients,
                                            machine_map.posture_coefficients),
                               rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(levels.numpy(), by_hand(machine_map.level_branch_coefficients,
                                                       machine_map.level_posture_coefficients),
                               rtol=1e-12, atol=1e-20)
    assert np.abs(levels.numpy() - got).min() > 1e-7  # two maps, not one read twice
    assert len(POSTURE_TERMS) == len(terms)


def test_one_evaluation_gives_the_residual_map_and_the_change_of_g() -> None:
    """`levels_and_change` of windows: the residual map at every row (`levels`), and g at
    the predicted instant minus g at the last row (`ahead` - `rows`)."""
    machine_map = _known_map(FEATURES, horizon=3)
    rows = _rows_with_errors(seed=8)
    windows = torch.from_numpy(np.stack([rows[:10], rows[20:30]]))
    with torch.no_grad():
        levels, change = machine_map.levels_and_change(windows)
        expected_change = (machine_map.ahead(windows[:, -1])
                           - machine_map.rows(windows)[:, -1]).numpy()
    np.testing.assert_allclose(levels.numpy(), np.stack([machine_map.levels(rows[:10]),
                                                         machine_map.levels(rows[20:30])]),
                               rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(change.numpy(), expected_change, rtol=1e-12, atol=1e-20)


def test_least_squares_recovers_the_coefficients() -> None:
    """Errors made by a known map are fitted back to 1e-9 m everywhere, from their changes
    between consecutive rows and, for the posture's constant, their mean."""
    truth = _known_map(FEATURES)
    rows = _rows(4000, seed=1)
    with torch.no_grad():
        error = truth.rows(torch.from_numpy(rows[None]))[0].numpy()
    fitted = MachineMap(FEATURES, 1, 0, 0.04, JACOBIAN, truth.scales.numpy())
    assert fitted.fit(rows, error, np.arange(len(rows))) < 1e-10  # m
    check = _rows(500, seed=2)
    with torch.no_grad():
        expected = truth.rows(torch.from_numpy(check[None]))[0].numpy()
        np.testing.assert_allclose(fitted.rows(torch.from_numpy(check[None]))[0].numpy(),
                                   expected, atol=1e-9)
    np.testing.assert_allclose(fitted.levels(check), expected, atol=1e-9)


def _drifting_record(truth: MachineMap, count: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.random.Generator]:
    """`count` feature rows whose tool x follows half a period of a sine over the record (a
    program that works its way across the mirror), the errors `truth` makes at them, the
    sine, and the random generator the x jitter was drawn from (for more draws)."""
    rows = _rows(count, seed=1)
    slow = np.sin(np.linspace(0.0, np.pi, count))
    rng = np.random.default_rng(4)
    rows[:, FEATURES.index('ref_x')] = 0.15 * slow + rng.uniform(-0.05, 0.05, count)
    with torch.no_grad():
        made = truth.rows(torch.from_numpy(rows[None]))[0].numpy()
    return rows, made, slow, rng


def test_a_slow_drift_of_the_error_leaves_the_coefficients_as_they_are() -> None:
    """Heat or drift adds to the error a slow part the motion does not explain (here 50 um
    over the record, half a period of a sine, with a noise of 0.5 um) while the tool's x
    drifts alike (a program that works its way across the mirror): the map fitted on the
    error's changes still gives the known map's changes to 5 % of their RMS (fitted on the
    levels, the drift goes into the posture terms: 85-130 % off)."""
    horizon = 3
    truth = _known_map(FEATURES, horizon)
    rows, made, slow, rng = _drifting_record(truth, 4000)
    drift = 50e-6 * slow[:, None] * np.array([1.0, -0.6])
    noise = rng.normal(0.0, 0.5e-6, made.shape)
    fitted = MachineMap(FEATURES, horizon, 0, 0.04, JACOBIAN, truth.scales.numpy())
    fitted.fit(rows, made + drift + noise, np.arange(len(rows)))
    check = torch.from_numpy(_rows(500, seed=2)[None])
    with torch.no_grad():
        changes = [m.rows(check)[0].numpy() - m.rows(check)[0, :1].numpy()
                   for m in (fitted, truth)]
    missed = np.sqrt(np.mean((changes[0] - changes[1]) ** 2, axis=0))
    assert (missed < 0.05 * np.sqrt(np.mean(changes[1] ** 2, axis=0))).all(), missed


def test_runs_too_short_for_the_longer_lags_fit_on_the_shorter_ones() -> None:
    """Runs of 300 samples at horizon 20 hold pairs 20 and 100 apart but none 500 apart:
    the map fits on the first two and recovers the known map; runs shorter than one
    horizon's pairs are refused naming it."""
    truth = _known_map(FEATURES, horizon=20)
    rows = _rows(3000, seed=1)
    with torch.no_grad():
        error = truth.rows(torch.from_numpy(rows[None]))[0].numpy()
    runs = np.concatenate([np.arange(start, start + 300) for start in range(0, 2700, 310)])
    fitted = MachineMap(FEATURES, 20, 0, 0.04, JACOBIAN, truth.scales.numpy())
    assert fitted.fit(rows, error, runs) < 1e-10
    assert fitted.fit_lags == (20, 100)
    check = torch.from_numpy(_rows(200, seed=2)[None])
    with torch.no_grad():
        np.testing.assert_allclose(fitted.rows(check)[0].numpy(), truth.rows(check)[0].numpy(),
                                   atol=1e-9)
    short = np.concatenate([np.arange(start, start + 15) for start in range(0, 2980, 20)])
    with pytest.raises(ValueError, match='needs at least 33 instants with every feature now '
                                         'and 20 samples later in the same run, got 0'):
        MachineMap(FEATURES, 20, 0, 0.04, JACOBIAN, truth.scales.numpy()).fit(rows, error,
                                                                              short)


def test_without_actuator_coordinates_the_map_acts_in_the_tools_axes() -> None:
    """A serial chain's rows carry no actuator columns: the map's motion terms read the
    tool's velocity and acceleration, its Jacobian the identity, and a known map of that
    form is fitted back to 1e-9 m."""
    tool = base_features(())
    assert motion_columns(tool) == (('ref_vx', 'ref_vy'), ('ref_ax', 'ref_ay'))
    truth = _with_random_coefficients(
        MachineMap(tool, 1, 0, 0.004, speed_scales=0.02 * np.asarray(FRICTION_SCALES)), seed=3)
    np.testing.assert_array_equal(truth.jacobian.numpy(), np.eye(2))
    rng = np.random.default_rng(3)
    rows = np.zeros((4000, len(tool)))
    for name, scale in (('ref_x', 0.2), ('ref_y', 0.2), ('ref_vx', 0.05), ('ref_vy', 0.05),
                        ('ref_ax', 0.2), ('ref_ay', 0.2)):
        rows[:, tool.index(name)] = rng.uniform(-scale, scale, len(rows))
    with torch.no_grad():
        error = truth.rows(torch.from_numpy(rows[None]))[0].numpy()
    # by hand for one row: x velocity 0.01 m/s alone moves X by c_v 0.01 + sum c_k tanh
    one = np.zeros((1, len(tool)))
    one[0, tool.index('ref_vx')] = 0.01
    coefficients = truth.branch_coefficients.numpy()[:, 0]
    by_hand = (coefficients[0] * 0.01 + sum(
        c * np.tanh(0.01 / s) for c, s in zip(coefficients[2:], truth.scales.numpy(),
                                              strict=True))
               + truth.posture_coefficients.numpy()[0, 0])
    with torch.no_grad():
        assert truth.rows(torch.from_numpy(one[None]))[0, 0, 0].item() == pytest.approx(
            by_hand, abs=1e-15)
    fitted = MachineMap(tool, 1, 0, 0.004, speed_scales=truth.scales.numpy())
    assert fitted.fit(rows, error, np.arange(len(rows))) < 1e-10


def test_the_residual_map_leaves_a_drift_slower_than_its_window_out() -> None:
    """The same slow drift (`test_a_slow_drift...`, here 40 windows long) with the tool's
    x drifting alike: the residual map, fitted on the error's deviations from its mean over
    its window, gives the known map's values to 5 % of their RMS; fitted over a window
    longer than the record (the error's levels), the drift bends it by far more."""
    truth = _known_map(FEATURES)
    with torch.no_grad():
        truth.level_branch_coefficients.copy_(truth.branch_coefficients)
        truth.level_posture_coefficients.copy_(truth.posture_coefficients)
    rows, made, slow, _ = _drifting_record(truth, 8000)
    error = made + 50e-6 * slow[:, None] * np.array([1.0, -0.6])
    check = _rows(500, seed=2)
    expected = truth.levels(check)
    missed = {}
    for name, window in (('window', 100), ('levels', 10 * len(rows))):
        fitted = MachineMap(FEATURES, 1, 0, LEVEL_WINDOW_SECONDS / window, JACOBIAN,
                            truth.scales.numpy())
        assert fitted.level_window == window
        fitted.fit(rows, error, np.arange(len(rows)))
        got = fitted.levels(check)
        missed[name] = np.sqrt(np.mean((got - got.mean(0) - expected + expected.mean(0)) ** 2,
                                       axis=0)) / np.std(expected, axis=0)
    assert (missed['window'] < 0.05).all(), missed
    assert (missed['levels'] > 0.5).all(), missed


def test_predicted_instant_from_the_plan_or_extrapolated() -> None:
    """With a preview reaching the predicted instant the map is read at the plan's row;
    without one, at the last row moved on `horizon` periods at constant acceleration."""
    preview_map = _known_map(feature_names(2), horizon=2, preview=2)
    names = feature_names(2)
    rows = _rows(5, seed=4, preview=2)
    plan = np.zeros((5, len(FEATURES)))
    for i, name in enumerate(FEATURES):
        if f'plan_{name}' in names:
            plan[:, i] = rows[:, names.index(f'plan_{name}')]
    for axis in 'xy':
        plan[:, FEATURES.index(f'ref_{axis}')] = (rows[:, names.index(f'ref_{axis}')]
                                                  + rows[:, names.index(f'plan_d{axis}')])
    plain = MachineMap(FEATURES, 2, 0, 0.04, JACOBIAN, preview_map.scales.numpy())
    with torch.no_grad():
        plain.branch_coefficients.copy_(preview_map.branch_coefficients)
        plain.posture_coefficients.copy_(preview_map.posture_coefficients)
        np.testing.assert_allclose(preview_map.ahead(torch.from_numpy(rows)).numpy(),
                                   plain.rows(torch.from_numpy(plan[None]))[0].numpy(),
                                   rtol=1e-12)
        moved = rows[:, :len(FEATURES)].copy()
        lead = 2 * 0.04
        for axis in 'xy':
            moved[:, FEATURES.index(f'ref_{axis}')] += lead * moved[:, FEATURES.index(
                f'ref_v{axis}')]
        for i in (1, 2, 3):
            moved[:, FEATURES.index(f'ups{i}_v')] += lead * moved[:, FEATURES.index(
                f'ups{i}_a')]
        np.testing.assert_allclose(plain.ahead(torch.from_numpy(rows[:, :len(FEATURES)])).numpy(),
                                   plain.rows(torch.from_numpy(moved[None]))[0].numpy(),
                                   rtol=1e-12)


def test_module_prior_is_persistence_plus_the_maps_change() -> None:
    """A network predicting no change on a map gives e(t) + g(t+h) - g(t), scripted alike."""
    machine_map = _known_map(FEATURES, horizon=3)
    module = _no_change_module(machine_map)
    rows, ends = _rows_with_errors(seed=5), np.arange(9, 40)
    predicted = predict_rows(module, rows, ends, 10)
    with torch.no_grad():
        table = torch.from_numpy(rows)
        change = (machine_map.ahead(table) - machine_map.rows(table[None])[0]).numpy()
    np.testing.assert_allclose(predicted, rows[ends, :2] + change[ends], rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(predict_rows(script_module(module), rows, ends, 10), predicted)


def test_speed_scales_follow_the_training_motion() -> None:
    rows = _rows(1000, seed=6)
    speeds = rows[:, [FEATURES.index(f'ups{i}_v') for i in (1, 2, 3)]]
    np.testing.assert_allclose(speed_scales(rows, FEATURES),
                               np.sqrt(np.mean(speeds ** 2)) * np.asarray(FRICTION_SCALES))
    with pytest.raises(ValueError, match='never move'):
        speed_scales(np.zeros((10, len(FEATURES))), FEATURES)


@pytest.mark.slow
def test_learned_on_a_spiral_it_predicts_a_grid(description: RobotDescription) -> None:
    """The map fitted on two spiral passes of the twin, with the preview of the predicted
    instant, predicts a grid program of the same machine: its prior e(t) + g(t+1) - g(t)
    has under 0.6x persistence's RMSE on both axes (the noise floor is about 0.3x there);
    fitted on the grid itself it does little better, so what it learned is the machine."""
    params = load_twin_parameters()
    data = {path: clean_recordings([to_recording(simulate(
        description, params, passes=2, seed=1, path=path))[0]], LomprChain(description))
        for path in ('spiral', 'grid')}
    ratios = {}
    for trained_on in ('spiral', 'grid'):
        problem = train_test_problem(data[trained_on], data['grid'], 5, 1, preview=1)
        if trained_on == 'grid':  # in distribution: the grid's own first 90 %
            problem = build_problem(data['grid'], 5, 1, preview=1)
        machine_map = fit_machine_map(problem, data[trained_on].reference,
                                      LomprChain(description))
        n = len(problem.features)
        module = PredictorModule(NoChangeNet(), np.zeros(n + 2), np.ones(n + 2), -np.ones(2),
                                 np.ones(2), residual=True, relative_errors=True,
                                 features=problem.features, machine_map=machine_map)
        test = problem.split.test
        actual = problem.error[test + 1]
        prior = predict_rows(module, problem.rows, test, 5)
        rmse = np.sqrt(np.mean((prior - actual) ** 2, axis=0))
        persistence = np.sqrt(np.mean((problem.error[test] - actual) ** 2, axis=0))
        ratios[trained_on] = rmse / persistence
    assert (ratios['spiral'] < 0.6).all(), ratios
    assert (ratios['spiral'] < 1.25 * ratios['grid']).all(), ratios
