# SPDX-License-Identifier: Apache-2.0
"""learning.map_prior: the prior a model serves beside its prediction, from its candidates
or, for a model file written before them, from its map's own methods."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from test_machine_map import _known_map, _no_change_module, _rows_with_errors

from lompr_predictor.data.features import FEATURES
from lompr_predictor.learning.map_prior import PredictionWithPrior, prediction_with_prior
from lompr_predictor.learning.model_file import script_module
from lompr_predictor.learning.models import predict_rows

if TYPE_CHECKING:
    from lompr_predictor.learning.machine_map import MachineMap


class _MapModelOfBefore(torch.nn.Module):
    """A map model as model files written before `candidates` have it: its forward reads
    the map's rows and predicted instant itself (here it predicts the map prior)."""

    if TYPE_CHECKING:  # TorchScript cannot read class annotations under the future import
        error_columns: torch.Tensor

    def __init__(self, machine_map: MachineMap) -> None:
        super().__init__()
        self.use_map = True
        self.machine_map = machine_map
        self.register_buffer('error_columns', torch.tensor([0, 1]))

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        newest = windows[:, -1]
        return (newest.index_select(1, self.error_columns) + self.machine_map.ahead(newest)
                - self.machine_map.rows(windows)[:, -1])


def test_a_model_file_of_before_candidates_is_served_its_prior_by_the_maps_methods() -> None:
    """A scripted model without `candidates` gets its prior from its map's `rows` and
    `ahead`; a model of today from its `candidates`: the same prior either way."""
    machine_map = _known_map(FEATURES, horizon=3)
    before = prediction_with_prior(script_module(_MapModelOfBefore(machine_map)))
    assert isinstance(before, PredictionWithPrior)
    rows, ends = _rows_with_errors(seed=6), np.arange(9, 40)
    served = predict_rows(script_module(before), rows, ends, 10, width=4)
    candidates = prediction_with_prior(script_module(_no_change_module(machine_map)))
    assert candidates is not None and not isinstance(candidates, PredictionWithPrior)
    expected = predict_rows(script_module(candidates), rows, ends, 10, width=4)
    np.testing.assert_allclose(served, expected, rtol=1e-12, atol=1e-18)
    change = served[:, 2:] - rows[ends, :2]  # the map's change over the horizon
    assert np.abs(change).max() > 1e-5
