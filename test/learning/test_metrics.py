# SPDX-License-Identifier: Apache-2.0
"""Table 1 metrics against values computed by hand on known signals."""

from __future__ import annotations

import numpy as np
import pytest

from lompr_predictor.learning.metrics import (
    axis_metrics,
    loss_difference_t,
    ratios,
    standing_text,
    standings,
    table_metrics,
)


def test_pointwise_metrics_by_hand() -> None:
    actual = np.array([10e-6, 20e-6, 30e-6, 40e-6])
    predicted = actual + np.array([1e-6, -2e-6, 2e-6, -1e-6])
    seconds = np.array([0.0, 0.04, 0.08, 0.12])
    m = axis_metrics(predicted, actual, seconds, low=0.0, high=100e-6, max_step=0.1)
    # errors 1, -2, 2, -1 um; normalised by 100 um: 1, -2, 2, -1 %
    assert m['mse_um2'] == pytest.approx((1 + 4 + 4 + 1) / 4)
    assert m['rmse_um'] == pytest.approx(np.sqrt(2.5))
    assert m['mae_um'] == pytest.approx(1.5)
    assert m['mse_pct'] == pytest.approx(2.5)
    assert m['rmse_pct'] == pytest.approx(np.sqrt(2.5))
    assert m['mae_pct'] == pytest.approx(1.5)
    # trapezoid of |n| = .01, .02, .02, .01 with steps 0.04: 0.04 * (.015 + .02 + .015)
    assert m['iae'] == pytest.approx(0.04 * 0.05)
    assert m['ise'] == pytest.approx(0.04 * (0.5 * (1e-4 + 4e-4) + 4e-4 + 0.5 * (4e-4 + 1e-4)))
    # t |n| = 0, .0008, .0016, .0012
    assert m['itae'] == pytest.approx(0.04 * (0.0004 + 0.0012 + 0.0014))
    # t n^2 = 0, .04*4e-4, .08*4e-4, .12*1e-4
    assert m['itse'] == pytest.approx(
        0.04 * (0.5 * 1.6e-5 + 0.5 * (1.6e-5 + 3.2e-5) + 0.5 * (3.2e-5 + 1.2e-5)))


def test_integrals_of_a_constant_error_match_closed_form() -> None:
    duration, step = 10.0, 0.04
    seconds = np.arange(0.0, duration + step / 2, step)
    actual = np.zeros_like(seconds)
    predicted = np.full_like(seconds, 5e-6)  # n = 5 um / 50 um = 0.1 throughout
    m = axis_metrics(predicted, actual, seconds, low=-20e-6, high=30e-6, max_step=0.1)
    assert m['iae'] == pytest.approx(0.1 * duration)
    assert m['ise'] == pytest.approx(0.01 * duration)
    assert m['itae'] == pytest.approx(0.1 * duration ** 2 / 2)  # trapezoid exact on t
    assert m['itse'] == pytest.approx(0.01 * duration ** 2 / 2)
    assert m['rmse_pct'] == pytest.approx(10.0)


def test_gaps_add_nothing_to_the_integrals() -> None:
    seconds = np.array([0.0, 0.04, 0.08, 5.0, 5.04])
    m = axis_metrics(np.full(5, 1e-6), np.zeros(5), seconds, 0.0, 1e-5, max_step=0.1)
    assert m['iae'] == pytest.approx(0.1 * 0.12)


def test_table_uses_stamps_from_the_first_and_ratios() -> None:
    stamps = 1_700_000_000_000_000_000 + 40_000_000 * np.arange(3, dtype=np.int64)
    actual = np.zeros((3, 2))
    predicted = np.array([[1e-6, 2e-6]] * 3)
    table = table_metrics(predicted, actual, stamps, np.array([0.0, 0.0]),
                          np.array([1e-5, 1e-5]), max_step=0.1)
    assert table['x']['itae'] == pytest.approx(0.1 * 0.08 ** 2 / 2)
    assert table['y']['rmse_um'] == pytest.approx(2.0)
    half = ratios(table, {'x': {k: 2 * v for k, v in table['x'].items()},
                          'y': {k: 2 * v for k, v in table['y'].items()}})
    assert all(v == pytest.approx(0.5) for axis in half.values() for v in axis.values())


def _models(**rmse: tuple[float, float]) -> dict[str, dict[str, dict[str, dict[str, float]]]]:
    return {name: {'metrics': {'x': {'rmse_um': x}, 'y': {'rmse_um': y}}}
            for name, (x, y) in rmse.items()}


def test_standings_name_the_leader_and_the_bo_lstms_margin_by_hand() -> None:
    """Per axis: the leader of all models, the best baseline (the BO-LSTM's own fallback is
    not one) and the BO-LSTM's RMSE over it minus 1; a tie is 0."""
    models = _models(persistence=(10.0, 4.0), ridge=(5.0, 2.0), hgb=(6.0, 2.0),
                     bo_lstm=(5.5, 1.5), bo_lstm_generalist=(4.0, 3.0))
    table = standings(models)
    assert table['x'] == {'leader': 'bo_lstm_generalist', 'best_baseline': 'ridge',
                          'best_baseline_rmse_um': 5.0, 'bo_lstm_rmse_um': 5.5,
                          'bo_lstm_vs_best_baseline': pytest.approx(0.1),
                          'published': 'bo_lstm', 'published_rmse_um': 5.5,
                          'published_vs_best_baseline': pytest.approx(0.1)}
    assert table['y']['leader'] == 'bo_lstm' and table['y']['best_baseline'] == 'ridge'
    assert table['y']['bo_lstm_vs_best_baseline'] == pytest.approx(-0.25)
    assert standing_text('x', table['x'], {'ridge': 'Ridge'}) == (
        'X: Ridge leads, the BO-LSTM 10.0 % behind it')
    assert standing_text('y', table['y'], {}) == 'Y: the BO-LSTM leads, 25.0 % below ridge'
    tie = standings(_models(persistence=(0.0, 1.0), bo_lstm=(0.0, 0.5)))['x']
    assert tie['bo_lstm_vs_best_baseline'] == 0.0
    assert standing_text('x', tie, {}) == 'X: the BO-LSTM ties persistence'


def test_the_loss_difference_t_statistic_by_hand() -> None:
    """Nine values: three blocks of three, block means 2, 3, 4: t = 3 / (1 / sqrt 3); a
    constant positive difference is infinite, zeros and a series of one block are 0."""
    assert loss_difference_t(np.array([1, 2, 3, 2, 3, 4, 3, 4, 5.0])) == pytest.approx(
        3 * np.sqrt(3), rel=1e-12)
    assert loss_difference_t(np.full(16, 2.0)) == np.inf
    assert loss_difference_t(np.zeros(16)) == 0.0
    assert loss_difference_t(np.array([5.0, 1.0, 2.0])) == 0.0


def test_standings_with_the_test_errors_give_each_margins_t_and_say_when_it_is_chance(
) -> None:
    """By hand (100 samples, ten blocks of ten, errors in um): the ridge's error is 1 on
    both axes; the BO-LSTM's is 0.5 on X (squared difference -0.75 everywhere: t minus
    infinity, a lead beyond chance) and on Y sqrt(1 + d), d per block +-0.5, +-0.2, +-0.4,
    +-0.1, +-0.3 plus 0.01 (mean 0.01, block spread of ten values: t 0.01 / (s / sqrt 10)),
    within chance."""
    deltas = np.repeat([0.5, -0.5, 0.2, -0.2, 0.4, -0.4, 0.1, -0.1, 0.3, -0.3], 10) + 0.01
    ridge = np.ones((100, 2)) * 1e-6
    ours = np.column_stack([np.full(100, 0.5), np.sqrt(1 + deltas)]) * 1e-6
    models = _models(ridge=(1.0, 1.0), bo_lstm=(0.5, float(np.sqrt(np.mean(1 + deltas)))))
    table = standings(models, None, {'ridge': ridge, 'bo_lstm': ours})
    assert table['x']['bo_lstm_vs_best_baseline_t'] == -np.inf
    assert table['x']['published_vs_best_baseline_t'] == -np.inf
    block_means = deltas.reshape(10, 10).mean(axis=1)
    expected = 0.01 / (block_means.std(ddof=1) / np.sqrt(10))
    assert table['y']['bo_lstm_vs_best_baseline_t'] == pytest.approx(expected, rel=1e-9)
    assert standing_text('x', table['x'], {}) == 'X: the BO-LSTM leads, 50.0 % below ridge'
    assert standing_text('y', table['y'], {}) == (
        f'Y: ridge leads, the BO-LSTM 0.5 % behind it (within chance on the test part: '
        f't +{expected:.2f})')
    published = standings(models, {'x': 'ridge', 'y': 'ridge'}, {'ridge': ridge,
                                                                 'bo_lstm': ours})
    assert published['y']['published_vs_best_baseline_t'] == 0.0  # the ridge itself
    assert 'committee_rmse_um' not in table['x']  # no committee scored: none in the standing
    # a committee whose errors are the BO-LSTM's on X and the ridge's on Y: its margins and
    # t are the BO-LSTM's on X, nothing on Y; it is none of the baselines
    committee = np.column_stack([ours[:, 0], ridge[:, 1]])
    models['bo_lstm_committee'] = _models(bo_lstm_committee=(0.5, 1.0))['bo_lstm_committee']
    with_committee = standings(models, None, {'ridge': ridge, 'bo_lstm': ours,
                                              'bo_lstm_committee': committee})
    assert with_committee['x']['best_baseline'] == 'ridge'
    assert with_committee['x']['committee_rmse_um'] == 0.5
    assert with_committee['x']['committee_vs_best_baseline'] == -0.5
    assert with_committee['x']['committee_vs_best_baseline_t'] == -np.inf
    assert with_committee['y']['committee_vs_best_baseline'] == 0.0
    assert with_committee['y']['committee_vs_best_baseline_t'] == 0.0
    assert standing_text('x', with_committee['x'], {}) == (
        'X: the BO-LSTM leads, 50.0 % below ridge; its committee 50.0 % below ridge')
    assert standing_text('y', with_committee['y'], {}).endswith(
        '; its committee as good as ridge')


def test_standings_say_what_each_axis_publishes_and_that_trees_cannot_be_exported() -> None:
    """An axis published by the ridge: its test RMSE against the best baseline, said in the
    line; where boosted trees lead what is published, the line says they cannot be
    exported."""
    models = _models(persistence=(10.0, 4.0), ridge=(5.0, 2.0), hgb=(4.0, 2.5),
                     bo_lstm=(5.5, 2.2))
    table = standings(models, {'x': 'ridge', 'y': 'ridge'})
    assert table['x']['published'] == 'ridge' and table['x']['published_rmse_um'] == 5.0
    assert table['x']['published_vs_best_baseline'] == pytest.approx(0.25)
    assert table['y']['published_vs_best_baseline'] == 0.0
    assert standing_text('x', table['x'], {'ridge': 'Ridge', 'hgb': 'HGB'}) == (
        'X: HGB leads, the BO-LSTM 37.5 % behind it; Ridge published (the validation '
        "part's choice), 25.0 % behind HGB; HGB cannot be exported to TorchScript")
    assert standing_text('y', table['y'], {'ridge': 'Ridge'}) == (
        'Y: Ridge leads, the BO-LSTM 10.0 % behind it; Ridge published (the validation '
        "part's choice), as good as Ridge")
    # a mean of the candidates: its key in the report, said as what it is without a label
    models['published'] = _models(published=(4.5, 1.9))['published']
    mean = standings(models, {'x': 'published', 'y': 'published'})
    assert mean['x']['best_baseline'] == 'hgb'  # what the model publishes is no baseline
    assert mean['x']['published_vs_best_baseline'] == pytest.approx(0.125)
    assert standing_text('y', mean['y'], {}) == (
        'Y: ridge leads, the BO-LSTM 10.0 % behind it; the mean of the candidates kept '
        "published (the validation part's choice), 5.0 % below ridge")
