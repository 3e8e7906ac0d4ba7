# SPDX-License-Identifier: Apache-2.0
"""learning.map_fit, how the machine map is fitted: pairs of instants within a run, the
deviations from a local mean, the changes per lag and the lags the runs allow, and the
ridge-regularised least squares, by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lompr_predictor.learning.map_fit import (
    POSTURE_TERMS,
    consecutive_pairs,
    lag_changes,
    least_squares,
    local_deviations,
    posture_terms,
    usable_lags,
)


def test_the_fit_pairs_instants_only_within_a_run() -> None:
    """Pairs `lag` apart are taken where every instant between is listed: not across the
    gap between two runs' window ends."""
    instants = np.r_[np.arange(10, 20), np.arange(40, 45)]
    np.testing.assert_array_equal(consecutive_pairs(instants, 3),
                                  np.r_[np.arange(10, 17), np.arange(40, 42)])
    assert len(consecutive_pairs(instants, 10)) == 0


def test_local_deviations_by_hand() -> None:
    """Values minus their mean over a centred window of 3 within each run of consecutive
    instants (two samples at a run's end), a NaN left out of the mean (the last: 50 alone)."""
    values = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 10.0, 20.0, np.nan, 50.0])
    got = local_deviations(values, np.array([0, 1, 2, 5, 6, 7, 8]), 3)
    np.testing.assert_allclose(got, [-0.5, 0.0, 0.5, -5.0, 5.0, np.nan, 0.0])


def test_changes_per_lag_leave_nans_out_and_lags_beyond_the_runs_are_dropped() -> None:
    basis = np.arange(10 * 2 * 1, dtype=float).reshape(10, 2, 1) ** 2
    error = np.column_stack([np.arange(10.0), -np.arange(10.0)])
    error[4, 0] = np.nan
    changes = lag_changes(basis, error, np.arange(10), (1, 8))
    design, target = changes[0]
    # instants 0..8 pair with the next; the two pairs touching row 4 have a NaN change
    assert len(design) == 9 - 2 and len(changes[1][0]) == 2
    np.testing.assert_array_equal(target[0], [1.0, -1.0])
    np.testing.assert_array_equal(design[0], basis[1] - basis[0])
    lags, kept = usable_lags((1, 8, 20), lag_changes(basis, error, np.arange(10), (1, 8, 20)))
    assert lags == (1, 8) and len(kept) == 2
    with pytest.raises(ValueError, match='needs at least 1 instants with every feature now '
                                         'and 20 samples later'):
        usable_lags((20,), lag_changes(basis, error, np.arange(10), (20,)))


def test_least_squares_solves_a_known_system_and_keeps_a_silent_column_at_zero() -> None:
    rng = np.random.default_rng(0)
    design = np.column_stack([rng.normal(size=500), 1e-6 * rng.normal(size=500),
                              np.zeros(500)])
    coefficients = least_squares(design, design @ np.array([2.0, -3e5, 0.0]))
    np.testing.assert_allclose(coefficients[:2], [2.0, -3e5], rtol=1e-6)
    assert coefficients[2] == 0.0
    terms = posture_terms(torch.tensor([2.0]), torch.tensor([3.0]))
    assert terms.tolist() == [[1.0, 2.0, 3.0, 4.0, 6.0, 9.0]] and len(POSTURE_TERMS) == 6
