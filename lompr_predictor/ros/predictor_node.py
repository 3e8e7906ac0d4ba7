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
While the new file loads the executor waits; messages queue in the subscriptions (input QoS
depth, 100 by default), so none is lost as long as loading takes under depth / rate.

A plain node, not a lifecycle one: the model is all it configures, and a node that cannot
load it should not exist (the error message says why); deactivating is
`compensation_enabled: false` (shadow mode), which keeps the predictions going.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from lompr_predictor.data.cleaning import GAP_FACTOR
from lompr_predictor.data.features import FEATURES
from lompr_predictor.learning.model_file import (
    LoadedModel,
    ModelFileError,
    check_sample_period,
    load_model,
)
from lompr_predictor.monitoring import (
    LatencyRecorder,
    Level,
    LogThrottle,
    RateMeter,
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.online.predictor import (
    FAULT_REASONS,
    CompensationLimits,
    OnlinePredictor,
    Output,
    StreamSettings,
)
from lompr_predictor.robot.description import WORLD_FRAME, load_robot_description
from lompr_predictor.ros.common import (
    DiagnosticsPublisher,
    ParameterSpec,
    declare_parameters,
    qos_from_parameters,
    qos_parameter_specs,
    run_node,
)
from lompr_predictor.stamps import set_stamp, stamp_to_ns

NODE_NAME = 'predictor_node'

PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec('model_path', '', 'TorchScript model file (lompr train); setting it at run '
                  'time loads, checks and warms the new file and swaps it in, or keeps the '
                  'running model and rejects the change with the reason'),
    ParameterSpec('model_sha256', '', 'if not empty, the sha256 the model file must have, '
                  'checked before the file is deserialised (a TorchScript file is code)'),
    ParameterSpec('compensation_enabled', True, 'publish the offset; false: shadow mode, '
                  'predictions go on and every offset is zero'),
    ParameterSpec('max_compensation', 5e-4, 'largest offset [m] (XY norm); the offset is '
                  'clamped to it', minimum=0.0, maximum=0.01),
    ParameterSpec('max_compensation_step', 5e-5, 'largest change of the offset [m] (XY norm) '
                  'from one sample to the next', minimum=0.0, maximum=0.01),
    ParameterSpec('robot_description_file', '', 'URDF the model must have been trained for '
                  '(its sha256 is checked); empty: the packaged nominal LOMPR description',
                  read_only=True),
    ParameterSpec('sample_period', 0.0, 'period [s] of the pose stamps, which the model must '
                  "have been trained at (within 2 %); 0: the model file's", minimum=0.0,
                  maximum=10.0, read_only=True),
    ParameterSpec('window', -1, "window length the model must have; -1: the model file's "
                  "(a model swapped in at run time must keep the running one's)",
                  minimum=-1, maximum=100_000, read_only=True),
    ParameterSpec('horizon', -1, "horizon [samples] the model must have (the controller's "
                  "lead); -1: the model file's", minimum=-1, maximum=100_000, read_only=True),
    ParameterSpec('gap_factor', GAP_FACTOR, 'a stamp interval above this many sample periods '
                  'is a gap (the trainer splits its data at the same one)',
                  minimum=1.0, maximum=1000.0, read_only=True),
    ParameterSpec('min_interval_factor', 0.5, 'a stamp interval below this many sample '
                  "periods means the input is not at the model's rate",
                  minimum=0.0, maximum=1.0, read_only=True),
    ParameterSpec('stale_periods', 5.0, 'no usable sample for this many sample periods: the '
                  'input is stale and the offset is cancelled', minimum=1.0,
                  maximum=1_000_000.0, read_only=True),
    ParameterSpec('stale_min_time', 0.05, 'the input is stale only after at least this many '
                  'seconds without a usable sample, whatever the rate: a process on a general-'
                  'purpose OS stalls for milliseconds, many periods at kHz rates', minimum=0.0,
                  maximum=3600.0, read_only=True),
    ParameterSpec('end_pose_topic', '/lompr/end_pose', 'PoseStamped measured tool tip input',
                  read_only=True),
    ParameterSpec('reference_topic', '/lompr/reference', 'PoseStamped reference input',
                  read_only=True),
    ParameterSpec('predicted_error_topic', '/lompr/predicted_error',
                  'Vector3Stamped predicted X/Y error output', read_only=True),
    ParameterSpec('compensation_topic', '/lompr/compensation',
                  'Vector3Stamped compensation offset output', read_only=True),
    ParameterSpec('diagnostics_topic', '/diagnostics', 'DiagnosticArray topic', read_only=True),
    ParameterSpec('frame_id', WORLD_FRAME, 'header.frame_id of the outputs', read_only=True),
    *qos_parameter_specs('input_qos', depth=100, reliability='best_effort',
                         what='the end pose and reference subscriptions'),
    *qos_parameter_specs('output_qos', depth=100, what='the prediction and compensation '
                         'publishers'),
    ParameterSpec('inference_threads', 1, 'torch threads; 1 keeps inference from contending '
                  'with the executor', minimum=1, maximum=256, read_only=True),
    ParameterSpec('diagnostics_period', 1.0, 'seconds between /diagnostics messages',
                  minimum=0.05, maximum=60.0, read_only=True),
    ParameterSpec('rate_window', 5.0, 'seconds over which input/output rates are averaged',
                  minimum=0.1, maximum=600.0, read_only=True),
    ParameterSpec('latency_samples', 1000, 'last latencies kept for the p50/p99',
                  minimum=10, maximum=1_000_000, read_only=True),
    ParameterSpec('accuracy_samples', 1000, 'last predicted instants the live RMS is over',
                  minimum=1, maximum=10_000_000, read_only=True),
    ParameterSpec('inference_time_warn', 0.001, 'p99 inference time [s] above which the '
                  'prediction status is WARN', minimum=1e-6, maximum=10.0),
    ParameterSpec('accuracy_warn', 0.0, 'live RMS prediction error [m] (either axis) above '
                  'which the prediction status is WARN (the machine has drifted from the '
                  'model); 0: no such warning', minimum=0.0, maximum=1.0),
    ParameterSpec('warning_throttle_period', 5.0, 'seconds between two warnings of the same '
                  'kind', minimum=0.0, maximum=3600.0),
)


@dataclass(frozen=True)
class PredictorNodeSettings:
    """Snapshot of the node's parameters (see `PARAMETERS` for meanings and ranges)."""

    model_path: str
    model_sha256: str
    compensation_enabled: bool
    max_compensation: float
    max_compensation_step: float
    robot_description_file: str
    sample_period: float
    window: int
    horizon: int
    gap_factor: float
    min_interval_factor: float
    stale_periods: float
    stale_min_time: float
    end_pose_topic: str
    reference_topic: str
    predicted_error_topic: str
    compensation_topic: str
    diagnostics_topic: str
    frame_id: str
    inference_threads: int
    diagnostics_period: float
    rate_window: float
    latency_samples: int
    accuracy_samples: int
    inference_time_warn: float
    accuracy_warn: float
    warning_throttle_period: float

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> PredictorNodeSettings:
        return cls(**{name: values[name] for name in cls.__dataclass_fields__})

    @property
    def limits(self) -> CompensationLimits:
        return CompensationLimits(self.max_compensation, self.max_compensation_step,
                                  self.compensation_enabled)


class PredictorNode(Node):
    """The predictor node (module docstring). Extra keyword arguments go to
    `rclpy.node.Node` (`context`, `parameter_overrides`, ...)."""

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.settings = PredictorNodeSettings.from_values(values)
        torch.set_num_threads(self.settings.inference_threads)
        self.description = load_robot_description(self.settings.robot_description_file or None)
        if not self.settings.model_path:
            msg = 'parameter model_path is empty: give the model file (lompr train --out)'
            raise ModelFileError(msg)
        expected: dict[str, Any] = {
            'features': FEATURES, 'robot_description_sha256': self.description.sha256}
        for name in ('window', 'horizon'):
            if getattr(self.settings, name) >= 0:
                expected[name] = getattr(self.settings, name)
        model = load_model(self.settings.model_path, expected=expected,
                           sha256=self.settings.model_sha256 or None)
        #: The stamps' period: the parameter if set, else the model's; later models must fit it.
        self.sample_period = self.settings.sample_period or model.metadata.sample_period
        check_sample_period(model.metadata, self.sample_period, self.settings.model_path)
        # A model swapped in later must fit the running window and the controller's lead.
        self._expected = {**expected, 'window': model.metadata.window,
                          'horizon': model.metadata.horizon}
        self.core = OnlinePredictor(
            model,
            StreamSettings(self.sample_period, self.settings.gap_factor,
                           self.settings.min_interval_factor, self.settings.stale_periods,
                           self.settings.accuracy_samples, self.settings.stale_min_time),
            self.settings.limits, latency_samples=self.settings.latency_samples)
        self._candidate: LoadedModel | None = None
        self.model_swaps = 0
        self.reload_error = ''
        self.callback_failures = 0

        self.pose_rate = RateMeter(self.settings.rate_window)
        self.reference_rate = RateMeter(self.settings.rate_window)
        self.output_rate = RateMeter(self.settings.rate_window)
        self.input_to_output = LatencyRecorder(self.settings.latency_samples)
        self._throttle = LogThrottle(self.settings.warning_throttle_period)
        self._faults_at_last_report = 0

        self._prediction_publisher = self.create_publisher(
            Vector3Stamped, self.settings.predicted_error_topic,
            qos_from_parameters(values, 'output_qos'))
        self._compensation_publisher = self.create_publisher(
            Vector3Stamped, self.settings.compensation_topic,
            qos_from_parameters(values, 'output_qos'))
        input_qos = qos_from_parameters(values, 'input_qos')
        self._pose_subscription = self.create_subscription(
            PoseStamped, self.settings.end_pose_topic, self.on_end_pose, input_qos)
        self._reference_subscription = self.create_subscription(
            PoseStamped, self.settings.reference_topic, self.on_reference, input_qos)
        stale_after = self.core.stream.stale_after
        self._stale_timer = self.create_timer(min(max(stale_after / 4, 0.005), 0.5),
                                              self.on_stale_timer)
        self._diagnostics = DiagnosticsPublisher(
            self, self.settings.diagnostics_topic, self.settings.diagnostics_period,
            hardware_id=f'urdf sha256 {self.description.sha256[:16]}')
        self._diagnostics.add('model', self.model_status)
        self._diagnostics.add('inputs', self.input_status)
        self._diagnostics.add('prediction', self.prediction_status)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        metadata = model.metadata
        self.get_logger().info(
            f'{metadata.model_type} model {model.path} (sha256 {model.sha256[:16]}, window '
            f'{metadata.window}, horizon {metadata.horizon} x {metadata.sample_period:g} s); '
            f'compensation {"on" if self.settings.compensation_enabled else "off (shadow)"}')

    # -- callbacks (each catches its own failures) -----------------------------------------

    def on_end_pose(self, msg: PoseStamped) -> None:
        start = time.perf_counter()
        self.pose_rate.tick()
        try:
            position = msg.pose.position
            self._publish(self.core.add_pose(stamp_to_ns(msg.header.stamp), position.x, position.y), start)
        except Exception as err:  # noqa: BLE001 - a callback must never end the spin
            self._callback_failed('end pose', err)

    def on_reference(self, msg: PoseStamped) -> None:
        start = time.perf_counter()
        self.reference_rate.tick()
        try:
            position = msg.pose.position
            self._publish(self.core.add_reference(stamp_to_ns(msg.header.stamp), position.x, position.y),
                          start)
        except Exception as err:  # noqa: BLE001
            self._callback_failed('reference', err)

    def on_stale_timer(self) -> None:
        try:
            self._publish(self.core.check_stale(), time.perf_counter())
        except Exception as err:  # noqa: BLE001
            self._callback_failed('staleness check', err)

    def _publish(self, outputs: list[Output], start: float) -> None:
        for output in outputs:
            if output.prediction is not None:
                self._prediction_publisher.publish(self._vector(output.instant_ns, output.prediction))
            self._compensation_publisher.publish(self._vector(output.instant_ns, output.compensation))
            if output.reason in FAULT_REASONS:
                self._warn(output.reason, f'offset set to zero ({output.reason}); output '
                           'resumes once the window has refilled with good samples')
            elif not output.reason:
                self.input_to_output.record(time.perf_counter() - start)
                self.output_rate.tick()

    def _vector(self, stamp_ns: int, xy: np.ndarray) -> Vector3Stamped:
        msg = Vector3Stamped()
        set_stamp(msg.header.stamp, stamp_ns)
        msg.header.frame_id = self.settings.frame_id
        msg.vector.x, msg.vector.y = float(xy[0]), float(xy[1])
        return msg

    def _callback_failed(self, where: str, err: Exception) -> None:
        self.callback_failures += 1
        self._warn(f'failure {where}', f'{where} callback failed ({type(err).__name__}: {err})')
        try:
            self._publish(self.core.abort('internal'), time.perf_counter())
        except Exception:  # noqa: BLE001 - nothing more can be done here
            pass

    def _warn(self, key: str, text: str) -> None:
        message = self._throttle.filter(key, text)
        if message is not None:
            self.get_logger().warning(message)

    # -- parameters -------------------------------------------------------------------------

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Load, check and warm a new model beside the running one; reject a bad one."""
        changes = {p.name: p.value for p in parameters}
        self._candidate = None
        if 'model_path' not in changes:
            sha = changes.get('model_sha256')
            if sha and sha.lower() != self.core.model.sha256:
                return SetParametersResult(successful=False, reason=(
                    f'the running model {self.core.model.path} has sha256 '
                    f'{self.core.model.sha256}, not {sha}; set model_path with it'))
            return SetParametersResult(successful=True)
        sha = changes.get('model_sha256', self.settings.model_sha256)
        try:
            self._candidate = load_model(changes['model_path'], expected=self._expected,
                                         sha256=sha or None)
            check_sample_period(self._candidate.metadata, self.sample_period,
                                changes['model_path'])
        except Exception as err:  # noqa: BLE001 - any failure keeps the running model
            detail = str(err) if isinstance(err, ModelFileError) else (
                f'model {changes["model_path"]}: {type(err).__name__}: {err}')
            self.reload_error = f'{detail}; still running {self.core.model.path}'
            self.get_logger().error(f'model not swapped: {self.reload_error}')
            return SetParametersResult(successful=False, reason=self.reload_error)
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: Sequence[Parameter]) -> None:
        """Take accepted changes (validated in `_validate_parameters`); a failure here is
        handled like any callback's."""
        try:
            changes = {p.name: p.value for p in parameters
                       if p.name in PredictorNodeSettings.__dataclass_fields__}
            self.settings = replace(self.settings, **changes)
            self._publish(self.core.set_limits(self.settings.limits), time.perf_counter())
            self._throttle.period = self.settings.warning_throttle_period
            if self._candidate is not None:
                self.core.replace_model(self._candidate)
                self._candidate = None
                self.model_swaps += 1
                self.reload_error = ''
                self.get_logger().info(f'model swapped: now {self.core.model.path} '
                                       f'(sha256 {self.core.model.sha256[:16]})')
        except Exception as err:  # noqa: BLE001
            self._callback_failed('parameter change', err)

    # -- diagnostics ------------------------------------------------------------------------

    def model_status(self) -> Status:
        model = self.core.model
        metadata = model.metadata
        values: dict[str, object] = {
            'path': model.path, 'sha256': model.sha256, 'type': metadata.model_type,
            'window': metadata.window, 'horizon': metadata.horizon,
            'sample_period_s': metadata.sample_period, 'swaps': self.model_swaps,
            'robot_description_sha256': metadata.robot_description_sha256,
        }
        if self.reload_error:
            return Status(Level.WARN, f'last reload refused: {self.reload_error}', values)
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
            'callback_failures': self.callback_failures,
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
        }
        mode = 'compensating' if self.settings.compensation_enabled else 'shadow mode'
        if inference.samples and inference.p99 > self.settings.inference_time_warn:
            return Status(Level.WARN, f'{mode}; inference p99 {inference.p99 * 1e6:.0f} us over '
                                      f'{self.settings.inference_time_warn * 1e6:.0f} us', values)
        warn = self.settings.accuracy_warn
        if warn > 0.0 and count and float(np.nanmax(rms)) > warn:
            return Status(Level.WARN, f'{mode}; live RMS error {np.nanmax(rms) * 1e6:.1f} um '
                                      f'over {warn * 1e6:.1f} um: the machine has drifted from '
                                      'the model', values)
        return Status(Level.OK, f'{mode}; {core.predictions_made} predictions', values)


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `predictor_node` (`ros2 run lompr_predictor predictor_node`)."""
    def build(context: Context) -> PredictorNode:
        return PredictorNode(context=context)

    return run_node(build, description=__doc__.split('\n', 1)[0], parameters=PARAMETERS,
                    argv=argv)


if __name__ == '__main__':
    sys.exit(main())
