"""The offline training pipeline (issue 4) as one library call: what `lompr train` runs.

`train_predictor(config)` reads and cleans the bags (`data.loading`), cuts the learning
problem (windows, chronological split: `data.problem`), tunes the LSTM's batch size, hidden
units and learning rate by Bayesian optimisation on the validation part (`tuning.py`, with
the objective of `objective.py`), trains the paper's BP baseline, scores persistence, BP and
BO-LSTM on the chronologically last 10 % (Table 1 metrics, `metrics.py`) and returns the
BO-LSTM module, its metadata, the report document and the test predictions.
`write_outputs(config, result)` writes the model file (`model_file.py`) and the report
folder (`report.py`), each file atomically.

The run's side effects are the study's: its storage (by default a SQLite file in the report
folder) and the trials' checkpoints (`trials/` in the report folder), which let the same
config resume. The torch thread count is left to the caller (an entry point sets it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lompr_predictor.data.bags import BagSource
from lompr_predictor.data.cleaning import CleanData
from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.data.problem import (
    DEFAULT_HORIZON,
    DEFAULT_WINDOW,
    TEST_FRACTION,
    VALIDATION_FRACTION,
    LearningProblem,
    build_problem,
)
from lompr_predictor.learning.metrics import ratios, score_predictions
from lompr_predictor.learning.model_file import (
    ExportedModule,
    ModelMetadata,
    library_versions,
    sidecar_path,
    write_model,
)
from lompr_predictor.learning.models import (
    BP_HYPERPARAMETERS,
    LSTM_STEPS,
    normalisation_metadata,
    persistence,
    predict_rows,
)
from lompr_predictor.learning.objective import CHECKPOINT_FOLDER, NetworkObjective
from lompr_predictor.learning.report import (
    base_report,
    irreducible_fields,
    write_report,
)
from lompr_predictor.learning.space import DEFAULT_TRIALS, PAPER_SPACE, SearchSpace
from lompr_predictor.learning.training import MAX_EPOCHS, PATIENCE, TrainSettings, train_network
from lompr_predictor.learning.tuning import (
    best_trial,
    default_storage,
    history,
    open_study,
    run_study,
    spent_trials,
    study_name_for,
)
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.stamps import seconds_since


@dataclass(frozen=True)
class TrainingConfig:
    """Everything a training run decides; the defaults are `lompr train`'s."""

    inputs: BagInputs  # bags, topics, bad-bag policy, cleaning rules
    model_path: Path  # model file to write
    report_dir: Path  # report folder (also holds the default study storage and checkpoints)
    robot_description: str | None = None  # URDF file; None: the packaged LOMPR description
    window: int = DEFAULT_WINDOW
    horizon: int = DEFAULT_HORIZON
    trials: int = DEFAULT_TRIALS  # tuning budget (finished and pruned trials count)
    seed: int = 0
    max_epochs: int = MAX_EPOCHS
    patience: int = PATIENCE
    space: SearchSpace = PAPER_SPACE
    storage: str | None = None  # Optuna storage URL; None: a SQLite file in report_dir
    study_name: str | None = None  # None: derived from the bags and the settings
    progress: bool = True  # progress bars

    @property
    def settings(self) -> TrainSettings:
        """The training loop's settings (every trial's, and BP's)."""
        return TrainSettings(max_epochs=self.max_epochs, patience=self.patience, seed=self.seed)


@dataclass(frozen=True)
class ScoredPredictions:
    """Each model's prediction of the test part and the actual error, for the plots."""

    seconds: np.ndarray  # (B,) predicted instants [s] from the first one
    actual: np.ndarray  # (B, 2) plant error [m]
    predictions: dict[str, np.ndarray]  # model name -> (B, 2) [m]


@dataclass(frozen=True)
class TrainingResult:
    """What a training run produced, before anything is written."""

    module: ExportedModule  # the BO-LSTM predictor, raw SI windows -> error [m]
    metadata: ModelMetadata
    report: dict[str, Any]  # report.json's document
    test_part: ScoredPredictions


@dataclass(frozen=True)
class _Tuned:
    """The tuning study's outcome: the best trial's module and the study's report part."""

    module: ExportedModule
    params: dict[str, Any]
    training_seconds: float  # the best trial's training time
    tuning_seconds: float  # the whole study's wall time in this run
    report: dict[str, Any]


def train_predictor(config: TrainingConfig) -> TrainingResult:
    """Read, clean, tune, train, score (module docstring); nothing is written but the study
    and its checkpoints."""
    started = time.perf_counter()
    description = load_robot_description(config.robot_description)
    data, sources = load_clean_data(config.inputs, description.geometry)
    read_seconds = time.perf_counter() - started
    problem = build_problem(data, config.window, config.horizon, test_fraction=TEST_FRACTION,
                            validation_fraction=VALIDATION_FRACTION)
    tuned = _tune(config, problem, sources)
    bp = train_network(problem, 'mlp', BP_HYPERPARAMETERS, config.settings, residual=False,
                       progress=config.progress, label='BP')

    test = problem.split.test
    targets = test + problem.horizon
    actual, stamps = problem.error[targets], problem.stamps[targets]
    predictions = {
        'persistence': persistence(problem.error, test),
        'bp': predict_rows(bp.module, problem.rows, test, problem.window),
        'bo_lstm': predict_rows(tuned.module, problem.rows, test, problem.window)}
    max_step = config.inputs.cleaning.gap_factor * problem.sample_period
    models = score_predictions(predictions, actual, stamps, problem.error_low,
                               problem.error_high, max_step)
    models['bp'].update(training_seconds=bp.seconds, hyperparameters=dict(BP_HYPERPARAMETERS),
                        target='error', epochs=bp.epochs)
    models['bo_lstm'].update(training_seconds=tuned.training_seconds,
                             hyperparameters=tuned.params, target='residual (e(t+h) - e(t))')
    report = _report(config, problem, data, sources, models, tuned, bp.seconds)
    metadata = ModelMetadata(
        features=FEATURES, window=problem.window, horizon=problem.horizon,
        sample_period=problem.sample_period, targets=TARGETS,
        normalisation=normalisation_metadata(tuned.module, problem.error_low,
                                             problem.error_high),
        model_type='lstm',
        hyperparameters={**tuned.params, 'architecture': 'LSTM (last state) + linear highway',
                         'lstm_steps': LSTM_STEPS,
                         'max_epochs': config.max_epochs, 'patience': config.patience,
                         'cleaning': vars(config.inputs.cleaning)},
        robot_description_sha256=description.sha256,
        training_bags=tuple({'path': str(Path(s.path).resolve()), 'sha256': s.sha256}
                            for s in sources if not s.skipped_reason),
        seed=config.seed, library_versions=library_versions(),
        test_metrics=models['bo_lstm']['metrics'])
    total = time.perf_counter() - started
    report['timings'] = {'read_clean_fk_seconds': read_seconds,
                         'tuning_seconds': tuned.tuning_seconds, 'total_seconds': total,
                         'read_fraction_of_total': read_seconds / total}
    report['model_file'] = str(Path(config.model_path).resolve())
    return TrainingResult(module=tuned.module, metadata=metadata, report=report,
                          test_part=ScoredPredictions(seconds=seconds_since(stamps),
                                                      actual=actual, predictions=predictions))


def write_outputs(config: TrainingConfig, result: TrainingResult) -> str:
    """Write the model file (module + metadata) with its sha256 beside it
    (`MODEL.sha256`), and the report folder (report.json with `model_sha256`, report.md,
    the plots) of `config`; each file atomically. Returns the model's sha256."""
    digest = write_model(config.model_path, result.module, result.metadata)
    report = {**result.report, 'model_sha256': digest,
              'model_sha256_file': str(sidecar_path(config.model_path).resolve())}
    scored = result.test_part
    write_report(config.report_dir, report, seconds=scored.seconds, actual=scored.actual,
                 predictions=scored.predictions)
    return digest


def study_key(config: TrainingConfig, sources: list[BagSource]) -> dict[str, Any]:
    """What defines the tuning problem, which names the study unless the config does: the
    same config on the same bags finds its study again."""
    return {'bags': [(s.path, s.sha256) for s in sources], 'window': config.window,
            'horizon': config.horizon, 'space': config.space.as_dict(), 'seed': config.seed,
            'settings': vars(config.settings), 'cleaning': vars(config.inputs.cleaning)}


def _tune(config: TrainingConfig, problem: LearningProblem,
          sources: list[BagSource]) -> _Tuned:
    """Run (or resume) the study to its budget; the best trial's module."""
    report_dir = Path(config.report_dir)
    storage = config.storage or default_storage(report_dir)
    study_name = config.study_name or study_name_for(study_key(config, sources))
    study = open_study(storage, study_name, seed=config.seed, budget=config.trials)
    objective = NetworkObjective(study, problem, config.space, config.settings,
                                 report_dir / CHECKPOINT_FOLDER, progress=config.progress)
    started = time.perf_counter()
    ran = run_study(study, objective, config.trials, progress=config.progress)
    tuning_seconds = time.perf_counter() - started
    best = best_trial(study)
    params = objective.params_of(best)
    module, seconds = objective.model_of(best)
    report = {'study_name': study_name, 'storage': storage, 'space': config.space.as_dict(),
              'trials_spent': len(spent_trials(study)), 'trials_run_now': ran,
              'best_trial': best.number, 'best_value': best.value, 'best_params': params,
              'trials': history(study),
              # the thread count in effect (set by the entry point): the times depend on it
              'settings': {**vars(config.settings), 'threads': torch.get_num_threads()}}
    return _Tuned(module=module, params=params, training_seconds=seconds,
                  tuning_seconds=tuning_seconds, report=report)


def _report(config: TrainingConfig, problem: LearningProblem, data: CleanData,
            sources: list[BagSource], models: dict[str, dict[str, Any]], tuned: _Tuned,
            bp_seconds: float) -> dict[str, Any]:
    report = base_report('train', problem, data, sources, config.inputs.cleaning)
    report.update(
        models=models,
        ratios_to_bp=ratios(models['bo_lstm']['metrics'], models['bp']['metrics']),
        training_time_ratio_lstm_to_bp=(tuned.training_seconds / bp_seconds
                                        if bp_seconds else None),
        tuning_time_ratio_to_bp=tuned.tuning_seconds / bp_seconds if bp_seconds else None,
        **irreducible_fields(models, sources, config.horizon),
        tuning=tuned.report)
    return report
