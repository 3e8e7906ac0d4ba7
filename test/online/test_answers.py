# SPDX-License-Identifier: Apache-2.0
"""online.answers: a prediction revised by the units, in time or dropped as late, through
the offset gate; a sample not worth an inference skipped; every instant without an output
the gate's missed one."""

from __future__ import annotations

from typing import Any

from lompr_predictor.online.answers import Answers
from lompr_predictor.online.offset import XY, CompensationLimits, OffsetGate, Output
from lompr_predictor.online.timing import OverrunGuard

PERIOD, LEAD, TOLERANCE = 40_000_000, 80_000_000, 5_000_000
SLOT: Any = None  # the units here read no slot


class Halve:
    """A unit that halves every prediction, or withholds it."""

    def __init__(self, withhold: bool = False) -> None:
        self.withhold = withhold

    def observe(self, *args: Any) -> None: ...

    def revise(self, instant_ns: int, prediction: XY, slot: Any) -> XY | None:
        del instant_ns, slot
        return None if self.withhold else (prediction[0] / 2, prediction[1] / 2)

    def clear(self) -> None: ...


def answers(clock: list[int], unit: Halve) -> tuple[Answers, OverrunGuard]:
    gate = OffsetGate(CompensationLimits(1e-3, 1e-3, True), PERIOD)
    overrun = OverrunGuard(LEAD, TOLERANCE)
    return Answers([unit], gate, overrun, LEAD, lambda: clock[0]), overrun


def test_a_prediction_in_time_is_revised_and_scheduled_for_its_instant() -> None:
    clock = [10**9 + 1_000_000]  # the sample arrived 1 ms after its stamp
    step, overrun = answers(clock, Halve())
    overrun.arrival(10**9, clock[0])
    assert step.worth_inferring(10**9, clock[0])
    outputs: list[Output] = []
    clock[0] += 2_000_000  # a 2 ms inference
    assert step.publish(10**9, (4e-6, -2e-6), SLOT, clock[0] - 2_000_000, outputs) == clock[0]
    assert len(outputs) == 1 and outputs[0].instant_ns == 10**9 + LEAD
    assert outputs[0].compensation == (-2e-6, 1e-6)  # halved by the unit, then negated
    assert overrun.late_outputs_dropped == 0
    assert (overrun.outputs_in_time, overrun.outputs_after_instant) == (1, 0)


def test_an_output_after_its_instant_but_within_the_tolerance_is_counted_so() -> None:
    clock = [10**9]
    step, overrun = answers(clock, Halve())
    overrun.arrival(10**9, clock[0])
    outputs: list[Output] = []
    clock[0] += LEAD + TOLERANCE // 2  # after the instant, within the tolerance
    step.publish(10**9, (4e-6, 0.0), SLOT, 10**9, outputs)
    assert len(outputs) == 1
    assert (overrun.outputs_in_time, overrun.outputs_after_instant) == (0, 1)


def test_a_late_output_is_dropped_and_a_withheld_one_is_missed() -> None:
    clock = [10**9]
    step, overrun = answers(clock, Halve())
    overrun.arrival(10**9, clock[0])
    outputs: list[Output] = []
    clock[0] += LEAD + TOLERANCE + 1  # the inference ended after the instant + tolerance
    step.publish(10**9, (4e-6, 0.0), SLOT, 10**9, outputs)
    assert outputs == [] and overrun.late_outputs_dropped == 1
    # the next sample: an inference as long as that one would finish late too
    overrun.arrival(10**9 + PERIOD, clock[0])
    assert not step.worth_inferring(10**9 + PERIOD, clock[0] + TOLERANCE + 1)
    assert overrun.inference_skipped_late == 1
    withheld, _ = answers([10**9], Halve(withhold=True))
    withheld.publish(10**9, (4e-6, 0.0), SLOT, 10**9, outputs)
    assert outputs == []
