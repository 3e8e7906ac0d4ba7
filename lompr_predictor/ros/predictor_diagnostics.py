"""The predictor node's /diagnostics statuses: the pure builders of
`online.predictor_status` fed with what the node holds, and the counts since the last
report that their warnings are about."""

from __future__ import annotations

from typing import TYPE_CHECKING

from lompr_predictor.monitoring import Status
from lompr_predictor.online import predictor_status
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.predictor_status import InputRates, Lifecycle, PredictionLimits
from lompr_predictor.online.preview import PreviewDrop

if TYPE_CHECKING:
    from lompr_predictor.ros.common import DiagnosticsPublisher
    from lompr_predictor.ros.predictor_node import PredictorNode


def _core_of(node: PredictorNode) -> OnlinePredictor | None:
    return node.core if node.configured else None


class PredictorDiagnostics:
    """The statuses 'model', 'inputs', 'reference preview' and 'prediction' of one
    predictor node."""

    def __init__(self, node: PredictorNode, publisher: DiagnosticsPublisher) -> None:
        self._node = node
        self._faults_at_last_report = 0
        self._overruns_at_last_report = 0
        self._missing_at_last_report = 0
        publisher.add('model', self.model_status)
        publisher.add('inputs', self.input_status)
        publisher.add('reference preview', self.preview_status)
        publisher.add('prediction', self.prediction_status)

    def _lifecycle(self) -> Lifecycle:
        node = self._node
        return Lifecycle(node.lifecycle_state, node.settings.autostart, node.configure_error)

    def model_status(self) -> Status:
        node = self._node
        return predictor_status.model_status(self._lifecycle(), node.settings.model_path,
                                             _core_of(node), node.history)

    def input_status(self) -> Status:
        node = self._node
        core = _core_of(node)
        new_faults = 0
        if core is not None:
            new_faults = core.faults.total - self._faults_at_last_report
            self._faults_at_last_report = core.faults.total
        clock_values: dict[str, object] = {
            'use_sim_time': bool(node.get_parameter('use_sim_time').value),
            'clock_s': round(node.clock_seconds(), 6),
            'clock_jumps_back': node.clock_jumps_back,
            'dropped_inactive': node.dropped_inactive}
        rates = InputRates(node.pose_rate, node.reference_rate, node.settings.end_pose_topic,
                           node.settings.rate_window, clock_values, node.callback_values())
        return predictor_status.input_status(self._lifecycle(), core, rates, new_faults)

    def preview_status(self) -> Status:
        node = self._node
        core = _core_of(node)
        new_missing = 0
        if core is not None:
            missing = core.plan.dropped.counts().get(PreviewDrop.MISSING, 0)
            new_missing, self._missing_at_last_report = (
                missing - self._missing_at_last_report, missing)
        return predictor_status.preview_status(self._lifecycle(), core, node.preview_rate,
                                               node.settings.reference_preview_topic,
                                               new_missing)

    def prediction_status(self) -> Status:
        node = self._node
        core = _core_of(node)
        new_overruns = 0
        if core is not None:
            overruns = predictor_status.overruns(core)
            new_overruns, self._overruns_at_last_report = (
                overruns - self._overruns_at_last_report, overruns)
        settings, outputs = node.settings, node.outputs
        limits = PredictionLimits(settings.compensation_enabled, settings.inference_time_warn,
                                  settings.accuracy_warn)
        return predictor_status.prediction_status(
            self._lifecycle(), core, limits, outputs.latency.summary(), outputs.rate.rate(),
            new_overruns)
