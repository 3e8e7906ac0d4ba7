# SPDX-License-Identifier: Apache-2.0
"""online.predictor_counts: the core's counts written as /diagnostics key-values and read
back from their strings as the same snapshot; a missing status or count named; the share in
time against a hand count."""

from __future__ import annotations

import math

import pytest

from lompr_predictor.monitoring import RejectionCounter
from lompr_predictor.online.offset import CompensationLimits, OffsetGate
from lompr_predictor.online.predictor_counts import (
    INPUTS_STATUS,
    PREDICTION_STATUS,
    CountsMissingError,
    PredictorCounts,
    read_counts,
    status_counts,
)
from lompr_predictor.online.timing import OverrunGuard

COUNTS = PredictorCounts(
    dropped={'non_finite': 3, 'out_of_order': 0}, faults={'gap': 2, 'stale': 1},
    predictions=100, clamped=4, step_limited=5, zeros_published=6, reclamped=7,
    inference_skipped_late=2, late_outputs_dropped=1, outputs_in_time=90,
    outputs_after_instant=7)


def as_diagnostics(values: dict[str, dict[str, object]]) -> dict[str, dict[str, str]]:
    """Key-values as a DiagnosticStatus carries them: strings."""
    return {name: {key: str(value) for key, value in status.items()}
            for name, status in values.items()}


def test_the_counts_read_back_are_the_counts_written() -> None:
    written = status_counts(COUNTS)
    assert written[INPUTS_STATUS]['rejected_total'] == 3
    assert written[INPUTS_STATUS]['faults_total'] == 3
    assert written[INPUTS_STATUS]['rejected.non_finite'] == 3
    assert written[PREDICTION_STATUS]['late_outputs_dropped'] == 1
    assert read_counts(as_diagnostics(written)) == COUNTS
    assert COUNTS.overruns == 3
    assert COUNTS.in_time_share == pytest.approx(90 / 100, abs=1e-15)
    nothing = PredictorCounts({}, {}, 0, 0, 0, 0, 0, 0, 0)
    assert math.isnan(nothing.in_time_share)


def test_a_missing_status_or_count_is_named() -> None:
    written = as_diagnostics(status_counts(COUNTS))
    with pytest.raises(CountsMissingError, match=r"^no predictor status 'prediction' was "
                                                 r"read \(of inputs\)"):
        read_counts({INPUTS_STATUS: written[INPUTS_STATUS]})
    del written[PREDICTION_STATUS]['outputs_in_time']
    with pytest.raises(CountsMissingError, match="has no 'outputs_in_time'"):
        read_counts(written)
    with pytest.raises(CountsMissingError, match=r'^no rejected\.<reason> counts in '):
        read_counts({INPUTS_STATUS: {'faults.gap': '1'},
                     PREDICTION_STATUS: as_diagnostics(status_counts(COUNTS))[
                         PREDICTION_STATUS]})


def test_a_snapshot_takes_each_count_from_where_the_core_keeps_it() -> None:
    """`PredictorCounts.taken`: the reasons as strings, every count from its owner."""
    dropped, faults = RejectionCounter(('non_finite', 'gap')), RejectionCounter(('stale',))
    dropped.add('non_finite', 3)
    faults.add('stale')
    gate = OffsetGate(CompensationLimits(1e-3, 1e-4, True), 4_000_000)
    gate.clamped, gate.step_limited, gate.zeros_published, gate.reclamped = 4, 5, 6, 7
    overrun = OverrunGuard(4_000_000, 1_000_000)
    overrun.inference_skipped_late, overrun.late_outputs_dropped = 2, 1
    overrun.outputs_in_time, overrun.outputs_after_instant = 90, 7
    taken = PredictorCounts.taken(dropped, faults, 100, gate, overrun)
    assert taken == PredictorCounts(
        dropped={'non_finite': 3, 'gap': 0}, faults={'stale': 1}, predictions=100, clamped=4,
        step_limited=5, zeros_published=6, reclamped=7, inference_skipped_late=2,
        late_outputs_dropped=1, outputs_in_time=90, outputs_after_instant=7)
