# SPDX-License-Identifier: Apache-2.0
"""The trained envelope: the ranges of the inputs a model was trained on, carried in its
metadata, so that the predictor knows when a sample lies outside what training saw.

A learned model is trustworthy where its training data were; a program that moves faster,
accelerates harder or reaches poses the recordings never did makes it extrapolate. For each
feature column that describes the commanded motion and posture (every column but the plant
error, whose level drifts with the machine's temperature and is taken relative inside the
model), the envelope holds the training rows' range widened by `margin` of it on each side.
A row is inside when every such column is; the predictor counts the rows outside, names the
column that left it first, and the live guard (`online.guard`) holds the model back while
too many recent rows lie outside.

Cheap at the sample rate: `contains` compares one row's floats, a few dozen comparisons,
written out as one Python function per envelope (a comparison in bytecode costs a fraction
of a call to `operator.le` through `map`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Widening of each column's training range, as a fraction of the range, on each side:
#: recordings of the same program differ by a little (noise, feed override rounding), which
#: is no extrapolation.
ENVELOPE_MARGIN = 0.1


@dataclass(frozen=True)
class InputEnvelope:
    """Per checked feature column (`columns`, indices into the model's features, named
    `names`), the inclusive [low, high] of the inputs inside the envelope."""

    columns: tuple[int, ...]
    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    margin: float
    #: `contains`, written out for these columns and bounds (`_written_check`).
    _check: Callable[[Sequence[float]], bool] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, '_check', _written_check(self.columns, self.low, self.high))

    def contains(self, row: Sequence[float]) -> bool:
        """Whether every checked column of the feature row `row` lies in its range (a NaN
        does not): one function of chained comparisons, at the sample rate."""
        return self._check(row)

    def first_outside(self, row: Sequence[float]) -> str | None:
        """The name of the first checked column of `row` outside its range, None if none."""
        for name, column, low, high in zip(self.names, self.columns, self.low, self.high,
                                           strict=True):
            if not low <= row[column] <= high:
                return name
        return None

    def to_metadata(self) -> dict[str, Any]:
        """The model file's `envelope` entry: the ranges by feature name."""
        return {'margin': self.margin,
                'ranges': {name: [low, high]
                           for name, low, high in zip(self.names, self.low, self.high,
                                                      strict=True)}}

    @classmethod
    def from_metadata(cls, entry: Mapping[str, Any],
                      features: Sequence[str]) -> InputEnvelope | None:
        """The envelope a model file's metadata holds for its `features`; None for a file
        written without one (it still loads: the guard then compares live scores only)."""
        if not entry:
            return None
        names = list(features)
        ranges = entry['ranges']
        checked = [name for name in names if name in ranges]
        return cls(columns=tuple(names.index(name) for name in checked),
                   names=tuple(checked),
                   low=tuple(float(ranges[name][0]) for name in checked),
                   high=tuple(float(ranges[name][1]) for name in checked),
                   margin=float(entry.get('margin', 0.0)))


def _written_check(columns: Sequence[int], low: Sequence[float],
                   high: Sequence[float]) -> Callable[[Sequence[float]], bool]:
    """`low[i] <= row[columns[i]] <= high[i]` for every i, in order, as one compiled function
    (the bounds its globals, the columns integer literals): a NaN fails its comparisons."""
    bounds: dict[str, Any] = {'__builtins__': {}}
    tests = []
    for i, (column, lower, upper) in enumerate(zip(columns, low, high, strict=True)):
        bounds[f'low{i}'], bounds[f'high{i}'] = lower, upper
        tests.append(f'low{i} <= row[{int(column)}] <= high{i}')
    source = f'def check(row):\n    return {" and ".join(tests) or "True"}\n'
    # the text is ours: integer columns and names; the bounds enter as values, not text
    exec(compile(source, '<envelope>', 'exec'), bounds)
    check: Callable[[Sequence[float]], bool] = bounds['check']
    return check


def fit_envelope(rows: np.ndarray, features: Sequence[str],
                 margin: float = ENVELOPE_MARGIN) -> InputEnvelope:
    """The envelope of training feature rows (N, F) named `features`: every column but the
    plant error's, its finite values' range widened by `margin` of it on each side."""
    if margin < 0:
        msg = f'the envelope margin is a fraction >= 0 of each range, got {margin}'
        raise ValueError(msg)
    columns = [i for i, name in enumerate(features) if not name.startswith('error_')]
    values = np.asarray(rows, dtype=float)[:, columns]
    finite = np.isfinite(values).all(axis=1)
    if not finite.any():
        msg = 'no training row has every feature: the envelope has nothing to span'
        raise ValueError(msg)
    low, high = values[finite].min(axis=0), values[finite].max(axis=0)
    widen = margin * (high - low)
    return InputEnvelope(columns=tuple(columns), names=tuple(features[i] for i in columns),
                         low=tuple((low - widen).tolist()), high=tuple((high + widen).tolist()),
                         margin=margin)


def joined_envelope(envelope: InputEnvelope, earlier: InputEnvelope | None) -> InputEnvelope:
    """`envelope` taking in an `earlier` one of the same features (None: none), column by
    column the wider bounds: a model fine-tuned on new rows was trained on both."""
    if earlier is None:
        return envelope
    before = dict(zip(earlier.names, zip(earlier.low, earlier.high, strict=True), strict=True))
    low = [min(value, before.get(name, (value, value))[0])
           for name, value in zip(envelope.names, envelope.low, strict=True)]
    high = [max(value, before.get(name, (value, value))[1])
            for name, value in zip(envelope.names, envelope.high, strict=True)]
    return InputEnvelope(columns=envelope.columns, names=envelope.names, low=tuple(low),
                         high=tuple(high), margin=envelope.margin)
