# SPDX-License-Identifier: Apache-2.0
"""data.problem: the windows a clean recording makes (none across a gap), each recording
split by time into training, validation and test, and the ranges from the training part
only."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from trainer_data import PERIOD_NS, synthetic_recording

from lompr_predictor.data.cleaning import CleanData, clean_recordings
from lompr_predictor.data.features import HISTORY
from lompr_predictor.data.problem import (
    MIN_WINDOW,
    ProblemError,
    build_problem,
    chronological_split,
    default_window,
    minmax_range,
    window_ends,
)
from lompr_predictor.robot.chain import LomprChain, load_chain
from lompr_predictor.robot.description import RobotDescription


def test_windows_never_cross_a_gap() -> None:
    segments = np.array([[0, 30], [30, 35], [35, 80]])
    window, horizon = 10, 3
    ends = window_ends(segments, window, horizon)
    segment_of = np.searchsorted(segments[:, 1], np.arange(80), side='right')
    for end in ends:
        rows = np.arange(end - window + 1 - HISTORY, end + horizon + 1)
        assert len(set(segment_of[rows])) == 1
    # every admissible window is there: 30 - 2 - 10 - 3 + 1 = 16 and 45 - 2 - 10 - 3 + 1 = 31
    assert len(ends) == 16 + 31
    # a preview of 5 samples after each row: the window's last row and the 5 after it, too
    ahead = window_ends(segments, window, horizon, preview=5)
    assert set(ahead) <= set(ends) and len(ahead) == 16 - 2 + 31 - 2
    for end in ahead:
        assert len(set(segment_of[np.arange(end - window + 1 - HISTORY, end + 6)])) == 1
    with pytest.raises(ValueError, match='preview'):
        window_ends(segments, window, horizon, preview=-1)


def test_split_is_chronological_and_test_is_last_tenth() -> None:
    ends = window_ends(np.array([[0, 1000]]), 10, 5)
    split = chronological_split(np.array([[0, 1000]]), ends, 5, test_fraction=0.1,
                                validation_fraction=0.2)
    np.testing.assert_array_equal(split.parts, [[0, 720, 900, 1000]])
    assert split.training_rows().sum() == 900 and split.training_rows()[:900].all()
    assert (split.train + 5 < 720).all()
    assert ((split.validation + 5 >= 720) & (split.validation + 5 < 900)).all()
    assert (split.test + 5 >= 900).all()
    assert split.train.max() < split.validation.min() < split.test.min()
    assert len(split.train) + len(split.validation) + len(split.test) == len(ends)


def test_each_recording_is_split_on_its_own() -> None:
    """Recordings of several programs: each one's last tenth tests and the last part of
    the rest validates, so every program is trained, validated and scored."""
    recordings = np.array([[0, 600], [600, 1000]])
    ends = window_ends(recordings, 10, 5)
    split = chronological_split(recordings, ends, 5, test_fraction=0.1,
                                validation_fraction=0.2)
    np.testing.assert_array_equal(split.parts, [[0, 432, 540, 600], [600, 888, 960, 1000]])
    for part, low, high in ((split.train, [0, 600], [432, 888]),
                            (split.validation, [432, 888], [540, 960]),
                            (split.test, [540, 960], [600, 1000])):
        target = part + 5
        first = target < 600
        assert first.any() and (~first).any()  # both recordings in every part
        assert ((target >= np.where(first, low[0], low[1]))
                & (target < np.where(first, high[0], high[1]))).all()
    rows = split.training_rows()
    assert rows.sum() == 540 + 360 and rows[:540].all() and rows[600:960].all()


def test_minmax_from_training_part_only() -> None:
    n = 200
    error = np.zeros((n, 2))
    error[:150, 0] = np.linspace(-1e-5, 2e-5, 150)
    error[195, 0] = 9e-5  # in the test part: must not widen the range
    stamps = np.arange(n, dtype=np.int64) * PERIOD_NS
    data = CleanData(stamps=stamps, error=error, reference=np.zeros((n, 3)),
                     segments=np.array([[0, n]]), sample_period=0.04,
                     chain=load_chain())
    problem = build_problem(data, 5, 1, test_fraction=0.1, validation_fraction=0.2)
    np.testing.assert_array_equal(problem.split.parts, [[0, 144, 180, 200]])
    np.testing.assert_allclose(problem.error_low, [-1e-5, 0.0])
    np.testing.assert_allclose(problem.error_high, [2e-5, 1.0])  # constant column: min + 1
    low, high = minmax_range(np.array([[1.0, np.nan], [3.0, 2.0]]))
    np.testing.assert_allclose([low, high], [[1.0, 2.0], [3.0, 3.0]])


def test_a_part_without_windows_names_the_options_that_make_them() -> None:
    ends = window_ends(np.array([[0, 40]]), 10, 5)
    with pytest.raises(ProblemError, match=r'^no validation windows: 40 clean samples are too '
                                           r'few for this window \(--window\) and horizon 5'):
        chronological_split(np.array([[0, 40]]), ends, 5, test_fraction=0.5,
                            validation_fraction=0.01)
    with pytest.raises(ValueError, match='the test fraction must lie in'):
        chronological_split(np.array([[0, 40]]), ends, 5, test_fraction=1.0)


def test_the_default_window_is_a_tenth_of_a_second_of_at_least_25_samples(
        description: RobotDescription) -> None:
    assert [default_window(period) for period in (0.04, 0.004, 0.001, 0.0005, 1 / 300)] == [
        MIN_WINDOW, MIN_WINDOW, 100, 200, 30]
    with pytest.raises(ProblemError, match=r'^the sample period must be > 0 s, got 0\.0$'):
        default_window(0.0)
    recording, _ = synthetic_recording(description.geometry, 3000)
    clean = clean_recordings([recording], LomprChain(description))
    assert clean.sample_period == pytest.approx(0.04)
    # the problem's window unless given: the recording's rate decides it
    assert build_problem(clean).window == 25
    assert build_problem(dataclasses.replace(clean, sample_period=1e-3)).window == 100
    assert build_problem(dataclasses.replace(clean, sample_period=1e-3), 40).window == 40
