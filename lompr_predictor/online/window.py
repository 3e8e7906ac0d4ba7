# SPDX-License-Identifier: Apache-2.0
"""The rolling window of feature rows the model reads, sample by sample.

The rows are those of `data.features.feature_rows`, the function the trainer uses, so a
window here equals the offline window over the same samples. A row needs `HISTORY` samples
before it (the second difference), so a full window of `window` rows takes `window +
HISTORY` samples after the window was last emptied.

Each sample costs one row, computed incrementally: the newest sample's actuator coordinates
(one `at` call of the chain's, e.g. the LOMPR's branch lengths by inverse kinematics, as
`feature_rows` does on arrays), then
`newest_row`, `feature_rows` applied to the last `HISTORY + 1` samples, written out on
Python floats (the same operations in the same order, so the same bits), since NumPy's
per-call overhead on arrays of three is many times the arithmetic. The rows live in a
preallocated buffer that holds each row twice, at k and k + window (k = its slot modulo
window), so that the window, oldest row first, is always one contiguous slice of it;
`arrays[start]` is that slice as a (1, window, F) float64 array sharing the buffer's memory
(one view per slot, made once): the model's input with no copy and no allocation per
sample.

With a reference preview of K samples (`features.with_preview`), each row also carries the
preview block of the planned instant K samples after it: the caller passes the planned
position there with each sample (`push`), the window keeps the last `HISTORY + 1` planned
samples as it does the measured ones and writes the block from `newest_row` of those, so
that a plan that matches the commanded path gives the offline block. A window is full
only once its every row has a block: a sample without a plan restarts that count
(`plan_lost`), the rows themselves are kept.
"""

from __future__ import annotations

import struct

import numpy as np

from lompr_predictor.data.features import FIRST_PLANNED_COLUMN, HISTORY, feature_names
from lompr_predictor.robot.chain import KinematicChain

# `newest_row` is written for a second difference of the differenced coordinates.
assert HISTORY == 2, 'window.newest_row computes the features of features.py by hand'
assert FIRST_PLANNED_COLUMN == 4, 'FeatureWindow._block writes the preview block'

#: stamp [ns], error x, y [m], then the differenced coordinates: reference x, y [m] and the
#: chain's actuator coordinates
Sample = tuple[float, ...]
#: The planned instant K samples after a sample [ns] and the planned tool tip there [m].
Planned = tuple[int, float, float, float]


def newest_row(older: Sample, previous: Sample, newest: Sample) -> tuple[float, ...]:
    """The last row of `feature_rows` over three consecutive samples (`Sample`), with the
    stamps as `stamps.seconds_since` the first: the same floating-point operations, so bit
    for bit the same row."""
    t1 = (previous[0] - older[0]) * 1e-9  # seconds_since: integer difference, then seconds
    dt2 = (newest[0] - older[0]) * 1e-9 - t1  # np.diff of the seconds (the first step is t1)
    before, last, now = older[3:], previous[3:], newest[3:]
    velocity = [(c2 - c1) / dt2 for c1, c2 in zip(last, now, strict=True)]
    acceleration = [(v - (c1 - c0) / t1) / dt2
                    for v, c0, c1 in zip(velocity, before, last, strict=True)]
    return (newest[1], newest[2], now[0], now[1], velocity[0], velocity[1],
            acceleration[0], acceleration[1], *velocity[2:], *acceleration[2:])


class FeatureWindow:
    """The feature rows of the last `window` samples since the window was last emptied,
    for the robot of `chain` (its actuator coordinates along the reference), with the
    preview block of `preview` samples (0: none)."""

    def __init__(self, window: int, chain: KinematicChain, preview: int = 0) -> None:
        if window < 1:
            msg = f'a window needs at least one row, got {window}'
            raise ValueError(msg)
        self.window = window
        self.preview = preview
        columns = len(feature_names(preview, chain.actuators))
        self._none: Sample = (0, *(0.0,) * (4 + len(chain.actuators)))
        self._no_block = (0.0,) * (columns - len(feature_names(0, chain.actuators)))
        self._planned_older = self._planned_previous = self._none
        self._planned_run = 0  # consecutive samples pushed with a plan
        #: Samples a full window takes after it was emptied.
        self.needed = window + HISTORY
        self._coordinates = chain.actuator_coordinates()
        # the last HISTORY + 1 samples (`Sample`), those before the first since the window
        # was emptied left as `_none` (never read: see `_filled`)
        self._previous = self._newest = self._none
        self._buffer = np.zeros((2 * window, columns))
        # a row is written with one C call: struct packing into the buffer's memory
        self._write_row = struct.Struct(f'={columns}d').pack_into
        self._memory = self._buffer.data.cast('B')
        self._row_bytes = self._buffer.strides[0]
        self._copy_bytes = window * self._row_bytes  # from a row to its second copy
        #: The window's view for each start slot (`array`), made once.
        self.arrays = tuple(self._buffer[start:start + window][np.newaxis]
                            for start in range(window))
        self._next = 0  # slot of the next row; the window starts there once full
        #: The newest row written, as floats (read by checks of the rows, e.g. the trained
        #: envelope's); meaningful once the window is full.
        self.newest: tuple[float, ...] = ()
        self._filled = 0  # samples since the window was last emptied

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the newest sample in the window [ns], None while it is empty."""
        return int(self._newest[0]) if self._filled else None

    @property
    def empty(self) -> bool:
        return self._filled == 0

    @property
    def fill(self) -> int:
        """Samples in the window, at most `needed`."""
        return min(self._filled, self.needed)

    @property
    def full(self) -> bool:
        return self._filled >= self.needed and (
            not self.preview or self._planned_run >= self.needed)

    def push(self, stamp_ns: int, error_x: float, error_y: float, reference_x: float,
             reference_y: float, reference_z: float, planned: Planned | None = None) -> bool:
        """Add one sample (plant error and reference tool tip, SI) and, with a preview, the
        plan `preview` samples later (None: no plan there); True once the window is full."""
        older, previous = self._previous, self._newest
        newest = (stamp_ns, error_x, error_y, reference_x, reference_y,
                  *self._coordinates.at(reference_x, reference_y, reference_z))
        self._previous, self._newest = previous, newest
        self._filled += 1
        block = self._block(reference_x, reference_y, planned) if self.preview else ()
        if self._filled > HISTORY:
            row = newest_row(older, previous, newest) + block
            self.newest = row
            slot = self._next
            offset = slot * self._row_bytes
            self._write_row(self._memory, offset, *row)
            self._write_row(self._memory, offset + self._copy_bytes, *row)
            self._next = slot + 1 if slot + 1 < self.window else 0
        return self.full

    def plan_lost(self) -> None:
        """The plan behind the rows' blocks was dropped: the window fills again from the
        next planned samples (its rows are kept)."""
        self._planned_run = 0

    def _block(self, reference_x: float, reference_y: float,
               planned: Planned | None) -> tuple[float, ...]:
        """The preview block of the sample at (reference_x, reference_y) given the plan
        `preview` samples later (`features.preview_block`), zeros until the last three
        samples had a plan (such a row is never read: `full`)."""
        if planned is None:
            self._planned_run = 0
            return self._no_block
        stamp_ns, x, y, z = planned
        older, previous = self._planned_older, self._planned_previous
        newest = (stamp_ns, 0.0, 0.0, x, y, *self._coordinates.at(x, y, z))
        self._planned_older, self._planned_previous = previous, newest
        self._planned_run += 1
        if self._planned_run <= HISTORY:
            return self._no_block
        row = newest_row(older, previous, newest)
        return (row[2] - reference_x, row[3] - reference_y, *row[4:])

    @property
    def start(self) -> int:
        """The slot a full window starts at: `arrays[start]` is the window."""
        return self._next

    def array(self) -> np.ndarray:
        """(1, window, F) float64 rows of a full window, oldest first: a view
        of the buffer (no copy), valid until the next `push` or `clear`; read, never keep
        or write it."""
        if not self.full:
            msg = f'the window holds {self.fill} of {self.needed} samples'
            raise ValueError(msg)
        return self.arrays[self._next]

    def rows(self) -> np.ndarray:
        """(window, F) copy of the rows of a full window (the model's input)."""
        return self.array()[0].copy()

    def clear(self) -> None:
        """Empty the window: the next `needed` samples refill it."""
        self._previous = self._newest = self._none
        self._filled = 0
        self._planned_run = 0
