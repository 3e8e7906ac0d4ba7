# SPDX-License-Identifier: Apache-2.0
"""The live guard driven on a stream of hand-made truths and predictions: shared by the
guard's tests, its status's and the offline replay's."""

from __future__ import annotations

import numpy as np

from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.guard import GuardSettings, LiveGuard

PERIOD = 40_000_000
HORIZON = 2
LEAD = HORIZON * PERIOD
PERIOD_S = PERIOD * 1e-9


def guard_rules(window_instants: float = 250, dwell_instants: float = 50,
              **changes: object) -> GuardSettings:
    """Rules of the guard with `changes`, its window and dwell given in instants of the
    tests' stream (`PERIOD`)."""
    rules: dict[str, object] = {'enabled': True, 'window': window_instants * PERIOD_S,
                                'margin': 0.05, 'min_dwell': dwell_instants * PERIOD_S,
                                'min_scored': 50, 'envelope_fraction': 0.2}
    return GuardSettings(**{**rules, **changes})  # type: ignore[arg-type]


def run_guard(guard: LiveGuard, truth: np.ndarray, model_error: np.ndarray,
         inside: np.ndarray | None = None, prior_error: np.ndarray | None = None,
         map_error: np.ndarray | None = None) -> np.ndarray:
    """Feed a plant error series `truth` (N, 2); the model predicts each instant's truth plus
    `model_error` (N, 2), its prior the truth plus `prior_error` (None: the model has
    no prior), a paired model's map prior the truth plus `map_error` (None: none),
    persistence the truth HORIZON samples before. Returns the published predictions (N,
    2), NaN until the first."""
    published = np.full_like(truth, np.nan)
    for k in range(len(truth)):
        stamp = k * PERIOD
        error = (float(truth[k, 0]), float(truth[k, 1]))
        guard.observe(AlignedSample(stamp, *error, 0.0, 0.0, 1.1), error, None)
        if k + HORIZON < len(truth):
            target = truth[k + HORIZON] + model_error[k + HORIZON]
            prior, map_prior = (None if errors is None else
                                tuple(map(float, truth[k + HORIZON] + errors[k + HORIZON]))
                                for errors in (prior_error, map_error))
            published[k] = guard.choose(stamp + LEAD, (float(target[0]), float(target[1])),
                                        (float(truth[k, 0]), float(truth[k, 1])),
                                        True if inside is None else bool(inside[k]),
                                        prior, map_prior)  # type: ignore[arg-type]
    return published


def random_walk(count: int, seed: int = 0) -> np.ndarray:
    """A plant error that changes by 1 um per sample on average: persistence misses by
    about sqrt(HORIZON) um."""
    return np.cumsum(np.random.default_rng(seed).normal(0.0, 1e-6, (count, 2)), axis=0)
