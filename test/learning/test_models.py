# SPDX-License-Identifier: Apache-2.0
"""Models, training and the model file: export -> load -> same predictions, refusals."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import stat
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from model_helpers import LinearWindowModel, save_constant
from model_helpers import metadata as file_metadata
from trainer_data import lissajous_reference, synthetic_recording

from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.data.problem import LearningProblem, build_problem
from lompr_predictor.learning import training
from lompr_predictor.learning.model_file import (
    MetadataMismatchError,
    ModelMetadata,
    ModelTrustError,
    load_model,
    save_model,
    script_module,
    sidecar_path,
    write_model,
)
from lompr_predictor.learning.models import (
    MlpNet,
    PredictorModule,
    ScaledRows,
    gather_windows,
    persistence,
    persistence_module,
    predict_rows,
)
from lompr_predictor.learning.training import (
    TrainSettings,
    build_module,
    evenly_spaced,
    train_network,
)
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription

SETTINGS = TrainSettings(max_epochs=8, patience=3, seed=3)
HYPER = {'batch_size': 200, 'hidden': 8, 'learning_rate': 0.01}


@pytest.fixture(scope='module')
def problem(description: RobotDescription) -> LearningProblem:
    recording, _ = synthetic_recording(description.geometry, 3000, noise=2e-7,
                                       reference=lissajous_reference(3000))
    data = clean_recordings([recording], LomprChain(description))
    return build_problem(data, window=12, horizon=10)


def metadata(problem: LearningProblem, description: RobotDescription) -> ModelMetadata:
    return ModelMetadata(
        features=FEATURES, window=problem.window, horizon=problem.horizon,
        sample_period=problem.sample_period, targets=TARGETS, normalisation={},
        model_type='lstm', hyperparameters=HYPER,
        robot_description_sha256=description.sha256,
        training_bags=({'path': 'synthetic', 'sha256': '0' * 64},), seed=SETTINGS.seed,
        library_versions={'torch': torch.__version__})


def test_trained_lstm_beats_persistence(problem: LearningProblem) -> None:
    trained = train_network(problem, 'lstm', HYPER, SETTINGS, progress=False)
    assert trained.history[-1] < trained.history[0]
    test = problem.split.test
    actual = problem.error[test + problem.horizon]
    predicted = predict_rows(trained.module, problem.rows, test, 12)
    model_rmse = np.sqrt(np.mean((predicted - actual) ** 2))
    persistence_rmse = np.sqrt(np.mean((persistence(problem.error, test) - actual) ** 2))
    assert model_rmse < 0.5 * persistence_rmse


def test_training_never_reads_the_test_part(problem: LearningProblem) -> None:
    start = int(problem.split.parts[0, 2])  # one recording: its test part comes last
    rows, error = problem.rows.copy(), problem.error.copy()
    rows[start:] = np.nan
    error[start:] = np.nan
    blind = dataclasses.replace(problem, rows=rows, error=error)
    trained = train_network(blind, 'lstm', HYPER, dataclasses.replace(SETTINGS, max_epochs=2),
                            progress=False)
    assert np.isfinite(trained.validation_loss)
    assert all(torch.isfinite(p).all() for p in trained.module.parameters())
    assert np.isfinite(trained.module.feature_centre.numpy()).all()


def test_an_epoch_draws_at_most_epoch_windows(problem: LearningProblem,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Each epoch trains on `epoch_windows` windows and scores as many validation windows,
    whatever the data holds: an epoch costs the same at any sample rate (the ridge start is
    scored once more, as epoch 0)."""
    seen: list[tuple[bool, int]] = []
    build = training.build_network

    def counted(*args: object, **kwargs: object) -> torch.nn.Module:
        net = build(*args, **kwargs)  # type: ignore[arg-type]
        net.register_forward_pre_hook(lambda module, inputs: seen.append(
            (module.training, inputs[0].shape[0])))
        return net

    monkeypatch.setattr(training, 'build_network', counted)
    cap = 150
    assert len(problem.split.train) > 10 * cap and len(problem.split.validation) > cap
    trained = train_network(problem, 'lstm', HYPER,
                            dataclasses.replace(SETTINGS, max_epochs=3, epoch_windows=cap),
                            progress=False)
    assert trained.epochs == 3
    assert sum(n for train, n in seen if train) == 3 * cap
    assert sum(n for train, n in seen if not train) == 4 * cap
    ends = evenly_spaced(problem.split.validation, cap)
    assert len(ends) == cap and len(set(ends)) == cap
    assert (ends[0], ends[-1]) == (problem.split.validation[0], problem.split.validation[-1])


def test_export_load_same_predictions(tmp_path: Path, problem: LearningProblem,
                                      description: RobotDescription) -> None:
    trained = train_network(problem, 'lstm', HYPER, dataclasses.replace(SETTINGS, max_epochs=2),
                            progress=False)
    ends = problem.split.test[:300]
    expected = predict_rows(trained.module, problem.rows, ends, problem.window)
    path = save_model(tmp_path / 'model.pt', trained.module, metadata(problem, description))
    loaded = load_model(path, expected={'features': FEATURES, 'window': 12, 'horizon': 10,
                                        'robot_description_sha256': description.sha256})
    windows = gather_windows(torch.from_numpy(problem.rows), ends, problem.window)
    np.testing.assert_allclose(loaded.predict(windows).numpy(), expected, rtol=1e-6, atol=1e-12)
    assert loaded.metadata.hyperparameters == HYPER


def test_mismatched_metadata_refused(tmp_path: Path, problem: LearningProblem,
                                     description: RobotDescription) -> None:
    features = len(FEATURES)
    module = PredictorModule(MlpNet(features, 12, 4), np.zeros(features), np.ones(features),
                             -np.ones(2), np.ones(2), residual=False, relative_errors=False)
    path = save_model(tmp_path / 'model.pt', module, metadata(problem, description))
    with pytest.raises(MetadataMismatchError, match="'horizon' is 10, this configuration needs 1"):
        load_model(path, expected={'horizon': 1})
    with pytest.raises(MetadataMismatchError, match='robot_description_sha256'):
        load_model(path, expected={'robot_description_sha256': 'f' * 64})


@pytest.mark.parametrize('error_level', [False, True])
def test_residual_module_is_persistence_plus_change_over_relative_errors_and_level(
        problem: LearningProblem, error_level: bool) -> None:
    """The LSTM's module: last error + the network's change; its input, the features with
    the errors relative to the last row (a constant offset on every error does not move
    them, nor, without the level, the change) and, with `error_level`, the errors' level
    appended (which moves by the offset, in normalised units)."""
    zero = persistence_module()
    ends = problem.split.test[:50]
    np.testing.assert_array_equal(predict_rows(zero, problem.rows, ends, 12),
                                  persistence(problem.error, ends))
    module = train_network(problem, 'lstm', {**HYPER, 'error_level': error_level},
                           dataclasses.replace(SETTINGS, max_epochs=1), progress=False).module
    offset = np.array([3e-6, -5e-6])
    shifted = problem.rows.copy()
    shifted[:, :2] += offset
    windows, moved = (torch.from_numpy(gather_windows(rows, ends, 12))
                      for rows in (problem.rows, shifted))
    before, after = module.normalise(windows), module.normalise(moved)
    features = len(FEATURES)
    assert after.shape[2] == features + (len(TARGETS) if error_level else 0)
    torch.testing.assert_close(after[:, :, :features], before[:, :, :features],
                               rtol=0, atol=1e-5)
    with torch.inference_mode():
        change = module.net(after).double() * module.target_half + module.target_centre
        predicted = module(moved).numpy()
    np.testing.assert_allclose(predicted, (moved[:, -1, :2] + change).numpy(), rtol=0,
                               atol=1e-15)
    unshifted = predict_rows(module, problem.rows, ends, 12)
    if not error_level:  # shift invariant: the prediction moves with the offset
        np.testing.assert_allclose(predicted, unshifted + offset, rtol=0, atol=1e-12)
        return
    level_step = torch.tensor(offset * module.feature_inverse_half.numpy()[features:],
                              dtype=torch.float32)
    assert float(level_step.abs().min()) > 1e-3  # the offset is visible in the level columns
    torch.testing.assert_close(after[:, :, features:], before[:, :, features:] + level_step,
                               rtol=0, atol=1e-5)
    assert np.abs(predicted - unshifted - offset).max() > 1e-12  # and the network sees it


@pytest.mark.parametrize(('relative_errors', 'error_level'),
                         [(True, False), (True, True), (False, False)])
def test_training_inputs_are_the_exported_modules_normalisation(
        problem: LearningProblem, relative_errors: bool, error_level: bool) -> None:
    """Training normalises windows gathered from rows scaled once in float32 (`ScaledRows`),
    the exported module its raw float64 windows (`PredictorModule.normalise`): one map, the
    same numbers to float32 rounding, on the data's windows and on random rows."""
    module = build_module(problem, 'lstm', 4, residual=True, relative_errors=relative_errors,
                          error_level=error_level)
    exported = script_module(module)
    rng = np.random.default_rng(5)
    ends = np.sort(rng.choice(np.concatenate([problem.split.train, problem.split.test]), 400))
    low, high = np.nanmin(problem.rows, axis=0), np.nanmax(problem.rows, axis=0)
    random_rows = low + (high - low) * rng.uniform(-0.5, 1.5, (600, problem.rows.shape[1]))
    random_ends = rng.integers(problem.window - 1, len(random_rows), 400)
    scale = module.feature_inverse_half.numpy()
    centre, mask = module.feature_centre.numpy(), module.relative_mask.numpy()
    for rows, chosen in ((problem.rows, ends), (random_rows, random_ends)):
        training = ScaledRows(module, rows).windows(chosen, problem.window)
        raw = gather_windows(rows, chosen, problem.window)
        reference = exported.normalise(torch.from_numpy(raw))
        assert training.dtype == reference.dtype == torch.float32
        # float32 rounding of each scaled operand (window, last row, centre) and of the result
        inputs = raw[:, :, module.input_columns.numpy()]
        operands = (np.abs(inputs) + np.abs(inputs[:, -1:, :]) * mask + np.abs(centre)) * scale
        bound = 4 * np.finfo(np.float32).eps * (operands + np.abs(reference.numpy()))
        difference = np.abs(training.numpy() - reference.numpy())
        assert np.all(difference <= bound), float((difference / bound).max())
        assert float(reference.abs().max()) > 0.5  # not the identity: the ranges are in use


# -- faults: only the model that was written is loaded, from one read ----------------------

#: Window and horizon of the models the fault tests write.
WINDOW, HORIZON = 4, 3


def _constant_module(value: float) -> torch.nn.Module:
    return LinearWindowModel(np.zeros((WINDOW * len(FEATURES), 2)), np.full(2, value))


@pytest.mark.faults
def test_a_module_with_copied_metadata_is_refused(tmp_path: Path) -> None:
    genuine = save_constant(tmp_path / 'genuine.pt', window=WINDOW, horizon=HORIZON)
    impostor = tmp_path / 'impostor.pt'  # predicts 1 m, carries the genuine metadata
    write_model(impostor, _constant_module(1.0), load_model(genuine).metadata)
    sidecar_path(impostor).unlink()  # copied without a hash
    with pytest.raises(ModelTrustError, match='no hash to check it against'):
        load_model(impostor)
    sidecar_path(impostor).write_bytes(sidecar_path(genuine).read_bytes())  # the genuine one
    with pytest.raises(ModelTrustError, match='changed or replaced after it was written'):
        load_model(impostor)
    with pytest.raises(ModelTrustError, match='the pinned sha256 is'):
        load_model(impostor, sha256=hashlib.sha256(genuine.read_bytes()).hexdigest())
    loose = load_model(impostor, verify=False)  # development only: loads, and says so
    assert loose.verified_by == 'not verified'


@pytest.mark.faults
def test_edited_metadata_is_refused(tmp_path: Path) -> None:
    path = save_constant(tmp_path / 'model.pt', window=WINDOW, horizon=HORIZON)
    edited = dataclasses.replace(load_model(path).metadata, horizon=9)
    staged = write_model(tmp_path / 'edited.pt', _constant_module(0.0), edited)
    assert staged
    path.write_bytes((tmp_path / 'edited.pt').read_bytes())  # the old MODEL.pt.sha256 stays
    with pytest.raises(ModelTrustError, match='changed or replaced'):
        load_model(path)


@pytest.mark.faults
def test_the_file_is_read_once_and_those_bytes_are_loaded(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    genuine = save_constant(tmp_path / 'model.pt', (1e-5, 0.0), window=WINDOW, horizon=HORIZON)
    digest = hashlib.sha256(genuine.read_bytes()).hexdigest()
    evil = save_constant(tmp_path / 'evil.pt', (1.0, 1.0), window=WINDOW, horizon=HORIZON)
    real_load = torch.jit.load  # noqa: TID251 - the test wraps the deserialiser itself

    def swap_then_load(source: Any, *args: Any, **kwargs: Any) -> Any:
        # the file is replaced between the hash check and the deserialisation
        genuine.write_bytes(evil.read_bytes())
        return real_load(source, *args, **kwargs)

    monkeypatch.setattr('torch.jit.load', swap_then_load)
    loaded = load_model(genuine)
    assert loaded.sha256 == digest and loaded.verified_by == 'sidecar'
    window = torch.zeros((1, WINDOW, len(FEATURES)), dtype=torch.float64)
    np.testing.assert_allclose(loaded.predict(window).numpy(), [[1e-5, 0.0]])


@pytest.mark.faults
def test_the_writer_records_the_hash_and_writes_with_the_umask(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        path = tmp_path / 'model.pt'
        digest = write_model(path, _constant_module(0.0), file_metadata(window=WINDOW))
    finally:
        os.umask(old)
    assert digest == hashlib.sha256(path.read_bytes()).hexdigest()
    assert sidecar_path(path).read_text() == f'{digest}  model.pt\n'  # sha256sum -c reads it
    for written in (path, sidecar_path(path)):
        assert stat.S_IMODE(written.stat().st_mode) == 0o644
    assert load_model(path).verified_by == 'sidecar'
