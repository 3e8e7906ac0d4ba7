"""The rolling window of feature rows the model reads, sample by sample.

The rows are those of `data.features.feature_rows`, the function the trainer uses, so a
window here equals the offline window over the same samples. A row needs `HISTORY` samples
before it (the second difference), so a full window of `window` rows takes `window +
HISTORY` samples after the window was last emptied.

Each sample costs one row, computed incrementally: `newest_row` is `feature_rows` applied to
the last `HISTORY + 1` samples, written out on Python floats (the same operations in the
same order, so the same bits), since NumPy's per-call overhead on arrays of three is many
times the arithmetic. The rows live in a preallocated buffer that holds each row twice, at
k and k + window (k = its slot modulo window), so that the window, oldest row first, is
always one contiguous slice of it; `tensor()` gives that slice as a (1, window, F) float64
tensor sharing the buffer's memory (one view per slot, made once): the model's input with
no copy and no allocation per sample.
"""

from __future__ import annotations

import struct

import numpy as np
import torch

from lompr_predictor.data.features import FEATURES, HISTORY

# `newest_row` is written for a second difference; a feature change must change it too.
assert HISTORY == 2, 'window.newest_row computes the features of features.py by hand'

Sample = tuple[int, float, float, float, float]  # stamp [ns], error x, y, reference x, y [m]
_NONE: Sample = (0, 0.0, 0.0, 0.0, 0.0)


def newest_row(older: Sample, previous: Sample, newest: Sample) -> tuple[float, ...]:
    """The last row of `feature_rows` over three consecutive samples (stamp [ns], plant
    error x, y, reference x, y [m]), with the stamps as `stamps.seconds_since` the first:
    the same floating-point operations, so bit for bit the same row."""
    s0, _, _, r0x, r0y = older
    s1, _, _, r1x, r1y = previous
    s2, ex, ey, rx, ry = newest
    t1 = (s1 - s0) * 1e-9  # seconds_since: integer difference first, then to seconds
    dt2 = (s2 - s0) * 1e-9 - t1  # np.diff of the seconds (the first step is t1 - 0.0 = t1)
    v1x, v1y = (r1x - r0x) / t1, (r1y - r0y) / t1
    vx, vy = (rx - r1x) / dt2, (ry - r1y) / dt2
    return ex, ey, rx, ry, vx, vy, (vx - v1x) / dt2, (vy - v1y) / dt2


class FeatureWindow:
    """The feature rows of the last `window` samples since the window was last emptied."""

    def __init__(self, window: int) -> None:
        if window < 1:
            msg = f'a window needs at least one row, got {window}'
            raise ValueError(msg)
        self.window = window
        #: Samples a full window takes after it was emptied.
        self.needed = window + HISTORY
        # the last HISTORY + 1 samples (stamp, error x, y, reference x, y), those before the
        # first since the window was emptied left as _NONE (never read: see `_filled`)
        self._previous = self._newest = _NONE
        self._buffer = np.zeros((2 * window, len(FEATURES)))
        # a row is written with one C call: struct packing into the buffer's memory
        self._write_row = struct.Struct(f'={len(FEATURES)}d').pack_into
        self._memory = self._buffer.data.cast('B')
        self._row_bytes = self._buffer.strides[0]
        self._copy_bytes = window * self._row_bytes  # from a row to its second copy
        buffer = torch.from_numpy(self._buffer)  # the same memory
        self._views = [buffer[start:start + window].unsqueeze(0) for start in range(window)]
        self._next = 0  # slot of the next row; the window starts there once full
        self._filled = 0  # samples since the window was last emptied

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the newest sample in the window [ns], None while it is empty."""
        return self._newest[0] if self._filled else None

    @property
    def empty(self) -> bool:
        return self._filled == 0

    @property
    def fill(self) -> int:
        """Samples in the window, at most `needed`."""
        return min(self._filled, self.needed)

    @property
    def full(self) -> bool:
        return self._filled >= self.needed

    def push(self, stamp_ns: int, error_x: float, error_y: float, reference_x: float,
             reference_y: float) -> bool:
        """Add one sample (plant error and reference, SI); True once the window is full."""
        older, previous = self._previous, self._newest
        newest = (stamp_ns, error_x, error_y, reference_x, reference_y)
        self._previous, self._newest = previous, newest
        self._filled += 1
        if self._filled > HISTORY:
            row = newest_row(older, previous, newest)
            slot = self._next
            offset = slot * self._row_bytes
            self._write_row(self._memory, offset, *row)
            self._write_row(self._memory, offset + self._copy_bytes, *row)
            self._next = slot + 1 if slot + 1 < self.window else 0
        return self._filled >= self.needed

    def tensor(self) -> torch.Tensor:
        """(1, window, len(FEATURES)) float64 rows of a full window, oldest first: a view
        of the buffer (no copy), valid until the next `push` or `clear`; read, never keep
        or write it."""
        if not self.full:
            msg = f'the window holds {self.fill} of {self.needed} samples'
            raise ValueError(msg)
        return self._views[self._next]

    def rows(self) -> np.ndarray:
        """(window, len(FEATURES)) copy of the rows of a full window (the model's input)."""
        return self.tensor()[0].numpy().copy()

    def clear(self) -> None:
        """Empty the window: the next `needed` samples refill it."""
        self._previous = self._newest = _NONE
        self._filled = 0
