# SPDX-License-Identifier: Apache-2.0
"""What the predictor core counted, as one snapshot, and its form on /diagnostics.

`OnlinePredictor.counts()` makes a `PredictorCounts` (`PredictorCounts.taken`); the
node's statuses write it as key-values (`status_counts`) and whoever reads those statuses
back, the cross-process closed loop, gets the same snapshot (`read_counts`): one pair of
functions, so a key renamed on one side cannot silently read as nothing on the other.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import RejectionCounter
from lompr_predictor.online.offset import OffsetGate
from lompr_predictor.online.timing import OverrunGuard

#: The statuses (their names after '<node>: ') the counts are written into.
INPUTS_STATUS = 'inputs'
PREDICTION_STATUS = 'prediction'
#: Key prefixes of the counts by reason.
DROPPED_PREFIX = 'rejected.'
FAULTS_PREFIX = 'faults.'
#: The plain counts of the prediction status: (`PredictorCounts` field, key).
PREDICTION_KEYS = (('predictions', 'predictions_total'), ('clamped', 'clamped_total'),
                   ('step_limited', 'step_limited_total'), ('zeros_published', 'zeros_published'),
                   ('reclamped', 'reclamped_total'),
                   ('inference_skipped_late', 'inference_skipped_late'),
                   ('late_outputs_dropped', 'late_outputs_dropped'),
                   ('outputs_in_time', 'outputs_in_time'),
                   ('outputs_after_instant', 'outputs_after_instant'))


class CountsMissingError(LomprError):
    """Statuses read back lack a count (`read_counts`)."""


@dataclass(frozen=True)
class PredictorCounts:
    """The core's counters since it was made."""

    dropped: Mapping[str, int]  # input samples not used, by `alignment.DropReason`
    faults: Mapping[str, int]  # windows emptied, by `faults.FaultReason`
    predictions: int  # finite predictions of any model
    clamped: int  # offsets clamped to max_compensation
    step_limited: int  # offsets limited to max_step
    zeros_published: int  # zero outputs of cancels
    reclamped: int  # offsets re-issued after max_compensation was lowered
    inference_skipped_late: int  # samples whose output would have been late: no inference
    late_outputs_dropped: int  # inferences that finished too late to publish
    #: Predictions published before their instant, and after it (within the tolerance),
    #: judged on the node's clock (`timing.OverrunGuard.lateness_ns`).
    outputs_in_time: int = 0
    outputs_after_instant: int = 0

    @classmethod
    def taken(cls, dropped: RejectionCounter, faults: RejectionCounter, predictions: int,
              gate: OffsetGate, overrun: OverrunGuard) -> PredictorCounts:
        """The snapshot of a core's counters: its inputs dropped and faults by reason, its
        predictions, its offset gate's and overrun policy's counts."""
        return cls(
            dropped={str(k): n for k, n in dropped.counts().items()},
            faults={str(k): n for k, n in faults.counts().items()},
            predictions=predictions, clamped=gate.clamped, step_limited=gate.step_limited,
            zeros_published=gate.zeros_published, reclamped=gate.reclamped,
            inference_skipped_late=overrun.inference_skipped_late,
            late_outputs_dropped=overrun.late_outputs_dropped,
            outputs_in_time=overrun.outputs_in_time,
            outputs_after_instant=overrun.outputs_after_instant)

    @property
    def overruns(self) -> int:
        """Outputs late or skipped."""
        return self.inference_skipped_late + self.late_outputs_dropped

    @property
    def in_time_share(self) -> float:
        """Of the instants a prediction was made or skipped for, the share whose offset was
        published before its instant (NaN before any)."""
        instants = self.outputs_in_time + self.outputs_after_instant + self.overruns
        return self.outputs_in_time / instants if instants else float('nan')


def status_counts(counts: PredictorCounts) -> dict[str, dict[str, object]]:
    """The key-values of `counts` by status name (`INPUTS_STATUS`, `PREDICTION_STATUS`);
    totals by reason are written for the reader's eye and not read back."""
    inputs: dict[str, object] = {'rejected_total': sum(counts.dropped.values())}
    inputs.update({f'{DROPPED_PREFIX}{reason}': n for reason, n in counts.dropped.items()})
    inputs['faults_total'] = sum(counts.faults.values())
    inputs.update({f'{FAULTS_PREFIX}{reason}': n for reason, n in counts.faults.items()})
    prediction: dict[str, object] = {key: getattr(counts, field)
                                     for field, key in PREDICTION_KEYS}
    return {INPUTS_STATUS: inputs, PREDICTION_STATUS: prediction}


def read_counts(statuses: Mapping[str, Mapping[str, str]]) -> PredictorCounts:
    """The counts `status_counts` wrote, from the statuses' key-values as /diagnostics
    carries them (strings), by status name; `CountsMissingError` naming what is missing."""
    inputs = _status(statuses, INPUTS_STATUS)
    prediction = _status(statuses, PREDICTION_STATUS)
    values: dict[str, int] = {}
    for field, key in PREDICTION_KEYS:
        if key not in prediction:
            msg = f'the predictor status {PREDICTION_STATUS!r} has no {key!r}'
            raise CountsMissingError(msg)
        values[field] = int(prediction[key])
    return PredictorCounts(dropped=_by_reason(inputs, DROPPED_PREFIX),
                           faults=_by_reason(inputs, FAULTS_PREFIX), **values)


def _status(statuses: Mapping[str, Mapping[str, str]], name: str) -> Mapping[str, str]:
    status = statuses.get(name)
    if status is None:
        msg = (f'no predictor status {name!r} was read (of {", ".join(statuses) or "none"}): '
               'the predictor never reported its counts')
        raise CountsMissingError(msg)
    return status


def _by_reason(values: Mapping[str, str], prefix: str) -> dict[str, int]:
    counts = {key[len(prefix):]: int(value) for key, value in values.items()
              if key.startswith(prefix)}
    if not counts:
        msg = f'no {prefix}<reason> counts in {", ".join(values)}'
        raise CountsMissingError(msg)
    return counts
