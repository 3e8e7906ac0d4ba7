# SPDX-License-Identifier: Apache-2.0
"""The plant error of each aligned sample, as the predictor core sees it (ROS-free).

The error a model predicts is the plant's (docs/interface.md, the error): the measured tool
tip minus the reference, minus the offset the controller applied at that instant, so that
compensating does not change what the model learns from. `PlantErrors` computes it for each
aligned sample and shows it, with the prediction published for that instant, to the core's
chain of sample units (`sample_units`), in stamp order. The interval between a sample and the
last one used is judged first (`faults.StreamRules`): a gap or an off-rate interval is a
fault the core handles before the sample starts its windows again.
"""

from __future__ import annotations

from collections.abc import Sequence

from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.faults import FaultReason, StreamRules
from lompr_predictor.online.offset import XY, ZERO, OffsetGate
from lompr_predictor.online.sample_units import SampleUnit


class PlantErrors:
    """The plant errors of the aligned samples, shown to `units` (module docstring); the
    offsets and predictions published come from `gate`."""

    def __init__(self, rules: StreamRules, gate: OffsetGate,
                 units: Sequence[SampleUnit]) -> None:
        self._rules = rules
        self._gate = gate
        #: The chain of sample units, in the order they see each sample.
        self.units = tuple(units)

    def interval_fault(self, previous_ns: int | None, stamp_ns: int) -> FaultReason | None:
        """The fault of the interval from the last used sample (None: there is none) to
        `stamp_ns`, None where the model was trained on such intervals."""
        if previous_ns is None:
            return None
        return self._rules.interval_fault(previous_ns, stamp_ns)

    def of(self, sample: AlignedSample) -> XY:
        """The sample's plant error [m], after showing it to the units; the offset and the
        prediction published for its instant are forgotten with every earlier one."""
        stamp_ns = sample.stamp_ns
        offset_x, offset_y = self._gate.offset_for(stamp_ns) or ZERO
        error = (sample.x - sample.reference_x - offset_x,
                 sample.y - sample.reference_y - offset_y)
        published = self._gate.prediction_for(stamp_ns)
        for unit in self.units:
            unit.observe(sample, error, published)
        return error

    def clear(self) -> None:
        """The windows were emptied: every unit starts a new stream."""
        for unit in self.units:
            unit.clear()
