# SPDX-License-Identifier: Apache-2.0
"""What `lompr train` publishes: per axis, the tuned BO-LSTM or the ridge baseline, whichever
predicts that axis's validation part better, so that the model file is never knowingly worse
than a plain linear filter of the window.

Why. On recordings at a high rate a closed-form ridge over the window can beat the tuned
network (docs/lab/learner_real_data.md); a node that then ran the network would compensate
worse than a baseline the report names. The choice is made on the validation part, never
the test part (that stays the honest score of what was chosen):

- the ridge's validation RMSE is that of its fit on the training part at the penalty the
  validation part chose (`baselines.Ridge`), the network's that of the tuned network, which
  was trained on the training part with the validation part stopping it;
- an axis goes to the ridge only where its validation RMSE is strictly lower; the ridge
  then published is the baseline the report scores (refitted on train + validation).

`RidgeModule` is the ridge baseline as a raw-SI module of the model file's contract (float64
windows (B, window, features) -> (B, 2) error [m]); `PublishedModule` runs the network and the
ridge and answers each axis with the chosen one, keeping the network's `candidates` (its
generalist, the map prior) for the live guard. A model with a ridge axis is no BO-LSTM to
fine-tune (`model_type`): the node's adaptation says it cannot adapt it.
Boosted trees have no TorchScript form; where they lead, the report says so and by how much.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from lompr_predictor.data.features import TARGETS

#: The report's and the metadata's names of the two models an axis can publish.
NETWORK, RIDGE = 'bo_lstm', 'ridge'


class RidgeModule(nn.Module):
    """A linear map of the flattened window, as `baselines.Ridge` fits it: the window's rows
    with the error columns relative to its last row, then the last error, standardised by
    `centre` and `scale`, times `coefficients` (2, D) plus `intercept` (2,) is the change of
    the error over the horizon [um]; the prediction is the last error plus that change [m].
    Computed in the windows' dtype (float64 in the node)."""

    if TYPE_CHECKING:  # the buffers, for the type checker only (see `models.PredictorModule`)
        centre: torch.Tensor
        scale: torch.Tensor
        weights: torch.Tensor
        intercept: torch.Tensor
        error_columns: torch.Tensor
        error_mask: torch.Tensor

    def __init__(self, centre: np.ndarray, scale: np.ndarray, coefficients: np.ndarray,
                 intercept: np.ndarray, error_columns: Sequence[int], n_features: int) -> None:
        super().__init__()
        for name, value in (('centre', centre), ('scale', scale),
                            ('weights', np.asarray(coefficients).T), ('intercept', intercept)):
            self.register_buffer(name, torch.tensor(np.asarray(value), dtype=torch.float64))
        self.register_buffer('error_columns', torch.tensor(list(error_columns),
                                                           dtype=torch.long))
        mask = np.zeros(n_features)
        mask[list(error_columns)] = 1.0
        self.register_buffer('error_mask', torch.tensor(mask, dtype=torch.float64))

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        dtype = windows.dtype
        newest = windows.select(1, -1)
        last = newest.index_select(1, self.error_columns)
        relative = windows - (newest * self.error_mask.to(dtype)).unsqueeze(1)
        flat = torch.cat([relative.flatten(1), last], 1)
        standard = (flat - self.centre.to(dtype)) / self.scale.to(dtype)
        change = standard.matmul(self.weights.to(dtype)) + self.intercept.to(dtype)
        return last + change * 1e-6


class PublishedModule(nn.Module):
    """The network's module with the axes in `ridge_axes` answered by `ridge` (module
    docstring): the same contract (`forward`), the same `candidates` after the first two
    columns, so the node, its live guard and `lompr evaluate` run it as they run the
    network."""

    if TYPE_CHECKING:  # for the type checker only (see `models.PredictorModule`)
        ridge_axes: torch.Tensor

    def __init__(self, network: Any, ridge: RidgeModule, ridge_axes: Sequence[bool]) -> None:
        """`network`: a `models.PredictorModule` or its scripted form."""
        super().__init__()
        self.network = network
        self.ridge = ridge
        self.register_buffer('ridge_axes', torch.tensor(list(ridge_axes), dtype=torch.bool))
        self.use_map = bool(network.use_map)
        #: a paired network's candidates carry its generalist (`map_prior.is_paired`)
        self.paired = hasattr(getattr(network, 'net', None), 'generalist')

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        return self.candidates(windows)[:, :2]

    def candidates(self, windows: torch.Tensor) -> torch.Tensor:
        """The network's `candidates` with its prediction replaced by the ridge's on the
        ridge's axes."""
        network = self.network.candidates(windows)
        own = torch.where(self.ridge_axes, self.ridge(windows), network[:, :2])
        return torch.cat([own, network[:, 2:]], 1)


@dataclass(frozen=True)
class Publication:
    """Which model each axis publishes and why: the validation RMSE [um] of each
    candidate per axis."""

    choice: Mapping[str, str]  # axis -> NETWORK or RIDGE
    validation_rmse_um: Mapping[str, Mapping[str, float]]  # model -> axis -> RMSE

    @property
    def ridge_axes(self) -> list[bool]:
        return [self.choice[axis] == RIDGE for axis in TARGETS]

    @property
    def model_type(self) -> str:
        """The model file's `model_type`: 'lstm' (fine-tunable) only if no axis is the
        ridge's."""
        kinds = {self.choice[axis] for axis in TARGETS}
        return 'lstm' if kinds == {NETWORK} else 'ridge' if kinds == {RIDGE} else 'lstm+ridge'

    def why(self, axis: str) -> str:
        """One line on the choice of `axis`."""
        rmse = self.validation_rmse_um
        return (f'validation RMSE BO-LSTM {rmse[NETWORK][axis]:.4g} um, ridge '
                f'{rmse[RIDGE][axis]:.4g} um')

    def report(self) -> dict[str, dict[str, Any]]:
        """Per axis: the model published, the validation RMSE of both, why."""
        return {axis: {'model': self.choice[axis], 'why': self.why(axis),
                       'validation_rmse_um': {name: values[axis] for name, values
                                              in self.validation_rmse_um.items()}}
                for axis in TARGETS}


def choose(validation_rmse_um: Mapping[str, Mapping[str, float]],
           network_only: bool = False) -> Publication:
    """Per axis the ridge where its validation RMSE is strictly below the network's, else
    the network (module docstring); the network on every axis if `network_only` (a model
    to fine-tune)."""
    network, ridge = validation_rmse_um[NETWORK], validation_rmse_um[RIDGE]
    choice = {axis: RIDGE if ridge[axis] < network[axis] and not network_only else NETWORK
              for axis in TARGETS}
    return Publication(choice=choice, validation_rmse_um={
        name: {axis: float(values[axis]) for axis in TARGETS}
        for name, values in validation_rmse_um.items()})


def rmse_um(predicted: np.ndarray, actual: np.ndarray) -> dict[str, float]:
    """Per axis RMSE [um] of (B, 2) predictions [m]."""
    error = (np.asarray(predicted) - np.asarray(actual)) * 1e6
    return {axis: float(np.sqrt(np.mean(error[:, i] ** 2))) for i, axis in enumerate(TARGETS)}


def published_module(network: Any, ridge: RidgeModule | None,
                     publication: Publication) -> Any:
    """The module to write: the network itself where every axis is the network's, else a
    `PublishedModule`."""
    if ridge is None or not any(publication.ridge_axes):
        return network
    return PublishedModule(network, ridge, publication.ridge_axes)
