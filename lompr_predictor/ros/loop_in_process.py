# SPDX-License-Identifier: Apache-2.0
"""The closed loop in one process (`closed_loop`): the twin, kinematics and predictor nodes
on one executor and private topic names, with a collector node that keeps every sample.

The predictor's staleness counts wall time here (the twin publishes no /clock), and its
counters come straight from its core (`OnlinePredictor.counts`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.context import Context
from rclpy.executors import Executor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import JointState

from lompr_predictor.progress import ProgressBar, progress_bar
from lompr_predictor.robot.description import MEASURED_JOINTS
from lompr_predictor.ros import kinematics_node, predictor_node, twin_node
from lompr_predictor.ros.common import events_executor, spin_until
from lompr_predictor.ros.kinematics_node import KinematicsNode
from lompr_predictor.ros.loop_settings import (
    ClosedLoopError,
    LoopRun,
    LoopSettings,
    loop_counts,
    loop_parameters,
)
from lompr_predictor.ros.predictor_node import PredictorNode
from lompr_predictor.ros.twin_node import TwinNode
from lompr_predictor.stamps import stamp_to_ns
from lompr_predictor.threads import torch_threads
from lompr_predictor.twin.digital_twin import DigitalTwin

#: Loggers of the nodes in the loop (their node names).
NODE_LOGGERS = (kinematics_node.NODE_NAME, predictor_node.NODE_NAME, twin_node.NODE_NAME)
#: Wall seconds the nodes may take to discover each other.
DISCOVERY_TIMEOUT = 10.0


def run_in_process(settings: LoopSettings, horizon: int, period: float, progress: bool,
                   label: str) -> LoopRun:
    """Run the loop in this process until the twin's passes are done (module docstring)."""
    # The nodes' start-up lines would interleave with the progress bar: warnings only.
    levels = {name: rclpy.logging.get_logger_effective_level(name) for name in NODE_LOGGERS}
    for name in NODE_LOGGERS:
        rclpy.logging.set_logger_level(name, rclpy.logging.LoggingSeverity.WARN)
    context = Context()
    rclpy.init(context=context, args=[])
    executor = events_executor(context)
    try:
        loop = _Loop(settings, context, executor, horizon, period)
        done = Future()
        loop.collector.on_done = lambda: done.set_result(True)
        # The loop is an entry point: torch threads as the predictor executable sets them.
        with torch_threads(loop.predictor.settings.inference_threads):
            loop.start(progress, label)
            started = time.monotonic()
            while not done.done():
                executor.spin_until_future_complete(done, timeout_sec=0.5)
                if time.monotonic() - started > settings.wall_timeout:
                    msg = (f'{label}: not finished after {settings.wall_timeout:g} s '
                           f'({loop.collector.count} of {loop.total} samples)')
                    raise ClosedLoopError(msg)
            return loop.result(time.monotonic() - started)
    finally:
        for node in executor.get_nodes():
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        context.try_shutdown()
        for name, level in levels.items():
            rclpy.logging.set_logger_level(name, level)


def loop_topics(prefix: str) -> dict[str, str]:
    """The loop's private topic names, under `prefix`."""
    return {name: f'{prefix}/{name}' for name in (
        'joint_states', 'reference', 'reference_preview', 'end_pose', 'compensation',
        'predicted_error', 'true_error', 'plant_error', 'diagnostics')}


def in_process_parameters(settings: LoopSettings, horizon: int, period: float,
                          topics: dict[str, str]) -> dict[str, dict[str, Any]]:
    """`loop_parameters` and what only the in-process loop sets: private topic names, and
    the predictor's staleness and lateness on wall time (`LoopSettings.stale_periods`,
    `late_tolerance`)."""
    shared = loop_parameters(settings, horizon, period)
    own: dict[str, dict[str, Any]] = {
        'kinematics_node': {'joint_state_topic': topics['joint_states'],
                            'end_pose_topic': topics['end_pose']},
        'predictor_node': {'stale_periods': settings.stale_periods,
                           'late_tolerance': settings.late_tolerance,
                           'end_pose_topic': topics['end_pose'],
                           'reference_topic': topics['reference'],
                           'reference_preview_topic': topics['reference_preview'],
                           'compensation_topic': topics['compensation'],
                           'predicted_error_topic': topics['predicted_error']},
        'twin_node': {'joint_state_topic': topics['joint_states'],
                      'reference_topic': topics['reference'],
                      'reference_preview_topic': topics['reference_preview'],
                      'compensation_topic': topics['compensation'],
                      'true_error_topic': topics['true_error'],
                      'plant_error_topic': topics['plant_error']},
    }
    return {node: {**values, **own[node], 'diagnostics_topic': topics['diagnostics']}
            for node, values in shared.items()}


class _Loop:
    """The nodes of one run, wired on private topics; the twin starts once all are matched."""

    def __init__(self, settings: LoopSettings, context: Context, executor: Executor,
                 horizon: int, period: float) -> None:
        self.settings = settings
        self.executor = executor
        self.horizon = horizon
        self.topics = loop_topics(f'/lompr_loop_{os.getpid()}_{id(self):x}')
        parameters = in_process_parameters(settings, horizon, period, self.topics)

        def overrides(node: str) -> list[Parameter]:
            return [Parameter(name, value=value) for name, value in parameters[node].items()]

        self.kinematics = KinematicsNode(context=context,
                                         parameter_overrides=overrides('kinematics_node'))
        self.predictor = PredictorNode(context=context,
                                       parameter_overrides=overrides('predictor_node'))
        self.twin = TwinNode(context=context, parameter_overrides=overrides('twin_node'))
        if not isinstance(self.twin.twin, DigitalTwin):
            msg = 'the closed loop runs the LOMPR twin (twin_node robot lompr)'
            raise ClosedLoopError(msg)
        #: the LOMPR twin the node runs (its path cycle gives each sample's pass)
        self.lompr = self.twin.twin
        topics = self.topics
        self.total = int(self.twin.total_samples or 0)
        self.collector = _Collector(context, topics, self.lompr, self.total, self._on_sample)
        self.switched_off_at: int | None = None
        self._bar: ProgressBar | None = None

    def start(self, progress: bool, label: str) -> None:
        """Spin the other nodes until every endpoint is matched, then start the twin."""
        for node in (self.kinematics, self.predictor, self.collector):
            self.executor.add_node(node)
        topics, graph = self.topics, self.collector
        wanted = {(topics['joint_states'], 'sub'): 2, (topics['reference'], 'sub'): 2,
                  (topics['true_error'], 'sub'): 1, (topics['plant_error'], 'sub'): 1,
                  (topics['end_pose'], 'sub'): 1, (topics['end_pose'], 'pub'): 1,
                  (topics['compensation'], 'sub'): 1, (topics['compensation'], 'pub'): 1}

        def matched() -> bool:
            return all((graph.count_subscribers(t) if kind == 'sub' else
                        graph.count_publishers(t)) >= n for (t, kind), n in wanted.items())

        if not spin_until(self.executor, matched, DISCOVERY_TIMEOUT):
            msg = f'the closed-loop nodes did not discover each other in {DISCOVERY_TIMEOUT} s'
            raise ClosedLoopError(msg)
        self._bar = progress_bar(total=self.total, desc=label, unit='sample',
                                 disable=not progress)
        self.executor.add_node(self.twin)

    def _on_sample(self, index: int) -> None:
        """Called by the collector for every sample the twin ran."""
        switch = self.settings.switch_off_at
        if switch is not None and self.switched_off_at is None and index + 1 >= switch:
            self.predictor.set_parameters([Parameter('compensation_enabled', value=False)])
            self.switched_off_at = index + 1
        if self._bar is not None and ((index + 1) % 50 == 0 or index + 1 == self.total):
            self._bar.n = index + 1
            self._bar.refresh()

    def result(self, wall_seconds: float) -> LoopRun:
        if self._bar is not None:
            self._bar.close()
        twin, core = self.twin, self.predictor.core
        counts = loop_counts({**twin.run_document(), **twin.log.counts()}, core.counts(),
                             kinematics_rejected=self.kinematics.rejected.counts())
        data = self.collector.arrays()
        cycle = self.lompr.cycle
        return LoopRun(
            settings=self.settings, horizon=self.horizon,
            sample_period=self.lompr.params.sample_period, stamps=data['stamps'],
            reference=data['reference'], joints=data['joints'],
            true_error=data['true_error'], plant_error=data['plant_error'],
            pass_index=cycle.pass_index(0, self.total), in_pass=cycle.in_pass(0, self.total),
            switched_off_at=self.switched_off_at, wall_seconds=wall_seconds, counts=counts)


class _Collector(Node):
    """Keeps every joint state, reference and debug error of the run, by sample index, and
    calls `on_sample(index)` once the twin's true error of a sample has arrived."""

    def __init__(self, context: Context, topics: dict[str, str], twin: DigitalTwin,
                 total: int, on_sample: Callable[[int], None]) -> None:
        super().__init__('lompr_closed_loop_collector', context=context)
        self.twin = twin
        self.total = total
        self.on_sample = on_sample
        self.on_done: Callable[[], None] | None = None
        self.count = 0
        self._data = {'joints': np.full((total, len(MEASURED_JOINTS)), np.nan),
                      'reference': np.full((total, 3), np.nan),
                      'true_error': np.full((total, 2), np.nan),
                      'plant_error': np.full((total, 2), np.nan)}
        self._seen = np.zeros((total, 4), dtype=bool)
        # Deep enough never to drop: lockstep keeps the collector within a few samples.
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(JointState, topics['joint_states'], self._joints, qos)
        self.create_subscription(PoseStamped, topics['reference'], self._reference, qos)
        self.create_subscription(Vector3Stamped, topics['true_error'],
                                 lambda msg: self._vector(msg, 'true_error', 2), qos)
        self.create_subscription(Vector3Stamped, topics['plant_error'],
                                 lambda msg: self._vector(msg, 'plant_error', 3), qos)

    def arrays(self) -> dict[str, np.ndarray]:
        """Stamps and the collected arrays (NaN where a message never came)."""
        return {'stamps': self.twin.stamps(0, self.total), **self._data}

    def _index(self, msg: Any) -> int:
        stamp = stamp_to_ns(msg.header.stamp)
        return self.twin.index_of(stamp)

    def _store(self, index: int, column: int) -> None:
        self._seen[index, column] = True
        if column == 2:
            self.on_sample(index)
        if self._seen[index].all():
            self.count += 1
            if self.count == self.total and self.on_done is not None:
                self.on_done()

    def _joints(self, msg: JointState) -> None:
        index = self._index(msg)
        names = list(msg.name)
        self._data['joints'][index] = [msg.position[names.index(n)] for n in MEASURED_JOINTS]
        self._store(index, 0)

    def _reference(self, msg: PoseStamped) -> None:
        index = self._index(msg)
        position = msg.pose.position
        self._data['reference'][index] = position.x, position.y, position.z
        self._store(index, 1)

    def _vector(self, msg: Vector3Stamped, name: str, column: int) -> None:
        index = self._index(msg)
        self._data[name][index] = msg.vector.x, msg.vector.y
        self._store(index, column)
