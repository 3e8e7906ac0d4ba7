"""The rolling window of feature rows the model reads, sample by sample.

The rows are those of `data.features.feature_rows`, the function the trainer uses, so a
window here equals the offline window over the same samples. A row needs `HISTORY` samples
before it (the second difference), so a full window of `window` rows takes `window +
HISTORY` samples after the window was last emptied. Each sample costs one row, not a whole
window: the last `HISTORY + 1` samples give the newest row and the older rows are kept.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from lompr_predictor.data.features import FEATURES, HISTORY, feature_rows
from lompr_predictor.stamps import seconds_since


class FeatureWindow:
    """The feature rows of the last `window` samples since the window was last emptied."""

    def __init__(self, window: int) -> None:
        if window < 1:
            msg = f'a window needs at least one row, got {window}'
            raise ValueError(msg)
        self.window = window
        #: Samples a full window takes after it was emptied.
        self.needed = window + HISTORY
        self._recent: deque[tuple[int, float, float, float, float]] = deque(maxlen=HISTORY + 1)
        self._rows = np.zeros((window, len(FEATURES)))
        self._filled = 0  # samples since the window was last emptied

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the newest sample in the window [ns], None while it is empty."""
        return self._recent[-1][0] if self._recent else None

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
        recent = self._recent
        recent.append((stamp_ns, error_x, error_y, reference_x, reference_y))
        self._filled += 1
        if self._filled > HISTORY:
            values = np.array([row[1:] for row in recent])
            stamps = seconds_since(np.array([row[0] for row in recent]))
            self._rows[:-1] = self._rows[1:]
            self._rows[-1] = feature_rows(stamps, values[:, 0:2], values[:, 2:4])[-1]
        return self._filled >= self.needed

    def rows(self) -> np.ndarray:
        """(window, len(FEATURES)) copy of the rows of a full window (the model's input)."""
        if not self.full:
            msg = f'the window holds {self.fill} of {self.needed} samples'
            raise ValueError(msg)
        return self._rows.copy()

    def clear(self) -> None:
        """Empty the window: the next `needed` samples refill it."""
        self._recent.clear()
        self._filled = 0
