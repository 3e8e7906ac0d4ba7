# SPDX-License-Identifier: Apache-2.0
"""The baselines behind one seam (`learning/baselines.py`): what the report iterates."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from trainer_data import lissajous_problem

from lompr_predictor.data.features import TARGETS
from lompr_predictor.data.problem import LearningProblem
from lompr_predictor.learning.baselines import (
    BASELINES,
    MAP_PRIOR,
    PERSISTENCE,
    RIDGE,
    FitContext,
    Fitted,
    WithoutPreview,
    fit_baselines,
    score_test_part,
)
from lompr_predictor.learning.metrics import METRIC_NAMES
from lompr_predictor.learning.report import markdown
from lompr_predictor.robot.description import RobotDescription


@pytest.fixture(scope='module')
def problem(description: RobotDescription) -> LearningProblem:
    return lissajous_problem(description, 2000, window=10, horizon=5)


@dataclass(frozen=True)
class HalfWay:
    """A baseline a user adds: halfway between persistence and zero."""

    name: str = 'halfway'
    label: str = 'Halfway'

    def fit(self, problem: LearningProblem, context: FitContext) -> Fitted:
        return Fitted(predict=lambda ends: 0.5 * problem.error[ends],
                      details={'target': 'error'})


def test_every_baseline_has_its_own_name_and_label() -> None:
    assert len({b.name for b in BASELINES}) == len({b.label for b in BASELINES}) == len(BASELINES)
    assert [b.name for b in BASELINES] == ['persistence', 'bp', 'ridge', 'hgb',
                                           'ridge_no_preview', 'hgb_no_preview', 'machine_map']


def test_baselines_fit_where_they_apply_and_predict_any_window_ends(
        problem: LearningProblem) -> None:
    chosen = (PERSISTENCE, RIDGE, WithoutPreview(RIDGE), MAP_PRIOR, HalfWay())
    fitted = fit_baselines(problem, FitContext(), chosen)
    # no preview in the problem, no machine map in the context: those two do not apply
    assert list(fitted) == ['persistence', 'ridge', 'halfway']
    ends = problem.split.validation[:7]
    assert np.array_equal(fitted['persistence'].fitted.predict(ends), problem.error[ends])
    assert fitted['ridge'].fitted.predict(ends).shape == (7, len(TARGETS))
    scored, models = score_test_part(problem, fitted, {}, gap_factor=2.5)
    assert list(models) == list(scored.predictions) == ['persistence', 'ridge', 'halfway']
    rmse = {name: models[name]['metrics']['x']['rmse_um'] for name in models}
    assert rmse['ridge'] < rmse['persistence'] < rmse['halfway']
    assert models['ridge']['label'] == 'Ridge'
    assert models['ridge']['hyperparameters']['alpha'] in models['ridge']['hyperparameters'][
        'alphas_tried']


def test_report_md_shows_every_model_labelled_or_not() -> None:
    """A model without a label is shown by its key, never left out of the tables."""
    def entry(rmse: float, **fields: Any) -> dict[str, Any]:
        return {'metrics': {axis: dict.fromkeys(METRIC_NAMES, rmse) for axis in TARGETS},
                **fields}

    report = {'command': 'evaluate', 'horizon': 5, 'sample_period': 0.04, 'window': 10,
              'split': {'test': 100}, 'counts': {}, 'bags': [],
              'models': {'persistence': entry(2.0, label='Persistence'),
                         'halfway': entry(3.0, label='Halfway'), 'newcomer': entry(4.0),
                         'model': entry(1.0)}}
    header = next(line for line in markdown(report).splitlines() if line.startswith('| metric'))
    assert header == '| metric | Persistence | Halfway | newcomer | Model |'
