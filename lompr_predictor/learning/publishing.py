# SPDX-License-Identifier: Apache-2.0
"""What `lompr train` publishes: per axis, the equal-weight mean of the candidates (the tuned
BO-LSTM, its generalist, the ridge baseline) that the validation part cannot tell from the best
of them, so that the model file does not bet on a margin the data cannot show; in such a mean
the BO-LSTM's place goes to its committee (the mean of the study's best networks).

Why (docs/training.md, docs/lab/learner_real_data.md): at high rates a closed-form ridge over
the window predicts about as well as the network, and which leads changes along a recording;
the network's validation RMSE is optimistic (its tuning and early stopping chose it there).
The mean of predictors alike in size but not in their errors beats each; one clearly worse
is left out (on the LOMPR twin the network alone is published). So among the tuned networks:
the point a study ends on turns on a few trials, and on real recordings the mean of its best
few networks predicts better than its best alone. Per axis (`choose`): each candidate's
squared error on the validation part (the ridge as fitted on the training part,
`baselines.Ridge`); the best by mean; every other kept unless its loss difference to the best
is positive at the one-sided 5 % level (`CRITICAL_T`; a Diebold-Mariano t whose standard
error comes from block means, `loss_difference_t`, since neighbouring errors are correlated);
equal weights (weights fitted on that part would inherit its optimism); in a mean that keeps
the network, the committee stands in for it. Where every axis publishes the network alone,
it stays alone (one network to run, a file that can be fine-tuned). The test part stays the
honest score of what was chosen.

`RidgeModule` is the ridge as a raw-SI module of the model file's contract; `PublishedModule`
answers each axis with its weights over the network, its generalist, the ridge and the
committee (the network and the other members, `MemberSum`, or `SharedMapMembers` where they
read one machine map), keeping the network's `candidates` for the live guard. A file that is
not the network alone is not fine-tuned (`model_type`; the node's adaptation says it cannot
adapt it). Boosted trees have no TorchScript form: where they lead, the report says so.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from lompr_predictor.data.features import TARGETS
from lompr_predictor.learning.metrics import COMMITTEE, CRITICAL_T, loss_difference_t

if TYPE_CHECKING:
    from lompr_predictor.learning.models import PredictorModule

#: The report's and the metadata's names of the candidates an axis can publish (the
#: generalist: a paired BO-LSTM's second network, `models.PairedNet`; `COMMITTEE`: the mean
#: of the network and the study's next best networks).
NETWORK, GENERALIST, RIDGE = 'bo_lstm', 'bo_lstm_generalist', 'ridge'


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
    """The network's module with each axis answered by `weights` (2, 4) over the network's
    prediction, its generalist's, `ridge`'s and the committee's (module docstring): the same
    contract (`forward`), the same `candidates` after the first two columns, so the node, its
    live guard and `lompr evaluate` run it as they run the network."""

    if TYPE_CHECKING:  # for the type checker only (see `models.PredictorModule`)
        weights: torch.Tensor

    def __init__(self, network: Any, ridge: RidgeModule, weights: np.ndarray,
                 members: Sequence[Any] = ()) -> None:
        """`network`: a `models.PredictorModule` or its scripted form; `weights` (2, 4) in
        the order of `MEMBERS`, zero on the generalist's column for an unpaired network and
        on the committee's without `members` (the committee's other networks, raw-SI modules
        of the same windows)."""
        super().__init__()
        self.network = network
        self.ridge = ridge
        self.members = (SharedMapMembers(members) if shares_one_map(members)
                        else MemberSum(members))
        self.committee_size = 1 + len(members)
        self.register_buffer('weights', torch.tensor(np.asarray(weights), dtype=torch.float64))
        self.use_map = bool(network.use_map)
        #: a paired network's candidates carry its generalist (`map_prior.is_paired`)
        self.paired = hasattr(getattr(network, 'net', None), 'generalist')

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        return self.candidates(windows)[:, :2]

    def candidates(self, windows: torch.Tensor) -> torch.Tensor:
        """The network's `candidates` with its prediction replaced by the weighted mean."""
        network = self.network.candidates(windows)
        weights = self.weights.to(windows.dtype)
        own = weights[:, 0] * network[:, :2] + weights[:, 2] * self.ridge(windows)
        if self.paired:
            own = own + weights[:, 1] * network[:, 2:4]
        committee = (network[:, :2] + self.members(windows)) / self.committee_size
        own = own + weights[:, 3] * committee
        return torch.cat([own, network[:, 2:]], 1)


class MemberSum(nn.Module):
    """The sum of the committee's other networks' predictions (B, 2) [m] (zero without
    any): each its own module on the raw windows."""

    def __init__(self, members: Sequence[Any]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)
        self.n_outputs = len(TARGETS)

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        total = torch.zeros((windows.shape[0], self.n_outputs), dtype=windows.dtype)
        for member in self.members:
            total = total + member(windows)
        return total


class SharedMapMembers(nn.Module):
    """`MemberSum` of networks that read one machine map (`shares_one_map`): the map's
    residual rows and prior computed once for all, each network then on those rows, as its
    own `candidates` would (the same numbers; the map is a third of a member's time)."""

    if TYPE_CHECKING:  # for the type checker only: what the module list holds
        members: list[PredictorModule]

    def __init__(self, members: Sequence[Any]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)  # type: ignore[assignment]
        self.n_outputs = len(TARGETS)

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        first = self.members[0]
        levels, change = first.machine_map.levels_and_change(windows)
        errors = windows.index_select(2, first.error_columns)
        inputs = torch.cat([windows, errors - levels], 2)
        prior = errors.select(1, -1) + change
        total = torch.zeros_like(prior)
        for member in self.members:
            total = total + member._predict(inputs, prior)[:, :self.n_outputs]
        return total


def shares_one_map(members: Sequence[Any]) -> bool:
    """Whether the `members` (raw-SI modules) are `models.PredictorModule`s (or their
    scripted form) that predict a change from one machine map's prior: every one on a map
    with the same coefficients and error columns, residual."""
    if not members or not all(bool(getattr(member, 'use_map', False))
                              and bool(getattr(member, 'residual', False))
                              for member in members):
        return False
    first = members[0].state_dict()
    names = [name for name in first if name.startswith('machine_map.')] + ['error_columns']
    return all(set(member.state_dict()) >= set(names)
               and all(torch.equal(member.state_dict()[name], first[name]) for name in names)
               for member in members[1:])


#: The report's names of the candidates an axis can publish, in `PublishedModule`'s order.
MEMBERS = (NETWORK, GENERALIST, RIDGE, COMMITTEE)
#: The key under which the report scores a published mean (`Publication.published_key`).
PUBLISHED = 'published'


@dataclass(frozen=True)
class Publication:
    """What each axis publishes and why: the candidates averaged per axis, each candidate's
    validation RMSE [um] and t statistic against the axis's best (`loss_difference_t`)."""

    members: Mapping[str, tuple[str, ...]]  # axis -> the candidates averaged
    validation_rmse_um: Mapping[str, Mapping[str, float]]  # model -> axis -> RMSE
    t_statistic: Mapping[str, Mapping[str, float]]  # model -> axis -> t against the best

    @property
    def weights(self) -> np.ndarray:
        """(2, 4) equal weights of each axis's members, in `MEMBERS`' order."""
        return np.array([[1.0 / len(self.members[axis]) if name in self.members[axis] else 0.0
                          for name in MEMBERS] for axis in TARGETS])

    @property
    def model_type(self) -> str:
        """The model file's `model_type`: 'lstm' (fine-tunable) only if every axis is the
        network alone, 'ridge' if every axis is the ridge alone, else 'ensemble' (a mean,
        or the committee)."""
        kinds = {self.members[axis] for axis in TARGETS}
        return ('lstm' if kinds == {(NETWORK,)} else 'ridge' if kinds == {(RIDGE,)}
                else 'ensemble')

    def published_key(self, axis: str) -> str:
        """The report's model key of what `axis` publishes: a single candidate's own, or
        `PUBLISHED` for a mean."""
        members = self.members[axis]
        return members[0] if len(members) == 1 else PUBLISHED

    @property
    def published_keys(self) -> dict[str, str]:
        """Per axis `published_key`."""
        return {axis: self.published_key(axis) for axis in TARGETS}

    @property
    def report_keys(self) -> set[str]:
        """The report's model keys of what the axes publish."""
        return set(self.published_keys.values())

    def why(self, axis: str) -> str:
        """One line on the choice of `axis`."""
        return 'validation RMSE ' + ', '.join(
            f'{LABELS[name]} {rmse[axis]:.4g} um (t {self.t_statistic[name][axis]:.2f})'
            for name, rmse in self.validation_rmse_um.items())

    def report(self) -> dict[str, dict[str, Any]]:
        """Per axis: the candidates averaged, the key the report scores them under, the
        validation RMSE and t statistic of each, why."""
        return {axis: {'members': list(self.members[axis]),
                       'model': self.published_key(axis), 'why': self.why(axis),
                       'validation_rmse_um': {name: values[axis] for name, values
                                              in self.validation_rmse_um.items()},
                       't_statistic': {name: values[axis] for name, values
                                       in self.t_statistic.items()}}
                for axis in TARGETS}


#: The candidates' names in the report's lines.
LABELS = {NETWORK: 'BO-LSTM', GENERALIST: 'its generalist', RIDGE: 'ridge',
          COMMITTEE: 'its committee'}


def choose(validation_errors: Mapping[str, np.ndarray],
           network_only: bool = False) -> Publication:
    """Per axis the candidates not worse than the best at `CRITICAL_T` (module docstring),
    from each candidate's (B, 2) signed errors on the validation part [m]; the network on
    every axis if `network_only` (a model to fine-tune). A `COMMITTEE` among them is no
    candidate of its own: it takes the network's place in a mean (its t is against the
    axis's best all the same)."""
    squared = {name: (np.asarray(errors, dtype=np.float64) * 1e6) ** 2
               for name, errors in validation_errors.items()}
    members: dict[str, tuple[str, ...]] = {}
    t_statistic: dict[str, dict[str, float]] = {name: {} for name in squared}
    for i, axis in enumerate(TARGETS):
        best = min((name for name in squared if name != COMMITTEE),
                   key=lambda name: float(squared[name][:, i].mean()))
        for name, values in squared.items():
            t_statistic[name][axis] = (0.0 if name == best else
                                       loss_difference_t(values[:, i] - squared[best][:, i]))
        kept = tuple(name for name in MEMBERS if name in squared and name != COMMITTEE
                     and t_statistic[name][axis] < CRITICAL_T)
        members[axis] = (NETWORK,) if network_only else kept
    if COMMITTEE in squared and {members[axis] for axis in TARGETS} != {(NETWORK,)}:
        members = {axis: tuple(COMMITTEE if name == NETWORK else name for name in kept)
                   for axis, kept in members.items()}
    return Publication(members=members, t_statistic=t_statistic, validation_rmse_um={
        name: {axis: float(np.sqrt(values[:, i].mean())) for i, axis in enumerate(TARGETS)}
        for name, values in squared.items()})


def published_predictions(publication: Publication,
                          predictions: Mapping[str, np.ndarray]) -> np.ndarray:
    """(B, 2) the published model's predictions from its candidates' (`MEMBERS` keys)."""
    weights = publication.weights
    return sum((weights[:, j] * predictions[name] for j, name in enumerate(MEMBERS)
                if weights[:, j].any()), start=np.zeros((1, len(TARGETS))))


def rmse_um(predicted: np.ndarray, actual: np.ndarray) -> dict[str, float]:
    """Per axis RMSE [um] of (B, 2) predictions [m]."""
    error = (np.asarray(predicted) - np.asarray(actual)) * 1e6
    return {axis: float(np.sqrt(np.mean(error[:, i] ** 2))) for i, axis in enumerate(TARGETS)}


def published_module(network: Any, ridge: RidgeModule | None, publication: Publication,
                     members: Sequence[Any] = ()) -> Any:
    """The module to write: the network itself where every axis is the network's alone,
    else a `PublishedModule` (with the committee's other networks, `members`, where an axis
    publishes the committee)."""
    if ridge is None or publication.model_type == 'lstm':
        return network
    committee = any(COMMITTEE in kept for kept in publication.members.values())
    return PublishedModule(network, ridge, publication.weights,
                           members if committee else ())
