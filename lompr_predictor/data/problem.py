# SPDX-License-Identifier: Apache-2.0
"""Learning windows of clean data: which windows exist, the chronological split, ranges.

- `window_ends`: windows of `window` rows whose last row and predicted row (`horizon`
  samples later) lie in one run without a missing sample (`CleanData.regular_runs`), so no
  window crosses a gap or spans more time than it says;
- `chronological_split`: the chronologically last `test_fraction` of each recording's
  samples is the test part, and the validation part is carved from the end of its training
  part (so that recordings of several programs each train, validate and test);
- `minmax_range`: ranges from the training part only.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lompr_predictor.data.cleaning import CleanData
from lompr_predictor.data.features import HISTORY, base_features, feature_names
from lompr_predictor.errors import LomprError
from lompr_predictor.robot.description import BRANCH_JOINTS

#: Defaults of the learning problem, in one place (`lompr train` uses these). The window's
#: default is a span of the machine's time (`default_window`): as many samples as the
#: recording holds in `WINDOW_SECONDS`, never fewer than `MIN_WINDOW` (at 25 Hz a tenth of
#: a second is 2.5 samples, too short a history for the network to read a motion's course).
WINDOW_SECONDS = 0.1
MIN_WINDOW = 25
DEFAULT_HORIZON = 1  # samples between a window's last row and the predicted one
TEST_FRACTION = 0.1  # the chronologically last part of the samples: the test part
VALIDATION_FRACTION = 0.15  # the last part of the rest: validation (tuning, early stopping)


class ProblemError(LomprError, ValueError):
    """The data cannot make the learning problem asked for (too few samples for the window
    and horizon): a user error (`lompr train` exits 2 with one line), raised before any
    trial runs."""


def window_ends(segments: np.ndarray, window: int, horizon: int,
                preview: int = 0) -> np.ndarray:
    """Indices of the last row of every window that, with its target `horizon` rows later,
    the `HISTORY` rows its features need and the `preview` rows after its last row (the
    preview block's), lies inside one segment."""
    if window < 1 or horizon < 0 or preview < 0:
        msg = (f'window must be >= 1, horizon and preview >= 0, got {window}, {horizon}, '
               f'{preview}')
        raise ValueError(msg)
    reach = max(horizon, preview)
    parts = [np.arange(start + HISTORY + window - 1, end - reach) for start, end in segments]
    return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, dtype=np.int64)


@dataclass(frozen=True)
class Split:
    """Window ends of each part, and where each recording's parts begin."""

    train: np.ndarray
    validation: np.ndarray
    test: np.ndarray
    #: (R, 4) rows, per recording: its first row, its first validation row, its first test
    #: row, its end
    parts: np.ndarray

    def training_rows(self) -> np.ndarray:
        """(N,) bool: the rows before each recording's test part, the data that trains (and
        sets the metrics' scale, the machine map and the envelope); never a test row."""
        rows = np.zeros(int(self.parts[:, 3].max()) if len(self.parts) else 0, dtype=bool)
        for first, _, test, _ in self.parts:
            rows[first:test] = True
        return rows


def recording_parts(recordings: np.ndarray, test_fraction: float,
                    validation_fraction: float) -> np.ndarray:
    """(R, 4) the parts of each recording's rows [first, end) (`Split.parts`): its last
    `test_fraction` tests, the last `validation_fraction` of the rest validates."""
    if not 0 <= test_fraction < 1 or not 0 < validation_fraction < 1:
        msg = 'the test fraction must lie in [0, 1) and the validation fraction in (0, 1)'
        raise ValueError(msg)
    first, end = np.asarray(recordings, dtype=np.int64).reshape(-1, 2).T
    test = first + np.round((end - first) * (1 - test_fraction)).astype(np.int64)
    validation = first + np.round((test - first) * (1 - validation_fraction)).astype(np.int64)
    return np.stack([first, validation, test, end], -1)


def split_by_parts(parts: np.ndarray, ends: np.ndarray, horizon: int,
                   preview: int = 0) -> Split:
    """The windows ending at `ends` by the part of their predicted row (`horizon` rows
    later), each recording split as `parts` says; a part without windows is a
    `ProblemError` naming the options that make windows (`preview`: theirs)."""
    target = ends + horizon
    recording = np.searchsorted(parts[:, 0], target, side='right') - 1
    validation, test = parts[recording, 1], parts[recording, 2]
    split = Split(train=ends[target < validation],
                  validation=ends[(target >= validation) & (target < test)],
                  test=ends[target >= test], parts=parts)
    for name in ('train', 'validation', 'test'):
        if len(getattr(split, name)) == 0:
            raise ProblemError(f'no {name} windows: {int(parts[:, 3].max())} clean samples are '
                               f'too few {_for_windows(horizon, preview)}')
    return split


def _for_windows(horizon: int, preview: int) -> str:
    """The end of a 'too few samples' message: the options that make a window this long,
    naming --preview where it, not the horizon, reaches furthest past a window."""
    reach = (f'horizon {horizon} (--horizon)' if preview <= horizon else
             f'preview {preview} (--preview: every window also needs the {preview} samples '
             'after it)')
    return f'for this window (--window) and {reach}, or the gaps leave no segment long enough'


def chronological_split(recordings: np.ndarray, ends: np.ndarray, horizon: int, *,
                        test_fraction: float = TEST_FRACTION,
                        validation_fraction: float = VALIDATION_FRACTION,
                        preview: int = 0) -> Split:
    """Split each recording (rows [first, end), `CleanData.recordings`) by time: its last
    `test_fraction` of rows is the test part; the last `validation_fraction` of the rest
    validates. A window belongs to the part of its predicted row, and a training or
    validation window's target row always precedes its recording's test part (its inputs,
    being earlier still, too). With recordings of several programs every program is in
    every part, so the test part scores each one. `preview`: the windows' preview (for the
    message when a part is empty)."""
    return split_by_parts(recording_parts(recordings, test_fraction, validation_fraction),
                          ends, horizon, preview)


def minmax_range(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column (min, max) ignoring NaN; a constant column gets max = min + 1 so that
    normalising by the range never divides by zero."""
    low = np.nanmin(values, axis=0)
    high = np.nanmax(values, axis=0)
    high = np.where(high > low, high, low + 1.0)
    return low, high


@dataclass(frozen=True)
class LearningProblem:
    """Feature rows, errors and the split windows of one clean data set, for one window
    length and horizon; the error's range over the training part (the metrics' scale; the
    models take their input ranges from training windows, `training.input_windows`)."""

    rows: np.ndarray  # (N, F) raw feature rows (features.feature_names(preview))
    error: np.ndarray  # (N, 2) plant error [m]
    stamps: np.ndarray  # (N,) int64 [ns]
    window: int
    horizon: int
    sample_period: float  # [s]
    split: Split
    error_low: np.ndarray  # (2,) training-part min of the error (the metrics' scale)
    error_high: np.ndarray  # (2,)
    preview: int = 0  # samples of the planned reference after each row (0: none)
    #: the robot's actuator coordinates the rows carry (`features.base_features`)
    actuators: tuple[str, ...] = BRANCH_JOINTS

    @property
    def features(self) -> tuple[str, ...]:
        """Names of the columns of `rows`."""
        return feature_names(self.preview, self.actuators)

    def targets(self, ends: np.ndarray, residual: bool) -> np.ndarray:
        """(B, 2) what a model learns for windows ending at `ends`: the error `horizon`
        rows later, minus the window's last error when `residual`."""
        target = self.error[ends + self.horizon]
        return target - self.error[ends] if residual else target


def without_preview(problem: LearningProblem) -> LearningProblem:
    """The same windows and split with the rows' preview block left out (the K = 0 inputs
    of the same instants, to see what the preview gives)."""
    return replace(problem, rows=problem.rows[:, :len(base_features(problem.actuators))],
                   preview=0)


def default_window(sample_period: float) -> int:
    """Samples per window unless given: `WINDOW_SECONDS` at the recording's `sample_period`
    [s], at least `MIN_WINDOW` (25 at 25 and 250 Hz, 100 at 1 kHz)."""
    if not sample_period > 0:
        msg = f'the sample period must be > 0 s, got {sample_period!r}'
        raise ProblemError(msg)
    return max(MIN_WINDOW, round(WINDOW_SECONDS / sample_period))


def build_problem(data: CleanData, window: int | None = None,
                  horizon: int = DEFAULT_HORIZON, *, preview: int = 0,
                  test_fraction: float = TEST_FRACTION,
                  validation_fraction: float = VALIDATION_FRACTION) -> LearningProblem:
    """Windows, chronological split and training-range normalisation of `data`, with the
    preview block of `preview` samples in the rows (0: none); `window` None: the default
    for its sample rate (`default_window`)."""
    window = default_window(data.sample_period) if window is None else window
    ends = window_ends(data.regular_runs(), window, horizon, preview)
    split = chronological_split(data.recordings, ends, horizon, test_fraction=test_fraction,
                                validation_fraction=validation_fraction, preview=preview)
    error_low, error_high = minmax_range(data.error[split.training_rows()])
    return LearningProblem(rows=data.features(preview), error=data.error, stamps=data.stamps,
                           window=window, horizon=horizon, sample_period=data.sample_period,
                           split=split, error_low=error_low, error_high=error_high,
                           preview=preview, actuators=data.chain.actuators)


def train_test_problem(train: CleanData, test: CleanData, window: int | None = None,
                       horizon: int = DEFAULT_HORIZON, *, preview: int = 0,
                       validation_fraction: float = VALIDATION_FRACTION) -> LearningProblem:
    """Train on some recordings, test on others (e.g. another seed of the same machine, or
    another program): each of `train`'s recordings split chronologically into training and
    validation (its last `validation_fraction`), every window of `test` the test part. The
    rows of `test` follow those of `train`; no window spans both. `window` None: the
    default for `train`'s sample rate (`default_window`)."""
    window = default_window(train.sample_period) if window is None else window
    n_train = len(train)
    ends = np.concatenate([window_ends(train.regular_runs(), window, horizon, preview),
                           window_ends(test.regular_runs(), window, horizon, preview) + n_train])
    trained = recording_parts(train.recordings, 0.0, validation_fraction)
    tested = np.repeat(test.recordings[:, :1], 3, axis=1)
    parts = np.concatenate([trained, np.column_stack([tested, test.recordings[:, 1:]]) + n_train])
    split = split_by_parts(parts, ends, horizon, preview)
    error_low, error_high = minmax_range(train.error[split.training_rows()[:n_train]])
    return LearningProblem(rows=np.vstack([train.features(preview), test.features(preview)]),
                           error=np.vstack([train.error, test.error]),
                           stamps=np.concatenate([train.stamps, test.stamps]),
                           window=window, horizon=horizon, sample_period=train.sample_period,
                           split=split, error_low=error_low, error_high=error_high,
                           preview=preview, actuators=train.chain.actuators)
