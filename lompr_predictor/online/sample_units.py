# SPDX-License-Identifier: Apache-2.0
"""Units the predictor core hands every aligned sample and every prediction (ROS-free).

The core (`predictor.OnlinePredictor`) keeps a chain of `SampleUnit`s, the live accuracy
first: each sees, in stamp order, every aligned sample with its plant error and the
prediction published for its instant earlier (`observe`), and every prediction a model made,
before the offset gate bounds it (`revise`), which it may replace or withhold. This is where
a unit that judges predictions by the live residuals plugs in (a guard choosing between the
model and persistence, a check of the window's rows against the model's ranges, a store of
aligned samples for adaptation): a small class given to the core's `units`, no change to the
core. A unit is cleared with the window (`clear`: after a fault or a reset the stream it
observed does not continue).
"""

from __future__ import annotations

from collections import deque
from typing import Protocol

import numpy as np

from lompr_predictor.learning.model_file import ModelMetadata
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.model_slot import ModelSlot
from lompr_predictor.online.offset import XY


class SampleUnit(Protocol):
    """One link of the core's chain (module docstring)."""

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        """One aligned sample, in stamp order: its plant error [m] (measured - reference -
        the offset applied at its instant) and the prediction published for its instant
        earlier (None where none was)."""
        ...

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        """The prediction [m] `slot`'s model made for `instant_ns` from the rows in
        `slot.window`: the prediction to hand on (this one or another), or None to publish
        nothing for that instant (the controller then applies no offset there)."""
        ...

    def clear(self) -> None:
        """The window was emptied: the samples that come next start a new stream."""
        ...


class LiveAccuracy:
    """RMS per axis of truth - prediction over the last `samples` instants whose truth
    arrived: a live figure to hold against the model's test RMSE. A `SampleUnit` that
    changes nothing and outlives faults (it measures the model, not the stream)."""

    def __init__(self, samples: int) -> None:
        self._x: deque[float] = deque(maxlen=samples)
        self._y: deque[float] = deque(maxlen=samples)

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        del sample
        if published is not None:
            self._x.append(error[0] - published[0])
            self._y.append(error[1] - published[1])

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        del instant_ns, slot
        return prediction

    def clear(self) -> None:
        """Residuals already measured stay: the model did not change."""

    def rms(self) -> tuple[np.ndarray, int]:
        """(2,) RMS [m] and how many residuals it is over; NaN before the first."""
        if not self._x:
            return np.full(2, np.nan), 0
        residuals = np.column_stack((self._x, self._y))
        return np.sqrt(np.mean(residuals ** 2, axis=0)), len(residuals)


#: How many times the error's training range (per axis, the model file's normalisation) a
#: predicted change over the horizon may span before it is no prediction of this machine: a
#: change larger than every error the model was trained on is an extrapolation (a jump of
#: the reference, a frame mix-up), never a correction to apply.
PLAUSIBLE_RANGES = 2.0


class PlausibleChange:
    """A `SampleUnit` last in the chain, before the offset gate: on an axis where the
    model predicts the error to change by more than `PLAUSIBLE_RANGES` times its training
    range over the horizon, persistence (the plant error the window ends at) is handed on
    instead, and counted (`implausible`). A model file without the range passes as it is."""

    def __init__(self) -> None:
        self.implausible = 0
        self._last: XY | None = None
        self._limits: tuple[float, float] | None = None
        self._metadata: object = None

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        del sample, published
        self._last = error

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        del instant_ns
        last, limits = self._last, self._limits_of(slot)
        if last is None or limits is None:
            return prediction
        kept = plausible(prediction, last, limits)
        self.implausible += kept != prediction
        return kept

    def clear(self) -> None:
        self._last = None

    def _limits_of(self, slot: ModelSlot) -> tuple[float, float] | None:
        """The largest plausible change per axis [m] for the slot's model (kept per model)."""
        metadata = slot.model.metadata
        if metadata is not self._metadata:
            self._metadata = metadata
            self._limits = plausible_limits(metadata)
        return self._limits


def plausible_limits(metadata: ModelMetadata) -> tuple[float, float] | None:
    """The largest plausible change of the error over the horizon per axis [m] for a model
    (`PLAUSIBLE_RANGES` times its training range); None for a file without the range."""
    low, high = (metadata.normalisation.get(key) for key in ('error_low', 'error_high'))
    if low is None or high is None:
        return None
    return PLAUSIBLE_RANGES * (high[0] - low[0]), PLAUSIBLE_RANGES * (high[1] - low[1])


def plausible(prediction: XY, last: XY, limits: tuple[float, float]) -> XY:
    """`prediction`, with persistence (`last`) on an axis where it changes by more than its
    limit: the one rule of the node's chain and of the offline replay."""
    x = prediction[0] if abs(prediction[0] - last[0]) <= limits[0] else last[0]
    y = prediction[1] if abs(prediction[1] - last[1]) <= limits[1] else last[1]
    return x, y
