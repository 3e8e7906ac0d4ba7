# SPDX-License-Identifier: Apache-2.0
"""The tuning objective: trains a trial, keeps its checkpoint, skips a repeated point, and
gives a trial's model back from its checkpoint or by training it again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import optuna
import pytest
from trainer_data import lissajous_reference, synthetic_recording

from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.problem import LearningProblem, build_problem
from lompr_predictor.learning.models import predict_rows
from lompr_predictor.learning.objective import NetworkObjective, checkpoint_path
from lompr_predictor.learning.space import SearchSpace
from lompr_predictor.learning.storage import default_storage, open_storage
from lompr_predictor.learning.training import TrainSettings
from lompr_predictor.learning.tuning import (
    DUPLICATE_OF,
    RESTART,
    WORKER,
    best_trial,
    open_study,
    run_study,
    worker_name,
)
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription

SPACE = SearchSpace(batch_sizes=(300,), hidden_units=(4, 6), learning_rates=(0.01,))


@pytest.fixture(scope='module')
def problem(description: RobotDescription) -> LearningProblem:
    recording, _ = synthetic_recording(description.geometry, 1500, noise=2e-7,
                                       reference=lissajous_reference(1500))
    return build_problem(clean_recordings([recording], LomprChain(description)), 8, 2)


def test_objective_trains_checkpoints_and_skips_a_repeated_point(
        tmp_path: Path, problem: LearningProblem) -> None:
    storage = open_storage(default_storage(tmp_path))
    study = open_study(storage, 'objective', seed=0, budget=3)
    point = {'batch_size': 300, 'hidden': 4, 'learning_rate': 0.01}
    study.enqueue_trial(point)
    study.enqueue_trial(point)
    study.enqueue_trial({**point, 'hidden': 6})
    objective = NetworkObjective(study, problem, SPACE, TrainSettings(max_epochs=2, seed=1),
                                 tmp_path / 'trials')
    assert run_study(study, storage, objective, progress=False) == 3
    first, repeated, other = study.trials
    assert repeated.user_attrs == {DUPLICATE_OF: 0, WORKER: worker_name()}
    assert repeated.value == first.value
    for trial in (first, other):
        path = checkpoint_path(tmp_path / 'trials', 'objective', trial.number)
        assert trial.user_attrs['checkpoint'] == str(path.resolve()) and path.is_file()
        assert trial.user_attrs['training_seconds'] > 0
        assert 0 <= trial.user_attrs['best_epoch'] <= 2  # 0: the ridge start
    assert not checkpoint_path(tmp_path / 'trials', 'objective', 1).exists()
    best = best_trial(study)
    assert best.number in (0, 2) and objective.params_of(best) == {
        **point, 'hidden': best.params['hidden'], 'weight_decay': 0.0, 'lstm_steps': 10,
        'error_level': False}

    # the checkpoint gives the trained module back; without it (the trial ran on another
    # machine) the same seeded training gives the same module again
    ends = problem.split.test[:200]
    loaded, seconds = objective.model_of(first)
    assert seconds == first.user_attrs['training_seconds']
    expected = predict_rows(loaded, problem.rows, ends, problem.window)
    Path(first.user_attrs['checkpoint']).unlink()
    retrained, _ = objective.model_of(first)
    np.testing.assert_array_equal(predict_rows(retrained, problem.rows, ends, problem.window),
                                  expected)


def test_a_restart_trains_its_point_with_another_seed_and_is_not_pruned(
        tmp_path: Path, problem: LearningProblem) -> None:
    """Restart k trains the point with the seed + k (another network, not the duplicate of
    its first training), never stopped by the pruner (which stops every other trial here
    at its first report), and gives the same module back when trained again."""
    storage = open_storage(default_storage(tmp_path))
    study = open_study(storage, 'restart', seed=0, budget=1, restarts=1)
    study.pruner = optuna.pruners.ThresholdPruner(upper=0.0)  # prunes every reporting trial
    # from random weights: a ridge start is the same for every seed, and three epochs on
    # this data may not leave it
    settings = TrainSettings(max_epochs=3, seed=1, linear_start=False)
    objective = NetworkObjective(study, problem, SPACE, settings, tmp_path / 'trials')
    assert run_study(study, storage, objective, progress=False) == 2
    first, restart = study.trials
    assert first.user_attrs['pruned_epoch'] == 1
    assert restart.user_attrs[RESTART] == 1 and restart.params == first.params
    assert 'pruned_epoch' not in restart.user_attrs and len(restart.intermediate_values) == 3
    assert DUPLICATE_OF not in restart.user_attrs and restart.value != first.value
    ends = problem.split.test[:200]
    loaded, _ = objective.model_of(restart)
    expected = predict_rows(loaded, problem.rows, ends, problem.window)
    Path(restart.user_attrs['checkpoint']).unlink()
    retrained, _ = objective.model_of(restart)
    np.testing.assert_array_equal(predict_rows(retrained, problem.rows, ends, problem.window),
                                  expected)
    reseeded = objective.train(objective.params_of(restart), restart=0)
    assert reseeded.validation_loss != restart.value  # seed + 1, not the study's seed
