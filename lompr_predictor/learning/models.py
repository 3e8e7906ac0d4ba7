# SPDX-License-Identifier: Apache-2.0
"""The predictors: BO-LSTM, the paper's BP (MLP) baseline, persistence, and the scripted
wrapper that meets the model-file contract (`model_file.py`).

Networks work on normalised tensors: each feature column taken through an affine map chosen
on the training windows (the LSTM: standardisation; the BP: min-max to [-1, 1]), the target
likewise. `PredictorModule` wraps a network with those constants so that the exported module
takes raw SI windows (float64, (B, window, features)) and returns the plant X/Y error [m]
`horizon` samples after each window's last row. The input map is defined once,
`normalise_windows`; training applies it to rows scaled once in float32 (`ScaledRows`).

- LSTM: the target is the change of the error over the horizon (`residual=True`), on a
  prior: persistence, or with a machine map (`machine_map.py`, `lompr train`'s default)
  persistence plus the change the map predicts, the network reading every row's map
  residual: the map carries what transfers between programs, the network what it misses.
  The LSTM's last state goes through an MLP head, beside a linear "autoregressive highway"
  on the flattened window (as LSTNet): the linear part carries noise averaging and the
  path's extrapolation, the LSTM the non-linear rest (friction and backlash at reversals).
  A new network's highway starts at the closed-form ridge over its window (`linear_start`).
  With 'paired' inputs (the default) two networks run side by side (`PairedNet`): one reads
  every feature and learns the programs it was trained on (the prediction); the other
  reads the map's residuals alone and holds on programs it was not (the fallback the live
  guard publishes where the first does worse: `PredictorModule.candidates`).
- BP: the paper's baseline, an MLP with one sigmoid hidden layer on the flattened window,
  predicting the error itself (`residual=False`).
- Persistence: e(t+h) = e(t), the floor every model has to beat.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, overload

import numpy as np
import torch
from torch import nn

from lompr_predictor.data.cleaning import CleanData
from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.data.problem import window_ends
from lompr_predictor.learning.machine_map import MachineMap
from lompr_predictor.learning.map_prior import is_paired, prediction_with_prior
from lompr_predictor.learning.space import NETWORK_INPUTS

MODEL_TYPES = ('lstm', 'mlp')
#: The columns a machine map appends to the rows the network reads: each row's plant error
#: minus the residual map's value there (`PredictorModule`, `MachineMap.levels`).
MAP_RESIDUALS = ('map_residual_x', 'map_residual_y')


#: Rows at the end of the window the LSTM runs over unless the hyperparameters say otherwise
#: (`lstm_steps`, tuned in the default space); the linear highway sees the whole window.
#: Few rows: the recurrent cost grows with the steps, and more did not predict better on the
#: twin's presets.
LSTM_STEPS = 10


class LstmNet(nn.Module):
    """LSTM over the window's last `steps` rows, its last hidden state through an MLP head
    (two GELU layers: it can express the switching of friction and backlash at a reversal,
    which a linear read-out of the state could not), plus a linear highway on the flattened
    window (the linear part: noise averaging, the path's extrapolation)."""

    def __init__(self, n_features: int, window: int, hidden: int, n_outputs: int = 2,
                 steps: int = LSTM_STEPS) -> None:
        super().__init__()
        self.steps = max(1, min(window, steps))
        self.lstm = nn.LSTM(n_features, hidden, batch_first=True)
        self.head = nn.Sequential(nn.Linear(hidden, hidden), nn.GELU(),
                                  nn.Linear(hidden, hidden), nn.GELU(),
                                  nn.Linear(hidden, n_outputs))
        self.highway = nn.Linear(window * n_features, n_outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _, (state, _) = self.lstm(x[:, x.shape[1] - self.steps:])
        return self.head(state[0]) + self.highway(x.flatten(1))


class PairedNet(nn.Module):
    """Two `LstmNet`s on the same normalised window: the specialist on every column, the
    generalist on the `machine_columns` alone (the map's residuals); outputs (B, 2 x
    n_outputs), the specialist's first. `lompr train` trains the two apart at one point of
    the search space (`pairing.py`); fine-tuning trains them together, their parameters
    disjoint, each on its own output as it would alone."""

    if TYPE_CHECKING:  # for the type checker only (see `PredictorModule`)
        machine_columns: torch.Tensor

    def __init__(self, n_features: int, window: int, hidden: int,
                 machine_columns: Sequence[int], n_outputs: int = 2,
                 steps: int = LSTM_STEPS) -> None:
        super().__init__()
        self.specialist = LstmNet(n_features, window, hidden, n_outputs, steps)
        self.generalist = LstmNet(len(machine_columns), window, hidden, n_outputs, steps)
        self.register_buffer('machine_columns', torch.tensor(list(machine_columns),
                                                             dtype=torch.long))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.specialist(x),
                          self.generalist(x.index_select(2, self.machine_columns))], 1)


class MlpNet(nn.Module):
    """The paper's BP network: flattened window -> one sigmoid hidden layer -> outputs."""

    def __init__(self, n_features: int, window: int, hidden: int, n_outputs: int = 2) -> None:
        super().__init__()
        self.hidden = nn.Linear(window * n_features, hidden)
        self.out = nn.Linear(hidden, n_outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(torch.sigmoid(self.hidden(x.flatten(1))))


#: The paper's BP engineering defaults: not tuned, the baseline as published.
BP_HYPERPARAMETERS = {'batch_size': 1500, 'hidden': 35, 'learning_rate': 0.01}


def build_network(model_type: str, n_features: int, window: int, hidden: int,
                  steps: int = LSTM_STEPS,
                  machine_columns: Sequence[int] | None = None) -> nn.Module:
    """A network of `model_type` ('lstm', over its window's last `steps` rows, or 'mlp');
    an LSTM given `machine_columns` (`paired_columns`) is a `PairedNet`."""
    if model_type == 'lstm' and machine_columns is not None:
        return PairedNet(n_features, window, hidden, machine_columns, len(TARGETS), steps)
    if model_type == 'lstm':
        return LstmNet(n_features, window, hidden, len(TARGETS), steps)
    if model_type == 'mlp':
        return MlpNet(n_features, window, hidden, len(TARGETS))
    msg = f'unknown model type {model_type!r}; choose one of {", ".join(MODEL_TYPES)}'
    raise ValueError(msg)


def range_to_affine(low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre, half range) mapping [low, high] to [-1, 1]: x_n = (x - centre) / half."""
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    return 0.5 * (low + high), 0.5 * (high - low)


def error_columns(features: Sequence[str] = FEATURES) -> list[int]:
    """Indices of the plant error columns (`TARGETS` order) among `features`."""
    names = list(features)
    return [names.index(f'error_{axis}') for axis in TARGETS]


def network_features(features: Sequence[str], machine_map: bool) -> tuple[str, ...]:
    """The columns of the rows the network's input is taken from: the features, then with a
    machine map its residuals (`MAP_RESIDUALS`)."""
    return tuple(features) + (MAP_RESIDUALS if machine_map else ())


def network_columns(features: Sequence[str] = FEATURES, relative_errors: bool = True,
                    error_level: bool = False,
                    inputs: str = 'all') -> tuple[list[int], list[float]]:
    """The network's input columns, as indices into `features` (`network_features`), and
    which of them are taken relative to the window's last row (1.0) or as they are (0.0).

    `inputs` 'all': every feature, the error columns (and map residuals) relative if
    `relative_errors`, then with `error_level` the error columns again as they are (the
    level, `PredictorModule`). 'paired' (needs a map): the same, of which the generalist of
    a `PairedNet` reads `paired_columns`; the level is the error's alone, not the map
    residual's: the residual's level carries what the residual map leaves of the machine's
    slow state, which a network validated on one recording learns and its next run does not
    repeat (docs/lab/programs_transfer.md, "In distribution: the level the first network reads").
    'machine' (needs a map): the map residuals alone, relative, then with `error_level`
    again as they are: what the map leaves of the error is the machine's drift, noise and
    unmodelled dynamics, while the raw error and the motion columns also tell where the path
    goes, which a network trained on one program learns and then gets wrong on another
    (docs/training.md, "Programs")."""
    names = list(features)
    errors = error_columns(features)
    residuals = [names.index(name) for name in MAP_RESIDUALS if name in names]
    if inputs not in NETWORK_INPUTS:
        msg = f'unknown network inputs {inputs!r}; choose one of {", ".join(NETWORK_INPUTS)}'
        raise ValueError(msg)
    if inputs in ('machine', 'paired') and not residuals:
        msg = f"the network inputs {inputs!r} read the machine map's residuals: give it a map"
        raise ValueError(msg)
    columns = list(residuals) if inputs == 'machine' else list(range(len(features)))
    relative = errors + residuals
    mask = [1.0 if relative_errors and column in relative else 0.0 for column in columns]
    if error_level:
        level = residuals if inputs == 'machine' else errors
        columns += level
        mask += [0.0] * len(level)
    return columns, mask


def paired_columns(features: Sequence[str]) -> list[int]:
    """Positions, among the 'paired' network input's columns (`network_columns` of
    `features`, which end in the map residuals), of what the generalist of a `PairedNet`
    reads: the map residuals relative to the window's last row (the 'machine' inputs
    without their level, `pairing.py`)."""
    columns = network_columns(features, True, False, 'paired')[0]
    residuals = [list(features).index(name) for name in MAP_RESIDUALS]
    return [position for position, column in enumerate(columns) if column in residuals]


def normalise_windows(windows: torch.Tensor, relative_mask: torch.Tensor, centre: torch.Tensor,
                      inverse_half: torch.Tensor | None) -> torch.Tensor:
    """The network's input map, the one definition (TorchScript-able): the masked columns
    taken relative to the window's last row, then (x - centre) * inverse_half per column.

    Without `inverse_half` the windows are taken as already scaled, with `centre` in the
    same scaled units: (w * s) - (w * s)[last] * mask - centre * s equals
    ((w - w[last] * mask) - centre) * s, which is how training uses it (`ScaledRows`).
    """
    shifted = windows - windows[:, -1:, :] * relative_mask - centre
    return shifted if inverse_half is None else shifted * inverse_half


class PredictorModule(nn.Module):
    """Raw SI windows (float64) -> predicted plant X/Y error [m]; TorchScript-able.

    With `relative_errors`, the window's error columns are taken relative to its last row
    (e(k) - e(t)): the error's recent course, at a fine resolution, which noise filtering
    and the change over the horizon mostly depend on; a constant offset on every error then
    moves the prediction by just that offset. With `error_level` too, the error columns are
    appended again as they are (`network_columns`): the level, which tells where a slow
    drift stands (how warm the machine is), at the price of that invariance. Tuned
    (`space.SearchSpace.error_levels`): at one point, on a thermal preset at horizon 25, the
    level cut the RMSE by 8 % (X) and 15 % (Y); on friction, wear and backlash presets it
    mostly cost a few per cent (docs/training.md, Models).
    """

    if TYPE_CHECKING:  # the buffers, for the type checker only: TorchScript cannot resolve
        # class-level annotations under `from __future__ import annotations`
        feature_centre: torch.Tensor
        feature_inverse_half: torch.Tensor
        target_centre: torch.Tensor
        target_half: torch.Tensor
        input_columns: torch.Tensor
        relative_mask: torch.Tensor
        error_columns: torch.Tensor

    def __init__(self, net: nn.Module, feature_low: np.ndarray, feature_high: np.ndarray,
                 target_low: np.ndarray, target_high: np.ndarray, *, residual: bool,
                 relative_errors: bool, error_level: bool = False,
                 features: Sequence[str] = FEATURES,
                 machine_map: MachineMap | None = None, inputs: str = 'all') -> None:
        super().__init__()
        self.net = net
        #: The machine map whose change over the horizon joins the prior and whose residual
        #: the network reads; a model without one holds an unused empty map (TorchScript
        #: wants the attribute's type fixed).
        self.use_map = machine_map is not None
        self.machine_map = (machine_map if machine_map is not None
                            else MachineMap(FEATURES, horizon=0, preview=0, sample_period=0.0))
        centre, half = range_to_affine(feature_low, feature_high)
        self.register_buffer('feature_centre', torch.tensor(centre, dtype=torch.float64))
        self.register_buffer('feature_inverse_half', torch.tensor(1.0 / half, dtype=torch.float64))
        centre, half = range_to_affine(target_low, target_high)
        self.register_buffer('target_centre', torch.tensor(centre, dtype=torch.float64))
        self.register_buffer('target_half', torch.tensor(half, dtype=torch.float64))
        self.residual = bool(residual)
        columns, mask = network_columns(network_features(features, self.use_map),
                                        relative_errors, error_level, inputs)
        self.register_buffer('input_columns', torch.tensor(columns, dtype=torch.long))
        self.register_buffer('relative_mask', torch.tensor(mask, dtype=torch.float64))
        self.register_buffer('error_columns', torch.tensor(error_columns(features),
                                                           dtype=torch.long))

    @classmethod
    def from_affine(cls, net: nn.Module, feature_centre: np.ndarray, feature_scale: np.ndarray,
                    target_centre: np.ndarray, target_scale: np.ndarray, *, residual: bool,
                    relative_errors: bool, error_level: bool = False,
                    features: Sequence[str] = FEATURES,
                    machine_map: MachineMap | None = None,
                    inputs: str = 'all') -> PredictorModule:
        """The module of an input map x_n = (x - centre) / scale and the output map
        y = y_n * scale + centre, e.g. standardisation (mean, standard deviation)."""
        feature_centre, feature_scale, target_centre, target_scale = (
            np.asarray(v, dtype=float) for v in (feature_centre, feature_scale, target_centre,
                                                 target_scale))
        return cls(net, feature_centre - feature_scale, feature_centre + feature_scale,
                   target_centre - target_scale, target_centre + target_scale,
                   residual=residual, relative_errors=relative_errors,
                   error_level=error_level, features=features, machine_map=machine_map,
                   inputs=inputs)

    def with_fixed_targets(self, targets: np.ndarray) -> PredictorModule:
        """This module with the output of each target axis that never varied in the
        training `targets` (B, 2) held at its value there: an axis the error has no part in
        (a single axis's Y) is predicted as it was, never from the network's output scaled
        by a range it did not have."""
        targets = np.asarray(targets, dtype=float)
        fixed = torch.from_numpy(np.ptp(targets, axis=0) == 0)
        with torch.no_grad():
            self.target_half[fixed] = 0.0
            self.target_centre[fixed] = torch.from_numpy(targets[0])[fixed]
        return self

    def normalise(self, windows: torch.Tensor) -> torch.Tensor:
        """Float64 windows of the network's rows (`network_features`) -> normalised float32
        network input."""
        return normalise_windows(windows.index_select(2, self.input_columns), self.relative_mask,
                                 self.feature_centre, self.feature_inverse_half).float()

    def normalise_targets(self, targets: np.ndarray) -> torch.Tensor:
        """(B, 2) training targets [m] -> the network's float32 targets: the inverse of the
        output map in `forward` (not part of the scripted module)."""
        half = self.target_half.numpy()
        scaled = (targets - self.target_centre.numpy()) / np.where(half > 0, half, 1.0)
        return torch.from_numpy(scaled.astype(np.float32))

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        # through `candidates`, which scripting compiles only because forward calls it (the
        # node calls it on the model file); the map prior it adds costs a few tensor ops
        return self.candidates(windows)[:, :2]

    def candidates(self, windows: torch.Tensor) -> torch.Tensor:
        """(B, 2 k [+ 2]) the predicted plant X/Y error [m] of each of the network's k
        outputs: the model's (`forward`), then with a `PairedNet` its generalist's; then,
        with a map, the map prior e(t) + g(t+h) - g(t) from the same map rows (the
        fallbacks the live guard scores beside the model, `map_prior`)."""
        # written for the exported graph, where each operation costs about as much as its
        # arithmetic: the last row by `select`, the outputs' scaling over their flat form
        if not self.use_map:
            last_error = windows.select(1, -1).index_select(1, self.error_columns)
            return self._predict(windows, last_error if self.residual
                                 else torch.zeros_like(last_error))
        levels, change = self.machine_map.levels_and_change(windows)
        errors = windows.index_select(2, self.error_columns)
        inputs = torch.cat([windows, errors - levels], 2)
        prior = errors.select(1, -1) + change
        return torch.cat([self._predict(inputs, prior if self.residual else change), prior], 1)

    def _predict(self, inputs: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """The network on its rows `inputs`, as (B, 2 k) error predictions: each output
        scaled to metres plus `base` (B, 2), what the network predicts a change from (the
        last error, with a map plus the map's change over the horizon)."""
        output = self.net(self.normalise(inputs)).double()
        outputs = output.shape[1] // 2
        return (output * self.target_half.repeat(outputs)
                + (self.target_centre.unsqueeze(0) + base).repeat(1, outputs))


def with_map_residuals(machine_map: MachineMap, rows: np.ndarray,
                       errors: Sequence[int]) -> np.ndarray:
    """(N, F + 2) raw feature rows (N, F) with each row's plant error (columns `errors`)
    minus the residual map there appended (`MAP_RESIDUALS`; NaN where the map lacks a
    feature): the rows a network with a machine map reads (`network_features`)."""
    return np.concatenate([rows, rows[:, list(errors)] - machine_map.levels(rows)], axis=1)


class ScaledRows:
    """Feature rows scaled once by a module's inverse half ranges, in float32, from which
    training gathers normalised windows with `normalise_windows` and no further product:
    the module's own input map, to float32 rounding, at a fraction of the cost per batch."""

    def __init__(self, module: PredictorModule, rows: np.ndarray) -> None:
        scale = module.feature_inverse_half.numpy()
        self.rows = torch.from_numpy((rows[:, module.input_columns.numpy()] * scale)
                                     .astype(np.float32))
        self.relative_mask = module.relative_mask.float()
        self.centre = torch.from_numpy((module.feature_centre.numpy() * scale).astype(np.float32))

    def windows(self, ends: np.ndarray, window: int) -> torch.Tensor:
        """(B, window, F) float32 network input of the windows ending at rows `ends`."""
        return normalise_windows(gather_windows(self.rows, ends, window), self.relative_mask,
                                 self.centre, None)


def normalisation_metadata(module: Any, error_low: np.ndarray, error_high: np.ndarray,
                           scheme: str = 'standard',
                           features: Sequence[str] = FEATURES) -> dict[str, Any]:
    """The constants inside a `PredictorModule` (scripted or not) and the error's training
    range (the metrics' scale), for the model file's metadata: for people and tools.
    `scheme`: how training chose the affine maps ('standard': mean and standard deviation of
    the training windows, 'minmax': their range mapped to [-1, 1])."""
    mask = module.relative_mask.tolist()
    columns = module.input_columns.tolist()
    names = network_features(features, bool(module.use_map))
    how = ('standardised by their training mean and standard deviation' if scheme == 'standard'
           else 'mapped to [-1, 1] by their training min-max')
    target = 'e(t+h) - e(t)' if module.residual else 'e(t+h)'
    if module.use_map:
        target += " - (g(t+h) - g(t)) (the machine map's change)"
    errors = ("; error columns taken relative to the window's last row first"
              if any(mask) else '')
    if len(set(columns)) < len(columns):
        errors += ', then appended again as they are (the level)'
    return {'scheme': scheme,
            'input': f'window rows {how}{errors}',
            'input_columns': [names[column] + (' - last row' if relative_column else '')
                              for column, relative_column in zip(columns, mask, strict=True)],
            'feature_centre': module.feature_centre.tolist(),
            'feature_scale': (1.0 / module.feature_inverse_half).tolist(),
            'target': f'{target}, {how}',
            'target_centre': module.target_centre.tolist(),
            'target_scale': module.target_half.tolist(),
            'error_low': np.asarray(error_low).tolist(),
            'error_high': np.asarray(error_high).tolist()}


class NoChangeNet(nn.Module):
    """Predicts no change over the horizon: inside a residual `PredictorModule` it makes the
    persistence predictor a model file, which the predictor node runs like any model (the
    closed loop's persistence compensator)."""

    def __init__(self, n_outputs: int = 2) -> None:
        super().__init__()
        self.n_outputs = n_outputs

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros((x.shape[0], self.n_outputs), dtype=x.dtype)


def persistence_module(features: Sequence[str] = FEATURES) -> PredictorModule:
    """Persistence as a raw-SI module: the window's last plant error, for any horizon."""
    n_features, n_targets = len(features), len(TARGETS)
    return PredictorModule(NoChangeNet(n_targets), np.zeros(n_features), np.ones(n_features),
                           -np.ones(n_targets), np.ones(n_targets), residual=True,
                           relative_errors=False, features=features)


def persistence(error: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(B, 2) persistence prediction: the error at each window's last row."""
    return np.asarray(error)[ends]


@overload
def gather_windows(rows: torch.Tensor, ends: np.ndarray, window: int) -> torch.Tensor: ...
@overload
def gather_windows(rows: np.ndarray, ends: np.ndarray, window: int) -> np.ndarray: ...
def gather_windows(rows: np.ndarray | torch.Tensor, ends: np.ndarray,
                   window: int) -> np.ndarray | torch.Tensor:
    """(B, window, F) windows of `rows` (an array or a tensor, the result alike) ending at
    rows `ends` (inclusive)."""
    index = np.asarray(ends)[:, None] + np.arange(1 - window, 1)[None, :]
    return rows[index]


def predict_rows(module: nn.Module, rows: np.ndarray, ends: np.ndarray, window: int,
                 batch: int = 4096, width: int = len(TARGETS)) -> np.ndarray:
    """(B, `width`) predictions [m] of a raw-SI module for the windows of feature `rows`
    ending at `ends`: what `LoadedModel.predict` gives for those windows, in batches."""
    table = torch.from_numpy(np.ascontiguousarray(rows, dtype=np.float64))
    out = []
    with torch.inference_mode():
        for start in range(0, len(ends), batch):
            out.append(module(gather_windows(table, ends[start:start + batch], window)).numpy())
    return np.concatenate(out) if out else np.zeros((0, width))


@dataclass(frozen=True)
class OfflinePredictions:
    """A model's predictions over clean recordings, one per admissible window."""

    ends: np.ndarray  # (B,) row of each window's last sample in the clean data
    stamps: np.ndarray  # (B,) int64 [ns] of the predicted instants (ends + horizon)
    predicted: np.ndarray  # (B, 2) predicted plant X/Y error [m]
    actual: np.ndarray  # (B, 2) measured plant error at those instants [m]
    newest_rows: np.ndarray  # (B, features) each window's last feature row
    last_error: np.ndarray  # (B, 2) plant error at each window's last row: persistence's [m]
    prior: np.ndarray  # (B, 2) the model's prior [m] (`map_prior`; NaN: it has none)
    map_prior: np.ndarray  # (B, 2) a paired model's map prior [m] (NaN: another model)


def offline_predictions(module: nn.Module, data: CleanData, window: int, horizon: int,
                        preview: int = 0) -> OfflinePredictions:
    """Predict every window of `data` (no window crosses a gap) with a raw-SI module, e.g.
    `model_file.load_model(path).module`, reading `preview` samples of the commanded path
    after each row: what the predictor node would have published for these recordings,
    sample for sample, given a preview that matched the path."""
    ends = window_ends(data.regular_runs(), window, horizon, preview)
    rows = data.features(preview)
    with_prior = prediction_with_prior(module)
    columns = np.full((len(ends), 3 * len(TARGETS)), np.nan)
    if with_prior is None:
        columns[:, :len(TARGETS)] = predict_rows(module, rows, ends, window)
    else:  # from one call, as the node has them
        width = (3 if is_paired(module) else 2) * len(TARGETS)
        columns[:, :width] = predict_rows(with_prior, rows, ends, window, width=width)
    predicted, prior, map_prior = np.split(columns, 3, axis=1)
    return OfflinePredictions(ends=ends, stamps=data.stamps[ends + horizon],
                              predicted=predicted, actual=data.error[ends + horizon],
                              newest_rows=rows[ends], last_error=data.error[ends],
                              prior=prior, map_prior=map_prior)
