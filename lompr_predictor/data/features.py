"""The model's input features: one definition for the offline trainer and the online node.

A model sees a window of `window` consecutive samples, each a row of `FEATURES`, and
predicts the plant's X/Y error `horizon` samples after the window's last sample. The rows
are computed by `feature_rows`, which is causal: row k depends on samples k-2..k only. The
trainer applies it to whole segments, the predictor node to its rolling buffer of the last
`window + HISTORY` samples; both get the same numbers for the same samples, which is what
makes node and offline predictions agree sample for sample.

Why these features: the plant error is mostly a function of the commanded motion (servo
lag follows velocity and acceleration, friction follows velocity, the elastic and
posture-dependent terms follow position), plus a slowly varying part seen only in the past
errors themselves. The reference is the commanded path, known without noise.
"""

from __future__ import annotations

import numpy as np

#: Feature names, in column order. Recorded in the model metadata and checked on load.
FEATURES: tuple[str, ...] = (
    'error_x', 'error_y',  # plant error [m] (measured tool tip - reference - compensation)
    'ref_x', 'ref_y',  # reference position [m]
    'ref_vx', 'ref_vy',  # reference velocity [m/s], backward difference
    'ref_ax', 'ref_ay',  # reference acceleration [m/s^2], backward difference
)
#: Samples before a window's first row that its features need (the second difference).
HISTORY = 2
#: Target axes, in output order.
TARGETS: tuple[str, ...] = ('x', 'y')


def feature_rows(stamps: np.ndarray, error: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N, len(FEATURES)) feature rows for N consecutive samples of one gap-free segment.

    stamps: (N,) seconds; error: (N, 2) plant error [m]; reference: (N, 2) reference X/Y [m].
    The first `HISTORY` rows lack a full difference and are NaN in the derivative columns.
    """
    stamps = np.asarray(stamps, dtype=float)
    error = np.asarray(error, dtype=float)
    reference = np.asarray(reference, dtype=float)
    rows = np.full((len(stamps), len(FEATURES)), np.nan)
    rows[:, 0:2] = error
    rows[:, 2:4] = reference
    if len(stamps) > 1:
        dt = np.diff(stamps)[:, None]
        velocity = np.diff(reference, axis=0) / dt
        rows[1:, 4:6] = velocity
        if len(stamps) > 2:
            rows[2:, 6:8] = np.diff(velocity, axis=0) / dt[1:]
    return rows
