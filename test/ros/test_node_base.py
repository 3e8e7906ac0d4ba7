# SPDX-License-Identifier: Apache-2.0
"""The shared ROS layer: settings from one declaration, the node base (plain and lifecycle
node), QoS overrides, the callback-exception policy, diagnostics, run_node."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Vector3Stamped
from model_helpers import save_constant
from rclpy.context import Context
from rclpy.exceptions import InvalidParameterValueException
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, ReliabilityPolicy
from ros_helpers import RosHarness

from lompr_predictor.monitoring import Level, Status
from lompr_predictor.ros.common import EXECUTORS, DiagnosticsPublisher, make_executor, run_node
from lompr_predictor.ros.node_base import (
    OUTPUT_QOS,
    SENSOR_INPUT_QOS,
    Endpoint,
    NodeBase,
    QosOverrideError,
    node_help,
)
from lompr_predictor.ros.parameters import declare_settings, parameter, parameter_specs

pytestmark = pytest.mark.ros


def _even(value: int) -> str | None:
    return None if value % 2 == 0 else 'must be even'


@dataclass(frozen=True)
class ToySettings:
    period: float = parameter(1.0, 'a period [s]', minimum=0.1, maximum=10.0)
    count: int = parameter(4, 'a count', minimum=0, maximum=100, read_only=True, check=_even)
    mode: str = parameter('fast', 'a mode', choices=('fast', 'slow'))
    names: tuple[str, ...] = parameter(('a', 'b'), 'some names', read_only=True)
    input_topic: str = parameter('/toy_in', 'input topic', read_only=True)
    output_topic: str = parameter('/toy_out', 'output topic', read_only=True)
    diagnostics_topic: str = parameter('/toy_diagnostics', 'diagnostics topic',
                                       read_only=True)


TOY_INPUT = Endpoint('subscription', Vector3Stamped, 'input_topic', SENSOR_INPUT_QOS,
                     'toy input')
TOY_OUTPUT = Endpoint('publisher', Vector3Stamped, 'output_topic', OUTPUT_QOS, 'toy output')


class ToyNode(NodeBase[ToySettings], Node):
    """Echoes its input; raises on a message with x < 0 (a callback failure)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('toy', **kwargs)
        self.declare_settings(ToySettings)
        self.applied: list[frozenset[str]] = []
        self.failures: list[str] = []
        self.output = self.advertise(TOY_OUTPUT)
        self.input = self.subscribe(TOY_INPUT, self.on_input)

    def on_input(self, msg: Vector3Stamped) -> None:
        if msg.vector.x < 0:
            raise ValueError(f'negative x {msg.vector.x}')
        self.output.publish(msg)

    def validate_settings(self, changes: dict[str, Any]) -> str | None:
        if changes.get('period') == 9.0:
            raise RuntimeError('validation blew up')
        return 'slow needs a period of 2 s or more' if (
            changes.get('mode') == 'slow' and changes.get('period', self.settings.period) < 2
        ) else None

    def apply_settings(self, previous: ToySettings, changed: frozenset[str]) -> None:
        self.applied.append(changed)
        if self.settings.period == 7.0:
            raise RuntimeError('apply blew up')

    def on_callback_failure(self, where: str) -> None:
        self.failures.append(where)
        if len(self.failures) == 2:
            raise RuntimeError('the hook fails too')


def overrides(**values: object) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def test_settings_are_declared_with_descriptors_from_one_declaration(ros: RosHarness) -> None:
    node = ros.add(Node('plain', context=ros.context,
                        parameter_overrides=overrides(period=2.5, names=['x', 'y', 'z'])))
    settings = declare_settings(node, ToySettings)
    assert settings == ToySettings(period=2.5, names=('x', 'y', 'z'))
    period = node.describe_parameter('period')
    assert period.description == 'a period [s]'
    assert (period.floating_point_range[0].from_value,
            period.floating_point_range[0].to_value) == (0.1, 10.0)
    count = node.describe_parameter('count')
    assert count.read_only and count.integer_range[0].to_value == 100
    assert node.describe_parameter('mode').additional_constraints == 'one of: fast, slow'
    assert list(parameter_specs(ToySettings)) == [
        'period', 'count', 'mode', 'names', 'input_topic', 'output_topic', 'diagnostics_topic']


@pytest.mark.parametrize(('values', 'match'), [
    ({'period': 50.0}, 'period'), ({'mode': 'sometimes'}, 'must be one of fast, slow'),
    ({'count': 3}, 'must be even')])
def test_a_bad_override_fails_at_start(ros: RosHarness, values: dict[str, object],
                                       match: str) -> None:
    with pytest.raises(InvalidParameterValueException, match=match):
        ToyNode(context=ros.context, parameter_overrides=overrides(**values))


def test_changes_are_validated_then_applied_as_a_new_snapshot(ros: RosHarness) -> None:
    node: ToyNode = ros.add(ToyNode(context=ros.context))
    first = node.settings
    assert node.set_parameters([Parameter('period', value=0.5)])[0].successful
    assert node.settings == ToySettings(period=0.5) and first.period == 1.0
    assert node.applied == [frozenset({'period'})]
    refused = {
        'period': (20.0, 'period'),  # rclpy: out of range
        'count': (6, 'read-only'),  # rclpy: read-only
        'mode': ('sometimes', 'mode must be one of fast, slow'),  # choices
    }
    for name, (value, reason) in refused.items():
        (result,) = node.set_parameters([Parameter(name, value=value)])
        assert not result.successful and reason in result.reason, result.reason
    # the node's own hook; a raising hook refuses with the reason
    (result,) = node.set_parameters([Parameter('mode', value='slow')])
    assert not result.successful and result.reason == 'slow needs a period of 2 s or more'
    (result,) = node.set_parameters([Parameter('period', value=9.0)])
    assert not result.successful and result.reason == 'RuntimeError: validation blew up'
    assert node.set_parameters_atomically([Parameter('mode', value='slow'),
                                           Parameter('period', value=3.0)]).successful
    assert node.settings == ToySettings(period=3.0, mode='slow')
    assert node.applied[-1] == frozenset({'mode', 'period'}) and len(node.applied) == 2
    assert node.callback_failures == 0


def test_a_failing_callback_is_counted_logged_and_handed_to_the_hook(ros: RosHarness) -> None:
    node: ToyNode = ros.add(ToyNode(context=ros.context))
    echoes = ros.collect('/toy_out', Vector3Stamped, 10)
    publisher = ros.node.create_publisher(Vector3Stamped, '/toy_in', 10)
    ros.wait_for_subscribers(publisher)
    ros.wait_for_publishers('/toy_out')
    for x in (1.0, -1.0, 2.0, -2.0, 3.0):
        msg = Vector3Stamped()
        msg.vector.x = x
        publisher.publish(msg)
    ros.spin_until(lambda: len(echoes) == 3, what='the three good messages echoed')
    assert [m.vector.x for m in echoes] == [1.0, 2.0, 3.0]  # the spin went on
    # two failures of the callback, and the second call of the hook failed too
    assert node.failures == ['toy input', 'toy input']
    assert node.callback_failures == 3
    assert node.last_callback_failure == 'toy input failure hook: RuntimeError: the hook fails too'
    assert node.callback_values()['callback_failures'] == 3
    # a parameter change whose application fails goes the same way
    assert node.set_parameters([Parameter('period', value=7.0)])[0].successful
    assert node.failures[-1] == 'parameter change' and node.callback_failures == 4
    # every run is timed by kind, the failing ones too, and the warnings' log calls
    rows = node.callback_times.rows
    assert rows['toy input'].total == 5 and rows['parameter change'].total >= 1
    assert rows['logging'].total >= 1
    assert node.callback_times.status().values['toy input.runs'] == 5


def test_qos_overrides_take_effect_on_the_endpoints(ros: RosHarness) -> None:
    default: ToyNode = ros.add(ToyNode(context=ros.context))
    assert default.input.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
    assert default.output.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    assert SENSOR_INPUT_QOS.reliability == ReliabilityPolicy.BEST_EFFORT  # not written into
    node: ToyNode = ros.add(ToyNode(namespace='other', context=ros.context, parameter_overrides=[
        Parameter('qos_overrides./toy_in.subscription.reliability', value='reliable'),
        Parameter('qos_overrides./toy_in.subscription.depth', value=7),
        Parameter('qos_overrides./toy_out.publisher.history', value='keep_all')]))
    assert node.input.qos_profile.depth == 7
    assert node.output.qos_profile.history == HistoryPolicy.KEEP_ALL
    described = node.describe_parameter('qos_overrides./toy_in.subscription.reliability')
    assert described.read_only

    def reliability(toy: ToyNode) -> ReliabilityPolicy | None:
        for info in toy.get_subscriptions_info_by_topic('/toy_in'):
            if info.node_name == 'toy' and info.node_namespace == toy.get_namespace():
                return info.qos_profile.reliability
        return None

    # what the middleware was given, as the ROS graph reports it
    ros.spin_until(lambda: reliability(node) == ReliabilityPolicy.RELIABLE,
                   what='a reliable subscription in the graph')
    assert reliability(default) == ReliabilityPolicy.BEST_EFFORT


@pytest.mark.filterwarnings('ignore:A zero depth with KEEP_LAST:UserWarning')
@pytest.mark.parametrize(('name', 'value', 'match'), [
    ('qos_overrides./toy_in.subscription.reliability', 'sometimes',
     r'qos_overrides\./toy_in\.subscription\.\*: .*`reliability`: `sometimes`'),
    ('qos_overrides./toy_out.publisher.depth', 0, 'depth must be at least 1')])
def test_a_bad_qos_override_stops_the_node_with_one_message(
        ros: RosHarness, name: str, value: object, match: str) -> None:
    with pytest.raises(QosOverrideError, match=match):
        ToyNode(context=ros.context, parameter_overrides=overrides(**{name: value}))


class ManagedToy(NodeBase[ToySettings], LifecycleNode):
    """The node base on a managed node: settings in the constructor, endpoints on
    configure."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('managed_toy', **kwargs)
        self.declare_settings(ToySettings)
        self.received = 0

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.output = self.advertise(TOY_OUTPUT)
        self.input = self.subscribe(TOY_INPUT, self.on_input)
        return super().on_configure(state)

    def on_input(self, msg: Vector3Stamped) -> None:
        self.received += 1
        self.output.publish(msg)


def test_the_node_base_serves_a_lifecycle_node(ros: RosHarness) -> None:
    node: ManagedToy = ros.add(ManagedToy(context=ros.context, parameter_overrides=overrides(
        **{'period': 2.0, 'qos_overrides./toy_out.publisher.depth': 3})))
    assert node.settings.period == 2.0
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.output.qos_profile.depth == 3
    assert type(node.output).__name__ == 'LifecyclePublisher'
    echoes = ros.collect('/toy_out', Vector3Stamped, 10)
    publisher = ros.node.create_publisher(Vector3Stamped, '/toy_in', 10)
    ros.wait_for_subscribers(publisher)
    ros.wait_for_publishers('/toy_out')
    publisher.publish(Vector3Stamped())  # inactive: the lifecycle publisher drops the echo
    ros.spin_until(lambda: node.received == 1, what='the message received')
    ros.spin_for(0.2)
    assert echoes == []
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    publisher.publish(Vector3Stamped())
    ros.spin_until(lambda: len(echoes) == 1, what='an echo once active')
    assert node.set_parameters([Parameter('period', value=3.0)])[0].successful
    assert node.settings.period == 3.0


def test_diagnostics_publisher_publishes_every_provider(ros: RosHarness) -> None:
    node = ros.add(Node('common_test', context=ros.context))
    diagnostics = DiagnosticsPublisher(node, topic='/test_diagnostics', period=0.1,
                                       hardware_id='lompr')
    diagnostics.add('input', lambda: Status(Level.WARN, '3 rejected', {'rejected_total': 3}))

    def broken() -> Status:
        raise ZeroDivisionError('no samples')

    diagnostics.add('broken', broken)
    arrays = ros.collect('/test_diagnostics', DiagnosticArray)
    ros.spin_until(lambda: len(arrays) >= 3, what='three diagnostic arrays')
    # a status an array, sent as it is read, the providers in turn
    assert [len(array.status) for array in arrays[:3]] == [1, 1, 1]
    (first,), (broken_status,) = arrays[0].status, arrays[1].status
    assert arrays[2].status[0].name == first.name
    assert first.name == 'common_test: input'
    assert first.level == DiagnosticStatus.WARN
    assert first.hardware_id == 'lompr'
    assert [(kv.key, kv.value) for kv in first.values] == [('rejected_total', '3')]
    assert broken_status.level == DiagnosticStatus.ERROR
    assert 'ZeroDivisionError: no samples' in broken_status.message


def test_diagnostics_go_on_in_wall_time_while_the_simulated_clock_stands_still(
        ros: RosHarness) -> None:
    # simulated time and no /clock: the node's clock stands at zero and its timers never fire
    node = ros.add(Node('stalled_clock_test', context=ros.context,
                        parameter_overrides=[Parameter('use_sim_time', value=True)]))
    diagnostics = DiagnosticsPublisher(node, topic='/test_stalled_diagnostics', period=0.2)
    diagnostics.add('inputs', lambda: Status(Level.WARN, 'samples out of order'))
    diagnostics.add('model', lambda: Status(Level.OK, 'loaded'))
    arrays = ros.collect('/test_stalled_diagnostics', DiagnosticArray)
    ros.spin_until(lambda: len(arrays) >= 4, what='statuses while the clock stands still')
    first = len(arrays)
    ros.spin_for(2.0)
    # at the rate of the ticks (one every 0.1 s), not every other one
    assert len(arrays) - first >= 14
    assert node.get_clock().now().nanoseconds == 0
    names = [array.status[0].name for array in arrays[:4]]
    assert names == ['stalled_clock_test: inputs', 'stalled_clock_test: model'] * 2
    assert all(array.header.stamp.sec == 0 == array.header.stamp.nanosec
               for array in arrays[:4])  # stamped by the node's clock, as ever


def test_diagnostics_wait_for_the_node_between_two_samples_while_they_flow(
        ros: RosHarness) -> None:
    node = ros.add(Node('quiet_moment_test', context=ros.context))
    diagnostics = DiagnosticsPublisher(node, topic='/test_quiet_diagnostics', period=1.0)
    between = [False]  # whether the node is inside `between_samples` right now
    read: list[tuple[float, bool]] = []  # (when, between) of every status read

    def status() -> Status:
        read.append((time.monotonic(), between[0]))
        return Status(Level.OK, 'fine')

    for name in ('inputs', 'model'):  # a tick every 0.5 s
        diagnostics.add(name, status)

    def answer() -> None:  # a sample answered every 10 ms
        between[0] = True
        diagnostics.between_samples()
        between[0] = False

    stream = node.create_timer(0.01, answer)
    ros.spin_for(2.2)
    node.destroy_timer(stream)
    stopped = time.monotonic()
    ros.spin_for(1.3)
    flowing = [inside for when, inside in read if when < stopped]
    after = [inside for when, inside in read if when >= stopped]
    # while samples flow every status is read between two of them, none at its tick
    assert len(flowing) >= 3 and all(flowing[1:])
    # once they stop, the ticks send the statuses again (the one waiting among them)
    assert len(after) >= 2 and not any(after)


def four_statuses(ros: RosHarness, name: str) -> tuple[DiagnosticsPublisher, list[Any]]:
    """Node `name`'s publisher of statuses a, b, c, d, ticking every 10 s (no tick in a
    test: `step` drives it), and the arrays it sends."""
    node = ros.add(Node(name, context=ros.context))
    diagnostics = DiagnosticsPublisher(node, topic=f'/{name}_diagnostics', period=40.0)
    for status in ('a', 'b', 'c', 'd'):
        diagnostics.add(status, lambda: Status(Level.OK, 'fine'))
    arrays = ros.collect(f'/{name}_diagnostics', DiagnosticArray)
    ros.wait_for_subscribers(diagnostics.publisher)
    return diagnostics, arrays


def test_a_status_asked_for_goes_with_the_next_tick_out_of_its_turn_once_a_period(
        ros: RosHarness) -> None:
    diagnostics, arrays = four_statuses(ros, 'soon_test')
    diagnostics.step()  # the round: a
    diagnostics.soon('c')
    diagnostics.soon('c')  # asked again: still once
    diagnostics.step()  # c out of its turn, then the round's b
    diagnostics.soon('c')  # within the period: waits for its turn
    diagnostics.step()  # the round's c
    diagnostics.soon('d')
    diagnostics.between_samples()  # asked for: sent at the node's next quiet moment
    ros.spin_until(lambda: len(arrays) >= 5, what='five statuses')
    ros.spin_for(0.2)
    names = [array.status[0].name.removeprefix('soon_test: ') for array in arrays]
    assert names == ['a', 'c', 'b', 'c', 'd']  # d once: asked for, and its turn
    with pytest.raises(ValueError, match="no status 'e'"):
        diagnostics.soon('e')


def test_a_watched_status_goes_out_of_its_turn_at_the_tick_its_check_holds(
        ros: RosHarness) -> None:
    diagnostics, arrays = four_statuses(ros, 'watch_test')
    ended = [False, False, True, True, False]  # the check's answer at each tick
    diagnostics.watch('d', lambda: ended.pop(0))
    for _ in range(5):
        diagnostics.step()
    ros.spin_until(lambda: len(arrays) >= 6, what='six statuses')
    ros.spin_for(0.2)
    names = [array.status[0].name.removeprefix('watch_test: ') for array in arrays]
    assert names == ['a', 'b', 'd', 'c', 'd', 'a']  # held twice: once a period out of turn
    assert not ended
    with pytest.raises(ValueError, match="no status 'e'"):
        diagnostics.watch('e', lambda: True)


def test_run_node_help_lists_parameters_and_qos_overrides(
        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        run_node(lambda context: Node('never', context=context), description='A test node.',
                 parameters_help=node_help(ToySettings, (TOY_INPUT, TOY_OUTPUT)),
                 argv=['prog', '--help'])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert 'A test node.' in out
    assert 'period (default 1.0 [0.1, 10.0]): a period [s]' in out
    assert "mode (default 'fast' {fast|slow}): a mode" in out
    assert "names (default ['a', 'b'], read-only): some names" in out
    assert ('qos_overrides./toy_in.subscription.{history,depth,reliability} (default '
            'keep_last, 1000, best_effort, read-only): QoS of the toy input subscription (the '
            'topic is input_topic)') in out
    assert 'qos_overrides./toy_out.publisher.{history' in out
    assert 'qos_overrides./toy_diagnostics.publisher.{history,depth,reliability} (default ' \
           'keep_last, 10, reliable' in out


def _flatten(prefix: str, tree: dict[str, Any]) -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f'{prefix}.{key}' if prefix else key
        flat.update(_flatten(name, value) if isinstance(value, dict) else {name: value})
    return flat


@pytest.mark.parametrize('node', ['kinematics_node', 'predictor_node',
                                  'command_compensator_node'])
def test_parameter_files_hold_the_declared_defaults(node: str) -> None:
    """config/<node>.yaml lists every parameter with the default of its one declaration, and
    no qos_overrides: their keys are resolved topic names, which would name the root
    namespace's topics and do nothing in another (the QoS is the declared default)."""
    import importlib
    from pathlib import Path

    import yaml

    module = importlib.import_module(f'lompr_predictor.ros.{node}')
    settings_type = {'kinematics_node': 'KinematicsNodeSettings',
                     'predictor_node': 'PredictorNodeSettings',
                     'command_compensator_node': 'CommandCompensatorSettings'}[node]
    specs = parameter_specs(getattr(module, settings_type))
    path = Path(__file__).parents[2] / 'lompr_predictor' / 'config' / f'{node}.yaml'
    values = _flatten('', yaml.safe_load(path.read_text())[f'/**/{node}']['ros__parameters'])
    assert values == {name: spec.ros_default for name, spec in specs.items()}


def test_executors_by_name() -> None:
    context = Context()
    rclpy.init(context=context)
    try:
        kinds = [type(make_executor(name, context)).__name__ for name in EXECUTORS]
        assert kinds == ['EventsExecutor', 'SingleThreadedExecutor']
        with pytest.raises(ValueError, match='unknown executor'):
            make_executor('multi', context)
    finally:
        context.try_shutdown()


# -- faults: incompatible QoS ---------------------------------------------------------------

@pytest.mark.faults
def test_incompatible_qos_is_counted_and_warns_on_diagnostics(ros: Any, tmp_path: Path) -> None:
    from geometry_msgs.msg import Vector3Stamped
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile

    from lompr_predictor.monitoring import Level
    from lompr_predictor.ros.predictor_node import PredictorNode

    model = save_constant(tmp_path / 'model.pt')
    node = ros.add(PredictorNode(context=ros.context, parameter_overrides=[
        Parameter('model_path', value=str(model))]))
    assert node.qos_watch.status().level == Level.OK
    # a subscriber asking for transient-local durability from a volatile publisher
    ros.node.create_subscription(Vector3Stamped, '/lompr/compensation', lambda _: None,
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    ros.spin_until(lambda: node.qos_watch.incompatible.total > 0, what='an incompatible-QoS event')
    status = node.qos_watch.status()
    assert status.level == Level.WARN and '/lompr/compensation publisher' in status.message
    assert status.values['incompatible_qos./lompr/compensation publisher'] >= 1
    assert 'durability' in node.qos_watch.last


FROZEN_HEAP_PROBE = """
import gc
from rclpy.node import Node
from lompr_predictor.ros.common import run_node

seen = []

def build(context):
    node = Node('freeze_probe', context=context)
    def probe():
        seen.append(gc.get_freeze_count())
        context.try_shutdown()
    node.create_timer(0.01, probe)
    return node

code = run_node(build, description='probe', argv=['probe'])
print(code, seen[0], len(gc.get_objects()))
"""


def test_run_node_spins_with_the_start_up_heap_frozen(tmp_path: Path) -> None:
    """The objects the libraries and the node made before spinning are out of the
    collector's sight (a full collection over them stalls a callback for long)."""
    result = subprocess.run([sys.executable, '-c', FROZEN_HEAP_PROBE], capture_output=True,
                            text=True, timeout=60, check=False)
    code, frozen, tracked = (int(field) for field in result.stdout.split())
    assert code == 0
    assert frozen > 10_000  # rclpy's and the node's objects, not a handful
    assert tracked < frozen / 10  # what the collector still walks is what came after


def test_the_stream_settings_are_the_predictors_declared_parameters() -> None:
    """`StreamSettings` has no defaults of its own: each field but the model's sample period
    is the predictor node's parameter of the same name, so it is declared once."""
    from lompr_predictor.online.faults import StreamSettings
    from lompr_predictor.ros.predictor_settings import PredictorNodeSettings

    fields = dataclasses.fields(StreamSettings)
    assert all(item.default is dataclasses.MISSING for item in fields)
    specs = parameter_specs(PredictorNodeSettings)
    changed = {name: spec.default * 2 for name, spec in specs.items()
               if name in {item.name for item in fields} and name != 'sample_period'}
    assert set(changed) == {item.name for item in fields} - {'sample_period'}
    stream = dataclasses.replace(PredictorNodeSettings(), **changed).stream(0.004)
    assert dataclasses.asdict(stream) == {**changed, 'sample_period': 0.004}


EXECUTOR_TIMING_PROBE = """
from dataclasses import dataclass
from rclpy.node import Node
from lompr_predictor.ros.common import EXECUTOR_ROW, run_node
from lompr_predictor.ros.node_base import NodeBase

class Probe(NodeBase, Node):
    pass

def build(context):
    node = Probe('timing_probe', context=context)
    def tick():
        rows = node.callback_times.rows
        if 'tick' in rows and rows['tick'].total >= 60:  # the first tick is not in yet
            print(rows['tick'].total, rows[EXECUTOR_ROW].total, rows[EXECUTOR_ROW].max_ns)
            context.try_shutdown()
    node.start_timer(0.005, 'tick', tick)
    return node

run_node(build, description='probe', argv=['probe'])
"""


def test_run_node_times_the_executors_own_work_per_callback() -> None:
    """Beside the callbacks, the executor's own CPU time (the spin's minus the callbacks')
    is recorded once per callback it ran."""
    result = subprocess.run([sys.executable, '-c', EXECUTOR_TIMING_PROBE], capture_output=True,
                            text=True, timeout=60, check=False)
    ticks, executor_runs, longest_ns = (int(field) for field in result.stdout.split())
    assert ticks == 60
    # one per tick of the spin steps (0.1 s, up to 20 ticks each) that have ended, never
    # of the one still running; one per step would be 2 or 3
    assert 5 <= executor_runs <= 60
    assert 0 < longest_ns < 1_000_000_000


def test_the_node_clock_under_simulated_time_is_the_ros_clock(ros: RosHarness) -> None:
    """`clock_ns` reads the clock's handle, not `Clock.now()`: the same nanoseconds, as
    /clock sets them, and the system time once simulated time is switched off."""
    from rclpy.clock import ROSClock
    from rclpy.time import Time

    node: ToyNode = ros.add(ToyNode(context=ros.context,
                                    parameter_overrides=overrides(use_sim_time=True)))
    clock = node.get_clock()
    assert isinstance(clock, ROSClock)
    assert node.clock_ns() == clock.now().nanoseconds == 0  # before the first /clock
    clock.set_ros_time_override(Time(nanoseconds=1_234_567_890_123))
    assert node.clock_ns() == clock.now().nanoseconds == 1_234_567_890_123
    assert node.clock_seconds() == pytest.approx(1234.567890123)
    node.set_parameters([Parameter('use_sim_time', value=False)])
    assert abs(node.clock_ns() - time.time_ns()) < 5_000_000_000


@pytest.mark.parametrize('name', EXECUTORS)
def test_the_spin_steps_leave_nothing_behind_on_either_executor(
        ros: RosHarness, name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The spin waits on a future that never completes, a fresh one each step: rclpy's own
    executors add a done-callback to the future at every call, which would pile up on one
    kept for days (ten a second)."""
    from lompr_predictor.ros import common

    monkeypatch.setattr(common, 'SPIN_STEP', 0.001)
    executor = make_executor(name, ros.context)
    futures: list[Any] = []
    stop = common.StopRequest()

    class Recording:  # the executor, each future it is given kept
        def spin_until_future_complete(self, future: Any, timeout_sec: float) -> None:
            futures.append(future)
            executor.spin_until_future_complete(future, timeout_sec=timeout_sec)
            stop.requested = len(futures) >= 50

    try:
        common._spin_timed(cast(Any, Recording()), ros.context, stop, [])
    finally:
        executor.shutdown()
    assert len(futures) == 50 and len({id(f) for f in futures}) == 50
    assert max(len(f._callbacks) for f in futures) <= 2  # what one step's call adds
    assert not any(f.done() for f in futures)


def test_the_executor_row_counts_the_callbacks_it_dispatched_not_those_run_apart(
        ros: RosHarness, monkeypatch: pytest.MonkeyPatch) -> None:
    """A callback one node calls `apart` from its own (the pipeline's end pose) is no
    callback of the executor: its own CPU is shared among the ticks it dispatched only."""
    from lompr_predictor.ros import common

    class Tick(NodeBase, Node):
        pass

    monkeypatch.setattr(common, 'SPIN_STEP', 0.02)
    caller, called = Tick('caller', context=ros.context), Tick('called', context=ros.context)
    inner = called.guard('inner', lambda: None)
    caller.start_timer(0.002, 'tick', lambda: caller.callback_times.apart(inner))
    executor = make_executor('events', ros.context)
    stop = common.StopRequest()

    class StopAfterTicks:  # the executor, stopped once 50 ticks have run
        def spin_until_future_complete(self, future: Any, timeout_sec: float) -> None:
            executor.spin_until_future_complete(future, timeout_sec=timeout_sec)
            tick = caller.callback_times.rows.get('tick')
            stop.requested = tick is not None and tick.total >= 50

    try:
        for node in (caller, called):
            executor.add_node(node)
        common._spin_timed(cast(Any, StopAfterTicks()), ros.context, stop, [caller, called])
    finally:
        executor.shutdown()
        caller.destroy_node()
        called.destroy_node()
    ticks = caller.callback_times.rows['tick'].total
    assert ticks >= 50 and called.callback_times.rows['inner'].total == ticks
    for node in (caller, called):  # every tick of the ended steps, once
        assert node.callback_times.rows[common.EXECUTOR_ROW].total == ticks
