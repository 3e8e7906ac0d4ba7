"""predictor_node: end poses + reference -> predicted error and a bounded compensation offset.

A thin node around `online.OnlinePredictor` (alignment by stamp, plant error, rolling window,
model, safety): it turns /lompr/end_pose and /lompr/reference into calls, publishes every
`Output` on /lompr/predicted_error and /lompr/compensation (Vector3Stamped, z = 0, stamped
with the instant they are for: pose stamp + horizon * sample_period), checks staleness on a
timer and reports on /diagnostics.

Model handling: the model file is loaded, checked against this node's configuration
(features, window, horizon, sample period, sha256 of its robot description) and warmed up
at start; a mismatch stops the node with one message naming the field. Setting
`model_path` at run time loads, checks and warms the new file inside the parameter
validation callback, beside the running model: a bad file rejects the parameter change
(the reason goes back to the caller and to /diagnostics) and the old model keeps running; a
good one is swapped in by the post-set callback, between two samples, keeping the window.
While the new file loads the executor waits; messages queue in the subscriptions (depth 100
by default, `qos_overrides.<topic>.subscription.depth`), so none is lost as long as loading
takes under depth / rate.

A plain node, not a lifecycle one: the model is all it configures, and a node that cannot
load it should not exist (the error message says why); deactivating is
`compensation_enabled: false` (shadow mode), which keeps the predictions going.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.context import Context
from rclpy.node import Node

from lompr_predictor.data.cleaning import GAP_FACTOR
from lompr_predictor.data.features import FEATURES
from lompr_predictor.learning.model_file import (
    VERIFIED_BY,
    LoadedModel,
    ModelFileError,
    check_sample_period,
    check_sha256_text,
    load_model,
)
from lompr_predictor.monitoring import (
    LatencyRecorder,
    Level,
    RateMeter,
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.online.faults import FAULT_REASONS, StreamSettings
from lompr_predictor.online.offset import CompensationLimits, Output
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.robot.description import WORLD_FRAME, load_robot_description
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import (
    OUTPUT_QOS,
    SENSOR_INPUT_QOS,
    Endpoint,
    NodeBase,
    node_help,
)
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.stamps import set_stamp
from lompr_predictor.threads import set_torch_threads

NODE_NAME = 'predictor_node'


@dataclass(frozen=True)
class PredictorNodeSettings:
    """The node's parameters: one field each, declared by `NodeBase.declare_settings`."""

    model_path: str = parameter(
        '', 'TorchScript model file (lompr train); setting it at run time loads, checks and '
        'warms the new file and swaps it in, or keeps the running model and rejects the '
        'change with the reason')
    model_sha256: str = parameter(
        '', 'if not empty, the sha256 the model file must have (the training report\'s '
        'model_sha256), checked on the bytes read before they are deserialised (a '
        'TorchScript file is code); takes precedence over the MODEL.sha256 file beside it',
        check=check_sha256_text)
    verify_model_hash: bool = parameter(
        True, 'refuse a model file whose bytes do not match model_sha256 or, if that is '
        'empty, the MODEL.sha256 file lompr train writes beside it; false (development '
        'only): load an unverified file', read_only=True)
    compensation_enabled: bool = parameter(
        True, 'publish the offset; false: shadow mode, predictions go on and every offset is '
        'zero')
    max_compensation: float = parameter(
        5e-4, 'largest offset [m] (XY norm); the offset is clamped to it', minimum=0.0,
        maximum=0.01)
    max_compensation_step: float = parameter(
        5e-5, 'largest change of the offset [m] (XY norm) from one sample to the next',
        minimum=0.0, maximum=0.01)
    robot_description_file: str = parameter(
        '', 'URDF the model must have been trained for (its sha256 is checked); empty: the '
        'packaged nominal LOMPR description', read_only=True)
    sample_period: float = parameter(
        0.0, 'period [s] of the pose stamps, which the model must have been trained at '
        "(within 2 %); 0: the model file's", minimum=0.0, maximum=10.0, read_only=True)
    window: int = parameter(
        -1, "window length the model must have; -1: the model file's (a model swapped in at "
        "run time must keep the running one's)", minimum=-1, maximum=100_000, read_only=True)
    horizon: int = parameter(
        -1, "horizon [samples] the model must have (the controller's lead); -1: the model "
        "file's", minimum=-1, maximum=100_000, read_only=True)
    gap_factor: float = parameter(
        GAP_FACTOR, 'a stamp interval above this many sample periods is a gap (the trainer '
        'splits its data at the same one)', minimum=1.0, maximum=1000.0, read_only=True)
    min_interval_factor: float = parameter(
        0.5, "a stamp interval below this many sample periods means the input is not at the "
        "model's rate", minimum=0.0, maximum=1.0, read_only=True)
    stale_periods: float = parameter(
        5.0, 'no usable sample for this many sample periods: the input is stale and the '
        'offset is cancelled', minimum=1.0, maximum=1_000_000.0, read_only=True)
    stale_min_time: float = parameter(
        0.05, 'the input is stale only after at least this many seconds without a usable '
        'sample, whatever the rate: a process on a general-purpose OS stalls for '
        'milliseconds, many periods at kHz rates', minimum=0.0, maximum=3600.0,
        read_only=True)
    end_pose_topic: str = parameter('/lompr/end_pose', 'PoseStamped measured tool tip input',
                                    read_only=True)
    reference_topic: str = parameter('/lompr/reference', 'PoseStamped reference input',
                                     read_only=True)
    predicted_error_topic: str = parameter(
        '/lompr/predicted_error', 'Vector3Stamped predicted X/Y error output', read_only=True)
    compensation_topic: str = parameter(
        '/lompr/compensation', 'Vector3Stamped compensation offset output', read_only=True)
    diagnostics_topic: str = parameter('/diagnostics', 'DiagnosticArray topic', read_only=True)
    frame_id: str = parameter(WORLD_FRAME, 'header.frame_id of the outputs', read_only=True)
    inference_threads: int = parameter(
        1, "torch threads, set by the executable's main() (process-wide); 1 keeps inference "
        'from contending with the executor', minimum=1, maximum=256, read_only=True)
    diagnostics_period: float = parameter(1.0, 'seconds between /diagnostics messages',
                                          minimum=0.05, maximum=60.0, read_only=True)
    rate_window: float = parameter(5.0, 'seconds over which input/output rates are averaged',
                                   minimum=0.1, maximum=600.0, read_only=True)
    latency_samples: int = parameter(1000, 'last latencies kept for the p50/p99',
                                     minimum=10, maximum=1_000_000, read_only=True)
    accuracy_samples: int = parameter(1000, 'last predicted instants the live RMS is over',
                                      minimum=1, maximum=10_000_000, read_only=True)
    inference_time_warn: float = parameter(
        0.001, 'p99 inference time [s] above which the prediction status is WARN',
        minimum=1e-6, maximum=10.0)
    accuracy_warn: float = parameter(
        0.0, 'live RMS prediction error [m] (either axis) above which the prediction status '
        'is WARN (the machine has drifted from the model); 0: no such warning', minimum=0.0,
        maximum=1.0)
    warning_throttle_period: float = parameter(
        5.0, 'seconds between two warnings of the same kind', minimum=0.0, maximum=3600.0)
    max_future_stamp: float = parameter(
        1.0, "an input stamped more than this many seconds ahead of the node's clock is "
        'dropped (not checked while the clock reads 0: sim time before the first /clock)',
        minimum=0.0, maximum=1e9, read_only=True)
    late_tolerance: float = parameter(
        0.005, 'seconds an output may come after the instant it is for (judged on the '
        "node's clock against the best-case input delay) before it is dropped as late; a "
        'sample whose inference could only finish late gets none', minimum=0.0,
        maximum=3600.0, read_only=True)

    @property
    def limits(self) -> CompensationLimits:
        return CompensationLimits(self.max_compensation, self.max_compensation_step,
                                  self.compensation_enabled)


END_POSE = Endpoint('subscription', PoseStamped, 'end_pose_topic', SENSOR_INPUT_QOS,
                    'end pose')
REFERENCE = Endpoint('subscription', PoseStamped, 'reference_topic', SENSOR_INPUT_QOS,
                     'reference')
PREDICTED_ERROR = Endpoint('publisher', Vector3Stamped, 'predicted_error_topic', OUTPUT_QOS,
                           'predicted error')
COMPENSATION = Endpoint('publisher', Vector3Stamped, 'compensation_topic', OUTPUT_QOS,
                        'compensation')
ENDPOINTS = (END_POSE, REFERENCE, PREDICTED_ERROR, COMPENSATION)


class PredictorNode(NodeBase[PredictorNodeSettings], Node):
    """The predictor node (module docstring). Extra keyword arguments go to
    `rclpy.node.Node` (`context`, `parameter_overrides`, ...)."""

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(PredictorNodeSettings)
        self.description = load_robot_description(settings.robot_description_file or None)
        if not settings.model_path:
            msg = 'parameter model_path is empty: give the model file (lompr train --out)'
            raise ModelFileError(msg)
        expected: dict[str, Any] = {
            'features': FEATURES, 'robot_description_sha256': self.description.sha256}
        for name in ('window', 'horizon'):
            if getattr(settings, name) >= 0:
                expected[name] = getattr(settings, name)
        model = self._load(settings.model_path, expected, settings.model_sha256)
        #: The stamps' period: the parameter if set, else the model's; later models must fit it.
        self.sample_period = settings.sample_period or model.metadata.sample_period
        check_sample_period(model.metadata, self.sample_period, settings.model_path)
        # A model swapped in later must fit the running window and the controller's lead.
        self._expected = {**expected, 'window': model.metadata.window,
                          'horizon': model.metadata.horizon}
        self.core = OnlinePredictor(
            model,
            StreamSettings(self.sample_period, settings.gap_factor,
                           settings.min_interval_factor, settings.stale_periods,
                           settings.accuracy_samples, settings.stale_min_time,
                           settings.max_future_stamp, settings.late_tolerance),
            settings.limits, latency_samples=settings.latency_samples, now_ns=self.clock_ns)
        self._candidate: LoadedModel | None = None
        self.model_swaps = 0
        self.reload_error = ''

        self.pose_rate = RateMeter(settings.rate_window)
        self.reference_rate = RateMeter(settings.rate_window)
        self.output_rate = RateMeter(settings.rate_window)
        self.input_to_output = LatencyRecorder(settings.latency_samples)
        self._faults_at_last_report = 0
        self._overruns_at_last_report = 0

        self._prediction_publisher = self.advertise(PREDICTED_ERROR)
        self._compensation_publisher = self.advertise(COMPENSATION)
        self._pose_subscription = self.subscribe(END_POSE, self.on_end_pose)
        self._reference_subscription = self.subscribe(REFERENCE, self.on_reference)
        stale_after = self.core.stream.stale_after
        self._stale_timer = self.start_timer(min(max(stale_after / 4, 0.005), 0.5),
                                             'staleness check', self.on_stale_timer)
        self._diagnostics = self.start_diagnostics(
            settings.diagnostics_topic, settings.diagnostics_period,
            hardware_id=f'urdf sha256 {self.description.sha256[:16]}')
        self._diagnostics.add('model', self.model_status)
        self._diagnostics.add('inputs', self.input_status)
        self._diagnostics.add('prediction', self.prediction_status)
        metadata = model.metadata
        self.get_logger().info(
            f'{metadata.model_type} model {model.path} (sha256 {model.sha256[:16]}, window '
            f'{metadata.window}, horizon {metadata.horizon} x {metadata.sample_period:g} s); '
            f'compensation {"on" if settings.compensation_enabled else "off (shadow)"}')

    # -- callbacks (run through NodeBase.guard: a failure aborts the core) -----------------

    def on_end_pose(self, msg: PoseStamped) -> None:
        start = time.perf_counter()
        self.pose_rate.tick()
        position = msg.pose.position
        self._publish(self.core.add_pose(msg.header.stamp, position.x, position.y), start)

    def on_reference(self, msg: PoseStamped) -> None:
        start = time.perf_counter()
        self.reference_rate.tick()
        position = msg.pose.position
        self._publish(self.core.add_reference(msg.header.stamp, position.x, position.y),
                      start)

    def on_stale_timer(self) -> None:
        self._publish(self.core.check_stale(), time.perf_counter())

    def on_callback_failure(self, where: str) -> None:
        """Empty the window and cancel the offset in force: nothing half-done is published."""
        del where
        self._publish(self.core.abort('internal'), time.perf_counter())

    def _publish(self, outputs: list[Output], start: float) -> None:
        for output in outputs:
            if output.prediction is not None:
                self._prediction_publisher.publish(
                    self._vector(output.instant_ns, output.prediction))
            self._compensation_publisher.publish(
                self._vector(output.instant_ns, output.compensation))
            if output.reason in FAULT_REASONS:
                self.warn_throttled(output.reason, f'offset set to zero ({output.reason}); '
                                    'output resumes once the window has refilled with good '
                                    'samples')
            elif not output.reason:
                self.input_to_output.record(time.perf_counter() - start)
                self.output_rate.tick()

    def _vector(self, stamp_ns: int, xy: np.ndarray) -> Vector3Stamped:
        msg = Vector3Stamped()
        set_stamp(msg.header.stamp, stamp_ns)
        msg.header.frame_id = self.settings.frame_id
        msg.vector.x, msg.vector.y = float(xy[0]), float(xy[1])
        return msg

    def _load(self, path: str, expected: dict[str, Any], pin: str) -> LoadedModel:
        """`load_model` with this node's hash policy (pin, else the sidecar, unless
        verify_model_hash is false)."""
        return load_model(path, expected=expected, sha256=pin or None,
                          verify=self.settings.verify_model_hash,
                          hint='predictor_node: -p model_sha256:=<sha256>, or for development '
                               'only -p verify_model_hash:=false')

    # -- parameters (NodeBase hooks) -------------------------------------------------------

    def validate_settings(self, changes: dict[str, Any]) -> str:
        """Load, check and warm a new model beside the running one; refuse a bad one."""
        self._candidate = None
        running = self.core.model
        if 'model_path' not in changes:
            sha = changes.get('model_sha256')
            if sha and sha.lower() != running.sha256:
                return (f'the running model {running.path} has sha256 {running.sha256}, not '
                        f'{sha}; set model_path with it')
            return ''
        path = changes['model_path']
        sha = changes.get('model_sha256', self.settings.model_sha256)
        try:
            candidate = self._load(path, self._expected, sha)
            check_sample_period(candidate.metadata, self.sample_period, path)
        except Exception as err:  # noqa: BLE001 - a model file is code: any failure refuses it
            detail = str(err) if isinstance(err, ModelFileError) else (
                f'model {path}: {type(err).__name__}: {err}')
            self.reload_error = f'{detail}; still running {running.path}'
            self.get_logger().error(f'model not swapped: {self.reload_error}')
            return self.reload_error
        self._candidate = candidate
        return ''

    def apply_settings(self, previous: PredictorNodeSettings, changed: frozenset[str]) -> None:
        """Take accepted changes: new limits, and the model validated in
        `validate_settings`."""
        del previous
        self._publish(self.core.set_limits(self.settings.limits), time.perf_counter())
        if 'model_path' in changed and self._candidate is not None:
            self.core.replace_model(self._candidate)
            self._candidate = None
            self.model_swaps += 1
            self.reload_error = ''
            self.get_logger().info(f'model swapped: now {self.core.model.path} '
                                   f'(sha256 {self.core.model.sha256[:16]})')

    # -- diagnostics ------------------------------------------------------------------------

    def model_status(self) -> Status:
        model = self.core.model
        metadata = model.metadata
        values: dict[str, object] = {
            'path': model.path, 'sha256': model.sha256, 'sha256_verified_by': model.verified_by,
            'type': metadata.model_type,
            'window': metadata.window, 'horizon': metadata.horizon,
            'sample_period_s': metadata.sample_period, 'swaps': self.model_swaps,
            'robot_description_sha256': metadata.robot_description_sha256,
        }
        if self.reload_error:
            return Status(Level.WARN, f'last reload refused: {self.reload_error}', values)
        if model.verified_by == VERIFIED_BY[2]:
            return Status(Level.WARN, f'{metadata.model_type} {model.sha256[:12]} NOT verified '
                                      '(verify_model_hash is false)', values)
        return Status(Level.OK, f'{metadata.model_type} {model.sha256[:12]}, horizon '
                                f'{metadata.horizon}', values)

    def input_status(self) -> Status:
        core = self.core
        faults = core.faults.total
        new_faults = faults - self._faults_at_last_report
        self._faults_at_last_report = faults
        values: dict[str, object] = {
            'end_pose_rate_hz': round(self.pose_rate.rate(), 3),
            'reference_rate_hz': round(self.reference_rate.rate(), 3),
            'end_poses_received': self.pose_rate.total,
            'references_received': self.reference_rate.total,
            'window_fill': f'{core.window_fill}/{core.window_needed}',
            **rejection_values(core.dropped),
            'faults_total': faults,
            **{f'faults.{reason}': n for reason, n in core.faults.counts().items()},
            'last_fault': core.last_fault,
            'last_bad_stamp': core.last_bad_stamp,
            **self.callback_values(),
        }
        if self.pose_rate.seconds_since_last() is None:
            return Status(Level.WARN, f'no end poses on {self.settings.end_pose_topic} for '
                                      f'{self.settings.rate_window:g} s', values)
        if new_faults:
            return Status(Level.WARN, f'{new_faults} faults since the last report (last: '
                                      f'{core.last_fault}); window {values["window_fill"]}',
                          values)
        if core.window_fill < core.window_needed:
            return Status(Level.WARN, f'filling the window {values["window_fill"]}', values)
        return Status(Level.OK, f'{values["end_pose_rate_hz"]} Hz', values)

    def prediction_status(self) -> Status:
        core = self.core
        inference = core.inference_time.summary()
        rms, count = core.accuracy()
        values: dict[str, object] = {
            **latency_values('inference', inference),
            **latency_values('input_to_output', self.input_to_output.summary()),
            'output_rate_hz': round(self.output_rate.rate(), 3),
            'predictions_total': core.predictions_made,
            'accuracy_rms_x_um': round(float(rms[0]) * 1e6, 3),
            'accuracy_rms_y_um': round(float(rms[1]) * 1e6, 3),
            'accuracy_samples': count,
            'compensation_enabled': self.settings.compensation_enabled,
            'offset_x_um': round(float(core.offset_in_force[0]) * 1e6, 3),
            'offset_y_um': round(float(core.offset_in_force[1]) * 1e6, 3),
            'clamped_total': core.clamped,
            'step_limited_total': core.step_limited,
            'zeros_published': core.zeros_published,
            'reclamped_total': core.reclamped,
            'inference_skipped_late': core.overrun.inference_skipped_late,
            'late_outputs_dropped': core.overrun.late_outputs_dropped,
        }
        mode = 'compensating' if self.settings.compensation_enabled else 'shadow mode'
        overruns = core.overrun.inference_skipped_late + core.overrun.late_outputs_dropped
        new_overruns, self._overruns_at_last_report = (
            overruns - self._overruns_at_last_report, overruns)
        if new_overruns:
            return Status(Level.WARN, f'{mode}; {new_overruns} outputs late or skipped since the '
                                      'last report (overrun: inference slower than the input)',
                          values)
        if inference.samples and inference.p99 > self.settings.inference_time_warn:
            return Status(Level.WARN, f'{mode}; inference p99 {inference.p99 * 1e6:.0f} us over '
                                      f'{self.settings.inference_time_warn * 1e6:.0f} us', values)
        warn = self.settings.accuracy_warn
        if warn > 0.0 and count and float(np.nanmax(rms)) > warn:
            return Status(Level.WARN, f'{mode}; live RMS error {np.nanmax(rms) * 1e6:.1f} um '
                                      f'over {warn * 1e6:.1f} um: the machine has drifted from '
                                      'the model', values)
        return Status(Level.OK, f'{mode}; {core.predictions_made} predictions', values)


def build_entry_point(context: Context, **node_kwargs: Any) -> PredictorNode:
    """The node of an executable: built, then the process's torch threads set from its
    `inference_threads` (process-wide, so here and not in the node: tests and one-process
    runs build several nodes). `node_kwargs` go to the node."""
    node = PredictorNode(context=context, **node_kwargs)
    set_torch_threads(node.settings.inference_threads)
    return node


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `predictor_node` (`ros2 run lompr_predictor predictor_node`)."""
    return run_node(build_entry_point, description=__doc__.split('\n', 1)[0],
                    parameters_help=node_help(PredictorNodeSettings, ENDPOINTS), argv=argv)


if __name__ == '__main__':
    sys.exit(main())
