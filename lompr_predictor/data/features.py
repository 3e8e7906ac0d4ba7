# SPDX-License-Identifier: Apache-2.0
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
of the robot description the model is trained for. That is the LOMPR's chain; a serial
chain has no actuator coordinates that follow from the tool tip alone, and its rows are the
tool's columns only (`robot.chain`). No scale fitted to one machine enters: the model
standardises every column with its training data.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lompr_predictor.robot.chain import ActuatorCoordinates
from lompr_predictor.robot.description import BRANCH_JOINTS

#: The columns every robot's rows start with, in order.
TOOL_FEATURES: tuple[str, ...] = (
    'error_x', 'error_y',  # plant error [m] (measured tool tip - reference - compensation)
    'ref_x', 'ref_y',  # reference position [m]
    'ref_vx', 'ref_vy',  # reference velocity [m/s], backward difference
    'ref_ax', 'ref_ay',  # reference acceleration [m/s^2], backward difference
)


def base_features(actuators: Sequence[str] = BRANCH_JOINTS) -> tuple[str, ...]:
    """A robot's feature columns without a preview: `TOOL_FEATURES`, then per actuator
    coordinate of its chain (`chain.KinematicChain.actuators`) its velocity [m/s or rad/s]
    along the reference, then per coordinate its acceleration."""
    return (TOOL_FEATURES + tuple(f'{name}_v' for name in actuators)
            + tuple(f'{name}_a' for name in actuators))


#: The LOMPR's feature names, in column order (its chain's actuators are the three driven
#: branches). Recorded in the model metadata and checked on load.
FEATURES: tuple[str, ...] = base_features(BRANCH_JOINTS)
#: Samples before a window's first row that its features need (the second difference).
HISTORY = 2
#: Target axes, in output order.
TARGETS: tuple[str, ...] = ('x', 'y')
#: The first column the reference preview gives for a coming instant: from it on, the
#: commanded motion there (its position enters as a displacement, `preview_features`).
FIRST_PLANNED_COLUMN = TOOL_FEATURES.index('ref_vx')
_REFERENCE_XY = (TOOL_FEATURES.index('ref_x'), TOOL_FEATURES.index('ref_y'))


def preview_features(base: Sequence[str]) -> tuple[str, ...]:
    """The preview block of a row k of a model with preview K over the `base` columns: the
    reference's displacement from row k to row k + K [m], then the commanded velocities and
    accelerations of row k + K."""
    return ('plan_dx', 'plan_dy', *(f'plan_{name}' for name in base[FIRST_PLANNED_COLUMN:]))


#: The LOMPR's preview block.
PREVIEW_FEATURES: tuple[str, ...] = preview_features(FEATURES)


def feature_names(preview: int = 0,
                  actuators: Sequence[str] = BRANCH_JOINTS) -> tuple[str, ...]:
    """The columns of a model's rows for a chain with `actuators`: `base_features`, then
    with a preview (K > 0 samples of the planned reference after each row) its
    `preview_features` block."""
    if preview < 0:
        msg = f'the preview is a number of samples >= 0, got {preview}'
        raise ValueError(msg)
    base = base_features(actuators)
    return base + preview_features(base) if preview else base


def actuators_of(features: Sequence[str]) -> tuple[str, ...]:
    """The actuator coordinates whose columns `features` hold (`base_features`' inverse)."""
    names = list(features)
    return tuple(name[:-2] for name in names[len(TOOL_FEATURES):]
                 if name.endswith('_v') and not name.startswith('plan_'))


def feature_rows(stamps: np.ndarray, error: np.ndarray, reference: np.ndarray,
                 coordinates: ActuatorCoordinates) -> np.ndarray:
    """(N, 8 + 2 A) feature rows for N consecutive samples of one gap-free segment.

    stamps: (N,) seconds; error: (N, 2) plant error [m]; reference: (N, 3) reference tool
    tip [m]; coordinates: the chain's A actuator coordinates along the tool tip. The first
    `HISTORY` rows lack a full difference and are NaN in the derivative columns.
    """
    stamps = np.asarray(stamps, dtype=float)
    error = np.asarray(error, dtype=float)
    reference = np.asarray(reference, dtype=float)
    # the differenced coordinates: reference X, Y and the actuator coordinates
    coordinates_along = np.asarray(coordinates.along(reference), dtype=float)
    differenced = np.concatenate([reference[:, :2], coordinates_along], axis=1)
    count = coordinates_along.shape[1]
    velocity_columns = [4, 5, *range(8, 8 + count)]
    acceleration_columns = [6, 7, *range(8 + count, 8 + 2 * count)]
    rows = np.full((len(stamps), len(TOOL_FEATURES) + 2 * count), np.nan)
    rows[:, 0:2] = error
    rows[:, 2:4] = reference[:, :2]
    if len(stamps) > 1:
        dt = np.diff(stamps)[:, None]
        velocity = np.diff(differenced, axis=0) / dt
        rows[1:, velocity_columns] = velocity
        if len(stamps) > 2:
            rows[2:, acceleration_columns] = np.diff(velocity, axis=0) / dt[1:]
    return rows


def preview_block(rows: np.ndarray, planned: np.ndarray) -> np.ndarray:
    """(N, F - 2) preview blocks of `rows` given `planned`, the rows of the instants K
    samples after each (both (N, F) base rows): the definition of the block, which
    `online.window` writes again on floats, sample by sample (tested equal)."""
    block = np.empty((len(rows), rows.shape[1] - FIRST_PLANNED_COLUMN + 2))
    block[:, :2] = planned[:, _REFERENCE_XY] - rows[:, _REFERENCE_XY]
    block[:, 2:] = planned[:, FIRST_PLANNED_COLUMN:]
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
