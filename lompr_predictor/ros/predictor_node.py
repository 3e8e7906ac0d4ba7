"""predictor_node: end poses + reference -> predicted error and a bounded compensation offset.

A thin managed (lifecycle) node around `online.OnlinePredictor` (alignment by stamp, plant
error, rolling window, model, safety): it turns /lompr/end_pose and /lompr/reference into
calls, publishes every `Output` on /lompr/predicted_error and /lompr/compensation
(Vector3Stamped, z = 0, stamped with the instant they are for: pose stamp + horizon *
sample_period), checks staleness on a timer and reports on /diagnostics.

Lifecycle (`rclpy.lifecycle`, services `~/change_state`, `~/get_state`, ...):

- unconfigured: parameters and /diagnostics only. `configure` loads the model file, checks it
  against this node's configuration (features, window, horizon, sample period, sha256 of its
  robot description), warms it up (`WARM_UP_INFERENCES` inferences, each checked), picks
  what runs the network (`inference_backend`, `online.inference.select_backend`) and
  creates the core, the endpoints and the staleness timer; a failure leaves the node
  unconfigured with the reason in the log and on /diagnostics (`configure_error`).
- inactive: configured, publishing nothing; input is counted and dropped.
- active: every sample is answered when it arrives. `activate` starts from an empty window.
- `deactivate` cancels the offset in force (a zero for each instant an offset is out for,
  `OffsetGate.cancel`) and stops; `cleanup` releases the model and the endpoints;
  `shutdown` does both.
- `autostart` (default true) configures and activates in the constructor, so a plain
  `predictor_node --ros-args -p model_path:=M` (or `ros2 run`) predicts at once; a model
  that cannot be configured then stops the executable with one line (exit code 2), which a
  supervisor sees. `autostart: false` waits for a lifecycle manager.

Time: every time the node reasons about is its ROS clock (simulated time from /clock under
use_sim_time): staleness (`stale_periods` of it), the staleness timer, rates, throttled
warnings and /diagnostics; wall time only for latencies. A sample is answered from its own
callback, never from a timer, so a simulator that stands still waiting for the answer
(lockstep) gets it. Before the first /clock the clock reads 0 and nothing is judged. The
clock going backwards (a simulator reset) is a fault `clock_jump`: the window is emptied,
the offset in force cancelled, and the restarted streams refill the window.

Model swaps: setting `model_path` while configured loads, checks and warms the new file
inside the parameter validation callback, beside the running model: a bad file rejects the
parameter change (the reason goes back to the caller and to /diagnostics) and the old model
keeps running; a good one is swapped in by the post-set callback, between two samples,
keeping the window. While the new file loads the executor waits; messages queue in the
subscriptions (depth 100 by default, `qos_overrides.<topic>.subscription.depth`), so none is
lost as long as loading takes under depth / rate. Unconfigured, a new `model_path` is taken
as is and loaded by the next `configure`.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from lifecycle_msgs.srv import ChangeState
from rclpy.clock import ClockChange, JumpThreshold, TimeJump
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.lifecycle import (
    LifecycleNode,
    LifecyclePublisher,
    LifecycleState,
    TransitionCallbackReturn,
)
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription
from rclpy.timer import Timer

from lompr_predictor.data.cleaning import GAP_FACTOR
from lompr_predictor.data.features import FEATURES
from lompr_predictor.errors import LomprError
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
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.online.faults import FAULT_REASONS, StreamSettings
from lompr_predictor.online.inference import BACKENDS, InferenceBackend, select_backend
from lompr_predictor.online.offset import XY, CompensationLimits, Output
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.robot.description import (
    WORLD_FRAME,
    RobotDescription,
    load_robot_description,
)
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import (
    OUTPUT_QOS,
    SENSOR_INPUT_QOS,
    Endpoint,
    NodeBase,
    StatusSettings,
    node_help,
)
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.ros.wire import Vector3StampedWriter, read_pose_stamped
from lompr_predictor.stamps import NS_PER_SECOND, Stamp
from lompr_predictor.threads import set_torch_threads

NODE_NAME = 'predictor_node'


@dataclass(frozen=True)
class PredictorNodeSettings(StatusSettings):
    """The node's parameters: one field each (after the shared `StatusSettings`),
    declared by `NodeBase.declare_settings`."""

    autostart: bool = parameter(
        True, 'configure and activate at start, so that a plain `ros2 run` predicts (a model '
        'that cannot be configured then stops the executable, exit code 2); false: start '
        'unconfigured and wait for a lifecycle manager (change_state)', read_only=True)
    model_path: str = parameter(
        '', 'TorchScript model file (lompr train); setting it at run time loads, checks and '
        'warms the new file and swaps it in, or keeps the running model and rejects the '
        'change with the reason')
    model_sha256: str = parameter(
        '', "if not empty, the sha256 the model file must have (the training report's "
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
        '', 'URDF of the robot (its calibrated geometry), the one the model must have been '
        "trained for: it gives the features' branch kinematics and its sha256 is checked; "
        'empty: the packaged nominal LOMPR description', read_only=True)
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
    frame_id: str = parameter(WORLD_FRAME, 'header.frame_id of the outputs', read_only=True)
    inference_backend: str = parameter(
        'auto', 'what runs the network: onnxruntime (an ONNX graph exported from the verified '
        'model file at configure, used only if it agrees with TorchScript to 1e-6 relative on '
        'a warm-up batch; configure fails if it cannot serve), torchscript (the file as '
        'loaded), or auto (onnxruntime, else torchscript with the reason on /diagnostics)',
        choices=BACKENDS, read_only=True)
    inference_threads: int = parameter(
        1, "torch threads, set by the executable's main() (process-wide); 1 keeps inference "
        'from contending with the executor', minimum=1, maximum=256, read_only=True)
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


class ConfigureError(LomprError):
    """`configure` refused for a reason other than the model file's own (`ModelFileError`)."""


class NotConfiguredError(LomprError):
    """The core of a predictor node that is not configured was asked for."""


#: Inferences `configure` runs on the loaded model before it may answer a sample (the first
#: calls of a TorchScript module profile and optimise its graph); each must give a finite
#: (1, 2) prediction.
WARM_UP_INFERENCES = 5


class PredictorNode(NodeBase[PredictorNodeSettings], LifecycleNode):
    """The predictor node (module docstring). `deferred`: leave the autostart to the
    caller's `start()` (an entry point sets the process's torch threads first). Extra
    keyword arguments go to `rclpy.node.Node` (`context`, `parameter_overrides`, ...)."""

    def __init__(self, node_name: str = NODE_NAME, *, deferred: bool = False,
                 **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(PredictorNodeSettings)
        self.lifecycle_state = 'unconfigured'
        self.active = False
        #: Why the last configure failed ('' after a successful one).
        self.configure_error = ''
        self._configure_exception: LomprError | None = None
        self._core: OnlinePredictor | None = None  # while configured (`core`)
        self.description: RobotDescription | None = None
        #: The stamps' period: the parameter if set, else the model's; later models must fit it.
        self.sample_period = 0.0
        self._expected: dict[str, Any] = {}
        self._candidate: LoadedModel | None = None
        self._candidate_backend: tuple[InferenceBackend, str] | None = None
        #: Why the backend serving is not the one `inference_backend` prefers ('' if it is).
        self.backend_why = ''
        self.model_swaps = 0
        self.reload_error = ''
        self.warm_up_seconds = 0.0
        self.dropped_inactive = 0  # samples received while not active
        self.clock_jumps_back = 0
        self._clock_started = False
        self._autostarting = False

        self.pose_rate = self.rate_meter(settings.rate_window)
        self.reference_rate = self.rate_meter(settings.rate_window)
        self.output_rate = self.rate_meter(settings.rate_window)
        self.input_to_output = LatencyRecorder(settings.latency_samples)
        self._faults_at_last_report = 0
        self._overruns_at_last_report = 0

        self._vector_writer = Vector3StampedWriter(settings.frame_id)  # outputs as bytes
        self._prediction_publisher: Publisher | None = None
        self._compensation_publisher: Publisher | None = None
        self._subscriptions_made: list[Subscription] = []
        self._stale_timer: Timer | None = None
        self._diagnostics = self.start_diagnostics(
            settings.diagnostics_topic, settings.diagnostics_period, hardware_id=NODE_NAME)
        self._diagnostics.add('model', self.model_status)
        self._diagnostics.add('inputs', self.input_status)
        self._diagnostics.add('prediction', self.prediction_status)
        # Backward jumps (a simulator reset) and a change of time source; the clock's start
        # (its first /clock, a forward jump from 0) is handled by the staleness timer.
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True),
            post_callback=self.guard('clock jump', self._on_clock_jump))
        self._refuse_unknown_transitions()
        if not deferred:
            self.start()

    def _refuse_unknown_transitions(self) -> None:
        """rclpy 7.1.6's `change_state` service raises out of the executor (and so ends the
        process) on a transition the current state does not have, where rclcpp answers
        `success: false`; answer false here too."""
        service = self._service_change_state  # LifecycleNodeMixin's service server
        handle = service.callback

        def change_state(request: ChangeState.Request,
                         response: ChangeState.Response) -> ChangeState.Response:
            try:
                return handle(request, response)
            except Exception as err:  # noqa: BLE001 - RCLError, private in rclpy: refuse
                self.get_logger().warning(f'transition {request.transition.id} '
                                          f'{request.transition.label!r} refused in state '
                                          f'{self.lifecycle_state}: {err}')
                response.success = False
                return response

        service.callback = change_state

    @property
    def core(self) -> OnlinePredictor:
        """The ROS-free predictor, which exists while the node is configured (inactive or
        active); `NotConfiguredError` otherwise."""
        if self._core is None:
            msg = f'{self.get_name()} is {self.lifecycle_state}: no model, no core'
            raise NotConfiguredError(msg)
        return self._core

    @property
    def configured(self) -> bool:
        return self._core is not None

    def start(self) -> None:
        """Configure and activate if `autostart`; raise the reason (a `LomprError`) if the
        node cannot be configured, after destroying it."""
        if not self.settings.autostart:
            self.get_logger().info('autostart false: unconfigured, waiting for a lifecycle '
                                   'manager (change_state configure, activate)')
            return
        self._autostarting = True  # the caller reports a failure: one line, not two
        try:
            configured = self.trigger_configure() == TransitionCallbackReturn.SUCCESS
        finally:
            self._autostarting = False
        if not configured:
            error = self._configure_exception or ConfigureError(self.configure_error)
            self.destroy_node()
            raise error
        if self.trigger_activate() != TransitionCallbackReturn.SUCCESS:
            self.destroy_node()
            msg = 'activate failed'
            raise ConfigureError(msg)

    # -- lifecycle transitions ------------------------------------------------------------

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Load, check and warm up the model; create the core and the endpoints. A failure
        leaves the node unconfigured with the reason (log, /diagnostics)."""
        try:
            self._configure()
        except Exception as err:  # noqa: BLE001 - a model file is code: any failure refuses it
            self._release()
            if not isinstance(err, LomprError):
                path = self.settings.model_path
                err = ConfigureError(f'model {path}: {type(err).__name__}: {err}')
            self._configure_exception = err
            self.configure_error = str(err)
            if not self._autostarting:
                self.get_logger().error(f'configure failed, staying unconfigured: {err}')
            return TransitionCallbackReturn.FAILURE
        self.configure_error = ''
        self._configure_exception = None
        self.lifecycle_state = 'inactive'
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Start from an empty window; publish from now on."""
        assert self._core is not None  # the lifecycle calls activate only when configured
        self._core.reset('inactive')
        self._clock_started = self.get_clock().now().nanoseconds > 0
        self.active = True
        self.lifecycle_state = 'active'
        self.get_logger().info('active: answering every sample')
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Cancel the offset in force (zeros, published before the publishers stop), stop."""
        self._stop('inactive')
        self.lifecycle_state = 'inactive'
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Release the model, the core and the endpoints."""
        self._release()
        self.lifecycle_state = 'unconfigured'
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop('inactive')
        self._release()
        self.lifecycle_state = 'finalized'
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A transition raised: release everything and go back to unconfigured."""
        self.active = False
        self._release()
        self.lifecycle_state = 'unconfigured'
        return TransitionCallbackReturn.SUCCESS

    def _configure(self) -> None:
        settings = self.settings
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
        self.sample_period = settings.sample_period or model.metadata.sample_period
        check_sample_period(model.metadata, self.sample_period, settings.model_path)
        self.warm_up_seconds = warm_up(model)
        backend, self.backend_why = select_backend(model, settings.inference_backend)
        # A model swapped in later must fit the running window and the controller's lead.
        self._expected = {**expected, 'window': model.metadata.window,
                          'horizon': model.metadata.horizon}
        self._core = OnlinePredictor(
            model,
            StreamSettings(self.sample_period, settings.gap_factor,
                           settings.min_interval_factor, settings.stale_periods,
                           settings.accuracy_samples, settings.stale_min_time,
                           settings.max_future_stamp, settings.late_tolerance),
            settings.limits, clock=self.clock_seconds,
            latency_samples=settings.latency_samples, now_ns=self.clock_ns,
            description=self.description, backend=backend)
        self._prediction_publisher = self.advertise(PREDICTED_ERROR)
        self._compensation_publisher = self.advertise(COMPENSATION)
        self._subscriptions_made = [self.subscribe(END_POSE, self.on_end_pose, raw=True),
                                    self.subscribe(REFERENCE, self.on_reference, raw=True)]
        stale_after = self._core.stream.stale_after
        self._stale_timer = self.start_timer(min(max(stale_after / 4, 0.005), 0.5),
                                             'staleness check', self.on_stale_timer)
        metadata = model.metadata
        self.get_logger().info(
            f'{metadata.model_type} model {model.path} (sha256 {model.sha256[:16]}, window '
            f'{metadata.window}, horizon {metadata.horizon} x {metadata.sample_period:g} s, '
            f'warmed up in {self.warm_up_seconds * 1e3:.1f} ms); compensation '
            f'{"on" if settings.compensation_enabled else "off (shadow)"}')

    def _stop(self, reason: str) -> None:
        """Cancel the offset in force while the publishers still publish; stop answering."""
        if self._core is not None and self.active:
            zeros = self._core.reset(reason)
            self._publish(zeros, time.perf_counter())
            self.get_logger().info(f'deactivated: offset cancelled ({len(zeros)} zero(s))')
        self.active = False

    def _release(self) -> None:
        """Destroy the endpoints and the timer, drop the core and the model."""
        self.active = False
        if self._stale_timer is not None:
            self.destroy_timer(self._stale_timer)
        for subscription in self._subscriptions_made:
            self.destroy_subscription(subscription)
        for publisher in (self._prediction_publisher, self._compensation_publisher):
            if isinstance(publisher, LifecyclePublisher):
                self.destroy_lifecycle_publisher(publisher)
        self._stale_timer, self._subscriptions_made = None, []
        self._prediction_publisher = self._compensation_publisher = None
        self._core = self._candidate = self.description = None

    def destroy_node(self) -> None:
        """Destroy the node now. rclpy's lifecycle state machine holds the node's handle
        until it is itself destroyed, which rclpy leaves to the garbage collector: a node
        refused at start would stay in the graph while anything (a traceback) refers to it."""
        self._jump_handle.unregister()
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()

    # -- callbacks (run through NodeBase.guard: a failure aborts the core) -----------------

    def on_end_pose(self, msg: bytes) -> None:
        """One serialized PoseStamped (the subscriptions are raw: `wire`)."""
        start = time.perf_counter()
        self.pose_rate.tick()
        if self._core is None or not self.active:
            self.dropped_inactive += 1
            return
        sec, nanosec, x, y, _ = read_pose_stamped(msg)
        self._publish(self._core.add_pose(Stamp(sec, nanosec), x, y), start)

    def on_reference(self, msg: bytes) -> None:
        start = time.perf_counter()
        self.reference_rate.tick()
        if self._core is None or not self.active:
            self.dropped_inactive += 1
            return
        sec, nanosec, x, y, z = read_pose_stamped(msg)
        self._publish(self._core.add_reference(Stamp(sec, nanosec), x, y, z), start)

    def on_stale_timer(self) -> None:
        """Runs on the node's clock: under simulated time only while that time advances."""
        if self._core is None or not self.active:
            return
        if not self._clock_started:  # the first /clock came: idle time counts from now
            self._clock_started = True
            self._core.restart_staleness()
            return
        self._publish(self._core.check_stale(), time.perf_counter())

    def _on_clock_jump(self, jump: TimeJump) -> None:
        """The clock went back (a simulator reset) or changed source (use_sim_time set)."""
        changed = jump.clock_change in (ClockChange.ROS_TIME_ACTIVATED,
                                        ClockChange.ROS_TIME_DEACTIVATED)
        if not changed and jump.delta.nanoseconds >= 0:
            return
        self.clock_jumps_back += 1
        now_ns = self.get_clock().now().nanoseconds
        self.warn_throttled('clock jump', (
            f'the clock changed source (now {now_ns * 1e-9:.3f} s)' if changed else
            f'the clock went back by {-jump.delta.nanoseconds * 1e-9:.3f} s to '
            f'{now_ns * 1e-9:.3f} s (a simulator reset?)')
            + ': window emptied, offset cancelled; output resumes once the window has '
              'refilled')
        if self._core is not None and self.active:
            self._publish(self._core.clock_jumped_back(None if changed else now_ns),
                          time.perf_counter())

    def on_callback_failure(self, where: str) -> None:
        """Empty the window and cancel the offset in force: nothing half-done is published."""
        del where
        if self._core is not None and self.active:
            self._publish(self._core.abort('internal'), time.perf_counter())

    def _publish(self, outputs: list[Output], start: float) -> None:
        predictions, compensations = self._prediction_publisher, self._compensation_publisher
        if predictions is None or compensations is None:
            return
        for output in outputs:
            if output.prediction is not None:
                predictions.publish(self._vector(output.instant_ns, output.prediction))
            compensations.publish(self._vector(output.instant_ns, output.compensation))
            if output.reason in FAULT_REASONS:
                self.warn_throttled(output.reason, f'offset set to zero ({output.reason}); '
                                    'output resumes once the window has refilled with good '
                                    'samples')
            elif not output.reason:
                self.input_to_output.record(time.perf_counter() - start)
                self.output_rate.tick()

    def _vector(self, stamp_ns: int, xy: XY) -> bytes:
        """A serialized Vector3Stamped (`wire`): no message object per output."""
        sec, nanosec = divmod(stamp_ns, NS_PER_SECOND)
        return self._vector_writer.pack(sec, nanosec, xy[0], xy[1])

    def _load(self, path: str, expected: dict[str, Any], pin: str) -> LoadedModel:
        """`load_model` with this node's hash policy (pin, else the sidecar, unless
        verify_model_hash is false)."""
        return load_model(path, expected=expected, sha256=pin or None,
                          verify=self.settings.verify_model_hash,
                          hint='predictor_node: -p model_sha256:=<sha256>, or for development '
                               'only -p verify_model_hash:=false')

    # -- parameters (NodeBase hooks) -------------------------------------------------------

    def validate_settings(self, changes: dict[str, Any]) -> str:
        """Configured: load, check and warm a new model beside the running one; refuse a
        bad one. Unconfigured: the next configure loads it."""
        self._candidate = None
        if self._core is None:
            return ''
        running = self._core.model
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
            warm_up(candidate)
            self._candidate_backend = select_backend(candidate, self.settings.inference_backend)
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
        if self._core is None:
            return
        outputs = self._core.set_limits(self.settings.limits)
        if self.active:
            self._publish(outputs, time.perf_counter())
        if ('model_path' in changed and self._candidate is not None
                and self._candidate_backend is not None):
            backend, self.backend_why = self._candidate_backend
            self._core.replace_model(self._candidate, backend)
            self._candidate = None
            self.model_swaps += 1
            self.reload_error = ''
            self.get_logger().info(f'model swapped: now {self._core.model.path} '
                                   f'(sha256 {self._core.model.sha256[:16]})')

    # -- diagnostics ------------------------------------------------------------------------

    def _lifecycle_values(self) -> dict[str, object]:
        return {'lifecycle_state': self.lifecycle_state, 'autostart': self.settings.autostart,
                'configure_error': self.configure_error}

    def model_status(self) -> Status:
        values = self._lifecycle_values()
        if self._core is None:
            values['path'] = self.settings.model_path
            if self.configure_error:
                return Status(Level.ERROR, f'unconfigured: configure failed: '
                                           f'{self.configure_error}', values)
            return Status(Level.WARN, f'{self.lifecycle_state}: no model loaded (waiting for '
                                      'configure)', values)
        model = self._core.model
        metadata = model.metadata
        values.update({
            'path': model.path, 'sha256': model.sha256, 'sha256_verified_by': model.verified_by,
            'type': metadata.model_type,
            'window': metadata.window, 'horizon': metadata.horizon,
            'sample_period_s': metadata.sample_period, 'swaps': self.model_swaps,
            'robot_description_sha256': metadata.robot_description_sha256,
            'warm_up_ms': round(self.warm_up_seconds * 1e3, 3),
            'inference_backend': self._core.backend.name,
            'inference_backend_why': self.backend_why,
        })
        if self.reload_error:
            return Status(Level.WARN, f'last reload refused: {self.reload_error}', values)
        summary = f'{metadata.model_type} {model.sha256[:12]}, horizon {metadata.horizon}'
        if not self.active:
            return Status(Level.WARN, f'{self.lifecycle_state} (not publishing): {summary}',
                          values)
        if self.backend_why:
            return Status(Level.WARN, f'{summary}; {self.backend_why}', values)
        if model.verified_by == VERIFIED_BY[2]:
            return Status(Level.WARN, f'{summary}; NOT verified (verify_model_hash is false)',
                          values)
        return Status(Level.OK, summary, values)

    def _time_values(self) -> dict[str, object]:
        return {'use_sim_time': bool(self.get_parameter('use_sim_time').value),
                'clock_s': round(self.clock_seconds(), 6),
                'clock_jumps_back': self.clock_jumps_back,
                'dropped_inactive': self.dropped_inactive}

    def input_status(self) -> Status:
        core = self._core
        if core is None:
            return Status(Level.WARN, self.lifecycle_state,
                          {**self._lifecycle_values(), **self._time_values()})
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
            **self._time_values(),
            **self.callback_values(),
        }
        if self.pose_rate.seconds_since_last() is None:
            return Status(Level.WARN, f'no end poses on {self.settings.end_pose_topic} for '
                                      f'{self.settings.rate_window:g} s', values)
        if new_faults:
            return Status(Level.WARN, f'{new_faults} faults since the last report (last: '
                                      f'{core.last_fault}); window {values["window_fill"]}',
                          values)
        if not self.active:
            return Status(Level.WARN, f'{self.lifecycle_state}: input dropped', values)
        if core.window_fill < core.window_needed:
            return Status(Level.WARN, f'filling the window {values["window_fill"]}', values)
        return Status(Level.OK, f'{values["end_pose_rate_hz"]} Hz', values)

    def prediction_status(self) -> Status:
        core = self._core
        if core is None:
            return Status(Level.WARN, self.lifecycle_state, self._lifecycle_values())
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
        if not self.active:
            mode = f'{self.lifecycle_state}, not publishing'
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


def warm_up(model: LoadedModel, inferences: int = WARM_UP_INFERENCES) -> float:
    """Run `inferences` predictions of a zero window, each of which must be a finite (1, 2)
    array (`ModelFileError` otherwise); returns the seconds they took."""
    window = torch.zeros((1, model.metadata.window, len(model.metadata.features)),
                         dtype=torch.float64)
    start = time.perf_counter()
    for _ in range(inferences):
        output = model.predict(window)
        if tuple(output.shape) != (1, 2) or not bool(torch.isfinite(output).all()):
            msg = (f'model {model.path}: warm-up gave {tuple(output.shape)} '
                   f'{output.flatten().tolist()[:4]}, not a finite (1, 2) prediction')
            raise ModelFileError(msg)
    return time.perf_counter() - start


def build_entry_point(context: Context, **node_kwargs: Any) -> PredictorNode:
    """The node of an executable: built, the process's torch threads set from its
    `inference_threads` (process-wide, so here and not in the node: tests and one-process
    runs build several nodes), then started (`autostart`: configured and activated, so the
    warm-up runs on those threads). `node_kwargs` go to the node."""
    node = PredictorNode(context=context, deferred=True, **node_kwargs)
    set_torch_threads(node.settings.inference_threads)
    node.start()
    return node


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `predictor_node` (`ros2 run lompr_predictor predictor_node`)."""
    return run_node(build_entry_point, description=__doc__.split('\n', 1)[0],
                    parameters_help=node_help(PredictorNodeSettings, ENDPOINTS), argv=argv)


if __name__ == '__main__':
    sys.exit(main())
