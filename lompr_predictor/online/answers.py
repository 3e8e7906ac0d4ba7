# SPDX-License-Identifier: Apache-2.0
"""An instant's answer (ROS-free): whether a sample is worth an inference, and what of a
prediction is published: the chain's revision, then in time or dropped as late, then the
offset gate.

The predictor core (`predictor.OnlinePredictor`) asks `worth_inferring` before the network
runs (an inference that could only finish late is skipped: `timing.OverrunGuard.skip`) and
hands the prediction to `publish`, which lets the units revise it (`sample_units`: the live
guard, the plausibility check; a unit may withhold it), reads the clock again to judge the
output's lateness on the time the inference took (`OverrunGuard.late`) and puts what is left
through the offset gate (`offset.OffsetGate`: bounds, step limit, schedule by instant). An
instant that gets no output is the gate's missed one, so the offset in force ends in time.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from lompr_predictor.online.model_slot import ModelSlot
from lompr_predictor.online.offset import XY, OffsetGate, Output
from lompr_predictor.online.sample_units import SampleUnit
from lompr_predictor.online.timing import OverrunGuard


class Answers:
    """The answer step of one core (module docstring); predictions `lead_ns` ahead of the
    sample their window ends at, lateness on `clock` (integer nanoseconds)."""

    def __init__(self, units: Sequence[SampleUnit], gate: OffsetGate, overrun: OverrunGuard,
                 lead_ns: int, clock: Callable[[], int]) -> None:
        self._units, self._gate, self._overrun = tuple(units), gate, overrun
        self._lead_ns, self._clock = lead_ns, clock

    def worth_inferring(self, stamp_ns: int, now_ns: int) -> bool:
        """Whether the sample is worth an inference at the clock's reading `now_ns`; an
        instant skipped gets no offset."""
        overrun = self._overrun
        if not overrun.skip(stamp_ns, now_ns):
            return True
        overrun.inference_skipped_late += 1
        self._gate.missed()
        return False

    def publish(self, stamp_ns: int, prediction: XY, slot: ModelSlot, started_ns: int,
                outputs: list[Output]) -> int:
        """Append the output of a prediction from the window that ends at `stamp_ns`
        (its inference started at `started_ns`), as the units revise it, unless it comes too
        late; the clock's new reading."""
        instant_ns = stamp_ns + self._lead_ns
        kept: XY | None = prediction
        for unit in self._units:
            kept = unit.revise(instant_ns, prediction, slot)
            if kept is None:
                break
            prediction = kept
        overrun, gate = self._overrun, self._gate
        ended = self._clock()
        overrun.inference_took(started_ns, ended)
        lateness = overrun.lateness_ns(stamp_ns, ended)
        if kept is None:
            gate.missed()
        elif lateness > overrun.tolerance_ns:
            overrun.late_outputs_dropped += 1
            gate.missed()
        else:
            outputs.append(gate.publish(instant_ns, prediction, stamp_ns))
            if lateness <= 0:
                overrun.outputs_in_time += 1
            else:
                overrun.outputs_after_instant += 1
        return ended
