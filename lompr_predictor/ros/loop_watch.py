# SPDX-License-Identifier: Apache-2.0
"""What both closed loops watch a run with: a private ROS domain, and a node of the loop's own
(`LoopMonitor`) that counts the twin's samples on its /clock and keeps the predictor's last
/diagnostics statuses.

Both modes run the nodes on the twin's simulated time (the twin publishes each sample's
instant on /clock, as a simulator does), on a domain of their own (`loop_domain_id`,
reserved once per process, discovery on localhost), so a run never hears another's /clock.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator
from contextlib import contextmanager

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from lompr_predictor.ros import predictor_node
from lompr_predictor.ros.domain import reserve_domain_id
from lompr_predictor.stamps import stamp_to_ns
from lompr_predictor.twin.digital_twin import EPOCH_NS


@functools.cache
def loop_domain_id() -> int:
    """The private ROS domain of this process's closed loops (reserved once)."""
    return reserve_domain_id()


def loop_environment(domain: int) -> dict[str, str]:
    """The environment a loop's nodes discover each other in: `domain`, localhost."""
    return {'ROS_DOMAIN_ID': str(domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}


@contextmanager
def environment(values: dict[str, str]) -> Iterator[None]:
    """`os.environ` with `values` set inside the block (rcl reads discovery settings from
    the environment when a context is initialised)."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def loop_context(domain: int) -> Context:
    """An initialised rclpy context on the loop's domain (shut it down with the run)."""
    context = Context()
    with environment(loop_environment(domain)):
        rclpy.init(context=context, args=[], domain_id=domain)
    return context


class LoopMonitor(Node):
    """A loop's view of its run: the twin's /clock (samples run) and the predictor's last
    /diagnostics statuses."""

    def __init__(self, context: Context, period_ns: int) -> None:
        super().__init__('lompr_loop_monitor', context=context)
        self.period_ns = period_ns
        self.samples = 0
        self.statuses: dict[str, dict[str, str]] = {}
        self.create_subscription(Clock, '/clock', self._on_clock,
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.create_subscription(DiagnosticArray, '/diagnostics', self._diagnostics,
                                 QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def _on_clock(self, msg: Clock) -> None:
        self.samples = (stamp_to_ns(msg.clock) - EPOCH_NS) // self.period_ns + 1

    def _diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.startswith(f'{predictor_node.NODE_NAME}: '):
                self.statuses[status.name.split(': ', 1)[1]] = {
                    kv.key: kv.value for kv in status.values}
