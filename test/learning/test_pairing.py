# SPDX-License-Identifier: Apache-2.0
"""The paired model: the tuned specialist and the generalist trained at its point, joined
into one module whose prediction is the first's and whose prior is the second's."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from trainer_data import lissajous_reference, synthetic_recording

from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.problem import build_problem
from lompr_predictor.learning.machine_map import fit_machine_map
from lompr_predictor.learning.map_prior import is_paired, prediction_with_prior
from lompr_predictor.learning.model_file import script_module
from lompr_predictor.learning.models import MAP_RESIDUALS, predict_rows
from lompr_predictor.learning.pairing import paired_module, train_generalist
from lompr_predictor.learning.training import TrainSettings, train_network
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription

SETTINGS = TrainSettings(max_epochs=3, patience=3, seed=1)
POINT = {'batch_size': 200, 'hidden': 8, 'learning_rate': 0.01, 'lstm_steps': 5,
         'error_level': True}


def test_the_paired_module_predicts_as_its_two_networks_did(
        description: RobotDescription) -> None:
    recording, _ = synthetic_recording(description.geometry, 1500, noise=2e-7,
                                       reference=lissajous_reference(1500))
    data = clean_recordings([recording], LomprChain(description))
    problem = build_problem(data, window=12, horizon=2)
    training_rows = problem.split.training_rows()[:len(data)]
    machine_map = fit_machine_map(problem, data.reference[training_rows], LomprChain(description))
    specialist = train_network(problem, 'lstm', POINT, SETTINGS, progress=False,
                               machine_map=machine_map, network_inputs='paired')
    generalist = train_generalist(problem, POINT, SETTINGS, machine_map)
    assert not is_paired(specialist.module) and not is_paired(generalist.module)
    # the point gives the specialist the error level, never the generalist: it reads the
    # map's two residuals, relative to the window's last row, and nothing else
    assert generalist.module.relative_mask.tolist() == [1.0] * len(MAP_RESIDUALS)
    # the tuned specialist comes back from its checkpoint scripted: joined alike
    joined = paired_module(script_module(specialist.module), generalist.module, machine_map,
                           problem, POINT)
    assert is_paired(joined)
    ends, window = problem.split.test, problem.window
    alone = [predict_rows(part.module, problem.rows, ends, window)
             for part in (specialist, generalist)]
    served = prediction_with_prior(script_module(joined))
    assert served is not None
    both = predict_rows(served, problem.rows, ends, window, width=6)
    np.testing.assert_allclose(both[:, :2], alone[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(both[:, 2:4], alone[1], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(predict_rows(joined, problem.rows, ends, window), both[:, :2])
    # then the map prior: persistence plus the map's change over the horizon
    newest = problem.rows[ends]
    with torch.no_grad():
        table = torch.from_numpy(newest)
        change = (machine_map.ahead(table) - machine_map.rows(table[:, None])[:, 0]).numpy()
    np.testing.assert_allclose(both[:, 4:], newest[:, :2] + change, rtol=1e-12, atol=1e-18)
    # two networks trained apart learn apart: they do not predict alike
    assert np.max(np.abs(alone[0] - alone[1])) > 1e-8


def test_a_generalist_of_another_normalisation_is_refused(
        description: RobotDescription) -> None:
    recordings = [synthetic_recording(description.geometry, 1500, noise=2e-7, seed=seed,
                                      reference=lissajous_reference(1500))[0]
                  for seed in (0, 1)]
    parts = []
    for recording in recordings:
        data = clean_recordings([recording], LomprChain(description))
        problem = build_problem(data, window=12, horizon=2)
        training_rows = problem.split.training_rows()[:len(data)]
        parts.append((problem, fit_machine_map(problem, data.reference[training_rows],
                                               LomprChain(description))))
    (problem, machine_map), (other, other_map) = parts
    settings = TrainSettings(max_epochs=1, patience=1, seed=1)
    specialist = train_network(problem, 'lstm', POINT, settings, progress=False,
                               machine_map=machine_map, network_inputs='paired')
    stranger = train_generalist(other, POINT, settings, other_map)
    with pytest.raises(ValueError, match='another normalisation'):
        paired_module(specialist.module, stranger.module, machine_map, problem, POINT)
