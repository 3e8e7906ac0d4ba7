# SPDX-License-Identifier: Apache-2.0
"""What `lompr train` publishes (`learning/publishing.py`): the ridge baseline as a model
file's module, the per-axis candidates kept on the validation part (the block t statistic
by hand), the committee in the network's place in a mean, a model file that publishes
their mean."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from model_helpers import metadata
from trainer_data import lissajous_problem

from lompr_predictor.data.features import FEATURES
from lompr_predictor.data.problem import LearningProblem
from lompr_predictor.learning.baselines import RIDGE, FitContext
from lompr_predictor.learning.fine_tuning import FineTuneError, load_parent
from lompr_predictor.learning.model_file import load_model, save_model, script_module
from lompr_predictor.learning.models import (
    persistence_module,
    predict_rows,
)
from lompr_predictor.learning.publishing import (
    COMMITTEE,
    GENERALIST,
    NETWORK,
    PUBLISHED,
    PublishedModule,
    choose,
    published_module,
    published_predictions,
)
from lompr_predictor.learning.publishing import (
    RIDGE as RIDGE_KEY,
)
from lompr_predictor.robot.description import RobotDescription


@pytest.fixture(scope='module')
def problem(description: RobotDescription) -> LearningProblem:
    return lissajous_problem(description, 1500, window=4, horizon=3)


def test_the_ridge_module_predicts_as_the_ridge_baseline(problem: LearningProblem) -> None:
    """The exported ridge (scripted) equals scikit-learn's prediction to 1e-9 of the error's
    scale in float64, and to 1e-6 of it run in float32."""
    fitted = RIDGE.fit(problem, FitContext())
    assert fitted.module is not None
    ends = problem.split.test
    expected = fitted.predict(ends)
    scale = float(np.max(np.abs(expected)))
    scripted = script_module(fitted.module)
    got = predict_rows(scripted, problem.rows, ends, problem.window)
    assert np.max(np.abs(got - expected)) <= 1e-9 * scale
    windows = torch.from_numpy(problem.rows[ends[:, None] + np.arange(-3, 1)[None, :]])
    single = scripted(windows.float()).double().numpy()
    assert np.max(np.abs(single - expected)) <= 1e-6 * scale
    assert set(fitted.details['validation_rmse_um']) == {'x', 'y'}


def test_each_axis_publishes_the_mean_of_the_candidates_the_validation_part_cannot_tell_apart(
) -> None:
    """By hand (errors in um, 100 samples: ten blocks of ten): on X the ridge's errors are
    twice the network's everywhere (left out, t infinite); on Y its squared errors are the
    network's times 1 + d, d per block +-0.5, +-0.2, +-0.4, +-0.1, +-0.3 (mean 0: t 0, the
    same RMSE): X the network alone, Y the mean of both; the generalist, three times the
    network's errors, is left out."""
    ones = np.tile([1.0, -1.0], 50)
    network = np.stack([ones, ones], 1) * 1e-6
    d = np.repeat([0.5, -0.5, 0.2, -0.2, 0.4, -0.4, 0.1, -0.1, 0.3, -0.3], 10)
    ridge = np.stack([2 * ones, ones * np.sqrt(1 + d)], 1) * 1e-6
    publication = choose({NETWORK: network, GENERALIST: 3 * network, RIDGE_KEY: ridge})
    assert publication.members == {'x': (NETWORK,), 'y': (NETWORK, RIDGE_KEY)}
    assert publication.t_statistic[RIDGE_KEY]['x'] == np.inf
    assert publication.t_statistic[GENERALIST] == {'x': np.inf, 'y': np.inf}
    assert abs(publication.t_statistic[RIDGE_KEY]['y']) < 1e-9
    assert abs(publication.t_statistic[NETWORK]['y']) < 1e-9
    assert publication.validation_rmse_um[RIDGE_KEY] == pytest.approx({'x': 2.0, 'y': 1.0})
    assert publication.weights.tolist() == [[1.0, 0.0, 0.0, 0.0], [0.5, 0.0, 0.5, 0.0]]
    assert publication.published_keys == {'x': NETWORK, 'y': PUBLISHED}
    assert publication.model_type == 'ensemble'
    assert publication.report()['y']['members'] == [NETWORK, RIDGE_KEY]
    assert 'its generalist 3 um (t inf)' in publication.report()['y']['why']
    # the mean, by hand: X the network's, Y the mean of the network's and the ridge's
    predictions = {NETWORK: np.array([[1.0, 2.0]]), GENERALIST: np.array([[9.0, 9.0]]),
                   RIDGE_KEY: np.array([[3.0, 4.0]])}
    assert published_predictions(publication, predictions).tolist() == [[1.0, 3.0]]
    # a model to fine-tune publishes the network alone; so does a clearly better network
    assert choose({NETWORK: network, RIDGE_KEY: ridge}, network_only=True).model_type == 'lstm'
    alone = choose({NETWORK: network, RIDGE_KEY: 2 * network})
    assert alone.model_type == 'lstm'
    assert published_module('network', None, alone) == 'network'
    assert choose({NETWORK: 2 * network, RIDGE_KEY: network}).model_type == 'ridge'


def test_a_mean_runs_the_committee_in_the_networks_place() -> None:
    """The candidates of the test above with a committee whose errors are 0.9 of the
    network's: X (the network alone) and Y (network and ridge) publish the committee in the
    network's place, its t against the network (the best) negative; its prediction enters
    the mean as the network's did. Where every axis keeps the network alone, it stays alone
    (the committee left out however good)."""
    ones = np.tile([1.0, -1.0], 50)
    network = np.stack([ones, ones], 1) * 1e-6
    d = np.repeat([0.5, -0.5, 0.2, -0.2, 0.4, -0.4, 0.1, -0.1, 0.3, -0.3], 10)
    ridge = np.stack([2 * ones, ones * np.sqrt(1 + d)], 1) * 1e-6
    publication = choose({NETWORK: network, RIDGE_KEY: ridge, COMMITTEE: 0.9 * network})
    assert publication.members == {'x': (COMMITTEE,), 'y': (COMMITTEE, RIDGE_KEY)}
    assert publication.weights.tolist() == [[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.5, 0.5]]
    assert publication.published_keys == {'x': COMMITTEE, 'y': PUBLISHED}
    assert publication.model_type == 'ensemble'
    assert publication.t_statistic[COMMITTEE]['x'] < 0
    assert publication.validation_rmse_um[COMMITTEE] == pytest.approx({'x': 0.9, 'y': 0.9})
    predictions = {NETWORK: np.array([[1.0, 2.0]]), RIDGE_KEY: np.array([[3.0, 4.0]]),
                   COMMITTEE: np.array([[5.0, 6.0]])}
    assert published_predictions(publication, predictions).tolist() == [[5.0, 5.0]]
    alone = choose({NETWORK: network, RIDGE_KEY: 2 * network, COMMITTEE: 0.5 * network})
    assert alone.members == {'x': (NETWORK,), 'y': (NETWORK,)}
    assert alone.model_type == 'lstm'
    assert published_module('network', None, alone, ['member']) == 'network'


def test_a_model_file_publishing_the_ridge_loads_and_evaluates(
        tmp_path: Path, problem: LearningProblem) -> None:
    """A network (here persistence) with the ridge on X and the mean of both on Y: the file
    loads (warm-up), predicts X as the ridge and Y as the mean, offline as the node would;
    fine-tuning refuses it (the adaptation's 'cannot adapt')."""
    fitted = RIDGE.fit(problem, FitContext())
    assert fitted.module is not None
    module = PublishedModule(persistence_module(FEATURES), fitted.module,
                             np.array([[0.0, 0.0, 1.0, 0.0], [0.5, 0.0, 0.5, 0.0]]))
    path = save_model(tmp_path / 'm.pt', module, metadata(
        window=4, horizon=3, model_type='ensemble'))
    loaded = load_model(path)
    ends = problem.split.test
    got = predict_rows(loaded.module, problem.rows, ends, 4)
    ridge = fitted.predict(ends)
    assert np.max(np.abs(got[:, 0] - ridge[:, 0])) <= 1e-9 * np.max(np.abs(ridge))
    mean = (problem.error[ends, 1] + ridge[:, 1]) / 2
    assert np.max(np.abs(got[:, 1] - mean)) <= 1e-9 * np.max(np.abs(ridge))
    assert loaded.module.candidates(torch.zeros((2, 4, len(FEATURES)),
                                                dtype=torch.float64)).shape == (2, 2)
    with pytest.raises(FineTuneError, match="this one is 'ensemble'"):
        load_parent(path, _FineTuneConfig(),  # type: ignore[arg-type]
                    loaded.metadata.robot_description_sha256)


def test_a_model_file_publishing_a_committee_averages_its_networks(
        tmp_path: Path, problem: LearningProblem) -> None:
    """A committee of a network (persistence) and one member (the ridge's module), published
    alone on X and with the ridge on Y: the file predicts X as the mean of persistence and
    the ridge, Y as half the ridge plus half that mean, by hand to 1e-9; `published_module`
    gives it the members only where an axis publishes the committee."""
    fitted = RIDGE.fit(problem, FitContext())
    assert fitted.module is not None
    ones = np.tile([1.0, -1.0], 50)
    network = np.stack([ones, ones], 1) * 1e-6
    d = np.repeat([0.5, -0.5, 0.2, -0.2, 0.4, -0.4, 0.1, -0.1, 0.3, -0.3], 10)
    ridge_errors = np.stack([2 * ones, ones * np.sqrt(1 + d)], 1) * 1e-6
    publication = choose({NETWORK: network, RIDGE_KEY: ridge_errors, COMMITTEE: network})
    member = script_module(fitted.module)
    module = published_module(persistence_module(FEATURES), fitted.module, publication,
                              [member])
    path = save_model(tmp_path / 'm.pt', module, metadata(
        window=4, horizon=3, model_type='ensemble'))
    ends = problem.split.test
    got = predict_rows(load_model(path).module, problem.rows, ends, 4)
    ridge, persistence = fitted.predict(ends), problem.error[ends]
    committee = (persistence + ridge) / 2
    scale = np.max(np.abs(ridge))
    assert np.max(np.abs(got[:, 0] - committee[:, 0])) <= 1e-9 * scale
    assert np.max(np.abs(got[:, 1] - (ridge[:, 1] + committee[:, 1]) / 2)) <= 1e-9 * scale
    without = choose({NETWORK: network, RIDGE_KEY: ridge_errors})
    assert published_module(persistence_module(FEATURES), fitted.module, without,
                            [member]).committee_size == 1


class _FineTuneConfig:
    """The fields of a `TrainingConfig` `load_parent` reads."""

    window, horizon, preview = 4, 3, 0
