# SPDX-License-Identifier: Apache-2.0
"""The predictor node's /diagnostics statuses: the pure builders of
`online.predictor_status` fed with what the node hands over, and the counts since the last
report that their warnings are about.

The node hands its meters once (`PredictorMeters`) and, at each report, what it holds then
(`PredictorReadings`, from the callable it gives): the statuses never reach into the node,
and this module does not import it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from lompr_predictor.adaptation.driver import off_status
from lompr_predictor.monitoring import HeldEvent, RateMeter, Status
from lompr_predictor.online import predictor_status
from lompr_predictor.online.alignment import SENDER_ERRORS
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.predictor_counts import INPUTS_STATUS, PREDICTION_STATUS
from lompr_predictor.online.predictor_status import InputRates, Lifecycle, PredictionLimits
from lompr_predictor.online.preview import PreviewDrop
from lompr_predictor.ros.common import DiagnosticsPublisher
from lompr_predictor.ros.predictor_outputs import OutputPublisher
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings
from lompr_predictor.runtime.predictor_runtime import PredictorRuntime


@dataclass(frozen=True)
class PredictorMeters:
    """The node's rate meters and output publisher, made once with the node."""

    end_pose: RateMeter
    reference: RateMeter
    preview: RateMeter
    outputs: OutputPublisher  # its rate and input-to-output latency


@dataclass(frozen=True)
class PredictorReadings:
    """What the node holds at a report."""

    lifecycle: Lifecycle
    settings: PredictorNodeSettings
    runtime: PredictorRuntime  # its core, guard, store and adaptation: None unconfigured
    clock_values: dict[str, object]  # the node's clock and the input dropped while inactive
    callback_values: dict[str, object]  # callback failures
    clock_ns: int  # the node's clock now

    @property
    def core(self) -> OnlinePredictor | None:
        return self.runtime.core


class PredictorDiagnostics:
    """The statuses 'model', 'inputs', 'reference preview', 'prediction', 'guard',
    'sample store' and 'adaptation' of one predictor node, read from `read()` at each
    report, sent between two samples while they flow (once the outputs are out)."""

    def __init__(self, publisher: DiagnosticsPublisher, meters: PredictorMeters,
                 read: Callable[[], PredictorReadings]) -> None:
        self._meters = meters
        self._read = read
        self._faults_at_last_report = 0
        self._overruns_at_last_report = 0
        self._missing_at_last_report = 0
        self._sender_errors_at_last_report = 0
        self._refusal, self._write_failure = HeldEvent(), HeldEvent()
        publisher.add('model', self.model_status)
        publisher.add(INPUTS_STATUS, self.input_status)
        publisher.add('reference preview', self.preview_status)
        publisher.add(PREDICTION_STATUS, self.prediction_status)
        publisher.add('guard', self.guard_status)
        publisher.add('sample store', self.store_status)
        publisher.add('adaptation', self.adaptation_status)
        publisher.watch('adaptation', self._attempt_ended)
        meters.outputs.between_samples = publisher.between_samples
        self._publisher = publisher

    def problem_seen(self) -> None:
        """An input dropped, a fault, the clock gone back: the 'inputs' status goes with
        the next tick, out of its turn (`DiagnosticsPublisher.soon`)."""
        self._publisher.soon(INPUTS_STATUS)

    def _attempt_ended(self) -> bool:
        """Whether an adaptation attempt has ended (killed, or done) and is not yet told."""
        adaptation = self._read().runtime.adaptation
        return adaptation is not None and adaptation.adaptation.ended()

    def model_status(self) -> Status:
        now = self._read()
        history = now.runtime.models.history
        shown = self._refusal.shown(history.refusals if history.reload_error else None,
                                    now.clock_ns, now.settings.status_hold)
        return predictor_status.model_status(now.lifecycle, now.settings.model_path, now.core,
                                             history, refusal_shown=shown)

    def input_status(self) -> Status:
        now, meters = self._read(), self._meters
        new_faults = new_sender_errors = 0
        if now.core is not None:
            faults = now.core.faults.total
            new_faults, self._faults_at_last_report = (
                faults - self._faults_at_last_report, faults)
            sent_wrong = sum(n for reason, n in now.core.dropped.counts().items()
                             if reason in SENDER_ERRORS)
            new_sender_errors, self._sender_errors_at_last_report = (
                sent_wrong - self._sender_errors_at_last_report, sent_wrong)
        rates = InputRates(meters.end_pose, meters.reference, now.settings.end_pose_topic,
                           now.settings.rate_window, now.clock_values, now.callback_values)
        return predictor_status.input_status(now.lifecycle, now.core, rates, new_faults,
                                             new_sender_errors)

    def preview_status(self) -> Status:
        now = self._read()
        new_missing = 0
        if now.core is not None:
            missing = now.core.plan.dropped.counts().get(PreviewDrop.MISSING, 0)
            new_missing, self._missing_at_last_report = (
                missing - self._missing_at_last_report, missing)
        return predictor_status.preview_status(now.lifecycle, now.core, self._meters.preview,
                                               now.settings.reference_preview_topic,
                                               new_missing)

    def prediction_status(self) -> Status:
        now, outputs = self._read(), self._meters.outputs
        new_overruns = 0
        if now.core is not None:
            counts = now.core.counts()  # an offset after its instant is as late for its user
            overruns = counts.overruns + counts.outputs_after_instant
            new_overruns, self._overruns_at_last_report = (
                overruns - self._overruns_at_last_report, overruns)
        settings = now.settings
        limits = PredictionLimits(settings.compensation_enabled, settings.inference_time_warn,
                                  settings.accuracy_warn)
        return predictor_status.prediction_status(
            now.lifecycle, now.core, limits, outputs.latency.summary(), outputs.rate.rate(),
            new_overruns)

    def guard_status(self) -> Status:
        now = self._read()
        envelope = now.core is not None and bool(now.core.model.metadata.envelope)
        return predictor_status.guard_status(now.lifecycle, now.runtime.guard, envelope)

    def store_status(self) -> Status:
        now = self._read()
        store, export = now.runtime.store, now.runtime.export
        if store is None or export is None:
            return predictor_status.store_status(now.lifecycle, now.settings.kept_minutes,
                                                 None, None, failure_shown=False)
        export.poll()  # a write that has finished: its outcome
        state = export.state
        shown = self._write_failure.shown(state.failed if state.last_error else None,
                                          now.clock_ns, now.settings.status_hold)
        return predictor_status.store_status(now.lifecycle, now.settings.kept_minutes, store,
                                             export, failure_shown=shown)

    def adaptation_status(self) -> Status:
        now = self._read()
        adaptation = now.runtime.adaptation
        if adaptation is None:
            return off_status(now.settings.adaptation_enabled, now.lifecycle.state)
        # an attempt that ended meanwhile (killed, done) is said in this status, not a
        # timer tick later: as the store's status collects its write
        now.runtime.tick_adaptation(now.lifecycle.active)
        return adaptation.status(now.clock_ns, now.settings.status_hold)
