"""Thin ROS helpers the lompr_predictor nodes share.

- `ParameterSpec` + `declare_parameters`: every parameter with a description, a range or a
  set of choices, read_only where it cannot change after start, declared in one call.
- `qos_parameter_specs` + `qos_from_parameters`: a QoS profile (depth, reliability) chosen
  by parameters.
- `DiagnosticsPublisher`: a DiagnosticArray on /diagnostics about once a second, one status
  per registered provider (the model of ros/diagnostics' diagnostic_updater).
- `spin_until`: spin an executor until a condition holds or a deadline passes.
- `run_node`: the `main()` of a node executable (ros2/demos style), with `--help` listing
  the node's parameters.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.context import Context
from rclpy.exceptions import (
    InvalidParameterValueException,
    InvalidTopicNameException,
    ParameterException,
)
from rclpy.executors import Executor, ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args

from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import Level, Status

RELIABILITY_CHOICES: dict[str, ReliabilityPolicy] = {
    'reliable': ReliabilityPolicy.RELIABLE,
    'best_effort': ReliabilityPolicy.BEST_EFFORT,
}


@dataclass(frozen=True)
class ParameterSpec:
    """One ROS parameter: name, default (its type is the parameter's type), description,
    and a numeric range [minimum, maximum] or string choices."""

    name: str
    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False

    def descriptor(self) -> ParameterDescriptor:
        descriptor = ParameterDescriptor(
            name=self.name, description=self.description, read_only=self.read_only)
        if (self.minimum is None) != (self.maximum is None):
            msg = f'parameter {self.name}: give both minimum and maximum, or neither'
            raise ValueError(msg)
        if self.minimum is not None:
            if isinstance(self.default, bool) or not isinstance(self.default, (int, float)):
                msg = f'parameter {self.name}: a range needs a numeric default'
                raise ValueError(msg)
            if isinstance(self.default, int):
                descriptor.integer_range = [IntegerRange(
                    from_value=int(self.minimum), to_value=int(self.maximum), step=0)]
            else:
                descriptor.floating_point_range = [FloatingPointRange(
                    from_value=float(self.minimum), to_value=float(self.maximum), step=0.0)]
        if self.choices:
            descriptor.additional_constraints = f'one of: {", ".join(self.choices)}'
        return descriptor

    def help_line(self) -> str:
        """One line for `--help`: name, default, range or choices, description."""
        if self.minimum is not None:
            bounds = f' [{self.minimum}, {self.maximum}]'
        elif self.choices:
            bounds = f' {{{"|".join(self.choices)}}}'
        else:
            bounds = ''
        flag = ', read-only' if self.read_only else ''
        return f'  {self.name} (default {self.default!r}{bounds}{flag}): {self.description}'


def declare_parameters(node: Node, specs: Sequence[ParameterSpec]) -> dict[str, Any]:
    """Declare every spec on `node` and return {name: value} after overrides.

    rclpy itself enforces ranges, types and read_only; string choices are checked here,
    for the start value (raises `InvalidParameterValueException`) and for later sets.
    """
    values: dict[str, Any] = {}
    for spec in specs:
        value = node.declare_parameter(spec.name, spec.default, spec.descriptor()).value
        if spec.choices and value not in spec.choices:
            raise InvalidParameterValueException(
                spec.name, value, f'must be one of {", ".join(spec.choices)}')
        values[spec.name] = value
    choices = {spec.name: spec.choices for spec in specs if spec.choices}
    if choices:
        def check_choices(parameters: list[Parameter]) -> SetParametersResult:
            for parameter in parameters:
                allowed = choices.get(parameter.name)
                if allowed and parameter.value not in allowed:
                    return SetParametersResult(
                        successful=False,
                        reason=f'{parameter.name} must be one of {", ".join(allowed)}')
            return SetParametersResult(successful=True)
        node.add_on_set_parameters_callback(check_choices)
    return values


def qos_parameter_specs(
    prefix: str, *, depth: int = 10, reliability: str = 'reliable', what: str = 'topics'
) -> list[ParameterSpec]:
    """`<prefix>_depth` and `<prefix>_reliability` (read-only: fixed when the endpoints are
    created). `what` names the topics in the descriptions."""
    return [
        ParameterSpec(
            f'{prefix}_depth', depth, f'QoS history depth (keep last N) of {what}',
            minimum=1, maximum=100_000, read_only=True),
        ParameterSpec(
            f'{prefix}_reliability', reliability,
            f'QoS reliability of {what}: reliable, or best_effort (sensor-data style; '
            'a best_effort subscription also hears reliable publishers)',
            choices=tuple(RELIABILITY_CHOICES), read_only=True),
    ]


def qos_from_parameters(values: Mapping[str, Any], prefix: str) -> QoSProfile:
    """The QoS profile that `qos_parameter_specs(prefix)` parameters describe."""
    return QoSProfile(
        depth=int(values[f'{prefix}_depth']),
        reliability=RELIABILITY_CHOICES[values[f'{prefix}_reliability']])


def status_message(name: str, hardware_id: str, status: Status) -> DiagnosticStatus:
    """The diagnostic_msgs form of a `Status`."""
    return DiagnosticStatus(
        level=bytes([int(status.level)]), name=name, message=status.message,
        hardware_id=hardware_id,
        values=[KeyValue(key=str(k), value=str(v)) for k, v in status.values.items()])


class DiagnosticsPublisher:
    """Publishes one DiagnosticArray every `period` seconds with a status per provider.

    A provider is a function returning a `Status`; it is called on the node's executor, so
    it may read the node's counters without locks. A provider that raises becomes an ERROR
    status naming the exception: diagnostics never take the node down.
    Status names are '<node name>: <provider name>', as diagnostic_updater writes them.
    """

    def __init__(
        self, node: Node, topic: str = '/diagnostics', period: float = 1.0,
        hardware_id: str = '',
    ) -> None:
        self._node = node
        self._hardware_id = hardware_id
        self._providers: list[tuple[str, Callable[[], Status]]] = []
        # diagnostic_aggregator and rqt subscribe reliable, depth 10 is their default.
        self._publisher = node.create_publisher(DiagnosticArray, topic, 10)
        self._timer = node.create_timer(period, self.publish)

    def add(self, name: str, provider: Callable[[], Status]) -> None:
        """Register a status provider under `name`."""
        self._providers.append((f'{self._node.get_name()}: {name}', provider))

    def collect(self) -> DiagnosticArray:
        """Call every provider now and build the array (stamped with the node's clock)."""
        array = DiagnosticArray()
        array.header.stamp = self._node.get_clock().now().to_msg()
        for name, provider in self._providers:
            try:
                status = provider()
            except Exception as err:  # noqa: BLE001 - reported, never raised
                status = Status(Level.ERROR, f'status provider failed: {type(err).__name__}: {err}')
            array.status.append(status_message(name, self._hardware_id, status))
        return array

    def publish(self) -> None:
        """Publish the current statuses (the timer calls this every period)."""
        self._publisher.publish(self.collect())


def spin_until(executor: Executor, condition: Callable[[], bool], timeout: float) -> bool:
    """Spin `executor` until `condition()` holds (True) or `timeout` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.02)
    return True


#: Longest time [s] `run_node` spends in the executor before it looks at the context again.
SPIN_STEP = 0.1


def events_executor(context: Context) -> Executor:
    """An `rclpy.experimental.EventsExecutor` on `context`: its callbacks cost about half the
    CPU of the `SingleThreadedExecutor`'s (rclpy 7.1.6), which decides whether a node keeps
    up with 1 kHz input. Spin it with `spin_once(timeout)` or `spin_until_future_complete`,
    never `spin()` (see `run_node`). Its constructor enables faulthandler on `sys.stderr`,
    which fails when stderr is not a real file (captured by pytest, a buffer): the process's
    own stderr is used for that."""
    captured, sys.stderr = sys.stderr, sys.__stderr__
    try:
        return EventsExecutor(context=context)
    finally:
        sys.stderr = captured


def _help_epilog(specs: Sequence[ParameterSpec]) -> str:
    lines = ['ROS parameters (set with --ros-args -p NAME:=VALUE or --params-file FILE):']
    lines += [spec.help_line() for spec in specs]
    return '\n'.join(lines)


def run_node(
    node_factory: Callable[[Context], Node | Sequence[Node]],
    *,
    description: str,
    parameters: Sequence[ParameterSpec] = (),
    argv: Sequence[str] | None = None,
) -> int:
    """Run one node until Ctrl-C or shutdown (the ros2/demos pattern); returns an exit code.

    `node_factory(context)` builds the node (or several, spun by one executor, as the
    one-process pipeline does) on a fresh context. Non-ROS arguments are
    parsed here: `--help` prints `description` and the parameters. A `LomprError`, a bad
    parameter or topic name while the node starts is printed as one line and exits with code 2.
    Uses the default context, whose SIGINT handler rclpy installs (a non-default context is
    not shut down by Ctrl-C), and an `events_executor` spun in `spin_once` steps of
    `SPIN_STEP` s: rclpy 7.1.6's `EventsExecutor.spin()` never returns to Python, so it
    ignores SIGINT and burns a full core while idle, whereas these steps idle at ~0.3 % CPU
    and notice a shutdown within a step.
    """
    argv = list(sys.argv if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog=argv[0].rsplit('/', 1)[-1] if argv else None, description=description,
        epilog=_help_epilog(parameters), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.parse_args(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    context = rclpy.get_default_context()
    nodes: Sequence[Node] = ()
    try:
        built = node_factory(context)
        nodes = [built] if isinstance(built, Node) else list(built)
        executor = events_executor(context)
        for node in nodes:
            executor.add_node(node)
        while context.ok():
            executor.spin_once(timeout_sec=SPIN_STEP)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (LomprError, ParameterException, InvalidTopicNameException) as err:
        print(f'{parser.prog}: error: {err}', file=sys.stderr)
        return 2
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    return 0
