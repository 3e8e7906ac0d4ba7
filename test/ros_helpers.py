# SPDX-License-Identifier: Apache-2.0
"""Launch-free ROS test helpers: one context, one executor, wait with deadlines.

Use through the `ros` fixture of conftest.py:

    def test_x(ros: RosHarness) -> None:
        node = ros.add(KinematicsNode(context=ros.context))
        received = ros.collect('/lompr/end_pose', PoseStamped)
        publisher = ros.node.create_publisher(JointState, '/joint_states', 10)
        ros.wait_for_subscribers(publisher)            # discovery, not a sleep
        ros.wait_for_publishers('/lompr/end_pose')
        publisher.publish(msg)
        ros.spin_until(lambda: len(received) == 1, what='one end pose')

Everything is created on the harness's own `rclpy.context.Context` and torn down with it.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.client import Client
from rclpy.context import Context
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile

from lompr_predictor.processes import stop_processes
from lompr_predictor.ros.common import spin_until

DEFAULT_TIMEOUT = 10.0
#: Wait [s] for the answer to a repeatable service request before it is sent again.
RESEND_AFTER = 2.0


class RosHarness:
    """A context, an executor spinning every node added, and a helper node `node` for the
    test's own publishers and subscriptions."""

    def __init__(self, executor_factory: Callable[[Context], Executor] | None = None) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        factory = executor_factory or (lambda context: SingleThreadedExecutor(context=context))
        self.executor = factory(self.context)
        self._nodes: list[Node] = []
        self.node = self.add(Node('test_harness', context=self.context))

    def add(self, node: Node) -> Any:
        """Spin `node` on the harness executor and destroy it at shutdown; returns it."""
        self.executor.add_node(node)
        self._nodes.append(node)
        return node

    def collect(self, topic: str, msg_type: type, qos: QoSProfile | int = 10) -> list[Any]:
        """Subscribe the helper node to `topic`; the returned list fills as messages arrive."""
        received: list[Any] = []
        self.node.create_subscription(msg_type, topic, received.append, qos)
        return received

    def spin_until(
        self, condition: Callable[[], bool], timeout: float = DEFAULT_TIMEOUT, what: str = '',
    ) -> None:
        """Spin until `condition()` holds; fail the test with `what` after `timeout` s."""
        if not spin_until(self.executor, condition, timeout):
            raise AssertionError(f'timed out after {timeout} s waiting for {what or condition}')

    def call(
        self, client: Client, request: Any, what: str, *, repeatable: bool = False,
        timeout: float = DEFAULT_TIMEOUT,
    ) -> Any:
        """The response of `client` to `request`, failing the test with `what` after `timeout`.

        `service_is_ready` says the server has matched our requests, not that it has matched
        our reader of its replies: Fast DDS discovers the two on their own, and a reply sent
        before its reader is matched is dropped (after rmw_fastrtps' 100 ms wait, with a
        warning in the server). A `repeatable` request (safe to do twice: a query, a
        transition that is refused) is therefore sent again every `RESEND_AFTER` s until an
        answer comes; once one has come, that service's replies are matched for good.
        """
        self.spin_until(client.service_is_ready, timeout, f'the {what} service')
        deadline = time.monotonic() + timeout
        futures = []
        while time.monotonic() < deadline:
            futures.append(client.call_async(request))
            wait = min(RESEND_AFTER if repeatable else timeout, deadline - time.monotonic())
            if spin_until(self.executor, lambda: any(f.done() for f in futures), wait):
                for future in futures:
                    if not future.done():
                        client.remove_pending_request(future)
                return next(f for f in futures if f.done()).result()
            if not repeatable:
                break
        raise AssertionError(f'timed out after {timeout} s waiting for {what} '
                             f'({len(futures)} request(s) sent)')

    def spin_for(self, seconds: float) -> None:
        """Spin for a fixed time: only to give a message that must NOT come its chance."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)

    def wait_for_subscribers(
        self, publisher: Publisher, count: int = 1, timeout: float = DEFAULT_TIMEOUT,
    ) -> None:
        """Spin until `publisher` has matched `count` subscriptions (discovery done)."""
        self.spin_until(lambda: publisher.get_subscription_count() >= count, timeout,
                        f'{count} subscriber(s) on {publisher.topic_name}')

    def wait_for_publishers(
        self, topic: str, count: int = 1, timeout: float = DEFAULT_TIMEOUT,
    ) -> None:
        """Spin until the graph shows `count` publishers on `topic` (discovery done)."""
        self.spin_until(lambda: self.node.count_publishers(topic) >= count, timeout,
                        f'{count} publisher(s) on {topic}')

    def shutdown(self) -> None:
        """Destroy nodes, executor and context (the fixture's teardown)."""
        for node in reversed(self._nodes):
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown()
        self.context.try_shutdown()


def start_executable(name: str, *ros_arguments: str) -> subprocess.Popen[str]:
    """A lompr executable (`lompr_predictor.ros.<name>`'s `main()`, as its console script
    runs it) as a process with `--ros-args` `ros_arguments`, in this session's private DDS
    domain (inherited environment); stdout and stderr piped."""
    return subprocess.Popen(
        [sys.executable, '-m', f'lompr_predictor.ros.{name}', '--ros-args', *ros_arguments],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop_process(process: subprocess.Popen[str]) -> tuple[int, str]:
    """Stop a node process as `ros2 launch` does (`processes.stop_processes`); the exit code
    and stderr. The stderr is also echoed to the test's captured stderr, which pytest shows
    when the test fails (so a failure in the test body shows what the node said)."""
    stopped = stop_processes([process], tracebacks=True)[0]
    sys.stderr.write(f'node process {process.pid} exited with {stopped.returncode} '
                     f'(stopped by {stopped.signal}), its stderr:\n{stopped.stderr}\n')
    return stopped.returncode, stopped.stderr


def stamp_ns(msg: Any) -> int:
    """A stamped message's header stamp in integer ns."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def set_stamp(msg: Any, ns: int) -> None:
    """Set a stamped message's header stamp to `ns` (integer ns)."""
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(ns), 1_000_000_000)


def xy(msgs: list[Any]) -> np.ndarray:
    """(N, 2) X/Y of Vector3Stamped messages."""
    return np.array([[m.vector.x, m.vector.y] for m in msgs])


def latest_status(diagnostics: list[DiagnosticArray], name: str) -> dict[str, Any] | None:
    """Key-values of the latest status called `name` ('<node>: <status>') in the collected
    /diagnostics, plus its '_message' and '_level'; None before the first."""
    for array in reversed(diagnostics):
        for status in array.status:
            if status.name == name:
                return {kv.key: kv.value for kv in status.values} | {
                    '_message': status.message, '_level': status.level}
    return None
