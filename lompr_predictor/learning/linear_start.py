# SPDX-License-Identifier: Apache-2.0
"""The LSTM's linear highway started at the closed-form ridge regression over its own window.

The highway (a linear map of the whole normalised window, `models.LstmNet`) trained by SGD
from random weights fits a long window poorly and ends elsewhere from run to run, while the
ridge over the same inputs, solved in closed form with its penalty chosen on the validation
part, is what leads one sample ahead at high rates. So a new network starts from it: the
highway holds the ridge's coefficients and the head's last layer is zero (the network's
first output is the ridge's prediction), and the training loop counts those starting weights
as epoch 0: the trained network is never worse on the validation part than that ridge, and
its LSTM learns what the ridge misses.

The ridge is fitted on the same normalised windows and targets as the network (centred, with
an intercept, the highway's bias), on at most `RIDGE_SAMPLE` training windows evenly spaced;
its penalties are relative to the mean eigenvalue of the inputs' scatter matrix, so that one
grid serves every window length and feature count.

Where the training windows are few for the highway's width (a short recording at a high
rate, its window long in samples), SGD's steps move the highway off the ridge to fit noise
the ridge's penalty kept out: there the highway is held at its start and only the LSTM and
its head train (`holds_highway`).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from lompr_predictor.learning.models import LstmNet, PairedNet
from lompr_predictor.learning.options import HOLD_BELOW_WINDOWS_PER_INPUT

#: Training windows the ridge is fitted on, at most (evenly spaced): its scatter matrix is
#: settled long before, and the cost stays a fraction of an epoch's.
RIDGE_SAMPLE = 20000
#: Penalties tried, as multiples of the mean eigenvalue of the centred inputs' scatter matrix.
RELATIVE_PENALTIES = tuple(10.0 ** k for k in range(-6, 2))
CHUNK = 4096  # windows gathered at a time


@dataclass(frozen=True)
class LinearFit:
    """A ridge regression in the network's normalised units: prediction = x @ weight.T + bias."""

    weight: np.ndarray  # (outputs, window * features)
    bias: np.ndarray  # (outputs,)
    penalty: float  # relative to the mean eigenvalue (`RELATIVE_PENALTIES`)
    validation_loss: float  # mean squared error on the validation windows, normalised units


def fit_ridge(windows: Callable[[np.ndarray], torch.Tensor], train_ends: np.ndarray,
              train_targets: torch.Tensor, validation_ends: np.ndarray,
              validation_targets: torch.Tensor) -> LinearFit | None:
    """The ridge from the flattened windows `windows(ends)` to the normalised targets, its
    penalty the one of `RELATIVE_PENALTIES` with the lowest validation loss; None when the
    inputs never vary (nothing to regress on)."""
    chosen = np.linspace(0, len(train_ends) - 1, min(len(train_ends), RIDGE_SAMPLE)).astype(int)
    x_mean, y_mean, scatter, cross = _moments(windows, train_ends[chosen],
                                              train_targets[chosen].double().numpy())
    eigenvalues, vectors = np.linalg.eigh(scatter)
    eigenvalues = np.clip(eigenvalues, 0.0, None)
    scale = float(np.mean(eigenvalues))
    if not scale > 0:
        return None
    projected = vectors.T @ cross
    validation_x = _flat(windows, validation_ends)
    validation_y = validation_targets.double().numpy()
    best: LinearFit | None = None
    for penalty in RELATIVE_PENALTIES:
        weight = vectors @ (projected / (eigenvalues + penalty * scale)[:, None])
        bias = y_mean - x_mean @ weight
        loss = float(np.mean((validation_x @ weight + bias - validation_y) ** 2))
        if best is None or loss < best.validation_loss:
            best = LinearFit(weight.T.copy(), bias, penalty, loss)
    return best


class RidgeFits:
    """The ridge fits of one study's trainings by their data's digest: its trials fit the same
    ridge wherever they read the same columns (the hyperparameters do not enter it), so a
    tuning process fits each once. Keeps the latest few."""

    def __init__(self, kept: int = 4) -> None:
        self._kept = kept
        self._fits: OrderedDict[str, LinearFit | None] = OrderedDict()

    def fit(self, windows: Callable[[np.ndarray], torch.Tensor], train_ends: np.ndarray,
            train_targets: torch.Tensor, validation_ends: np.ndarray,
            validation_targets: torch.Tensor, *, rows: torch.Tensor) -> LinearFit | None:
        """`fit_ridge` of these arguments, fitted once: `rows` are the (scaled) rows the
        windows are taken from, which with the ends and targets decide the fit."""
        digest = hashlib.sha256()
        for part in (rows, train_targets, validation_targets):
            digest.update(part.numpy().tobytes())
        for ends in (train_ends, validation_ends):
            digest.update(np.ascontiguousarray(ends, dtype=np.int64).tobytes())
        digest.update(windows(train_ends[:1]).numpy().tobytes())  # the window's shape, scaling
        key = digest.hexdigest()
        if key not in self._fits:
            self._fits[key] = fit_ridge(windows, train_ends, train_targets, validation_ends,
                                        validation_targets)
            while len(self._fits) > self._kept:
                self._fits.popitem(last=False)
        return self._fits[key]


def start_from(net: LstmNet, fit: LinearFit) -> None:
    """Set `net`'s highway to `fit` and zero its head's last layer: its output is then the
    ridge's prediction, the LSTM's part starting at nothing."""
    set_highway(net, fit)
    last = net.head[-1]
    assert isinstance(last, nn.Linear)
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()


def holds_highway(net: LstmNet, training_windows: int, rule: str) -> bool:
    """Whether `net`'s highway stays at its ridge start while the rest trains: `rule` 'held'
    or 'trained' (`options.HIGHWAY_RULES`), or 'auto': held when `training_windows` are
    fewer than `HOLD_BELOW_WINDOWS_PER_INPUT` per input of the highway."""
    if rule == 'auto':
        return training_windows < HOLD_BELOW_WINDOWS_PER_INPUT * net.highway.in_features
    return rule == 'held'


def set_highway(net: LstmNet, fit: LinearFit) -> None:
    """Set `net`'s highway to the ridge `fit`."""
    with torch.no_grad():
        net.highway.weight.copy_(torch.from_numpy(fit.weight))
        net.highway.bias.copy_(torch.from_numpy(fit.bias))


def refit_highways(net: LstmNet | PairedNet, windows: Callable[[np.ndarray], torch.Tensor],
                   train_ends: np.ndarray, train_targets: torch.Tensor,
                   validation_ends: np.ndarray, validation_targets: torch.Tensor) -> None:
    """Fit each LSTM's highway in `net` again, in closed form, to what its LSTM part leaves
    of the targets on these windows (fine-tuning on new recordings: the linear part of the
    parent moves to the new data at once, not by the few SGD steps it would take to undo
    a closed-form fit); the LSTM parts are kept."""
    chosen = np.linspace(0, len(train_ends) - 1, min(len(train_ends), RIDGE_SAMPLE)).astype(int)
    train_ends, train_targets = train_ends[chosen], train_targets[chosen]
    for lstm, reads in _lstms(net):
        def inputs(ends: np.ndarray, reads: Callable[[torch.Tensor], torch.Tensor] = reads
                   ) -> torch.Tensor:
            return reads(windows(ends))
        fit = fit_ridge(inputs, train_ends, train_targets - _nonlinear(lstm, inputs, train_ends),
                        validation_ends,
                        validation_targets - _nonlinear(lstm, inputs, validation_ends))
        if fit is not None:
            set_highway(lstm, fit)


def _lstms(net: LstmNet | PairedNet
           ) -> list[tuple[LstmNet, Callable[[torch.Tensor], torch.Tensor]]]:
    """Each LSTM network of `net` and how it reads `net`'s input."""
    if isinstance(net, PairedNet):
        return [(net.specialist, lambda x: x),
                (net.generalist, lambda x: x.index_select(2, net.machine_columns))]
    return [(net, lambda x: x)]


def _nonlinear(net: LstmNet, inputs: Callable[[np.ndarray], torch.Tensor],
               ends: np.ndarray) -> torch.Tensor:
    """The LSTM's part of `net`'s output (its head's): the output less the highway's."""
    parts = []
    with torch.no_grad():
        for start in range(0, len(ends), CHUNK):
            x = inputs(ends[start:start + CHUNK])
            parts.append(net(x) - net.highway(x.flatten(1)))
    return torch.cat(parts)


def _flat(windows: Callable[[np.ndarray], torch.Tensor], ends: np.ndarray) -> np.ndarray:
    return np.concatenate([windows(ends[start:start + CHUNK]).flatten(1).double().numpy()
                           for start in range(0, len(ends), CHUNK)])


def _moments(windows: Callable[[np.ndarray], torch.Tensor], ends: np.ndarray,
             targets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The inputs' and targets' means, the centred inputs' scatter matrix and their centred
    cross products with the targets, accumulated a chunk of windows at a time."""
    x_sum = scatter = cross = None
    for start in range(0, len(ends), CHUNK):
        x = windows(ends[start:start + CHUNK]).flatten(1).double().numpy()
        y = targets[start:start + CHUNK]
        if x_sum is None:
            x_sum, scatter, cross = x.sum(0), x.T @ x, x.T @ y
        else:
            x_sum, scatter, cross = x_sum + x.sum(0), scatter + x.T @ x, cross + x.T @ y
    assert x_sum is not None and scatter is not None and cross is not None
    count = len(ends)
    x_mean, y_mean = x_sum / count, targets.mean(0)
    return (x_mean, y_mean, scatter - count * np.outer(x_mean, x_mean),
            cross - count * np.outer(x_mean, y_mean))
