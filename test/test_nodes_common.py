"""Shared node helpers: parameter declaration, QoS from parameters, diagnostics, run_node."""

from __future__ import annotations

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from ros_helpers import RosHarness

from lompr_predictor.monitoring import Level, Status
from lompr_predictor.ros.common import (
    DiagnosticsPublisher,
    ParameterSpec,
    declare_parameters,
    qos_from_parameters,
    qos_parameter_specs,
    run_node,
)

pytestmark = pytest.mark.ros

SPECS = [
    ParameterSpec('period', 1.0, 'a period [s]', minimum=0.1, maximum=10.0),
    ParameterSpec('count', 5, 'a count', minimum=1, maximum=100, read_only=True),
    ParameterSpec('name', 'abc', 'a free string'),
    *qos_parameter_specs('input', depth=50, what='the input topic'),
]


def make_node(ros: RosHarness, name: str = 'common_test', **overrides: object) -> Node:
    return ros.add(Node(name, context=ros.context, parameter_overrides=[
        Parameter(name, value=value) for name, value in overrides.items()]))


def test_declare_parameters_sets_descriptors_and_returns_values(ros: RosHarness) -> None:
    node = make_node(ros, period=2.5)
    values = declare_parameters(node, SPECS)
    assert values == {'period': 2.5, 'count': 5, 'name': 'abc', 'input_depth': 50,
                      'input_reliability': 'reliable'}
    period = node.describe_parameter('period')
    assert period.description == 'a period [s]'
    assert (period.floating_point_range[0].from_value,
            period.floating_point_range[0].to_value) == (0.1, 10.0)
    count = node.describe_parameter('count')
    assert count.read_only and count.integer_range[0].to_value == 100
    assert 'best_effort' in node.describe_parameter('input_reliability').additional_constraints
    # rclpy enforces range and read_only; our callback enforces choices.
    assert not node.set_parameters([Parameter('period', value=20.0)])[0].successful
    assert not node.set_parameters([Parameter('count', value=6)])[0].successful
    assert node.set_parameters([Parameter('period', value=0.5)])[0].successful


def test_out_of_range_and_bad_choice_overrides_fail_at_start(ros: RosHarness) -> None:
    with pytest.raises(InvalidParameterValueException, match='period'):
        declare_parameters(make_node(ros, period=50.0), SPECS)
    with pytest.raises(InvalidParameterValueException, match='reliable, best_effort'):
        declare_parameters(make_node(ros, 'other', input_reliability='sometimes'), SPECS)


def test_qos_from_parameters() -> None:
    qos = qos_from_parameters({'out_depth': 7, 'out_reliability': 'best_effort'}, 'out')
    assert qos.depth == 7 and qos.reliability == ReliabilityPolicy.BEST_EFFORT


def test_diagnostics_publisher_publishes_every_provider(ros: RosHarness) -> None:
    node = make_node(ros)
    diagnostics = DiagnosticsPublisher(node, topic='/test_diagnostics', period=0.1,
                                       hardware_id='lompr')
    diagnostics.add('input', lambda: Status(Level.WARN, '3 rejected', {'rejected_total': 3}))

    def broken() -> Status:
        raise ZeroDivisionError('no samples')

    diagnostics.add('broken', broken)
    arrays = ros.collect('/test_diagnostics', DiagnosticArray)
    ros.spin_until(lambda: len(arrays) >= 2, what='two diagnostic arrays')
    first, broken_status = arrays[0].status
    assert first.name == 'common_test: input'
    assert first.level == DiagnosticStatus.WARN
    assert first.hardware_id == 'lompr'
    assert [(kv.key, kv.value) for kv in first.values] == [('rejected_total', '3')]
    assert broken_status.level == DiagnosticStatus.ERROR
    assert 'ZeroDivisionError: no samples' in broken_status.message


def test_run_node_help_lists_parameters(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        run_node(lambda context: Node('never', context=context), description='A test node.',
                 parameters=SPECS, argv=['prog', '--help'])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert 'A test node.' in out
    assert 'period (default 1.0 [0.1, 10.0]): a period [s]' in out
    assert "input_reliability (default 'reliable' {reliable|best_effort}, read-only)" in out
