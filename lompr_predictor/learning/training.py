# SPDX-License-Identifier: Apache-2.0
"""Training loop: one function, `train_network`, for the LSTM (in tuning and at the end) and
the paper's BP baseline alike, so their training times compare like for like.

The LSTM's recipe: standardised inputs and targets, AdamW, a cosine learning-rate decay
over `max_epochs` (per step), gradient clipping, the best validation epoch kept, and early
stopping only in the schedule's last quarter (the validation loss wanders while the rate is
high). The BP keeps the paper's: min-max inputs, Adam, the rate cut on a validation plateau.
Each epoch reports the validation loss to an Optuna trial when given (which may prune it).
Everything is seeded; the torch thread count is the caller's (`threads.set_torch_threads`).
The measurements behind these choices are in docs/results.md.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from lompr_predictor.data.problem import LearningProblem, minmax_range
from lompr_predictor.learning.linear_start import (
    RidgeFits,
    fit_ridge,
    holds_highway,
    refit_highways,
    start_from,
)
from lompr_predictor.learning.machine_map import MachineMap
from lompr_predictor.learning.models import (
    LSTM_STEPS,
    LstmNet,
    PairedNet,
    PredictorModule,
    ScaledRows,
    build_network,
    error_columns,
    gather_windows,
    network_columns,
    network_features,
    with_map_residuals,
)
from lompr_predictor.learning.options import TrainSettings
from lompr_predictor.progress import progress_bar

#: The paper's BP trains with its own budget (min-max inputs, plateau schedule).
BP_MAX_EPOCHS = 100
BP_PATIENCE = 10
GRADIENT_CLIP = 1.0  # max gradient norm: a too-high learning rate stalls instead of exploding
LR_DECAY = 0.3  # learning-rate factor after `LR_DECAY_PATIENCE` epochs without improvement
LR_DECAY_PATIENCE = 3
EVAL_BATCH = 8192


@dataclass
class TrainedModel:
    """A trained network wrapped for raw SI windows, and how its training went."""

    module: PredictorModule
    model_type: str
    hyperparameters: dict[str, Any]
    residual: bool
    relative_errors: bool
    validation_loss: float  # best epoch's validation MSE, normalised target units
    epochs: int  # epochs run
    best_epoch: int
    seconds: float  # wall time of the training loop
    history: list[float] = field(default_factory=list)  # validation loss per epoch
    pruned_epoch: int = 0  # epoch at which the tuning pruner stopped it (0: not stopped)
    start_loss: float = math.nan  # validation loss of the weights it started from (`init`)
    #: fine-tuning: the epochs started from `init` with its highways fitted again to the new
    #: data (`linear_start.refit_highways`), which predicted its validation part better
    highway_refitted: bool = False
    #: a new LSTM's highway held at its ridge start while the rest trained (`_ridge_start`)
    highway_held: bool = False


RANGE_SAMPLE = 20000  # training windows that set the input normalisation
#: How each model type's inputs and targets are normalised.
NORMALISATION = {'lstm': 'standard', 'mlp': 'minmax'}


def evenly_spaced(ends: np.ndarray, at_most: int) -> np.ndarray:
    """`ends` itself, or `at_most` of them evenly spaced from the first to the last."""
    if len(ends) <= at_most:
        return ends
    return ends[np.linspace(0, len(ends) - 1, at_most).astype(int)]


@dataclass(frozen=True)
class NetworkRows:
    """What a network learns from, for one learning problem: the rows its input is taken
    from (the problem's rows, with a machine map each row's map residual appended,
    `models.network_features`) and the map's change over the horizon from each row, which
    the prior already predicts (zeros without a map)."""

    rows: np.ndarray  # (N, F')
    features: tuple[str, ...]  # names of the columns of `rows`
    map_change: np.ndarray  # (N, 2) [m]

    def targets(self, problem: LearningProblem, ends: np.ndarray, residual: bool) -> np.ndarray:
        """(B, 2) the network's targets for the windows ending at `ends`, in SI units."""
        return problem.targets(ends, residual) - self.map_change[ends]


def network_rows(problem: LearningProblem, machine_map: MachineMap | None) -> NetworkRows:
    """The rows and targets a network of `problem` learns from, with or without a map."""
    if machine_map is None:
        return NetworkRows(problem.rows, problem.features, np.zeros((len(problem.rows), 2)))
    values, ahead = machine_map.values(problem.rows)
    return NetworkRows(with_map_residuals(machine_map, problem.rows,
                                          error_columns(problem.features)),
                       network_features(problem.features, True), ahead - values)


def input_windows(problem: LearningProblem, inputs: NetworkRows, relative_errors: bool,
                  error_level: bool = False, network_inputs: str = 'all') -> np.ndarray:
    """(M * window, C) rows of training windows (evenly spaced, at most `RANGE_SAMPLE`) in
    the network's input columns (`models.network_columns`): the training inputs that set
    the normalisation."""
    ends = evenly_spaced(problem.split.train, RANGE_SAMPLE)
    columns, mask = network_columns(inputs.features, relative_errors, error_level,
                                    network_inputs)
    windows = gather_windows(inputs.rows[:, columns], ends, problem.window)
    windows -= windows[:, -1:, :] * np.asarray(mask)
    return windows.reshape(-1, windows.shape[-1])


def moments(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column (mean, standard deviation), a zero deviation taken as 1."""
    centre, scale = np.mean(values, axis=0), np.std(values, axis=0)
    return centre, np.where(scale > 0, scale, 1.0)


def build_module(problem: LearningProblem, model_type: str, hidden: int, *, residual: bool,
                 relative_errors: bool, error_level: bool = False,
                 steps: int = LSTM_STEPS, machine_map: MachineMap | None = None,
                 network_inputs: str = 'all',
                 inputs: NetworkRows | None = None) -> PredictorModule:
    """An untrained network wrapped with the problem's training normalisation (the model
    type's, `NORMALISATION`) and the fitted `machine_map` if any, reading
    `network_inputs` of its rows (`models.network_columns`; `inputs`: the problem's
    `network_rows`, when the caller has them already)."""
    inputs = inputs or network_rows(problem, machine_map)
    fit = np.concatenate([problem.split.train, problem.split.validation])
    targets = inputs.targets(problem, fit, residual)
    width = len(network_columns(inputs.features, relative_errors, error_level,
                                network_inputs)[0])
    # 'paired' inputs: the specialist alone; its generalist is trained at the tuned point
    # (`pairing.py`)
    net = build_network(model_type, width, problem.window, hidden, steps)
    windows = input_windows(problem, inputs, relative_errors, error_level, network_inputs)
    options: dict[str, Any] = {'residual': residual, 'relative_errors': relative_errors,
                               'error_level': error_level, 'features': problem.features,
                               'machine_map': machine_map, 'inputs': network_inputs}
    if NORMALISATION[model_type] == 'standard':
        centre, scale = moments(windows)
        target_centre, target_scale = moments(targets)
        module = PredictorModule.from_affine(net, centre, scale, target_centre, target_scale,
                                             **options)
    else:
        low, high = minmax_range(windows)
        target_low, target_high = minmax_range(targets)
        module = PredictorModule(net, low, high, target_low, target_high, **options)
    return module.with_fixed_targets(targets)


def validation_loss(net: nn.Module, inputs: ScaledRows, ends: np.ndarray,
                    targets: torch.Tensor, window: int) -> float:
    """Mean squared error of `net` on normalised targets, in batches without gradients."""
    total, outputs = 0.0, targets.shape[1]
    with torch.no_grad():
        for start in range(0, len(ends), EVAL_BATCH):
            x = inputs.windows(ends[start:start + EVAL_BATCH], window)
            output = net(x)
            diff = output - each_output(output, targets[start:start + EVAL_BATCH])
            total += float((diff * diff).sum())
            outputs = output.shape[1]
    return total / (len(ends) * outputs)


def each_output(output: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """`targets` (B, 2) once for each prediction in a network's `output` (B, 2 k): a
    `PairedNet`'s two networks learn the same targets, and its loss is their mean."""
    return targets.repeat(1, output.shape[1] // targets.shape[1])


class _Schedule:
    """The optimiser and its learning-rate schedule: the LSTM's AdamW with a cosine decay
    over every step of `max_epochs`, the BP's Adam with a decay on plateaus (the paper's)."""

    def __init__(self, net: nn.Module, model_type: str, hyperparameters: Mapping[str, Any],
                 total_steps: int) -> None:
        rate = float(hyperparameters['learning_rate'])
        self.cosine = model_type == 'lstm'
        self.optimiser: torch.optim.Optimizer
        self._per_step: Any = None
        self._plateau: Any = None
        if self.cosine:
            self.optimiser = torch.optim.AdamW(
                net.parameters(), lr=rate,
                weight_decay=float(hyperparameters.get('weight_decay', 0.0)))
            self._per_step = torch.optim.lr_scheduler.CosineAnnealingLR(
                self.optimiser, max(1, total_steps))
        else:
            self.optimiser = torch.optim.Adam(net.parameters(), lr=rate)
            self._plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(
                self.optimiser, factor=LR_DECAY, patience=LR_DECAY_PATIENCE)

    def step(self) -> None:
        """One batch's step of the optimiser, and of the rate if it decays per step."""
        self.optimiser.step()
        if self._per_step is not None:
            self._per_step.step()

    def epoch_done(self, validation_loss: float) -> None:
        if self._plateau is not None:
            self._plateau.step(validation_loss)


def _train_epoch(net: nn.Module, schedule: _Schedule,
                 windows: Callable[[np.ndarray, int], torch.Tensor], ends: np.ndarray,
                 targets: torch.Tensor, batch: int, window: int) -> None:
    """One epoch over the windows ending at `ends` (in that order), `batch` at a time."""
    net.train()
    for start in range(0, len(ends), batch):
        x = windows(ends[start:start + batch], window)
        output = net(x)
        loss = nn.functional.mse_loss(output, each_output(output, targets[start:start + batch]))
        schedule.optimiser.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(net.parameters(), GRADIENT_CLIP)
        schedule.step()


def train_network(
    problem: LearningProblem,
    model_type: str,
    hyperparameters: Mapping[str, Any],
    settings: TrainSettings = TrainSettings(),
    *,
    residual: bool = True,
    relative_errors: bool = True,
    trial: Any = None,
    prune: bool = True,
    progress: bool = True,
    label: str = '',
    machine_map: MachineMap | None = None,
    network_inputs: str = 'all',
    init: PredictorModule | None = None,
    ridge_fits: RidgeFits | None = None,
) -> TrainedModel:
    """Train one network on `problem`; hyperparameters: batch_size, hidden, learning_rate,
    and optionally weight_decay (default 0), lstm_steps (default `LSTM_STEPS`) and
    error_level (default False: the window's error level as more input columns,
    `PredictorModule`). With a fitted `machine_map` the network builds on it and reads
    `network_inputs` of its rows (`models.network_columns`). With `init` (a trained module,
    `fine_tuning`), a copy of it is trained on from its weights, its machine map and
    normalisation kept (`machine_map`, `network_inputs` and the structural hyperparameters
    are its own), and its starting weights count as epoch 0's: the result is never worse
    on validation than where it started. `trial`, `prune`: an Optuna trial that may stop
    it (`_fit`). `ridge_fits`: the study's ridge starts, each fitted once (`linear_start`).
    """
    torch.manual_seed(settings.seed)
    module, rows = _starting_module(problem, model_type, hyperparameters, residual=residual,
                                    relative_errors=relative_errors, machine_map=machine_map,
                                    network_inputs=network_inputs, init=init)
    data = _FitData.of(problem, module, rows, residual=residual, settings=settings,
                       batch=int(hyperparameters['batch_size']))
    schedule = _Schedule(module.net, model_type, hyperparameters,
                         settings.max_epochs * math.ceil(data.epoch_size / data.batch))
    record, refitted = _start(module.net, data, settings, fine_tuning=init is not None,
                              ridge_fits=ridge_fits)
    held = isinstance(module.net, LstmNet) and not module.net.highway.weight.requires_grad
    seconds = _train_epochs(module.net, schedule, data, record, settings, trial, prune=prune,
                            bar=label or model_type, progress=progress)
    module.net.load_state_dict(record.best_state)
    module.eval()
    return TrainedModel(module=module, model_type=model_type,
                        hyperparameters=dict(hyperparameters), residual=residual,
                        relative_errors=relative_errors,
                        validation_loss=record.best, epochs=record.epoch,
                        best_epoch=record.best_epoch, seconds=seconds, history=record.history,
                        pruned_epoch=record.pruned_epoch, start_loss=record.start_loss,
                        highway_refitted=refitted, highway_held=held)


def _train_epochs(net: nn.Module, schedule: _Schedule, data: _FitData, record: _Record,
                  settings: TrainSettings, trial: Any, *, prune: bool, bar: str,
                  progress: bool) -> float:
    """Every epoch of one training (`_fit`) under a progress bar named `bar`; their wall
    time [s]. A highway held at its ridge start is held for this training only: trainable
    again after (a fine-tuning of the network trains every weight)."""
    started = time.perf_counter()
    with progress_bar(range(1, settings.max_epochs + 1), desc=bar, unit='epoch', leave=False,
                      disable=not progress) as epochs:
        _fit(net, schedule, data, record, epochs, settings, np.random.default_rng(settings.seed),
             trial, prune=prune)
    net.requires_grad_(True)
    return time.perf_counter() - started


def _starting_module(problem: LearningProblem, model_type: str,
                     hyperparameters: Mapping[str, Any], *, residual: bool,
                     relative_errors: bool, machine_map: MachineMap | None,
                     network_inputs: str, init: PredictorModule | None
                     ) -> tuple[PredictorModule, NetworkRows]:
    """The module training starts from (a copy of `init`, or a new one of the
    hyperparameters' shape) and the rows its network learns from."""
    if init is not None:
        module = copy.deepcopy(init)
        return module, network_rows(problem, module.machine_map if module.use_map else None)
    rows = network_rows(problem, machine_map)
    return build_module(problem, model_type, int(hyperparameters['hidden']),
                        residual=residual, relative_errors=relative_errors,
                        error_level=bool(hyperparameters.get('error_level', False)),
                        steps=int(hyperparameters.get('lstm_steps', LSTM_STEPS)),
                        machine_map=machine_map, network_inputs=network_inputs,
                        inputs=rows), rows


def _start(net: nn.Module, data: _FitData, settings: TrainSettings, *, fine_tuning: bool,
           ridge_fits: RidgeFits | None) -> tuple[_Record, bool]:
    """Where the epochs start, as the record before the first: a new LSTM at its ridge start,
    a fine-tuned network at its parent's weights or those with its highways refitted
    (`linear_start`), each counted as epoch 0; else random weights, not counted. Also
    whether the highways were refitted."""
    ridge_started = (settings.linear_start and not fine_tuning and isinstance(net, LstmNet)
                     and _ridge_start(net, data, ridge_fits, settings.highway))
    record = _Record.starting(net, data, counts=fine_tuning or ridge_started)
    refitted = settings.linear_start and fine_tuning and _refit_start(net, data, record)
    return record, refitted


def _ridge_start(net: LstmNet, data: _FitData, fits: RidgeFits | None, highway: str) -> bool:
    """Start `net` at the ridge over its own window (`linear_start`; from `fits` when given),
    its highway held there by the `highway` rule (`linear_start.holds_highway`); False when
    there is nothing to regress on."""
    arguments = (lambda ends: data.inputs.windows(ends, data.window), data.train_ends,
                 data.train_y, data.validation_ends, data.validation_y)
    fit = fit_ridge(*arguments) if fits is None else fits.fit(*arguments, rows=data.inputs.rows)
    if fit is not None:
        start_from(net, fit)
        net.highway.requires_grad_(not holds_highway(net, len(data.train_ends), highway))
    return fit is not None


def _refit_start(net: nn.Module, data: _FitData, record: _Record) -> bool:
    """Fine-tuning: `net` (the parent's weights, scored in `record`) with its highways
    fitted again to the new data (`linear_start.refit_highways`) where that predicts the
    validation part better, the epochs' start and epoch 0's candidate; else as it was."""
    if not isinstance(net, (LstmNet, PairedNet)):
        return False
    refit_highways(net, lambda ends: data.inputs.windows(ends, data.window), data.train_ends,
                   data.train_y, data.validation_ends, data.validation_y)
    net.eval()
    loss = data.validation_loss(net)
    if not loss < record.best:
        net.load_state_dict(record.best_state)
        return False
    record.best, record.best_state = loss, copy.deepcopy(net.state_dict())
    return True


@dataclass(frozen=True)
class _FitData:
    """What the epochs train and validate on: scaled rows, window ends, normalised targets."""

    inputs: ScaledRows
    train_ends: np.ndarray
    validation_ends: np.ndarray
    train_y: torch.Tensor
    validation_y: torch.Tensor
    window: int
    batch: int
    epoch_size: int  # training windows per epoch

    @classmethod
    def of(cls, problem: LearningProblem, module: PredictorModule, rows: NetworkRows, *,
           residual: bool, settings: TrainSettings, batch: int) -> _FitData:
        """The training part's windows and at most `settings.epoch_windows` of the
        validation part's, evenly spaced (an epoch scores them all)."""
        split = problem.split
        validation_ends = evenly_spaced(split.validation, settings.epoch_windows)
        train_y, validation_y = (module.normalise_targets(rows.targets(problem, ends, residual))
                                 for ends in (split.train, validation_ends))
        return cls(ScaledRows(module, rows.rows), split.train, validation_ends, train_y,
                   validation_y, problem.window, batch,
                   min(len(split.train), settings.epoch_windows))

    def validation_loss(self, net: nn.Module) -> float:
        return validation_loss(net, self.inputs, self.validation_ends, self.validation_y,
                               self.window)


@dataclass
class _Record:
    """The best epoch so far and the course of one training."""

    best: float  # validation loss
    best_state: dict[str, Any]
    best_epoch: int = 0
    epoch: int = 0  # epochs run
    history: list[float] = field(default_factory=list)
    pruned_epoch: int = 0
    start_loss: float = math.nan

    @classmethod
    def starting(cls, net: nn.Module, data: _FitData, *, counts: bool) -> _Record:
        """The record before the first epoch. Where the starting weights `counts` (a
        fine-tuned parent, a ridge start) they are a candidate too (epoch 0): the result is
        never worse on validation than where it started."""
        record = cls(math.inf, copy.deepcopy(net.state_dict()))
        if counts:
            net.eval()
            record.start_loss = data.validation_loss(net)
            record.best = record.start_loss if math.isfinite(record.start_loss) else math.inf
        return record


def _fit(net: nn.Module, schedule: _Schedule, data: _FitData, record: _Record,
         epochs: Any, settings: TrainSettings, rng: np.random.Generator, trial: Any, *,
         prune: bool) -> None:
    """Train epoch by epoch into `record` until the patience, the pruner or a non-finite
    loss stops it.

    `trial` (an Optuna trial) gets the validation loss each epoch; when its pruner says so
    (and `prune`), training stops there
    (`pruned_epoch`) and the result is the best loss so far. The caller returns that as the
    trial's value rather than raising `TrialPruned`: Optuna's GP sampler learns nothing
    from a pruned trial and would propose the same point again, whereas a stopped trial's
    (poor) loss steers it away.
    """
    for epoch in epochs:
        record.epoch = epoch
        order = rng.permutation(len(data.train_ends))[:data.epoch_size]
        _train_epoch(net, schedule, data.inputs.windows, data.train_ends[order],
                     data.train_y[order], data.batch, data.window)
        net.eval()
        loss_value = data.validation_loss(net)
        if not math.isfinite(loss_value):
            loss_value = math.inf
        record.history.append(loss_value)
        schedule.epoch_done(loss_value)
        epochs.set_postfix(validation=f'{loss_value:.3g}')
        if loss_value < record.best:
            record.best, record.best_epoch = loss_value, epoch
            record.best_state = copy.deepcopy(net.state_dict())
        if trial is not None:
            trial.report(loss_value, epoch)
            if prune and trial.should_prune():
                record.pruned_epoch = epoch
                return
        # with the cosine decay the validation loss is noisy while the rate is high and
        # improves most as it decays: no early stop before the schedule's last quarter
        settled = not schedule.cosine or 4 * epoch >= 3 * settings.max_epochs
        if (settled and epoch - record.best_epoch >= settings.patience) or loss_value == math.inf:
            return
