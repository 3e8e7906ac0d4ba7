# SPDX-License-Identifier: Apache-2.0
"""learning.space: a search space's points, the trial's hyperparameters in their types (a
parameter of one value fixed, not asked), and a value out of range refused in one line."""

from __future__ import annotations

import math

import optuna
import pytest

from lompr_predictor.learning.space import DEFAULT_SPACE, PAPER_SPACE, SearchSpace, SpaceError


def test_the_papers_space_asks_three_parameters_and_fixes_the_rest() -> None:
    assert PAPER_SPACE.points() == 4 * 4 * 3
    assert DEFAULT_SPACE.points() == 3 * 3 * 3 * 3 * 2 * 2
    trial = optuna.trial.FixedTrial({'batch_size': 600, 'hidden': 15,
                                     'learning_rate': 0.01})
    point = PAPER_SPACE.suggest(trial)
    assert point == {'batch_size': 600, 'hidden': 15, 'learning_rate': 0.01,
                     'weight_decay': 0.0, 'lstm_steps': 10, 'error_level': False}
    assert [type(point[name]) for name in point] == [int, int, float, float, int, bool]
    with pytest.raises(ValueError):  # a tuned parameter the trial does not give
        PAPER_SPACE.suggest(optuna.trial.FixedTrial({'batch_size': 600}))
    assert PAPER_SPACE.as_dict()['hidden_units'] == [5, 15, 35, 50]


@pytest.mark.parametrize(('space', 'window', 'message'), [
    (SearchSpace(), 0, 'the window must be >= 1 rows, got 0'),
    (SearchSpace(batch_sizes=()), 8, 'the search space has no value of batch_sizes'),
    (SearchSpace(learning_rates=(0.01, 1.5)), 8,
     'search space learning-rates: 1.5 is out of range (each must be in (0, 1])'),
    (SearchSpace(weight_decays=(math.nan,)), 8,
     'search space weight-decays: nan is out of range (each must be in [0, 1))'),
    (SearchSpace(hidden_units=(0,)), 8,
     'search space hidden-units: 0 is out of range (each must be >= 1)'),
])
def test_a_space_out_of_range_is_refused_in_one_line(space: SearchSpace, window: int,
                                                     message: str) -> None:
    with pytest.raises(SpaceError) as refused:
        space.check(window)
    assert str(refused.value) == message
    DEFAULT_SPACE.check(1)  # the default space fits any window
