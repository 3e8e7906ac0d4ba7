# SPDX-License-Identifier: Apache-2.0
"""The machine map's least squares: its basis, the fit on the error's changes and on its
course, the misfit, and what a model file records of it (`MapFit`, mixed into
`machine_map.MachineMap`); the helpers that pair a recording's instants over the fit's lags.

Why apart from the map: the map is the module the node runs (`machine_map`, TorchScript);
the fit runs once in the trainer and the adaptation, on NumPy, and shares with the map only
its buffers. The reasons for the fit's form (on changes, over several lags, a second fit on
the error's course) are the map's, in its module docstring.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from lompr_predictor.data.features import TARGETS

#: Terms of the posture polynomial in the tool's x, y (per axis).
POSTURE_TERMS = ('1', 'x', 'y', 'x^2', 'x*y', 'y^2')
#: Relative Tikhonov penalty of the least squares (times the basis' mean square): keeps a
#: scale that the training motion never excites at zero instead of at a large value.
RIDGE = 1e-9


class MapFit:
    """The fitting half of `machine_map.MachineMap` (module docstring)."""

    if TYPE_CHECKING:  # the map's buffers and attributes this half reads and sets
        jacobian: torch.Tensor
        scales: torch.Tensor
        branch_coefficients: torch.Tensor
        posture_coefficients: torch.Tensor
        level_branch_coefficients: torch.Tensor
        level_posture_coefficients: torch.Tensor
        position_columns: torch.Tensor
        velocity_columns: torch.Tensor
        acceleration_columns: torch.Tensor
        fit_lags: tuple[int, ...]
        level_window: int
        fit_rms: float
        extrapolation: float

        def branch_motion(self, velocity: torch.Tensor,
                          acceleration: torch.Tensor) -> torch.Tensor: ...

    def basis(self, rows: np.ndarray) -> np.ndarray:
        """(N, 2, C) the map's basis at feature rows (N, F): g = basis @ coefficients."""
        table = torch.from_numpy(np.ascontiguousarray(rows, dtype=np.float64))
        with torch.no_grad():
            position = table.index_select(1, self.position_columns)
            motion = self.branch_motion(table.index_select(1, self.velocity_columns),
                                        table.index_select(1, self.acceleration_columns))
            # branch part: motion[n, p, i] * J[a, i]; posture part: term[n, m] * delta(a, a')
            branch = motion.unsqueeze(1) * self.jacobian.unsqueeze(-2)  # (N, 2, P, M)
            terms = posture_terms(position[:, 0], position[:, 1])  # (N, M)
            eye = torch.eye(len(TARGETS), dtype=torch.float64)
            posture = terms.unsqueeze(1).unsqueeze(-1) * eye.unsqueeze(1)  # (N, 2, M, 2)
        return torch.cat([branch.flatten(2), posture.flatten(2)], 2).numpy()

    def fit(self, rows: np.ndarray, error: np.ndarray, instants: np.ndarray) -> float:
        """Least squares of the coefficients on the plant error's changes, e(t+d) - e(t)
        against g(t+d) - g(t), over the lags d in `FIT_LAGS` horizons, of feature rows
        (N, F) and plant errors (N, 2) at `instants` (row indices; consecutive ones are
        consecutive samples of one gap-free run, as window ends are; pairs with a NaN left
        out); each lag's equations weighted by the inverse RMS of its error changes, so that
        each has the same say. Then the posture's constant, which no change sees, set to the
        mean of what the map leaves of the error at `instants`; and the residual map, the
        same least squares on the error's deviations from its mean over `level_window`
        samples (`local_deviations`). Returns `fit_rms`. The module docstring says why two
        fits, and why on changes."""
        basis = self.basis(rows)
        self.fit_lags, changes = usable_lags(
            self.fit_lags, lag_changes(basis, error, instants, self.fit_lags))
        weights = [1.0 / max(float(np.sqrt(np.mean(target ** 2))), 1e-15)
                   for _, target in changes]
        coefficients = least_squares(
            np.vstack([weight * lag_design.reshape(-1, lag_design.shape[2])
                       for weight, (lag_design, _) in zip(weights, changes, strict=True)]),
            np.concatenate([weight * lag_target.reshape(-1)
                            for weight, (_, lag_target) in zip(weights, changes, strict=True)]))
        self._set_coefficients(coefficients, basis, error, instants, levels=False)
        design, target = (local_deviations(values, instants, self.level_window)
                          for values in (basis, np.asarray(error, dtype=float)))
        usable = np.isfinite(design).all(axis=(1, 2)) & np.isfinite(target).all(axis=1)
        self._set_coefficients(least_squares(design[usable].reshape(-1, design.shape[2]),
                                              target[usable].reshape(-1)),
                               basis, error, instants, levels=True)
        horizon_design, horizon_target = changes[0]
        missed = horizon_target - horizon_design @ coefficients
        self.fit_rms = float(np.sqrt(np.mean(missed ** 2)))
        return self.fit_rms

    def _set_coefficients(self, coefficients: np.ndarray, basis: np.ndarray,
                          error: np.ndarray, instants: np.ndarray, levels: bool) -> None:
        """Take `coefficients` (the basis' order) as g's or with `levels` the residual
        map's, the posture's constant raised by the mean of what they leave of the error at
        `instants` (the fits do not see a constant)."""
        level = np.asarray(error, dtype=float)[instants] - basis[instants] @ coefficients
        branch, posture = ((self.level_branch_coefficients, self.level_posture_coefficients)
                           if levels else (self.branch_coefficients, self.posture_coefficients))
        constant = np.zeros(posture.shape)
        constant[POSTURE_TERMS.index('1')] = np.nanmean(level, axis=0)
        with torch.no_grad():
            branch.copy_(torch.from_numpy(coefficients[:branch.numel()].reshape(branch.shape)))
            posture.copy_(torch.from_numpy(
                coefficients[branch.numel():].reshape(posture.shape) + constant))

    def misfit(self, rows: np.ndarray, error: np.ndarray, instants: np.ndarray) -> float:
        """`fit`'s objective at `instants`: over the lags, the RMS of what g's change misses
        of the plant error's change as a share of that change's RMS (0: all explained, 1: no
        better than no map); inf without a usable pair."""
        coefficients = torch.cat([self.branch_coefficients.flatten(),
                                  self.posture_coefficients.flatten()]).numpy()
        shares = [np.mean((target - design @ coefficients) ** 2) / np.mean(target ** 2)
                  for design, target in lag_changes(self.basis(rows), error, instants,
                                                         self.fit_lags)
                  if len(target)]
        return float(np.sqrt(np.mean(shares))) if shares else float('inf')

    def metadata(self) -> dict[str, Any]:
        """The map's constants, for the model file's metadata (people and tools)."""
        return {'form': 'g = J (c_v v + c_a a + sum_k c_k tanh(v / s_k)) + P(x, y)',
                'jacobian': self.jacobian.tolist(),
                'friction_scales': self.scales.tolist(),
                'branch_coefficients': dict(zip(
                    ('velocity', 'acceleration',
                     *(f'tanh(v / {s:.3g})' for s in self.scales.tolist())),
                    self.branch_coefficients.tolist(), strict=True)),
                'posture_terms': list(POSTURE_TERMS),
                'posture_coefficients': self.posture_coefficients.tolist(),
                'extrapolation_seconds': self.extrapolation,
                'residual_map': {
                    'fitted_on': ("the error's deviations from its mean over "
                                  f'{self.level_window} samples'),
                    'branch_coefficients': self.level_branch_coefficients.tolist(),
                    'posture_coefficients': self.level_posture_coefficients.tolist()}}


def posture_terms(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(..., len(POSTURE_TERMS)) the posture polynomial's terms at x, y (...)."""
    return torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y], -1)


def lag_changes(basis: np.ndarray, error: np.ndarray, instants: np.ndarray,
                lags: Sequence[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per lag of `lags`, the changes (M, 2, C) of a map's basis (N, 2, C) and (M, 2) of
    the plant error (N, 2) between the instants t and t + lag of `instants` that lie in one
    run (`MachineMap.fit`), pairs with a NaN left out."""
    error = np.asarray(error, dtype=float)
    changes = []
    for lag in lags:
        first = consecutive_pairs(instants, lag)
        design, target = basis[first + lag] - basis[first], error[first + lag] - error[first]
        usable = np.isfinite(design).all(axis=(1, 2)) & np.isfinite(target).all(axis=1)
        changes.append((design[usable], target[usable]))
    return changes


def usable_lags(lags: tuple[int, ...], changes: list[tuple[np.ndarray, np.ndarray]]
                ) -> tuple[tuple[int, ...], list[tuple[np.ndarray, np.ndarray]]]:
    """The lags (and their `lag_changes`) with at least as many pairs as the map has
    coefficients: a lag longer than the recording's runs allow is left out (a high rate
    makes the longer lags many samples), the horizon's own never (`ValueError`)."""
    kept = [k for k, (design, _) in enumerate(changes) if len(design) >= design.shape[2]]
    if not kept or kept[0] != 0:
        design = changes[0][0]
        msg = (f'the machine map needs at least {design.shape[2]} instants with every '
               f'feature now and {lags[0]} samples later in the same run, got {len(design)}')
        raise ValueError(msg)
    return tuple(lags[k] for k in kept), [changes[k] for k in kept]


def local_deviations(values: np.ndarray, instants: np.ndarray, window: int) -> np.ndarray:
    """(M, ...) `values` (N, ...) at the sorted distinct `instants` (M row indices) minus
    their mean over the `window` instants centred on each in the same run (consecutive
    indices; shorter at a run's ends), NaN left out of the means."""
    instants = np.unique(np.asarray(instants, dtype=np.int64))
    picked = np.asarray(values, dtype=float)[instants]
    finite = np.isfinite(picked)
    sums = np.cumsum(np.concatenate([np.zeros_like(picked[:1]), np.where(finite, picked, 0.0)]),
                     axis=0)
    counts = np.cumsum(np.concatenate([np.zeros_like(picked[:1]), finite.astype(float)]), axis=0)
    runs = np.concatenate([[0], np.flatnonzero(np.diff(instants) != 1) + 1, [len(instants)]])
    start = np.repeat(runs[:-1], np.diff(runs))
    end = np.repeat(runs[1:], np.diff(runs))
    position = np.arange(len(instants))
    low = np.maximum(position - window // 2, start)
    high = np.minimum(position + window // 2 + 1, end)
    with np.errstate(invalid='ignore', divide='ignore'):
        return picked - (sums[high] - sums[low]) / (counts[high] - counts[low])


def least_squares(design: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The coefficients of design (M, C) @ c = target (M,), each column scaled to unit mean
    square and `RIDGE` added (a column that never varies stays at zero)."""
    scale = np.sqrt(np.mean(design ** 2, axis=0))
    scale[scale == 0] = 1.0
    scaled = design / scale
    gram = scaled.T @ scaled
    gram[np.diag_indices_from(gram)] += RIDGE * len(scaled)
    return np.linalg.solve(gram, scaled.T @ target) / scale


def consecutive_pairs(instants: np.ndarray, lag: int) -> np.ndarray:
    """The instants t of `instants` (row indices) whose rows t..t+lag are all in it: the
    first rows of the pairs `lag` samples apart within one run."""
    instants = np.unique(np.asarray(instants, dtype=np.int64))
    first = np.arange(max(len(instants) - lag, 0))
    return instants[first[instants[first + lag] - instants[first] == lag]]
