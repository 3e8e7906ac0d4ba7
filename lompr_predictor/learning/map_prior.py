"""The map prior beside the prediction: what a model with a machine map predicts before its
network adds anything.

Why. A model with a machine map (`machine_map.py`) predicts e(t) + g(t+h) - g(t) + n, the
prior plus its network's correction n. The map has a few dozen coefficients with the
machine's structure and transfers between programs; the network learns more and can learn
the path: on a program it was not trained on, the network's correction can make the
prediction worse than the prior alone (and than persistence) while the prior still does
better than persistence. The live guard (`online.guard`) therefore scores the prior as a
third candidate beside the model and persistence, and hands an axis to whichever of the two
fallbacks does better.

`PredictionWithPrior` runs a model (a loaded TorchScript module or the trainer's
`models.PredictorModule`) and returns (B, 4): its prediction (X, Y) then its prior (X, Y),
[m]. It is built around the verified module at load time, so model files written before it
existed serve it too; a model without a map has no prior (`with_prior` gives None).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from lompr_predictor.learning.model_file import ExportedModule, LoadedModel, script_module

if TYPE_CHECKING:
    from lompr_predictor.learning.machine_map import MachineMap

#: Rows per batch when the prior of many windows is computed offline.
OFFLINE_BATCH = 4096


class PredictionWithPrior(nn.Module):
    """A map model's prediction and its map prior side by side (module docstring)."""

    if TYPE_CHECKING:  # for the type checker only (see `models.PredictorModule`)
        error_columns: torch.Tensor
        machine_map: MachineMap

    def __init__(self, module: Any) -> None:
        """`module`: a `models.PredictorModule` with a map, or its scripted form."""
        super().__init__()
        self.model = module
        # the map as a submodule of its own: TorchScript calls its methods from here
        self.machine_map = module.machine_map
        self.register_buffer('error_columns', module.error_columns.clone())

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.model(windows), self.prior(windows[:, -1])], 1)

    def prior(self, newest: torch.Tensor) -> torch.Tensor:
        """(B, 2) the prior e(t) + g(t+h) - g(t) [m] from windows' newest rows (B, F)."""
        now = self.machine_map.rows(newest.unsqueeze(1))[:, 0]
        return (newest.index_select(1, self.error_columns) + self.machine_map.ahead(newest)
                - now)


def has_prior(model: LoadedModel) -> bool:
    """Whether the model builds on a machine map (its metadata says so), hence has a prior."""
    return bool(model.metadata.machine_map)


def with_prior(model: LoadedModel) -> ExportedModule | None:
    """The scripted `PredictionWithPrior` of a loaded model (None without a map)."""
    if not has_prior(model):
        return None
    return script_module(PredictionWithPrior(model.module))


def offline_prior(module: Any, newest_rows: np.ndarray) -> np.ndarray:
    """(B, 2) the map prior [m] for windows whose newest feature rows are `newest_rows`
    (B, F), for a module with a map: what the node's guard scores beside the model."""
    prior = PredictionWithPrior(module)
    table = torch.from_numpy(np.ascontiguousarray(newest_rows, dtype=np.float64))
    with torch.inference_mode():
        parts = [prior.prior(table[start:start + OFFLINE_BATCH])
                 for start in range(0, len(table), OFFLINE_BATCH)]
    return torch.cat(parts).numpy() if parts else np.zeros((0, 2))
