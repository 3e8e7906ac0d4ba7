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
errors themselves. The reference is the commanded path, known without noise. Friction,
backlash and servo lag act per actuator, and in a parallel robot an actuator's velocity is
a nonlinear function of the Cartesian velocity and the posture: so the rows also carry the
velocity and acceleration of the three driven branches along the reference, their lengths
from the closed-form inverse kinematics (`kinematics.VerticalToolBranches`, tool vertical)
of the robot description the model is trained for. No scale fitted to one machine enters:
the model standardises every column with its training data.
"""

from __future__ import annotations

import numpy as np

from lompr_predictor.robot.description import BRANCH_JOINTS
from lompr_predictor.robot.kinematics import VerticalToolBranches

#: Feature names, in column order. Recorded in the model metadata and checked on load.
FEATURES: tuple[str, ...] = (
    'error_x', 'error_y',  # plant error [m] (measured tool tip - reference - compensation)
    'ref_x', 'ref_y',  # reference position [m]
    'ref_vx', 'ref_vy',  # reference velocity [m/s], backward difference
    'ref_ax', 'ref_ay',  # reference acceleration [m/s^2], backward difference
    *(f'{branch}_v' for branch in BRANCH_JOINTS),  # branch velocity [m/s] along the reference
    *(f'{branch}_a' for branch in BRANCH_JOINTS),  # branch acceleration [m/s^2]
)
#: Samples before a window's first row that its features need (the second difference).
HISTORY = 2
#: Target axes, in output order.
TARGETS: tuple[str, ...] = ('x', 'y')
#: The columns of `FEATURES` the reference preview gives for a coming instant: the commanded
#: motion there (its position enters as a displacement, `PREVIEW_FEATURES`).
PLANNED_COLUMNS: tuple[int, ...] = tuple(
    index for index, name in enumerate(FEATURES)
    if not name.startswith('error_') and name not in ('ref_x', 'ref_y'))
_REFERENCE_XY = (FEATURES.index('ref_x'), FEATURES.index('ref_y'))
#: The preview block of a row k of a model with preview K: the reference's displacement from
#: row k to row k + K [m], then the commanded velocities and accelerations of row k + K.
PREVIEW_FEATURES: tuple[str, ...] = (
    'plan_dx', 'plan_dy', *(f'plan_{FEATURES[index]}' for index in PLANNED_COLUMNS))


def feature_names(preview: int = 0) -> tuple[str, ...]:
    """The columns of a model's rows: `FEATURES`, then with a preview (K > 0 samples of the
    planned reference after each row) the `PREVIEW_FEATURES` block."""
    if preview < 0:
        msg = f'the preview is a number of samples >= 0, got {preview}'
        raise ValueError(msg)
    return FEATURES + PREVIEW_FEATURES if preview else FEATURES


def feature_rows(stamps: np.ndarray, error: np.ndarray, reference: np.ndarray,
                 branches: VerticalToolBranches) -> np.ndarray:
    """(N, len(FEATURES)) feature rows for N consecutive samples of one gap-free segment.

    stamps: (N,) seconds; error: (N, 2) plant error [m]; reference: (N, 3) reference tool
    tip [m]; branches: the inverse kinematics of the robot description. The first `HISTORY`
    rows lack a full difference and are NaN in the derivative columns.
    """
    stamps = np.asarray(stamps, dtype=float)
    error = np.asarray(error, dtype=float)
    reference = np.asarray(reference, dtype=float)
    rows = np.full((len(stamps), len(FEATURES)), np.nan)
    rows[:, 0:2] = error
    rows[:, 2:4] = reference[:, :2]
    # the differenced coordinates: reference X, Y and the three branch lengths
    coordinates = np.concatenate([reference[:, :2], branches.along(reference)], axis=1)
    if len(stamps) > 1:
        dt = np.diff(stamps)[:, None]
        velocity = np.diff(coordinates, axis=0) / dt
        rows[1:, 4:6], rows[1:, 8:11] = velocity[:, :2], velocity[:, 2:]
        if len(stamps) > 2:
            acceleration = np.diff(velocity, axis=0) / dt[1:]
            rows[2:, 6:8], rows[2:, 11:14] = acceleration[:, :2], acceleration[:, 2:]
    return rows


def preview_block(rows: np.ndarray, planned: np.ndarray) -> np.ndarray:
    """(N, len(PREVIEW_FEATURES)) preview blocks of `rows` given `planned`, the rows of the
    instants K samples after each (both (N, len(FEATURES))): the definition of the block,
    which `online.window` writes again on floats, sample by sample (tested equal)."""
    block = np.empty((len(rows), len(PREVIEW_FEATURES)))
    block[:, :2] = planned[:, _REFERENCE_XY] - rows[:, _REFERENCE_XY]
    block[:, 2:] = planned[:, PLANNED_COLUMNS]
    return block


def with_preview(rows: np.ndarray, preview: int) -> np.ndarray:
    """`feature_rows` of one gap-free segment with the preview block of `preview` samples
    appended (K = 0: the rows as they are): offline, the preview is the commanded path
    itself, row k + K of the segment; the last K rows, which have none, get NaN."""
    if preview == 0:
        return rows
    planned = np.full_like(rows, np.nan)
    covered = max(len(rows) - preview, 0)
    planned[:covered] = rows[preview:]
    return np.concatenate([rows, preview_block(rows, planned)], axis=1)
