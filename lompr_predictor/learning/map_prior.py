# SPDX-License-Identifier: Apache-2.0
"""The model's prior beside its prediction: what a model predicts from the machine alone,
which the live guard scores as the third candidate beside the model and persistence.

Why. A model with a machine map (`machine_map.py`) predicts e(t) + g(t+h) - g(t) + n, the
map prior plus its network's correction n. The map has a few dozen coefficients with the
machine's structure and transfers between programs; a network that reads the path learns
the programs it was trained on, and on another program its correction can make the
prediction worse than what the machine alone predicts (and than persistence). The live
guard (`online.guard`) therefore scores the prior as a third candidate beside the model and
persistence, and hands an axis to whichever of the two fallbacks does better. The prior is

- for a paired model (`models.PairedNet`, `lompr train`'s default), its generalist's
  prediction: the map prior plus a network that reads the map's residuals alone; the map
  prior itself comes beside it as a second fallback (a generalist trained on one program, or
  on a machine whose physics differ, can do worse than the map alone, which has only the
  machine's structure to get wrong);
- for a model with a map and one network, the map prior itself.

`prediction_with_prior(module)` wraps a model (a loaded TorchScript module or the trainer's
`models.PredictorModule`) into a module that returns (B, 4): its prediction (X, Y) then its
prior (X, Y), [m], or for a paired model (B, 6), the map prior (X, Y) last, in one call.
It is built around the verified module at load time, so model files written before it
existed serve it too; a model without a map has no prior (None).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from lompr_predictor.learning.model_file import ExportedModule, LoadedModel, script_module

if TYPE_CHECKING:
    from lompr_predictor.learning.machine_map import MachineMap


class PredictionWithPrior(nn.Module):
    """A map model's prediction and its map prior side by side (module docstring), from
    its map's `rows` and `ahead`: for model files written before models had `candidates`."""

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


class PredictionWithCandidates(nn.Module):
    """A map model's prediction and its priors side by side (module docstring) as the model
    gives them, its `candidates`: the map evaluated once, for a paired model both networks
    in the same call."""

    def __init__(self, module: Any) -> None:
        """`module`: a `models.PredictorModule` with a map, or its scripted form."""
        super().__init__()
        self.model = module

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        return self.model.candidates(windows)


def is_paired(module: Any) -> bool:
    """Whether a model's module (scripted or not) runs a `models.PairedNet`, itself or as
    the network of a `publishing.PublishedModule` (which says so in `paired`)."""
    return bool(getattr(module, 'paired', False)) or hasattr(getattr(module, 'net', None),
                                                              'generalist')


def prediction_with_prior(module: Any) -> nn.Module | None:
    """The module (B, window, F) -> (B, 4) of a model's prediction and its prior, (B, 6)
    with a paired model's map prior (module docstring); None for a model without a map."""
    if not getattr(module, 'use_map', False):
        return None
    # model files written before `candidates` existed (one network) have the map's own
    # methods instead, which a model of today compiles only through `candidates`
    return (PredictionWithCandidates(module) if hasattr(module, 'candidates')
            else PredictionWithPrior(module))


def with_prior(model: LoadedModel) -> ExportedModule | None:
    """The scripted `prediction_with_prior` of a loaded model (None without a map)."""
    wrapper = prediction_with_prior(model.module)
    return None if wrapper is None else script_module(wrapper)
