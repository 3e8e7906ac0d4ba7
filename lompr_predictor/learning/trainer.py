# SPDX-License-Identifier: Apache-2.0
"""The offline training pipeline as one library call: what `lompr train` runs.

`train_predictor(config)` reads and cleans the bags (`data.loading`), cuts the learning
problem (windows, chronological split: `data.problem`), tunes the LSTM's batch size, hidden
units and learning rate by Bayesian optimisation on the validation part (`tuning.py`, with
the objective of `objective.py`), fits the baselines (`baselines.BASELINES`: persistence, the
paper's BP, ridge, boosted trees, the machine map's prior), scores them and the BO-LSTM on the
chronologically last 10 % (Table 1 metrics, `metrics.py`) and returns the BO-LSTM module, its
metadata, the report document and the test predictions. The run's options are
`options.TrainingConfig`'s, each declared once there.
`write_outputs(config, result)` writes the model file (`model_file.py`) and the report
folder (`report.py`), each file atomically.

The tuning study runs on `config.workers` local processes (`workers.py`; by default the
cores available) and may be shared with other commands, on other machines, through one
storage: `run_workers(config)` is such an extra worker (it reads the bags and runs trials
until the budget is spent, nothing else), and `train_predictor` is the finishing command (it
runs what the budget still lacks, waits for other workers' running trials, then builds the
model from the best trial). Both refuse a config that cannot run (`check_config`) and
connect to the storage before reading any bag.

The run's side effects are the study's: its storage (by default a journal file in the report
folder) and the trials' checkpoints (`trials/` in the report folder, or `config.checkpoints`),
which let the same config resume. The torch thread count is left to the caller (an entry
point sets it; worker processes take the caller's).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import torch

from lompr_predictor.data.bags import BagSource, BagTopics
from lompr_predictor.data.cleaning import CleanData
from lompr_predictor.data.features import TARGETS
from lompr_predictor.data.loading import load_clean_data
from lompr_predictor.data.problem import (
    TEST_FRACTION,
    VALIDATION_FRACTION,
    LearningProblem,
    build_problem,
    train_test_problem,
)
from lompr_predictor.errors import LomprError
from lompr_predictor.learning.baselines import (
    BP,
    RESIDUAL_TARGET,
    RIDGE,
    FitContext,
    FittedBaseline,
    ScoredPredictions,
    beats,
    fit_baselines,
    score_test_part,
)
from lompr_predictor.learning.envelope import fit_envelope
from lompr_predictor.learning.machine_map import MachineMap, fit_machine_map
from lompr_predictor.learning.map_prior import PredictionWithCandidates, is_paired
from lompr_predictor.learning.metrics import ratios, standings
from lompr_predictor.learning.model_file import (
    ExportedModule,
    ModelMetadata,
    library_versions,
    script_module,
    sidecar_path,
    write_model,
)
from lompr_predictor.learning.models import normalisation_metadata, predict_rows
from lompr_predictor.learning.objective import NetworkObjective
from lompr_predictor.learning.options import (
    OptionError,
    TrainingConfig,
    TrainSettings,
    check_options,
    recorded_options,
    shortest_window,
    study_options,
)
from lompr_predictor.learning.pairing import paired_module, train_generalist
from lompr_predictor.learning.publishing import (
    COMMITTEE,
    GENERALIST,
    NETWORK,
    PUBLISHED,
    Publication,
    choose,
    published_module,
    published_predictions,
)
from lompr_predictor.learning.report import (
    base_report,
    irreducible_fields,
    write_report,
)
from lompr_predictor.learning.storage import (
    StorageSpec,
    StudyStorage,
    default_storage,
    open_storage,
    parse_storage,
)
from lompr_predictor.learning.training import NORMALISATION
from lompr_predictor.learning.tuning import (
    BEST_EPOCH,
    HIGHWAY_HELD,
    best_trial,
    committee_trials,
    history,
    open_study,
    restart_index,
    study_budget,
    study_name_for,
    study_restarts,
    trial_counts,
    worker_counts,
)
from lompr_predictor.learning.workers import StudySpec, TuningRun, tune
from lompr_predictor.robot.chain import LOMPR_KIND, KinematicChain, load_chain
from lompr_predictor.threads import default_workers


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
    best_model_seconds: float  # loading (or retraining) the best trial's module
    members: tuple[ExportedModule, ...]  # the committee's networks beside the best's
    generalist_seconds: float  # training a paired model's generalist (`pairing.py`)
    report: dict[str, Any]


@dataclass(frozen=True)
class WorkerSummary:
    """What `run_workers` did and where the study stands."""

    study_name: str
    storage: str  # the storage, password hidden
    run: TuningRun
    budget: int
    restarts: int
    complete: int
    pruned: int
    failed: int
    read_seconds: float


def check_config(config: TrainingConfig, *, finishing: bool = True) -> StorageSpec:
    """Refuse, with one message, a config that cannot run, before any bag is read: its
    options (`options.check_options`), the space for its window and the storage's spelling
    (`storage.parse_storage`); the storage it names. `finishing`: `train_predictor`'s
    needs, else `run_workers`'."""
    check_options(config, finishing=finishing)
    config.space.check(shortest_window(config.window))
    text = config.storage or default_storage(_report_dir(config))
    return parse_storage(text, heartbeat=config.heartbeat)


def run_workers(config: TrainingConfig) -> WorkerSummary:
    """An extra worker of a shared study (`lompr train --workers-only`): read and clean the
    bags, run the study's trials with `config.workers` local processes until its budget is
    spent; no baseline, no model, no report."""
    chain = load_chain(config.robot)  # a robot named wrong: refused before anything is made
    storage = open_storage(check_config(config, finishing=False))
    started = time.perf_counter()
    data, sources = load_clean_data(config.inputs, chain)
    read_seconds = time.perf_counter() - started
    problem = _problem(data, None, config)
    config = _with_window(config, problem)
    machine_map = _machine_map(config, problem, data, chain)
    study, run = _run_study(config, problem, machine_map, sources, chain, storage)
    counts = trial_counts(study)
    return WorkerSummary(study_name=study.study_name, storage=storage.spec.describe(), run=run,
                         budget=study_budget(study), restarts=study_restarts(study),
                         complete=counts.complete,
                         pruned=counts.pruned, failed=counts.failed, read_seconds=read_seconds)


def train_predictor(config: TrainingConfig) -> TrainingResult:
    """Read, clean, tune, train, score (module docstring); nothing is written but the study
    and its checkpoints."""
    chain = load_chain(config.robot)  # a robot named wrong: refused before anything is made
    storage = open_storage(check_config(config))  # connects: fails before reading any bag
    started = time.perf_counter()
    data, problem, trained_on, sources = read_problem(config, chain)
    read_seconds = time.perf_counter() - started
    config = _with_window(config, problem)
    machine_map = _machine_map(config, problem, data, chain)
    tuned = _tune(config, problem, machine_map, sources, chain, storage)
    baselines = fit_baselines(problem, FitContext(config.settings, config.progress,
                                                  machine_map))
    scoring_started = time.perf_counter()
    publication = _publication(tuned, baselines[RIDGE.name], problem,
                               config.publish == NETWORK)
    predicted = network_predictions(tuned.module, problem, members=tuned.members)
    if PUBLISHED in publication.report_keys:
        predicted[PUBLISHED] = published_predictions(publication, {
            **predicted, RIDGE.name: baselines[RIDGE.name].fitted.predict(problem.split.test)})
    scored, models = score_test_part(problem, baselines, predicted,
                                     config.inputs.cleaning.gap_factor)
    models['bo_lstm'].update(training_seconds=tuned.training_seconds,
                             hyperparameters=tuned.params, target=RESIDUAL_TARGET)
    standing = standings(models, publication.published_keys, {
        name: predictions - scored.actual for name, predictions in scored.predictions.items()})
    report = _report(config, problem, data, sources, models, tuned, publication, standing)
    scoring_seconds = time.perf_counter() - scoring_started
    metadata = _model_metadata(config, problem, tuned, machine_map, chain, trained_on,
                               models, publication, baselines[RIDGE.name], standing)
    total = time.perf_counter() - started
    # where the time went; write_outputs adds writing_seconds
    report['timings'] = {'read_clean_fk_seconds': read_seconds,
                         'tuning_seconds': tuned.tuning_seconds,
                         'best_model_seconds': tuned.best_model_seconds,
                         'generalist_seconds': tuned.generalist_seconds,
                         'bp_seconds': baselines[BP.name].seconds,
                         'baselines_seconds': sum(fitted.seconds for name, fitted
                                                  in baselines.items() if name != BP.name),
                         'scoring_seconds': scoring_seconds,
                         'total_seconds': total, 'read_fraction_of_total': read_seconds / total}
    report['model_file'] = str(Path(_model_path(config)).resolve())
    if config.test_inputs is not None:
        report['test_part'] = 'every window of the test bags: ' + ', '.join(
            config.test_inputs.bags)
    module = published_module(tuned.module, baselines[RIDGE.name].fitted.module, publication,
                              tuned.members)
    return TrainingResult(module=script_module(module), metadata=metadata, report=report,
                          test_part=scored)


def _publication(tuned: _Tuned, ridge: FittedBaseline, problem: LearningProblem,
                 network_only: bool) -> Publication:
    """Per axis, the candidates the validation part cannot tell from its best: the BO-LSTM,
    its generalist (a paired network), the ridge, the committee in the BO-LSTM's place in a
    mean (`publishing.choose`)."""
    validation = problem.split.validation
    actual = problem.error[validation + problem.horizon]
    errors = {name: predicted - actual for name, predicted in network_predictions(
        tuned.module, problem, validation, members=tuned.members).items()}
    if ridge.fitted.validation_prediction is not None:
        errors[RIDGE.name] = ridge.fitted.validation_prediction - actual
    return choose(errors, network_only)


def network_predictions(module: Any, problem: LearningProblem, ends: np.ndarray | None = None,
                        members: tuple[Any, ...] = ()) -> dict[str, np.ndarray]:
    """The trained BO-LSTM's predictions of the windows ending at `ends` (by default the
    test part's; key 'bo_lstm'), with a paired network its generalist's (`GENERALIST`),
    from one call, and with the committee's other networks (`members`) its mean
    (`COMMITTEE`)."""
    test = problem.split.test if ends is None else ends
    if not is_paired(module):
        predicted = {'bo_lstm': predict_rows(module, problem.rows, test, problem.window)}
    else:
        three = predict_rows(PredictionWithCandidates(module), problem.rows, test,
                             problem.window, width=3 * len(TARGETS))  # + generalist's, map's
        predicted = {'bo_lstm': three[:, :len(TARGETS)],
                     GENERALIST: three[:, len(TARGETS):-len(TARGETS)]}
    if members:
        predicted[COMMITTEE] = np.mean([predicted['bo_lstm'], *(
            predict_rows(member, problem.rows, test, problem.window) for member in members)],
            axis=0)
    return predicted


def _model_metadata(config: TrainingConfig, problem: LearningProblem, tuned: _Tuned,
                    machine_map: MachineMap | None, chain: KinematicChain,
                    trained_on: list[BagSource], models: dict[str, dict[str, Any]],
                    publication: Publication, ridge: FittedBaseline,
                    standing: dict[str, dict[str, Any]]) -> ModelMetadata:
    """The metadata the model file carries (docs/interface.md, the model file); the test
    metrics are the BO-LSTM's, the standing (`standings`) says what each axis publishes."""
    published = ({'published': {axis: list(members)
                                for axis, members in publication.members.items()},
                  'ridge': {**ridge.fitted.details['hyperparameters'],
                            'input': 'the flattened window, error columns relative to its '
                                     'last row, then the last error, standardised',
                            'target': RESIDUAL_TARGET}}
                 if publication.model_type != 'lstm' else {})
    if any(COMMITTEE in members for members in publication.members.values()):
        published['committee'] = tuned.report['committee']  # its trials, the best first
    return ModelMetadata(
        features=problem.features, preview=problem.preview, window=problem.window,
        horizon=problem.horizon,
        sample_period=problem.sample_period, targets=TARGETS,
        normalisation=normalisation_metadata(tuned.module, problem.error_low,
                                             problem.error_high, NORMALISATION['lstm'],
                                             problem.features),
        model_type=publication.model_type,
        hyperparameters={**tuned.params,  # every one, tuned or fixed (`SearchSpace.suggest`)
                         'architecture': ('two networks (every feature; the map residuals '
                                          'alone), each ' if is_paired(tuned.module) else '')
                                         + 'LSTM over the last lstm_steps rows, last state -> '
                                         'MLP head (2 GELU layers) + linear highway on the window'
                                         + (', on the machine map' if machine_map else ''),
                         'optimiser': 'AdamW, cosine learning-rate decay over max_epochs',
                         **recorded_options(config),
                         'cleaning': vars(config.inputs.cleaning), **published},
        robot_description_sha256=chain.sha256, robot=chain.metadata(),
        training_bags=tuple({'path': str(Path(s.path).resolve()), 'sha256': s.sha256}
                            for s in trained_on if not s.skipped_reason),
        seed=config.seed, library_versions=library_versions(),
        test_metrics=models['bo_lstm']['metrics'],
        standing=standing,
        machine_map=machine_map.metadata() if machine_map is not None else {},
        envelope=fit_envelope(problem.rows[problem.split.training_rows()],
                              problem.features).to_metadata())


def write_outputs(config: TrainingConfig, result: TrainingResult) -> str:
    """Write the model file (module + metadata) with its sha256 beside it
    (`MODEL.pt.sha256`), and the report folder (report.json with `model_sha256`, report.md,
    the plots) of `config`; each file atomically. The report's timings get
    `writing_seconds` (model file and plots). Returns the model's sha256."""
    started = time.perf_counter()
    model_path = _model_path(config)
    digest = write_model(model_path, result.module, result.metadata)
    result.report['model_sha256'] = digest
    result.report['model_sha256_file'] = str(sidecar_path(model_path).resolve())
    scored = result.test_part

    def writing_time() -> None:
        result.report.setdefault('timings', {})['writing_seconds'] = (
            time.perf_counter() - started)

    write_report(_report_dir(config), result.report, seconds=scored.seconds,
                 actual=scored.actual, predictions=scored.predictions,
                 before_documents=writing_time)
    return digest


class DataError(LomprError):
    """The recordings cannot make the learning problem (too short for the window, horizon,
    preview or split)."""


def read_problem(config: TrainingConfig, chain: KinematicChain
                 ) -> tuple[CleanData, LearningProblem, list[BagSource], list[BagSource]]:
    """Read and clean the config's bags (and test bags): the clean training data, the
    learning problem (`_problem`), the training bags and every bag read (the test bags
    last: the irreducible level is theirs)."""
    data, sources = load_clean_data(config.inputs, chain)
    if config.test_inputs is None:
        return data, _problem(data, None, config), list(sources), list(sources)
    test_data, test_sources = load_clean_data(config.test_inputs, chain)
    return data, _problem(data, test_data, config), list(sources), sources + test_sources


def _problem(data: CleanData, test: CleanData | None, config: TrainingConfig) -> LearningProblem:
    """The learning problem: `data` split chronologically, or trained (and validated) on
    `data` and tested on `test`; `DataError` (one line, before any training) when the
    recordings are too short for it (an error no machine makes is refused as they are read,
    `loading.load_clean_data`)."""
    try:
        if test is None:
            return build_problem(data, config.window, config.horizon, preview=config.preview,
                                 test_fraction=TEST_FRACTION,
                                 validation_fraction=VALIDATION_FRACTION)
        return train_test_problem(data, test, config.window, config.horizon,
                                  preview=config.preview,
                                  validation_fraction=VALIDATION_FRACTION)
    except ValueError as err:
        raise DataError(str(err)) from err


def _with_window(config: TrainingConfig, problem: LearningProblem) -> TrainingConfig:
    """`config` with the window its problem was built with: the one given, or the default
    for the recording's rate (`problem.default_window`), which the study's definition, the
    report and the model file then record."""
    return dataclasses.replace(config, window=problem.window)


def _model_path(config: TrainingConfig) -> Path:
    if config.model_path is None:
        raise OptionError('no model file to write: give a model_path', ('model_path',))
    return Path(config.model_path)


def _report_dir(config: TrainingConfig) -> Path:
    if config.report_dir is None:
        raise OptionError('no report folder: give a report_dir', ('report_dir',))
    return Path(config.report_dir)


def study_definition(config: TrainingConfig, sources: list[BagSource],
                     chain: KinematicChain) -> dict[str, Any]:
    """What defines the tuning problem, recorded in the study (a command with other settings
    is refused) and naming it unless the config does: the bags by content (their paths
    differ between machines), the robot chain, topics, cleaning, space, the options
    declared to define it (`options.study_options`: window, horizon, seed, preview), the
    machine map's and the training loop's settings."""
    return {'bags': sorted(s.sha256 for s in sources if not s.skipped_reason),
            'robot_description': chain.sha256,
            # only for other robots than the LOMPR, which came later: its studies keep
            # their names
            **({'robot': chain.metadata()} if chain.kind != LOMPR_KIND else {}),
            'topics': _topics(config.inputs.topics),
            'cleaning': vars(config.inputs.cleaning), 'space': config.space.as_dict(),
            **study_options(config),
            # only with the map, which came later: studies without it keep their names
            **({'machine_map': True, 'network_inputs': config.network_inputs}
               if config.machine_map else {}),
            'settings': _study_settings(config.settings), 'model_type': 'lstm'}


def _study_settings(settings: TrainSettings) -> dict[str, Any]:
    """The training loop's settings as a study records them: the ridge start only when on
    (it came later: studies trained without it keep their names with --no-linear-start,
    and a default study is a new one, its trials not mixed with theirs), the highway's rule
    only when not 'auto' (likewise later)."""
    return {name: value for name, value in vars(settings).items()
            if (name != 'linear_start' or value) and (name != 'highway' or value != 'auto')}


def _topics(topics: BagTopics) -> list[str]:
    """The topics read, as a study records them: the joints' and the reference's, then the
    end pose's and the compensation's where not the defaults (studies of bags read with the
    defaults keep their names)."""
    defaults = BagTopics()
    return [topics.joints, topics.reference, *(
        name for name, default in ((topics.end_pose, defaults.end_pose),
                                   (topics.compensation, defaults.compensation))
        if name != default)]


def _machine_map(config: TrainingConfig, problem: LearningProblem, data: CleanData,
                 chain: KinematicChain) -> MachineMap | None:
    """The machine map of the problem's training part (None when the config wants none)."""
    if not config.machine_map:
        return None
    training = problem.split.training_rows()[:len(data)]
    try:
        return fit_machine_map(problem, data.reference[training], chain)
    except ValueError as err:  # the recordings' runs: too short for the horizon's pairs
        msg = f'{err}; record longer runs without gaps, or train without it (--no-machine-map)'
        raise DataError(msg) from err


def _run_study(config: TrainingConfig, problem: LearningProblem,
               machine_map: MachineMap | None, sources: list[BagSource],
               chain: KinematicChain,
               storage: StudyStorage) -> tuple[optuna.Study, TuningRun]:
    """Open (create, resume or join) the study and run it to its budget here."""
    definition = study_definition(config, sources, chain)
    name = config.study_name or study_name_for(definition)
    study = open_study(storage, name, seed=config.seed, budget=config.trials,
                       restarts=config.restarts, definition=definition)
    make_objective = partial(NetworkObjective, problem=problem, space=config.space,
                             settings=config.settings, checkpoints=config.checkpoint_dir,
                             machine_map=machine_map, network_inputs=config.network_inputs)
    spec = StudySpec(storage=storage.spec, name=name, seed=config.seed, budget=config.trials,
                     restarts=config.restarts)
    workers = config.workers if config.workers is not None else default_workers()
    run = tune(spec, study, storage, make_objective, workers=workers, progress=config.progress)
    return study, run


def _tune(config: TrainingConfig, problem: LearningProblem, machine_map: MachineMap | None,
          sources: list[BagSource], chain: KinematicChain,
          storage: StudyStorage) -> _Tuned:
    """Run (or resume, or finish) the study to its budget; the best trial's module."""
    study, run = _run_study(config, problem, machine_map, sources, chain, storage)
    objective = NetworkObjective(study, problem, config.space, config.settings,
                                 config.checkpoint_dir, progress=config.progress,
                                 machine_map=machine_map, network_inputs=config.network_inputs)
    started = time.perf_counter()
    best = best_trial(study)
    params = objective.params_of(best)
    module, seconds = objective.model_of(best)
    committee = committee_trials(study, config.committee)
    members = tuple(objective.model_of(trial)[0] for trial in committee[1:])
    best_model_seconds = time.perf_counter() - started
    generalist_seconds = 0.0
    if config.network_inputs == 'paired' and machine_map is not None:
        generalist = train_generalist(problem, params, config.settings, machine_map,
                                      progress=config.progress)
        module = script_module(paired_module(module, generalist.module, machine_map, problem,
                                             params))
        generalist_seconds = generalist.seconds
    counts = trial_counts(study)
    trials = history(study)
    report = {'study_name': study.study_name, 'storage': storage.spec.describe(),
              'checkpoints': str(config.checkpoint_dir.resolve()),
              'space': config.space.as_dict(), 'budget': study_budget(study),
              'restarts': study_restarts(study), 'restarts_run': counts.restarts,
              'best_restart': restart_index(best),
              'trials_spent': counts.spent, 'trials_complete': counts.complete,
              'trials_pruned': counts.pruned, 'trials_failed': counts.failed,
              # the pruner stops a trial by ending its training (its best loss is its value)
              'trials_stopped_by_pruner': sum(1 for t in trials if t.get('pruned_epoch')),
              'epochs_run': sum(int(t.get('epochs') or 0) for t in trials),
              'trials_training_seconds': sum(float(t.get('training_seconds') or 0.0)
                                             for t in trials),
              'trials_run_now': run.trials_run, 'local_workers': list(run.workers),
              'workers': worker_counts(study),
              'best_trial': best.number, 'best_value': best.value, 'best_params': params,
              'best_epoch': best.user_attrs.get(BEST_EPOCH),
              'best_highway_held': best.user_attrs.get(HIGHWAY_HELD),
              'committee': [{'trial': trial.number, 'value': trial.value,
                             'params': objective.params_of(trial)} for trial in committee],
              'committee_asked': config.committee,
              'trials': trials,
              # the thread count in effect (set by the entry point): the times depend on it
              'settings': {**vars(config.settings), 'threads': torch.get_num_threads()}}
    return _Tuned(module=module, params=params, training_seconds=seconds,
                  tuning_seconds=run.seconds, best_model_seconds=best_model_seconds,
                  members=members,
                  generalist_seconds=generalist_seconds, report=report)


def _report(config: TrainingConfig, problem: LearningProblem, data: CleanData,
            sources: list[BagSource], models: dict[str, dict[str, Any]],
            tuned: _Tuned, publication: Publication,
            standing: dict[str, dict[str, Any]]) -> dict[str, Any]:
    report = base_report('train', problem, data, sources, config.inputs.cleaning)
    bp_seconds = models[BP.name]['training_seconds']
    report.update(
        models=models,
        ratios_to_bp=ratios(models['bo_lstm']['metrics'], models['bp']['metrics']),
        bo_lstm_beats={name: beats(models['bo_lstm']['metrics'], models[name]['metrics'])
                       for name in models if name != 'bo_lstm'},
        standings=standing,
        published=publication.report(),
        training_time_ratio_lstm_to_bp=(tuned.training_seconds / bp_seconds
                                        if bp_seconds else None),
        tuning_time_ratio_to_bp=tuned.tuning_seconds / bp_seconds if bp_seconds else None,
        **irreducible_fields(models, sources, config.horizon),
        tuning=tuned.report)
    return report
