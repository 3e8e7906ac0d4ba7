# SPDX-License-Identifier: Apache-2.0
"""ros.loop_watch: a loop's domain reserved once per process, its environment set only
inside the block, and its monitor counting the twin's samples from /clock and keeping the
predictor's statuses by name (the loops themselves: test/system)."""

from __future__ import annotations

import os

import pytest
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rosgraph_msgs.msg import Clock

from lompr_predictor.ros.loop_watch import (
    LoopMonitor,
    environment,
    loop_context,
    loop_domain_id,
    loop_environment,
)
from lompr_predictor.stamps import ns_to_sec_nanosec
from lompr_predictor.twin.digital_twin import EPOCH_NS

PERIOD_NS = 4_000_000


def test_the_environment_is_the_loops_only_inside_the_block(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv('ROS_AUTOMATIC_DISCOVERY_RANGE', raising=False)
    monkeypatch.setenv('ROS_DOMAIN_ID', '7')
    assert loop_domain_id() == loop_domain_id()  # reserved once
    values = loop_environment(42)
    assert values == {'ROS_DOMAIN_ID': '42', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    with environment(values):
        assert os.environ['ROS_DOMAIN_ID'] == '42'
        assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    assert os.environ['ROS_DOMAIN_ID'] == '7'
    assert 'ROS_AUTOMATIC_DISCOVERY_RANGE' not in os.environ  # unset again, not ''


def test_the_monitor_counts_samples_and_keeps_the_predictors_statuses() -> None:
    context = loop_context(loop_domain_id())
    try:
        monitor = LoopMonitor(context, PERIOD_NS)
        sec, nanosec = ns_to_sec_nanosec(EPOCH_NS + 9 * PERIOD_NS)
        monitor._on_clock(Clock(clock=Time(sec=sec, nanosec=nanosec)))
        assert monitor.samples == 10  # the instants 0 to 9
        monitor._diagnostics(DiagnosticArray(status=[
            DiagnosticStatus(name='predictor_node: prediction',
                             values=[KeyValue(key='predictions_total', value='12')]),
            DiagnosticStatus(name='kinematics_node: joint states',
                             values=[KeyValue(key='received_total', value='99')])]))
        assert monitor.statuses == {'prediction': {'predictions_total': '12'}}
        monitor.destroy_node()
    finally:
        rclpy.shutdown(context=context)
