"""`lompr train BAG_DIR... --out MODEL.pt --report DIR`: the offline trainer (issue 4).

Reads and cleans the bags (`dataset.py`), tunes the LSTM's batch size, hidden units and
learning rate with Bayesian optimisation (`tuning.py`) on a validation split carved from
the training 90 %, trains the paper's BP baseline, scores persistence, BP and BO-LSTM on the
chronologically last 10 % (`metrics.py`), writes the best model as one TorchScript file with
its metadata (`model_file.py`) and the report folder (`report.py`).

The functions shared with `lompr evaluate` (reading, scoring, metadata) live here too.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lompr_predictor.data.bags import (
    DEFAULT_JOINT_TOPIC,
    DEFAULT_REFERENCE_TOPIC,
    BagSource,
    read_bags,
)
from lompr_predictor.data.cleaning import (
    GAP_FACTOR,
    HAMPEL_HALF_WINDOW,
    HAMPEL_THRESHOLD,
    CleanData,
    CleaningConfig,
    clean_recordings,
)
from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.data.problem import LearningProblem, build_problem
from lompr_predictor.learning.metrics import ratios, table_metrics
from lompr_predictor.learning.report import irreducible_level, write_report
from lompr_predictor.learning.space import DEFAULT_TRIALS, PAPER_SPACE, SearchSpace, parse_values
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.stamps import seconds_since
from lompr_predictor.threads import set_torch_threads

DEFAULT_WINDOW = 25
DEFAULT_HORIZON = 1
#: The paper's BP engineering defaults (issue 4).
BP_HYPERPARAMETERS = {'batch_size': 1500, 'hidden': 35, 'learning_rate': 0.01}
TEST_FRACTION = 0.1
VALIDATION_FRACTION = 0.15


def add_data_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by train and evaluate: topics, bad bags, cleaning, description."""
    parser.add_argument('--joint-topic', default=DEFAULT_JOINT_TOPIC)
    parser.add_argument('--reference-topic', default=DEFAULT_REFERENCE_TOPIC)
    parser.add_argument('--skip-bad', action='store_true',
                        help='skip a corrupt or truncated bag (listed in the report) '
                             'instead of stopping')
    parser.add_argument('--robot-description', default=None,
                        help='URDF file (default: the packaged LOMPR description)')
    parser.add_argument('--gap-factor', type=float, default=GAP_FACTOR,
                        help='a step longer than this many sample periods splits the data')
    parser.add_argument('--hampel-window', type=int, default=HAMPEL_HALF_WINDOW,
                        help='half window of the Hampel spike filter [samples]')
    parser.add_argument('--hampel-threshold', type=float, default=HAMPEL_THRESHOLD,
                        help='spike threshold in robust sigmas')
    parser.add_argument('--threads', type=int, default=1,
                        help='torch intra-op threads (default 1: faster on a loaded machine)')
    parser.add_argument('--quiet', action='store_true', help='no progress bars')


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        'train', help='train a BO-LSTM error predictor from rosbag2 recordings',
        description=__doc__.split('\n\n')[0])
    parser.add_argument('bags', nargs='+', metavar='BAG_DIR', help='rosbag2 directories')
    parser.add_argument('--out', required=True, help='model file to write (TorchScript)')
    parser.add_argument('--report', required=True, help='report folder')
    parser.add_argument('--horizon', type=int, default=DEFAULT_HORIZON,
                        help="samples between the window's last row and the predicted instant")
    parser.add_argument('--window', type=int, default=DEFAULT_WINDOW, help='samples per window')
    parser.add_argument('--trials', type=int, default=DEFAULT_TRIALS, help='tuning budget')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--max-epochs', type=int, default=None)
    parser.add_argument('--patience', type=int, default=None)
    parser.add_argument('--batch-sizes', default=None,
                        help=f'comma list (default {",".join(map(str, PAPER_SPACE.batch_sizes))})')
    parser.add_argument('--hidden-units', default=None,
                        help=f'comma list (default {",".join(map(str, PAPER_SPACE.hidden_units))})')
    parser.add_argument('--learning-rates', default=None,
                        help=f'comma list (default {",".join(map(str, PAPER_SPACE.learning_rates))})')
    parser.add_argument('--storage', default=None,
                        help='Optuna storage URL (default: a SQLite file in the report folder); '
                             'rerunning the same command resumes the study')
    parser.add_argument('--study-name', default=None,
                        help='default: derived from the bags and settings')
    add_data_arguments(parser)
    parser.set_defaults(run=run)


def cleaning_config(args: argparse.Namespace) -> CleaningConfig:
    return CleaningConfig(gap_factor=args.gap_factor, hampel_half_window=args.hampel_window,
                          hampel_threshold=args.hampel_threshold)


def load_data(args: argparse.Namespace, geometry: Any) -> tuple[CleanData, list[BagSource]]:
    """Read and clean the bags named on the command line."""
    recordings, sources = read_bags(args.bags, joint_topic=args.joint_topic,
                                    reference_topic=args.reference_topic, skip_bad=args.skip_bad)
    return clean_recordings(recordings, geometry, cleaning_config(args)), sources


def score(predictions: Mapping[str, np.ndarray], actual: np.ndarray, stamps: np.ndarray,
          low: np.ndarray, high: np.ndarray, max_step: float) -> dict[str, dict[str, Any]]:
    """{model: {'metrics': Table 1 metrics per axis}} of each prediction."""
    return {name: {'metrics': table_metrics(predicted, actual, stamps, low, high, max_step)}
            for name, predicted in predictions.items()}


def base_report(command: str, problem: LearningProblem, data: CleanData,
                sources: Sequence[BagSource], config: CleaningConfig) -> dict[str, Any]:
    split = problem.split
    return {
        'command': command, 'argv': sys.argv, 'created_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
        'bags': [vars(s) for s in sources], 'counts': data.counts, 'cleaning': vars(config),
        'sample_period': problem.sample_period, 'window': problem.window,
        'horizon': problem.horizon, 'features': list(FEATURES), 'targets': list(TARGETS),
        'split': {'train': len(split.train), 'validation': len(split.validation),
                  'test': len(split.test), 'validation_start_row': split.validation_start,
                  'test_start_row': split.test_start},
        'error_range_um': {axis: [problem.error_low[i] * 1e6, problem.error_high[i] * 1e6]
                           for i, axis in enumerate(TARGETS)},
    }


def irreducible_fields(models: Mapping[str, Any], sources: Sequence[BagSource],
                       horizon: int) -> dict[str, Any]:
    """The twin's irreducible RMSE at `horizon` (when a bag carries its ground truth) and
    each model's RMSE as a multiple of it; None for both without ground truth."""
    irreducible = irreducible_level([s.path for s in sources if not s.skipped_reason], horizon)
    return {'irreducible_rmse_um': irreducible,
            'rmse_to_irreducible': None if irreducible is None else {
                name: {axis: m['metrics'][axis]['rmse_um'] / irreducible[axis] for axis in TARGETS}
                for name, m in models.items()}}


def normalisation_metadata(module: Any, problem: LearningProblem) -> dict[str, Any]:
    """The constants inside a `PredictorModule` (scripted or not), for people and tools."""
    def bounds(centre: Any, half: Any) -> tuple[list[float], list[float]]:
        return (centre - half).tolist(), (centre + half).tolist()

    feature_low, feature_high = bounds(module.feature_centre, 1.0 / module.feature_inverse_half)
    target_low, target_high = bounds(module.target_centre, module.target_half)
    return {'input': 'window rows mapped to [-1, 1] by their training min-max; error columns '
                     "taken relative to the window's last row first" if bool(
                         module.relative_mask.any()) else 'window rows mapped to [-1, 1]',
            'feature_low': feature_low, 'feature_high': feature_high,
            'target': ('e(t+h) - e(t)' if module.residual else 'e(t+h)') + ', mapped to [-1, 1]',
            'target_low': target_low, 'target_high': target_high,
            'error_low': problem.error_low.tolist(), 'error_high': problem.error_high.tolist()}


def run(args: argparse.Namespace) -> int:
    import optuna

    from lompr_predictor.learning.model_file import (
        ModelMetadata,
        library_versions,
        load_checkpoint,
        save_checkpoint,
        save_model,
        script_module,
    )
    from lompr_predictor.learning.models import LSTM_STEPS, persistence, predict_rows
    from lompr_predictor.learning.training import MAX_EPOCHS, PATIENCE, TrainSettings, train_network
    from lompr_predictor.learning.tuning import (
        default_storage,
        finished_twin,
        history,
        open_study,
        run_study,
        spent_trials,
        study_name_for,
    )

    set_torch_threads(args.threads)
    started = time.perf_counter()
    progress = not args.quiet
    description = load_robot_description(args.robot_description)
    data, sources = load_data(args, description.geometry)
    read_seconds = time.perf_counter() - started
    problem = build_problem(data, args.window, args.horizon, test_fraction=TEST_FRACTION,
                            validation_fraction=VALIDATION_FRACTION)
    space = SearchSpace(
        batch_sizes=parse_values(args.batch_sizes, int) if args.batch_sizes else PAPER_SPACE.batch_sizes,
        hidden_units=parse_values(args.hidden_units, int) if args.hidden_units else PAPER_SPACE.hidden_units,
        learning_rates=(parse_values(args.learning_rates, float) if args.learning_rates
                        else PAPER_SPACE.learning_rates))
    settings = TrainSettings(max_epochs=args.max_epochs or MAX_EPOCHS,
                             patience=args.patience or PATIENCE, seed=args.seed)
    report_dir = Path(args.report)
    checkpoints = report_dir / 'trials'
    checkpoints.mkdir(parents=True, exist_ok=True)
    storage = args.storage or default_storage(report_dir)
    study_name = args.study_name or study_name_for({
        'bags': [(s.path, s.sha256) for s in sources], 'window': args.window,
        'horizon': args.horizon, 'space': space.as_dict(), 'seed': args.seed,
        'settings': vars(settings), 'cleaning': vars(cleaning_config(args))})
    study = open_study(storage, study_name, seed=args.seed, budget=args.trials)

    def objective(trial: optuna.Trial) -> float:
        params = space.suggest(trial)
        twin = finished_twin(study, trial)
        if twin is not None:
            trial.set_user_attr('duplicate_of', twin.number)
            return float(twin.value)
        trained = train_network(problem, 'lstm', params, settings, trial=trial,
                                progress=progress, label=f'trial {trial.number}')
        path = save_checkpoint(checkpoints / f'{study_name}-{trial.number}.pt', trained.module)
        trial.set_user_attr('checkpoint', str(path.resolve()))
        trial.set_user_attr('training_seconds', trained.seconds)
        trial.set_user_attr('best_epoch', trained.best_epoch)
        if trained.pruned_epoch:
            trial.set_user_attr('pruned_epoch', trained.pruned_epoch)
        return trained.validation_loss

    tuning_started = time.perf_counter()
    ran = run_study(study, objective, args.trials, progress=progress)
    tuning_seconds = time.perf_counter() - tuning_started
    best = study.best_trial
    if 'duplicate_of' in best.user_attrs:
        best = study.trials[int(best.user_attrs['duplicate_of'])]
    best_params = space.suggest(optuna.trial.FixedTrial(best.params))
    checkpoint = Path(best.user_attrs.get('checkpoint', ''))
    if checkpoint.is_file():
        lstm_module = load_checkpoint(checkpoint)
        lstm_seconds = float(best.user_attrs['training_seconds'])
    else:  # the best trial ran on another machine of a shared study: train it here
        retrained = train_network(problem, 'lstm', best_params, settings, progress=progress,
                                  label='best trial')
        lstm_module, lstm_seconds = script_module(retrained.module), retrained.seconds
    lstm_module.eval()
    bp = train_network(problem, 'mlp', BP_HYPERPARAMETERS, settings, residual=False,
                       progress=progress, label='BP')

    test = problem.split.test
    actual = problem.error[test + problem.horizon]
    predictions = {
        'persistence': persistence(problem.error, test),
        'bp': predict_rows(bp.module, problem.rows, test, problem.window),
        'bo_lstm': predict_rows(lstm_module, problem.rows, test, problem.window)}
    stamps = problem.stamps[test + problem.horizon]
    max_step = args.gap_factor * problem.sample_period
    models = score(predictions, actual, stamps, problem.error_low, problem.error_high, max_step)
    models['bp'].update(training_seconds=bp.seconds, hyperparameters=BP_HYPERPARAMETERS,
                        target='error', epochs=bp.epochs)
    models['bo_lstm'].update(training_seconds=lstm_seconds, hyperparameters=best_params,
                             target='residual (e(t+h) - e(t))')
    config = cleaning_config(args)
    report = base_report('train', problem, data, sources, config)
    report.update(
        models=models,
        ratios_to_bp=ratios(models['bo_lstm']['metrics'], models['bp']['metrics']),
        training_time_ratio_lstm_to_bp=lstm_seconds / bp.seconds if bp.seconds else None,
        tuning_time_ratio_to_bp=tuning_seconds / bp.seconds if bp.seconds else None,
        **irreducible_fields(models, sources, args.horizon),
        tuning={'study_name': study_name, 'storage': storage, 'space': space.as_dict(),
                'trials_spent': len(spent_trials(study)), 'trials_run_now': ran,
                'best_trial': best.number, 'best_value': best.value, 'best_params': best_params,
                'trials': history(study), 'settings': vars(settings)})
    metadata = ModelMetadata(
        features=FEATURES, window=problem.window, horizon=problem.horizon,
        sample_period=problem.sample_period, targets=TARGETS,
        normalisation=normalisation_metadata(lstm_module, problem),
        model_type='lstm',
        hyperparameters={**best_params, 'architecture': 'LSTM (last state) + linear highway',
                         'lstm_steps': LSTM_STEPS,
                         'max_epochs': settings.max_epochs, 'patience': settings.patience,
                         'cleaning': vars(config)},
        robot_description_sha256=description.sha256,
        training_bags=tuple({'path': str(Path(s.path).resolve()), 'sha256': s.sha256}
                            for s in sources if not s.skipped_reason),
        seed=args.seed, library_versions=library_versions(),
        test_metrics=models['bo_lstm']['metrics'])
    save_model(args.out, lstm_module, metadata)
    total = time.perf_counter() - started
    report['timings'] = {'read_clean_fk_seconds': read_seconds, 'tuning_seconds': tuning_seconds,
                         'total_seconds': total, 'read_fraction_of_total': read_seconds / total}
    report['model_file'] = str(Path(args.out).resolve())
    seconds = seconds_since(stamps)
    write_report(report_dir, report, seconds=seconds, actual=actual, predictions=predictions)
    print(f'model written to {args.out}; report in {report_dir}')
    return 0
