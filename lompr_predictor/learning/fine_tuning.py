# SPDX-License-Identifier: Apache-2.0
"""Fine-tuning a trained model on new recordings: `lompr train --init MODEL`, the offline form
of adaptation (a model trained on one machine, or on the machine as it was, learning the
machine as it is now from a few recordings of it).

`fine_tune_predictor(config, init)` checks the model file against the run (the robot
description, window, horizon and preview must be the run's, and the recordings sampled at
its sample period: one line naming the field otherwise), rebuilds its BO-LSTM as a
trainable module (`editable_module`: the file's network, machine map and normalisation,
checked to predict as the file does), trains it on
the new recordings' training part from its weights (`training.train_network` with `init`)
for at most `config.max_epochs` epochs, with the hyperparameters the file records and no
tuning study, the best validation epoch kept, the starting weights counting as epoch 0 (so
it is never worse on validation than where it started), and scores it on the test part
against persistence, the machine map and the model it started from (`parent`). A paired
model's two networks (`pairing.py`) are fine-tuned together, each on its own output, and
both are scored.

The machine map's coefficients are also fitted again on the new training part (`refit_map`;
its Jacobian, the robot's kinematics, and its friction speed scales stay the parent's):
another machine of the same robot, or the machine worn or retuned, differs in just what
those coefficients are (each branch's servo lag, friction, the posture's sag), which the
least squares finds in milliseconds from minutes of data (fitted on the new training part,
judged on its validation part). If the refitted map fits the validation part better by
`MAP_REFIT_GAIN` (`MachineMap.misfit`: the share of the plant error's changes it misses,
the fit's own objective), the network is fine-tuned on it too, from the same weights, and
of the two the lower validation loss is kept: a network reads the new residuals from where
the parent's left it, which does not always pay within the epochs allowed. The
normalisation stays the parent's. The new model's metadata is the parent's with the new
bags, test metrics, fine-tuning settings, the map's coefficients, an envelope that takes in
both the parent's and the new rows, and `parent_sha256`.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lompr_predictor.data.features import TARGETS
from lompr_predictor.data.problem import LearningProblem
from lompr_predictor.errors import LomprError
from lompr_predictor.learning.baselines import (
    MAP_PRIOR,
    PERSISTENCE,
    RESIDUAL_TARGET,
    FitContext,
    beats,
    fit_baselines,
    score_test_part,
)
from lompr_predictor.learning.envelope import InputEnvelope, fit_envelope, joined_envelope
from lompr_predictor.learning.machine_map import MachineMap
from lompr_predictor.learning.model_file import (
    PERIOD_TOLERANCE,
    LoadedModel,
    ModelMetadata,
    library_versions,
    load_model,
    script_module,
)
from lompr_predictor.learning.models import (
    PredictorModule,
    build_network,
    predict_rows,
)
from lompr_predictor.learning.options import TrainingConfig, TrainSettings
from lompr_predictor.learning.report import base_report, irreducible_fields
from lompr_predictor.learning.trainer import (
    TrainingResult,
    check_config,
    network_predictions,
    read_problem,
)
from lompr_predictor.learning.training import TrainedModel, train_network
from lompr_predictor.robot.chain import load_chain, spec_with_model

#: Windows on which the rebuilt module must predict as the file does, at most.
CHECK_WINDOWS = 256
#: ... to this [m]: both run the same float32 network on the same inputs.
CHECK_TOLERANCE = 1e-9
#: Relative: the machine map refitted on the new recordings is kept when its misfit of the
#: validation part's error changes (`MachineMap.misfit`) is below the parent map's by more than
#: this (else the parent's stays: the same machine, to whose map a few minutes of data would
#: only add noise).
MAP_REFIT_GAIN = 0.1


#: The hyperparameters a fine-tuning continues with: a model file must record them.
TRAINED_WITH = ('batch_size', 'learning_rate', 'hidden')


class FineTuneError(LomprError):
    """A model file cannot be fine-tuned (not a BO-LSTM, its network cannot be rebuilt, or
    the recordings are sampled at another rate)."""


def parent_settings(path: str | Path) -> tuple[int, int, int]:
    """(window, horizon, preview) of the model file at `path`, which a fine-tuning of it
    keeps (verified by its sidecar, as every model file is opened)."""
    metadata = load_model(path).metadata
    return metadata.window, metadata.horizon, metadata.preview


def load_parent(path: str | Path, config: TrainingConfig, robot_sha256: str) -> LoadedModel:
    """The model file to start from, checked against the run: `MetadataMismatchError` (one
    line naming the field) for another robot description, window, horizon, preview or
    targets, `FineTuneError` for a model that is not a BO-LSTM."""
    parent = load_model(path, expected={
        'robot_description_sha256': robot_sha256, 'window': config.window,
        'horizon': config.horizon, 'preview': config.preview, 'targets': TARGETS})
    if parent.metadata.model_type != 'lstm':
        msg = (f'model {path}: --init fine-tunes a BO-LSTM (model_type lstm), this one is '
               f'{parent.metadata.model_type!r}')
        raise FineTuneError(msg)
    missing = [name for name in TRAINED_WITH if name not in parent.metadata.hyperparameters]
    if missing:
        msg = (f'model {path}: it does not record the hyperparameters it was trained with '
               f'({", ".join(missing)}), which a fine-tuning continues with')
        raise FineTuneError(msg)
    return parent


def editable_module(parent: LoadedModel) -> PredictorModule:
    """The parent file's module as a trainable `PredictorModule`: the same network (its
    shape read from the weights), machine map and normalisation, its weights and constants
    loaded from the file; `FineTuneError` if they do not fit."""
    scripted, metadata = parent.module, parent.metadata
    state = scripted.state_dict()
    hyperparameters = metadata.hyperparameters
    use_map = bool(scripted.use_map)
    inputs = str(hyperparameters.get('network_inputs', 'machine' if use_map else 'all'))
    error_level = bool(hyperparameters.get('error_level', False))
    try:
        width = len(state['input_columns'])
        paired = inputs == 'paired'
        lstm = scripted.net.specialist if paired else scripted.net
        prefix = 'net.specialist.' if paired else 'net.'
        hidden = int(state[prefix + 'lstm.weight_hh_l0'].shape[1])
        net = build_network('lstm', width, metadata.window, hidden, int(lstm.steps),
                            state['net.machine_columns'].tolist() if paired else None)
        machine_map = (MachineMap(metadata.features, metadata.horizon, metadata.preview,
                                  metadata.sample_period) if use_map else None)
        module = PredictorModule(net, np.zeros(width), np.ones(width), np.zeros(len(TARGETS)),
                                 np.ones(len(TARGETS)), residual=bool(scripted.residual),
                                 relative_errors=True, error_level=error_level,
                                 features=metadata.features, machine_map=machine_map,
                                 inputs=inputs)
        # the columns the file was trained on, in the layout of its day (a paired file
        # written before its level was the error's alone reads the residual's too)
        module.input_columns = state['input_columns'].clone()
        module.relative_mask = state['relative_mask'].clone()
        module.load_state_dict(with_residual_map(state) if use_map else state)
    except (KeyError, AttributeError, RuntimeError, ValueError) as err:
        msg = (f'model {parent.path}: its network cannot be rebuilt for training '
               f'({str(err).splitlines()[0]})')
        raise FineTuneError(msg) from err
    module.eval()
    return module


def with_residual_map(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A map model's state with the residual map's coefficients; a model file written
    before the map had a second fit has g's (its networks read e - g), which these are."""
    return {f'machine_map.level_{name}_coefficients': state[f'machine_map.{name}_coefficients']
            for name in ('branch', 'posture')} | dict(state)


def check_rebuilt(module: PredictorModule, parent: LoadedModel, rows: np.ndarray,
                  ends: np.ndarray) -> None:
    """`FineTuneError` unless the rebuilt module predicts the windows ending at `ends` as
    the file does (to `CHECK_TOLERANCE`)."""
    ends = ends[np.linspace(0, len(ends) - 1, min(len(ends), CHECK_WINDOWS)).astype(int)]
    window = parent.metadata.window
    rebuilt = predict_rows(module, rows, ends, window)
    original = predict_rows(parent.module, rows, ends, window)
    gap = float(np.max(np.abs(rebuilt - original))) if len(ends) else 0.0
    if not gap <= CHECK_TOLERANCE:
        msg = (f'model {parent.path}: rebuilt for training it predicts up to {gap:.3g} m '
               'away from the file: not fine-tuned')
        raise FineTuneError(msg)


def fine_tune_predictor(config: TrainingConfig, init: str | Path) -> TrainingResult:
    """Fine-tune the model file `init` on the config's bags (module docstring); nothing is
    written (`trainer.write_outputs` writes the result)."""
    check_config(config)
    started = time.perf_counter()
    chain = load_chain(config.robot)
    parent = load_parent(init, config, chain.sha256)
    chain = load_chain(spec_with_model(config.robot, parent.metadata.robot))
    data, problem, trained_on, sources = read_problem(config, chain)
    if abs(problem.sample_period - parent.metadata.sample_period) > (
            PERIOD_TOLERANCE * parent.metadata.sample_period):
        msg = (f'the recordings are sampled every {problem.sample_period * 1e3:.3g} ms, the '
               f'model {init} was trained at {parent.metadata.sample_period * 1e3:.3g} ms: '
               'not fine-tuned')
        raise FineTuneError(msg)
    read_seconds = time.perf_counter() - started
    module = editable_module(parent)
    check_rebuilt(module, parent, problem.rows, problem.split.test)
    refitted, map_refit = refit_map(module, problem)
    hyperparameters = dict(parent.metadata.hyperparameters)
    settings = config.settings
    candidates = {'kept': module, **({'refitted': refitted} if refitted is not None else {})}
    runs = {name: train_network(problem, 'lstm', hyperparameters, settings,
                                residual=bool(module.residual), progress=config.progress,
                                label=f'fine-tuning, map {name}', init=start)
            for name, start in candidates.items()}
    chosen = min(runs, key=lambda name: runs[name].validation_loss)
    trained = runs[chosen]
    map_refit.update(decision=chosen, validation_loss={
        name: run.validation_loss for name, run in runs.items()})
    machine_map = trained.module.machine_map if module.use_map else None
    baselines = fit_baselines(problem, FitContext(settings, machine_map=machine_map),
                              (PERSISTENCE, MAP_PRIOR))
    test = problem.split.test
    scored, models = score_test_part(problem, baselines, {
        'parent': predict_rows(parent.module, problem.rows, test, problem.window),
        **network_predictions(trained.module, problem)}, config.inputs.cleaning.gap_factor)
    models['bo_lstm'].update(training_seconds=trained.seconds, hyperparameters=hyperparameters,
                             target=RESIDUAL_TARGET, epochs=trained.epochs)
    report = base_report('train', problem, data, sources, config.inputs.cleaning)
    report.update(
        models=models,
        bo_lstm_beats={name: beats(models['bo_lstm']['metrics'], models[name]['metrics'])
                       for name in models if name != 'bo_lstm'},
        **irreducible_fields(models, sources, problem.horizon),
        fine_tuning={**_fine_tuning_part(parent, trained, settings), 'machine_map': map_refit},
        model_file=str(Path(config.model_path or '').resolve()),
        timings={'read_clean_fk_seconds': read_seconds, 'fine_tuning_seconds': trained.seconds,
                 'total_seconds': time.perf_counter() - started})
    metadata = _metadata(parent, problem, trained_on, trained, settings, config,
                         models['bo_lstm']['metrics'])
    return TrainingResult(module=script_module(trained.module), metadata=metadata,
                          report=report, test_part=scored)


def refit_map(module: PredictorModule, problem: LearningProblem,
              ) -> tuple[PredictorModule | None, dict[str, Any]]:
    """A copy of the module with its machine map fitted again on the problem's training
    part, if that fits the validation part better by `MAP_REFIT_GAIN` (else None; module
    docstring), and the figures it was decided on, for the report."""
    ends = problem.split.validation
    if not module.use_map or len(ends) == 0:
        return None, {}
    refitted = copy.deepcopy(module)
    refitted.machine_map.fit(problem.rows, problem.error, problem.split.train)
    before, after = (machine_map.misfit(problem.rows, problem.error, ends)
                     for machine_map in (module.machine_map, refitted.machine_map))
    figures = {'validation_misfit': {'parent_map': before, 'refitted_map': after},
               'gain_needed': MAP_REFIT_GAIN}
    return (refitted if after < (1.0 - MAP_REFIT_GAIN) * before else None), figures


def _fine_tuning_part(parent: LoadedModel, trained: TrainedModel,
                      settings: TrainSettings) -> dict[str, Any]:
    """What the report says of the fine-tuning: where it started and how it went."""
    return {'parent_model': str(Path(parent.path).resolve()), 'parent_sha256': parent.sha256,
            'parent_verified_by': str(parent.verified_by),
            'parent_test_metrics': dict(parent.metadata.test_metrics),
            'max_epochs': settings.max_epochs, 'epochs': trained.epochs,
            'best_epoch': trained.best_epoch, 'validation_loss_start': trained.start_loss,
            'validation_loss_best': trained.validation_loss,
            'validation_loss_history': trained.history,
            'highway_refitted': trained.highway_refitted,
            'kept_the_parent_weights': trained.best_epoch == 0 and not trained.highway_refitted}


def _metadata(parent: LoadedModel, problem: LearningProblem, trained_on: list[Any],
              trained: TrainedModel, settings: TrainSettings, config: TrainingConfig,
              test_metrics: dict[str, Any]) -> ModelMetadata:
    """The parent's metadata with what the fine-tuning changed (module docstring)."""
    before = parent.metadata
    envelope = joined_envelope(
        fit_envelope(problem.rows[problem.split.training_rows()], problem.features),
        InputEnvelope.from_metadata(before.envelope, before.features))
    return dataclasses.replace(
        before, training_bags=tuple({'path': str(Path(s.path).resolve()), 'sha256': s.sha256}
                                    for s in trained_on if not s.skipped_reason),
        seed=config.seed, library_versions=library_versions(), test_metrics=test_metrics,
        hyperparameters={**before.hyperparameters, 'fine_tuning': {
            **vars(settings), 'epochs': trained.epochs, 'best_epoch': trained.best_epoch,
            'cleaning': vars(config.inputs.cleaning)}},
        machine_map=(trained.module.machine_map.metadata() if trained.module.use_map
                     else before.machine_map),
        envelope=envelope.to_metadata(), parent_sha256=parent.sha256)
