# SPDX-License-Identifier: Apache-2.0
"""The closed loop in one process (`closed_loop`): the twin, kinematics and predictor nodes
on one executor, on the twin's simulated time, as across processes (`loop_watch`: a private
domain, the twin's /clock watched for progress).

The run is read from the twin's run log once its passes are done, and the predictor's
counters come straight from its core (`OnlinePredictor.counts`).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.executors import Executor
from rclpy.parameter import Parameter

from lompr_predictor.progress import progress_bar
from lompr_predictor.ros import kinematics_node, predictor_node, twin_node
from lompr_predictor.ros.common import events_executor
from lompr_predictor.ros.kinematics_node import KinematicsNode
from lompr_predictor.ros.loop_settings import (
    ClosedLoopError,
    LoopRun,
    LoopSettings,
    loop_counts,
    loop_parameters,
)
from lompr_predictor.ros.loop_watch import LoopMonitor, loop_context, loop_domain_id
from lompr_predictor.ros.predictor_node import PredictorNode
from lompr_predictor.ros.twin_node import TwinNode
from lompr_predictor.threads import torch_threads
from lompr_predictor.twin.digital_twin import DigitalTwin
from lompr_predictor.twin.run_log import read_run_log

#: Loggers of the nodes in the loop (their node names).
NODE_LOGGERS = (kinematics_node.NODE_NAME, predictor_node.NODE_NAME, twin_node.NODE_NAME)


def run_in_process(settings: LoopSettings, horizon: int, period: float, progress: bool,
                   label: str) -> LoopRun:
    """Run the loop in this process until the twin's passes are done (module docstring)."""
    # The nodes' start-up lines would interleave with the progress bar: warnings only.
    levels = {name: rclpy.logging.get_logger_effective_level(name) for name in NODE_LOGGERS}
    for name in NODE_LOGGERS:
        rclpy.logging.set_logger_level(name, rclpy.logging.LoggingSeverity.WARN)
    context = loop_context(loop_domain_id())
    executor = events_executor(context)
    try:
        with tempfile.TemporaryDirectory(prefix='lompr_loop_') as folder:
            loop = _Loop(settings, context, executor, horizon, period, Path(folder) / 'run.npz')
            # The loop is an entry point: torch threads as the predictor executable sets them.
            with torch_threads(loop.predictor.settings.inference_threads):
                return loop.run(progress, label)
    finally:
        for node in executor.get_nodes():
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        context.try_shutdown()
        for name, level in levels.items():
            rclpy.logging.set_logger_level(name, level)


class _Loop:
    """The nodes of one run and the monitor that watches it."""

    def __init__(self, settings: LoopSettings, context: Context, executor: Executor,
                 horizon: int, period: float, run_log: Path) -> None:
        self.settings, self.executor, self.horizon = settings, executor, horizon
        self.run_log = run_log
        parameters = loop_parameters(settings, horizon, period, run_log)

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
        self.total = int(self.twin.total_samples or 0)
        self.monitor = LoopMonitor(context, round(period * 1e9))
        self.switched_off_at: int | None = None

    def run(self, progress: bool, label: str) -> LoopRun:
        """Spin the nodes until the twin has written its run log; the run."""
        for node in (self.kinematics, self.predictor, self.monitor, self.twin):
            self.executor.add_node(node)
        bar = progress_bar(total=self.total, desc=label, unit='sample', disable=not progress)
        started = time.monotonic()
        while not self.run_log.exists():
            self.executor.spin_once(timeout_sec=0.1)
            self._switch_off()
            bar.n = min(self.monitor.samples, self.total)
            bar.refresh()
            if time.monotonic() - started > self.settings.wall_timeout:
                msg = (f'{label}: not finished after {self.settings.wall_timeout:g} s '
                       f'({self.monitor.samples} of {self.total} samples)')
                raise ClosedLoopError(msg)
        bar.n = self.total
        bar.close()
        return self._result(time.monotonic() - started)

    def _switch_off(self) -> None:
        """Switch compensation off once the twin has reached `switch_off_at`."""
        switch = self.settings.switch_off_at
        if switch is not None and self.switched_off_at is None and (
                self.monitor.samples >= switch):
            self.predictor.set_parameters([Parameter('compensation_enabled', value=False)])
            self.switched_off_at = self.monitor.samples

    def _result(self, wall_seconds: float) -> LoopRun:
        arrays, document = read_run_log(self.run_log)
        counts = loop_counts(document, self.predictor.core.counts(),
                             kinematics_rejected=self.kinematics.rejected.counts())
        count, cycle = len(arrays['stamps']), self.lompr.cycle
        return LoopRun(
            settings=self.settings, horizon=self.horizon,
            sample_period=self.lompr.params.sample_period, stamps=arrays['stamps'],
            reference=arrays['reference'], joints=arrays['joints'],
            true_error=arrays['true_error'], plant_error=arrays['plant_error'],
            pass_index=cycle.pass_index(0, count), in_pass=cycle.in_pass(0, count),
            switched_off_at=self.switched_off_at, wall_seconds=wall_seconds, counts=counts,
            answered=arrays['answered'])
