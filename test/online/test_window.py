# SPDX-License-Identifier: Apache-2.0
"""online.window alone: the rolling feature rows equal the offline ones."""

from __future__ import annotations

import numpy as np
import pytest

from lompr_predictor.data.features import (
    FEATURES,
    HISTORY,
    feature_names,
    feature_rows,
    with_preview,
)
from lompr_predictor.online.window import FeatureWindow
from lompr_predictor.robot.chain import load_chain
from lompr_predictor.stamps import seconds_since

T0 = 1_700_000_000_000_000_000
PERIOD_NS = 40_000_000
CHAIN = load_chain()
BRANCHES = CHAIN.actuator_coordinates()


def samples(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps [ns] (with jitter), plant error (n, 2) and reference tool tip (n, 3) [m]."""
    k = np.arange(n)
    stamps = T0 + k * PERIOD_NS + (k % 3) * 1_000_123
    error = np.stack([10e-6 * np.sin(0.4 * k), -5e-6 * np.cos(0.3 * k)], -1)
    reference = np.stack([0.01 * k ** 1.5 * 1e-1, 0.02 - 1e-3 * k ** 2,
                          1.097 + 1e-4 * np.sin(0.2 * k)], -1)
    return stamps, error, reference


def push_all(window: FeatureWindow, stamps: np.ndarray, error: np.ndarray,
             reference: np.ndarray) -> list[bool]:
    return [window.push(int(s), *e, *r) for s, e, r in zip(stamps, error, reference,
                                                           strict=True)]


def test_rows_equal_feature_rows_of_the_same_samples() -> None:
    stamps, error, reference = samples(9)
    window = FeatureWindow(3, CHAIN)
    assert window.needed == 3 + HISTORY
    full = push_all(window, stamps, error, reference)
    assert full == [False] * 4 + [True] * 5
    offline = feature_rows((stamps - stamps[0]) * 1e-9, error, reference, BRANCHES)
    np.testing.assert_allclose(window.rows(), offline[-3:], rtol=1e-12, atol=0)
    # second difference of the reference x: 0.01 * 0.1 * k^1.5 over the last three stamps
    dt = np.diff(stamps[-3:]) * 1e-9
    velocity = np.diff(reference[-3:, 0]) / dt
    assert window.rows()[-1, 6] == pytest.approx((velocity[1] - velocity[0]) / dt[1], rel=1e-9)


def test_fill_and_a_window_that_is_not_full() -> None:
    stamps, error, reference = samples(4)
    window = FeatureWindow(3, CHAIN)
    assert window.empty
    assert window.last_stamp_ns is None
    push_all(window, stamps, error, reference)
    assert (window.fill, window.full) == (4, False)
    assert window.last_stamp_ns == int(stamps[-1])
    with pytest.raises(ValueError, match='holds 4 of 5 samples'):
        window.rows()


def test_a_cleared_window_refills_from_new_samples_only() -> None:
    stamps, error, reference = samples(12)
    window = FeatureWindow(2, CHAIN)
    push_all(window, stamps[:6], error[:6], reference[:6])
    window.clear()
    assert window.empty and window.fill == 0
    assert push_all(window, stamps[6:10], error[6:10], reference[6:10]) == [False] * 3 + [True]
    offline = feature_rows((stamps[6:10] - stamps[6]) * 1e-9, error[6:10], reference[6:10],
                           BRANCHES)
    np.testing.assert_allclose(window.rows(), offline[-2:], rtol=1e-12, atol=0)


def test_a_window_needs_a_row() -> None:
    with pytest.raises(ValueError, match='at least one row'):
        FeatureWindow(0, CHAIN)


def test_each_row_is_feature_rows_of_its_last_samples_bit_for_bit() -> None:
    # the incremental row is feature_rows on the last HISTORY + 1 samples (stamps as seconds
    # since the first of them), the same operations: equal to the last bit, across the
    # buffer's wrap-around and a clear, in every column (the branch velocities and
    # accelerations from the inverse kinematics of the newest tip included)
    rng = np.random.default_rng(3)
    n = 60
    stamps = T0 + np.cumsum(rng.integers(900_000, 1_100_000, n))
    error = rng.normal(scale=1e-5, size=(n, 2))
    reference = np.cumsum(rng.normal(scale=1e-4, size=(n, 3)), axis=0)
    reference += (0.05, -0.1, 1.097)
    window = FeatureWindow(5, CHAIN)
    start = 0
    for k in range(n):
        if k == 31:
            window.clear()
            start = k
        window.push(int(stamps[k]), *error[k], *reference[k])
        if k - start < window.needed - 1:
            continue
        expected = np.stack([
            feature_rows(seconds_since(stamps[j - HISTORY:j + 1]), error[j - HISTORY:j + 1],
                         reference[j - HISTORY:j + 1], BRANCHES)[-1]
            for j in range(k - 4, k + 1)])
        assert np.array_equal(window.rows(), expected)
        array = window.array()
        assert array.shape == (1, 5, len(FEATURES)) and array.dtype == np.float64
        assert np.array_equal(array[0], expected)


def test_the_model_input_is_a_view_made_once() -> None:
    stamps, error, reference = samples(12)
    window = FeatureWindow(3, CHAIN)
    push_all(window, stamps[:5], error[:5], reference[:5])
    first = window.array()
    assert window.array() is first  # no allocation per call
    assert first.flags.c_contiguous
    rows = window.rows()
    rows[:] = 0.0  # a copy: the window is untouched
    assert np.abs(first).sum() > 0
    for k in range(5, 8):  # three pushes later the same slot starts the window again
        window.push(int(stamps[k]), *error[k], *reference[k])
    assert window.array() is first
    offline = feature_rows((stamps[:8] - stamps[0]) * 1e-9, error[:8], reference[:8], BRANCHES)
    np.testing.assert_allclose(first[0], offline[-3:], rtol=1e-12, atol=0)



def sample(error: np.ndarray, reference: np.ndarray,
           k: int) -> tuple[float, float, float, float, float]:
    """Error x, y and reference x, y, z of sample `k`, as `FeatureWindow.push` takes them."""
    (ex, ey), (rx, ry, rz) = error[k].tolist(), reference[k].tolist()
    return ex, ey, rx, ry, rz


def test_preview_blocks_equal_the_offline_blocks_of_the_commanded_path() -> None:
    n, preview, size = 30, 4, 5
    stamps, error, reference = samples(n + preview)
    offline = with_preview(feature_rows(seconds_since(stamps), error, reference, BRANCHES),
                           preview)[:n]
    window = FeatureWindow(size, CHAIN, preview)
    full = [window.push(int(stamps[k]), *sample(error, reference, k),
                        planned=(int(stamps[k + preview]), *reference[k + preview].tolist()))
            for k in range(n)]
    assert full == [False] * (size + HISTORY - 1) + [True] * (n - size - HISTORY + 1)
    assert window.rows().shape == (size, len(feature_names(preview)))
    np.testing.assert_allclose(window.rows(), offline[-size:], rtol=1e-9, atol=1e-15)


def test_a_sample_without_a_plan_holds_the_window_until_every_row_has_a_block() -> None:
    n, preview, size = 20, 2, 3
    stamps, error, reference = samples(n + preview)

    def push(k: int, planned: bool = True) -> bool:
        plan = (int(stamps[k + preview]), *reference[k + preview].tolist()) if planned else None
        return window.push(int(stamps[k]), *sample(error, reference, k), planned=plan)

    window = FeatureWindow(size, CHAIN, preview)
    assert [push(k) for k in range(6)] == [False] * 4 + [True] * 2
    assert not push(6, planned=False)  # no plan for this sample's row
    assert [push(k) for k in range(7, 12)] == [False] * 4 + [True]
    window.plan_lost()  # a contradicted plan: the same
    assert [push(k) for k in range(12, 17)] == [False] * 4 + [True]
    assert window.fill == window.needed  # the rows themselves were kept throughout
