# SPDX-License-Identifier: Apache-2.0
"""What `lompr train` publishes (`learning/publishing.py`): the ridge baseline as a model
file's module, the per-axis choice on the validation part, a model file that publishes it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from model_helpers import metadata
from trainer_data import lissajous_reference, synthetic_recording

from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.features import FEATURES
from lompr_predictor.data.problem import LearningProblem, build_problem
from lompr_predictor.learning.baselines import RIDGE, FitContext
from lompr_predictor.learning.fine_tuning import FineTuneError, load_parent
from lompr_predictor.learning.model_file import load_model, save_model, script_module
from lompr_predictor.learning.models import (
    persistence_module,
    predict_rows,
)
from lompr_predictor.learning.publishing import (
    NETWORK,
    PublishedModule,
    choose,
    published_module,
)
from lompr_predictor.learning.publishing import (
    RIDGE as RIDGE_KEY,
)
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription


@pytest.fixture(scope='module')
def problem(description: RobotDescription) -> LearningProblem:
    recording, _ = synthetic_recording(description.geometry, 1500, noise=2e-7,
                                       reference=lissajous_reference(1500))
    return build_problem(clean_recordings([recording], LomprChain(description)), window=4,
                         horizon=3)


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


def test_each_axis_publishes_the_model_of_the_lower_validation_rmse() -> None:
    """By hand: X to the ridge (lower), Y to the network (a tie stays the network's)."""
    publication = choose({NETWORK: {'x': 2.0, 'y': 1.0}, RIDGE_KEY: {'x': 1.5, 'y': 1.0}})
    assert publication.choice == {'x': 'ridge', 'y': 'bo_lstm'}
    assert publication.ridge_axes == [True, False]
    assert publication.model_type == 'lstm+ridge'
    assert publication.report()['x'] == {
        'model': 'ridge', 'validation_rmse_um': {'bo_lstm': 2.0, 'ridge': 1.5},
        'why': 'validation RMSE BO-LSTM 2 um, ridge 1.5 um'}
    network = choose({NETWORK: {'x': 1.0, 'y': 1.0}, RIDGE_KEY: {'x': 1.5, 'y': 2.0}})
    assert network.model_type == 'lstm'
    assert published_module('network', None, network) == 'network'
    assert choose({NETWORK: {'x': 3.0, 'y': 3.0},
                   RIDGE_KEY: {'x': 1.0, 'y': 2.0}}).model_type == 'ridge'


def test_a_model_file_publishing_the_ridge_loads_and_evaluates(
        tmp_path: Path, problem: LearningProblem) -> None:
    """A network (here persistence) with the ridge on X: the file loads (warm-up), predicts
    X as the ridge and Y as the network, offline as the node would; fine-tuning refuses it
    (the adaptation's 'cannot adapt')."""
    fitted = RIDGE.fit(problem, FitContext())
    assert fitted.module is not None
    module = PublishedModule(persistence_module(FEATURES), fitted.module, [True, False])
    path = save_model(tmp_path / 'm.pt', module, metadata(
        window=4, horizon=3, model_type='lstm+ridge'))
    loaded = load_model(path)
    ends = problem.split.test
    got = predict_rows(loaded.module, problem.rows, ends, 4)
    ridge = fitted.predict(ends)
    assert np.max(np.abs(got[:, 0] - ridge[:, 0])) <= 1e-9 * np.max(np.abs(ridge))
    assert np.array_equal(got[:, 1], problem.error[ends, 1])
    assert loaded.module.candidates(torch.zeros((2, 4, len(FEATURES)),
                                                dtype=torch.float64)).shape == (2, 2)
    with pytest.raises(FineTuneError, match="this one is 'lstm\\+ridge'"):
        load_parent(path, _FineTuneConfig(),  # type: ignore[arg-type]
                    loaded.metadata.robot_description_sha256)


class _FineTuneConfig:
    """The fields of a `TrainingConfig` `load_parent` reads."""

    window, horizon, preview = 4, 3, 0
