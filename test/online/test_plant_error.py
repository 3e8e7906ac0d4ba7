# SPDX-License-Identifier: Apache-2.0
"""The plant error of an aligned sample: measured - reference - the offset applied at its
instant, shown to the units with the prediction published for it; the interval rules."""

from __future__ import annotations

import pytest
from test_predictor import PERIOD_NS, limits, stream

from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.faults import FaultReason, StreamRules
from lompr_predictor.online.offset import XY, OffsetGate
from lompr_predictor.online.plant_error import PlantErrors


class Recorder:
    """A sample unit that writes down what it is shown and how often it was cleared."""

    def __init__(self) -> None:
        self.seen: list[tuple[int, XY, XY | None]] = []
        self.cleared = 0

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        self.seen.append((sample.stamp_ns, error, published))

    def revise(self, instant_ns: int, prediction: XY, slot: object) -> XY | None:
        del instant_ns, slot
        return prediction

    def clear(self) -> None:
        self.cleared += 1


def sample(stamp_ns: int, x: float, y: float) -> AlignedSample:
    return AlignedSample(stamp_ns, x, y, reference_x=0.25, reference_y=-0.5, reference_z=1.0)


def test_the_error_is_measured_minus_reference_minus_the_offset_of_its_instant() -> None:
    """An offset published for the second instant (the prediction 2 / -1 um, bounded to
    its opposite) is taken off that sample's error alone, and the units see that
    prediction with it; before and after, no offset and no prediction."""
    gate = OffsetGate(limits(), PERIOD_NS)
    first, second = Recorder(), Recorder()
    errors = PlantErrors(StreamRules(stream(), PERIOD_NS), gate, (first, second))
    gate.publish(2 * PERIOD_NS, (2e-6, -1e-6), PERIOD_NS)
    got = [errors.of(sample(k * PERIOD_NS, 0.25 + 3e-6, -0.5 + 4e-6)) for k in (1, 2, 3)]
    assert got[0] == pytest.approx((3e-6, 4e-6), abs=1e-15)
    assert got[1] == pytest.approx((3e-6 + 2e-6, 4e-6 - 1e-6), abs=1e-15)
    assert got[2] == pytest.approx((3e-6, 4e-6), abs=1e-15)
    assert [published for _, _, published in first.seen] == [None, (2e-6, -1e-6), None]
    assert first.seen == second.seen and [stamp for stamp, _, _ in first.seen] == [
        PERIOD_NS, 2 * PERIOD_NS, 3 * PERIOD_NS]
    errors.clear()
    assert first.cleared == second.cleared == 1


def test_the_interval_from_the_last_used_sample_is_judged() -> None:
    """Gap factor 2.5, minimum interval 0.5 periods: 3 periods is a gap, 0.4 off-rate, 1 and
    2.5 fine, and the first sample (none before it) is fine."""
    errors = PlantErrors(StreamRules(stream(), PERIOD_NS), OffsetGate(limits(), PERIOD_NS), ())
    assert errors.interval_fault(None, 5 * PERIOD_NS) is None
    assert errors.interval_fault(0, 3 * PERIOD_NS) is FaultReason.GAP
    assert errors.interval_fault(0, 2 * PERIOD_NS // 5) is FaultReason.OFF_RATE
    assert errors.interval_fault(0, PERIOD_NS) is None
    assert errors.interval_fault(0, 5 * PERIOD_NS // 2) is None
