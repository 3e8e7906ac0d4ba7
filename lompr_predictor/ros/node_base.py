# SPDX-License-Identifier: Apache-2.0
"""What every lompr node shares: settings, endpoints, one callback-exception policy,
diagnostics. `NodeBase` is a mixin placed before the rclpy class, so it serves a plain node
and a managed one alike (`class TwinNode(NodeBase[TwinNodeSettings], Node)`,
`class KinematicsNode(NodeBase[...], ManagedNode, LifecycleNode)`).

- Settings: `declare_settings(SettingsType)` declares every field of the frozen settings
  dataclass as a parameter (`parameters.parameter`), validates each change (ranges and
  read_only by rclpy; choices, checks and the node's `validate_settings` hook here) and
  applies an accepted one as a new frozen snapshot (`apply_settings` hook). Every node's
  settings share `StatusSettings`, `SchedulingSettings` (applied by `common.run_node`) and
  `FrameSettings`.
- Endpoints: an `Endpoint` names a publisher or subscription, its message type, the settings
  field holding its topic and its default QoS, chosen on purpose; `advertise` and
  `subscribe` make it with rclpy's `QoSOverridingOptions` (a bad override stops the node
  with one line, `QosOverrideError`); a lifecycle node gets a lifecycle publisher. Each
  counts incompatible-QoS events and warns instead of rclpy's log line (the `qos` status).
- One callback-exception policy: every subscription, timer and parameter-change callback
  runs through `guard`, which catches any exception, counts it (`callback_values()`), logs
  it throttled and calls the node's `on_callback_failure` hook (the predictor cancels its
  offset); a callback never ends the spin. `guard` also times each run
  (`monitoring.CallbackTimes`).
- Diagnostics: `start_diagnostics(topic, period, hardware_id)` -> `DiagnosticsPublisher`,
  with the `qos` and `callback timing` statuses of its own; `warn_throttled(key, text)`: one
  warning per key and throttle period.
- Time: every time a node reasons about is its own clock (`clock_seconds`, `clock_ns`: ROS
  time, /clock under `use_sim_time`): timers, rates, throttles, diagnostics; wall time only
  for latencies. Thread counts are the entry points' (`threads.set_torch_threads`).
"""

from __future__ import annotations

import contextlib
import copy
import gc
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar

from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockChange, JumpThreshold, ROSClock, TimeJump
from rclpy.lifecycle import LifecycleNodeMixin
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import (
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from rclpy.subscription import Subscription
from rclpy.timer import Timer

from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import (
    CallbackTimes,
    Level,
    LogThrottle,
    RateMeter,
)
from lompr_predictor.robot.description import ROBOT_FRAME
from lompr_predictor.ros.common import USE_FQN, USE_FQN_PARAMETER, DiagnosticsPublisher
from lompr_predictor.ros.parameters import (
    ParameterSpec,
    changes_problem,
    parameter,
    parameter_specs,
    settings_help,
)
from lompr_predictor.ros.parameters import declare_settings as declare_parameters
from lompr_predictor.ros.qos_watch import QosWatch
from lompr_predictor.scheduling import (
    MAX_NICE,
    MIN_NICE,
    Scheduling,
    SchedulingOutcome,
    cpu_list_problem,
)

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

S = TypeVar('S', bound='DataclassInstance')

#: Inputs from a robot or another node: best effort hears reliable and best-effort
#: (sensor-data) publishers alike, whereas a reliable subscription hears nothing from a
#: best-effort publisher; depth 1000 queues 1 s at 1 kHz while the process is held up (a
#: burst of other work on the machine): a sample lost there is a gap that costs the window's
#: refill, a queued one at most its own answer.
SENSOR_INPUT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
#: Commands that must not be lost on the way (the compensation a controller applies).
COMMAND_INPUT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
#: Outputs: reliable, so that a reliable subscriber (a controller, a recorder) hears them;
#: best-effort subscribers hear them too.
OUTPUT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
#: /diagnostics: diagnostic_aggregator and rqt subscribe reliable with depth 10.
DIAGNOSTICS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
#: Seconds between two warnings of the same kind, for a node without the parameter.
DEFAULT_THROTTLE_PERIOD = 5.0



@dataclass(frozen=True)
class StatusSettings:
    """The parameters every node's status report shares; a node's settings dataclass
    derives from it (its own fields follow these)."""

    diagnostics_topic: str = parameter('/diagnostics', 'DiagnosticArray topic', read_only=True)
    diagnostics_period: float = parameter(1.0, 'seconds between /diagnostics messages',
                                          minimum=0.05, maximum=60.0, read_only=True)
    rate_window: float = parameter(5.0, 'seconds over which the rates on /diagnostics are '
                                   'averaged', minimum=0.1, maximum=600.0, read_only=True)
    hardware_id: str = parameter(
        '', "hardware_id of the node's diagnostic statuses (the device they are about); "
        "empty: the name of the robot description's <robot>", read_only=True)
    callback_histograms: bool = parameter(
        False, "also publish each kind of work's duration histogram in the callback timing "
        'status (what the benches read); false: its runs, means and percentiles only')


@dataclass(frozen=True)
class SchedulingSettings(StatusSettings):
    """`StatusSettings` and how the node's process is scheduled (`scheduling.py`), applied
    once its node(s) are built (`common.run_node`); a setting the platform or the process's
    privileges refuse stops the executable with one line naming it (exit code 2), or with
    `scheduling_required` false is left out and said on the `scheduling` status."""

    nice: int = parameter(
        0, "added at start to the nice value of the node's process (as nice -n): negative "
        'raises its priority (needs CAP_SYS_NICE, e.g. root, or an RLIMIT_NICE allowing it), '
        'positive lowers it; 0 keeps it', minimum=MIN_NICE, maximum=MAX_NICE, read_only=True)
    sched_fifo_priority: int = parameter(
        0, 'if > 0, the process runs under SCHED_FIFO at this real-time priority, ahead of '
        'every normal process (needs CAP_SYS_NICE or an RLIMIT_RTPRIO of at least it); 0: '
        'the normal policy', minimum=0, maximum=99, read_only=True)
    cpu_affinity: tuple[int, ...] = parameter(
        (), 'CPUs the process runs on, e.g. [1] (a core kept free of other work); empty: '
        'those it may use at start', read_only=True, check=cpu_list_problem, items=int)
    scheduling_required: bool = parameter(
        True, 'true: a nice, sched_fifo_priority or cpu_affinity the system refuses stops the '
        'executable (exit code 2); false: the node runs without it and its scheduling '
        "status on /diagnostics says what was refused (the launch file's choice)",
        read_only=True)

    @property
    def scheduling(self) -> Scheduling:
        """What these settings ask for the process: the parameters of the same names."""
        return Scheduling(**{item.name: getattr(self, item.name)
                             for item in fields(Scheduling)})


@dataclass(frozen=True)
class FrameSettings(SchedulingSettings):
    """`StatusSettings` and the frame of a node whose messages carry poses or vectors: the
    robot frame (Z down, docs/interface.md), optionally prefixed for a cell that shares its
    TF tree with others, as robot_state_publisher's `frame_prefix` does."""

    frame_id: str = parameter(
        ROBOT_FRAME, 'the robot frame (Z down): header.frame_id (after frame_prefix) of every '
        'pose and vector the node publishes and reads; an input in another frame is dropped',
        read_only=True)
    frame_prefix: str = parameter(
        '', "prefix of frame_id, as robot_state_publisher's frame_prefix (e.g. cell1/): cells "
        'on one TF tree keep their frames apart', read_only=True)

    @property
    def frame(self) -> str:
        """The frame the node's messages carry: frame_prefix + frame_id."""
        return f'{self.frame_prefix}{self.frame_id}'


if TYPE_CHECKING:
    _NodeType = Node  # for the type checker the mixin is a Node: its methods use Node's API
else:
    class _NodeType:  # at run time a plain mixin, placed before Node or LifecycleNode
        pass


class QosOverrideError(LomprError):
    """A `qos_overrides.*` parameter that cannot be applied (unknown value, depth < 1)."""


def root_topic(topic: str) -> str:
    """A topic name as it resolves in the root namespace ('joint_states' -> '/joint_states')."""
    return topic if topic.startswith('/') else f'/{topic}'


@dataclass(frozen=True)
class Endpoint:
    """A publisher or subscription of a node (module docstring)."""

    kind: Literal['publisher', 'subscription']
    msg_type: Any  # the message class
    topic_parameter: str  # the settings field that holds the topic name
    qos: QoSProfile  # default QoS (copied: rclpy's overriding writes into the profile)
    what: str  # what flows there, for logs and --help

    def parameter_prefix(self, topic: str) -> str:
        """`qos_overrides.<topic>.<kind>` for the fully qualified `topic` (a relative name
        is taken in the root namespace, as rclpy resolves it there)."""
        return f'qos_overrides.{root_topic(topic)}.{self.kind}'

    def help_line(self, settings_type: type) -> str:
        """One `--help` line: the override parameters at the default topic, their defaults."""
        topic = parameter_specs(settings_type)[self.topic_parameter].default
        qos = self.qos
        defaults = ', '.join((qos.history.name.lower(), str(qos.depth),
                              qos.reliability.name.lower()))
        return (f'  {self.parameter_prefix(topic)}.{{history,depth,reliability}} (default '
                f'{defaults}, read-only): QoS of the {self.what} {self.kind} (the topic is '
                f'{self.topic_parameter})')


def check_qos(qos: QoSProfile) -> SetParametersResult:
    """The QoS overriding validation: keep_last needs a depth of at least 1."""
    if qos.history == HistoryPolicy.KEEP_LAST and qos.depth < 1:
        return SetParametersResult(successful=False,
                                   reason=f'depth must be at least 1 with keep_last, got '
                                          f'{qos.depth}')
    return SetParametersResult(successful=True)


#: Policies a user may override: history, depth, reliability.
QOS_OVERRIDING = QoSOverridingOptions.with_default_policies(callback=check_qos)


class NodeBase(_NodeType, Generic[S]):
    """The shared lifecycle of the lompr nodes (module docstring). Mix in before the rclpy
    class; call `declare_settings` first in the constructor."""

    settings: S

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # Whether the node's clock reads /clock (use_sim_time), kept current by the clock's
        # own change callback, which rcl runs when the source changes: `clock_seconds`.
        clock = self.get_clock()
        self._simulated_time = isinstance(clock, ROSClock) and clock.ros_time_is_active
        self._time_source_handle = clock.create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=None, on_clock_change=True),
            post_callback=self._on_time_source)
        self.callback_failures = 0
        self.last_callback_failure = ''
        self.log_throttle = LogThrottle(DEFAULT_THROTTLE_PERIOD, clock=self.clock_seconds)
        self._specs: dict[str, ParameterSpec] = {}
        #: Incompatible-QoS events and peers of the endpoints made here (the `qos` status).
        self.qos_watch = QosWatch(self, self.guard, self.warn_throttled)
        #: Wall and CPU time of every guarded callback, logging call and garbage collection.
        self.callback_times = CallbackTimes()
        #: What the process asked of the kernel and what it refused (`common.run_node` sets
        #: it once the nodes are built; the `scheduling` status).
        self.scheduling_outcome = SchedulingOutcome()
        gc.callbacks.append(self.callback_times.on_gc)

    # -- hooks a node overrides ---------------------------------------------------------

    def validate_settings(self, changes: dict[str, Any]) -> str | None:
        """Why changed settings values are refused (None to accept); runs after the generic
        checks, before anything is changed."""
        del changes
        return None

    def apply_settings(self, previous: S, changed: frozenset[str]) -> None:
        """Act on accepted changes; `self.settings` is already the new snapshot."""
        del previous, changed

    def on_callback_failure(self, where: str) -> None:
        """Called after a callback raised (counted and logged already)."""
        del where

    # -- settings ---------------------------------------------------------------------------

    def declare_settings(self, settings_type: type[S]) -> S:
        """Declare the parameters of `settings_type`, keep the snapshot in `self.settings`,
        and validate and apply every later change (module docstring)."""
        self._specs = parameter_specs(settings_type)
        self.settings = declare_parameters(self, settings_type)
        self._update_throttle()
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(
            self.guard('parameter change', self._apply_parameters))
        return self.settings

    def _settings_changes(self, parameters: Sequence[Parameter]) -> dict[str, Any]:
        return {p.name: self._specs[p.name].settings_value(p.value) for p in parameters
                if p.name in self._specs}

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        changes = self._settings_changes(parameters)
        if not changes:
            return SetParametersResult(successful=True)
        reason = changes_problem(self._specs, changes)
        if reason is None:
            try:
                reason = self.validate_settings(changes)
            except Exception as err:  # noqa: BLE001 - a validation that fails refuses the change
                reason = f'{type(err).__name__}: {err}'
        return SetParametersResult(successful=reason is None, reason=reason or '')

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        changes = self._settings_changes(parameters)
        if not changes:
            return
        previous = self.settings
        self.settings = replace(previous, **changes)
        self._update_throttle()
        self.apply_settings(previous, frozenset(changes))

    def _update_throttle(self) -> None:
        self.log_throttle.period = float(getattr(
            self.settings, 'warning_throttle_period', DEFAULT_THROTTLE_PERIOD))

    # -- endpoints --------------------------------------------------------------------------

    def advertise(self, endpoint: Endpoint) -> Publisher:
        """The publisher of `endpoint` (a lifecycle publisher on a lifecycle node)."""
        create = (self.create_lifecycle_publisher if isinstance(self, LifecycleNodeMixin)
                  else self.create_publisher)
        topic = self.resolve_topic_name(getattr(self.settings, endpoint.topic_parameter))
        try:
            publisher = create(endpoint.msg_type, topic, copy.copy(endpoint.qos),
                               qos_overriding_options=QOS_OVERRIDING,
                               event_callbacks=self.qos_watch.publisher_events(topic))
        except (InvalidQosOverridesError, RuntimeError) as err:
            raise self._qos_error(endpoint, topic, err) from err
        return self.qos_watch.watch(publisher)

    def subscribe(self, endpoint: Endpoint, callback: Callable[[Any], None], *,
                  raw: bool = False) -> Subscription:
        """The subscription of `endpoint`; `callback` runs through `guard`. `raw`: the
        callback gets the serialized bytes (see `wire`), not a message object."""
        topic = self.resolve_topic_name(getattr(self.settings, endpoint.topic_parameter))
        try:
            subscription = self.create_subscription(
                endpoint.msg_type, topic, self.guard(endpoint.what, callback),
                copy.copy(endpoint.qos), qos_overriding_options=QOS_OVERRIDING, raw=raw,
                event_callbacks=self.qos_watch.subscription_events(topic))
        except (InvalidQosOverridesError, RuntimeError) as err:
            raise self._qos_error(endpoint, topic, err) from err
        return self.qos_watch.watch(subscription)

    def _qos_error(self, endpoint: Endpoint, topic: str, err: Exception) -> QosOverrideError:
        prefix = endpoint.parameter_prefix(topic)
        return QosOverrideError(f'{prefix}.*: {err}')

    def start_timer(self, period: float, where: str, callback: Callable[[], None], *,
                    clock: Clock | None = None) -> Timer:
        """A timer of the node's clock (or `clock`) whose callback runs through `guard`."""
        return self.create_timer(period, self.guard(where, callback), clock=clock)

    # -- time -------------------------------------------------------------------------------

    def clock_seconds(self) -> float:
        """The node's clock now [s]: ROS time, /clock under use_sim_time (0 before the first
        /clock message), else the system time.

        Read several times per sample (rate meters, staleness): without simulated time it
        is the system time, which rcl reads as `time.time_ns` does (CLOCK_REALTIME), read
        here without `Clock.now()`'s Time object and locks (0.1 against ~10 us)."""
        return self.clock_ns() * 1e-9

    def clock_ns(self) -> int:
        """The node's clock now in integer ns (the same clock as `clock_seconds`). Under
        simulated time read from the clock's handle, the value `Clock.now()` returns without
        the Time object it builds and the handle's guard against a concurrent destruction
        (the node's clock lives as long as the node, read on its executor's thread): 1-2
        against 6-9 us, several times a sample."""
        if not self._simulated_time:
            return time.time_ns()
        return int(self.get_clock().handle.get_now().nanoseconds)

    def _on_time_source(self, jump: TimeJump) -> None:
        if jump.clock_change == ClockChange.ROS_TIME_ACTIVATED:
            self._simulated_time = True
        elif jump.clock_change == ClockChange.ROS_TIME_DEACTIVATED:
            self._simulated_time = False

    def destroy_node(self) -> None:
        self._time_source_handle.unregister()
        with contextlib.suppress(ValueError):
            gc.callbacks.remove(self.callback_times.on_gc)
        super().destroy_node()

    def rate_meter(self, window: float) -> RateMeter:
        """A `RateMeter` over `window` seconds of the node's clock."""
        return RateMeter(window, clock=self.clock_seconds)

    # -- the callback-exception policy ------------------------------------------------------

    def guard(self, where: str, callback: Callable[..., None]) -> Callable[..., None]:
        """`callback` under the node's one callback-exception policy (module docstring)."""
        def guarded(*args: Any) -> None:
            self._run_guarded(where, callback, args)
        return guarded

    def _run_guarded(self, where: str, function: Callable[..., None], args: tuple[Any, ...],
                     *, failure_hook: bool = True) -> None:
        try:
            self.callback_times.measure(where, function, *args)
        except Exception as err:  # noqa: BLE001 - the nodes' one callback-exception policy
            self.callback_failures += 1
            self.last_callback_failure = f'{where}: {type(err).__name__}: {err}'
            self.warn_throttled(f'failure {where}', f'{where} callback failed '
                                                    f'({type(err).__name__}: {err})')
            if failure_hook:  # a failing hook is counted and logged, and not called again
                self._run_guarded(f'{where} failure hook', self.on_callback_failure, (where,),
                                  failure_hook=False)

    def callback_values(self) -> dict[str, object]:
        """Key-values of the callback failures for a diagnostic status."""
        return {'callback_failures': self.callback_failures,
                'last_callback_failure': self.last_callback_failure}

    # -- diagnostics and logging ------------------------------------------------------------

    def start_diagnostics(self, topic: str, period: float,
                          hardware_id: str = '') -> DiagnosticsPublisher:
        """A `DiagnosticsPublisher` on `topic` (QoS overridable), every `period` seconds, its
        statuses about the `hardware_id` parameter, else `hardware_id`."""
        diagnostics = DiagnosticsPublisher(
            self, topic, period, hardware_id=getattr(self.settings, 'hardware_id', '')
            or hardware_id, qos=copy.copy(DIAGNOSTICS_QOS),
            qos_overriding_options=QOS_OVERRIDING, guard=self.guard,
            event_callbacks=self.qos_watch.publisher_events(topic),
            apart=self.callback_times.apart)
        self.qos_watch.watch(diagnostics.publisher)
        diagnostics.add('qos', self.qos_watch.status)
        diagnostics.add('callback timing', lambda: self.callback_times.status(
            bool(getattr(self.settings, 'callback_histograms', False))))
        diagnostics.add('scheduling', lambda: self.scheduling_outcome.status())
        return diagnostics

    def warn_throttled(self, key: str, text: str) -> None:
        """Log a warning, at most one per `key` and throttle period."""
        message = self.log_throttle.filter(key, text)
        if message is not None:
            self.callback_times.measure('logging', self.get_logger().warning, message)

    def log_line(self, level: Level, text: str) -> None:
        """Log `text` at `level` (a ROS-free part's line): a warning throttled per its
        text, an error or information as it comes."""
        # rclpy binds a severity to each line that logs: one line per severity
        if level is Level.WARN:
            self.warn_throttled(text, text)
        elif level >= Level.ERROR:
            self.get_logger().error(text)
        else:
            self.get_logger().info(text)


def node_help(settings_type: type, endpoints: Sequence[Endpoint] = ()) -> list[str]:
    """`--help` lines of a node (`common.run_node`): its parameters, from the settings
    dataclass, and the QoS override parameters of its endpoints and /diagnostics."""
    lines = settings_help(settings_type)
    lines += [endpoint.help_line(settings_type) for endpoint in endpoints]
    if 'diagnostics_topic' in parameter_specs(settings_type):
        diagnostics = Endpoint('publisher', None, 'diagnostics_topic', DIAGNOSTICS_QOS,
                               'diagnostics')
        lines.append(diagnostics.help_line(settings_type))
        lines.append(USE_FQN.help_line(USE_FQN_PARAMETER))
    return lines
