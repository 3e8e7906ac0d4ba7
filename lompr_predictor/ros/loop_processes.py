# SPDX-License-Identifier: Apache-2.0
"""The closed loop as three processes (`closed_loop`): twin_node, kinematics_node and
predictor_node started as their executables on a private ROS domain and the twin's
simulated time (/clock), as a simulator drives real nodes.

The parent watches the twin's /clock for progress and the predictor's /diagnostics for its
counters (`predictor_counts.read_counts`, the inverse of what the node writes); the twin
writes every sample into a run log, read once the run is done (with, per sample, whether
its offset had come: `LoopRun.answered`).
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from lompr_predictor.online.predictor_counts import (
    CountsMissingError,
    PredictorCounts,
    read_counts,
)
from lompr_predictor.processes import Stopped, stop_processes
from lompr_predictor.progress import ProgressBar, progress_bar
from lompr_predictor.robot.paths import build_cycle
from lompr_predictor.ros import predictor_node
from lompr_predictor.ros.common import events_executor
from lompr_predictor.ros.domain import reserve_domain_id
from lompr_predictor.ros.loop_settings import (
    ClosedLoopError,
    LoopRun,
    LoopSettings,
    loop_counts,
    loop_parameters,
)
from lompr_predictor.stamps import stamp_to_ns
from lompr_predictor.twin.digital_twin import EPOCH_NS
from lompr_predictor.twin.parameters import load_twin_parameters
from lompr_predictor.twin.run_log import read_run_log

#: Lines of a killed process's log shown: its tracebacks (`processes.TRACEBACK_SIGNAL`).
KILLED_LOG_LINES = 60


def run_processes(settings: LoopSettings, horizon: int, progress: bool,
                  label: str) -> LoopRun:
    """Run the loop as three processes until the twin's passes are done (module
    docstring)."""
    if settings.switch_off_at is not None:
        msg = 'switch_off_at needs the in-process loop (processes=False)'
        raise ClosedLoopError(msg)
    params = load_twin_parameters(settings.twin_parameters_file or None)
    cycle = build_cycle(settings.path, params.path, params.sample_period)
    total = settings.samples or (settings.lead_in_passes + settings.passes) * len(cycle)
    with tempfile.TemporaryDirectory(prefix='lompr_loop_') as folder:
        run_log = Path(folder) / 'run.npz'
        watch = _Watch(loop_commands(settings, horizon, params.sample_period, run_log),
                       Path(folder), round(params.sample_period * 1e9), loop_domain_id())
        watched = watch.run(run_log, total, settings.wall_timeout,
                            progress_bar(total=total, desc=label, unit='sample',
                                         disable=not progress), label)
        arrays, document = read_run_log(run_log)
    count = len(arrays['stamps'])
    counts = loop_counts(
        document, watched.predictor,
        processes={name: end.returncode for name, end in watched.ends.items()},
        # the signal each obeyed (SIGINT unless it was lost or the process hung at exit)
        stopped_by={name: end.signal.name if end.signal else 'exited'
                     for name, end in watched.ends.items()},
        ros_domain_id=watch.domain)
    return LoopRun(
        settings=settings, horizon=horizon, sample_period=params.sample_period,
        stamps=arrays['stamps'], reference=arrays['reference'], joints=arrays['joints'],
        true_error=arrays['true_error'], plant_error=arrays['plant_error'],
        pass_index=cycle.pass_index(0, count), in_pass=cycle.in_pass(0, count),
        switched_off_at=None, wall_seconds=watched.wall_seconds, counts=counts,
        answered=arrays['answered'])


@functools.cache
def loop_domain_id() -> int:
    """The private ROS domain of this process's cross-process loops (reserved once)."""
    return reserve_domain_id()


@contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
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


def ros_value(value: Any) -> str:
    """A parameter value as `-p name:=value` writes it."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def loop_commands(settings: LoopSettings, horizon: int, period: float,
                  run_log: Path) -> dict[str, list[str]]:
    """The three executables of a cross-process loop, as `python -m` commands (the same
    `main()` as the console scripts)."""
    parameters = loop_parameters(settings, horizon, period)
    own: dict[str, dict[str, Any]] = {
        'kinematics_node': {'use_sim_time': True}, 'predictor_node': {'use_sim_time': True},
        'twin_node': {'publish_clock': True, 'wait_for_subscribers': 1,
                      'run_log': str(run_log)}}
    return {node: [sys.executable, '-m', f'lompr_predictor.ros.{node}', '--ros-args',
                   *(item for name, value in {**shared, **own[node]}.items()
                     for item in ('-p', f'{name}:={ros_value(value)}'))]
            for node, shared in parameters.items()}


class _Monitor(Node):
    """The parent's view of a cross-process loop: the twin's /clock (progress) and the
    predictor's last /diagnostics statuses."""

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


def _log_tail(path: Path, lines: int = 15) -> str:
    try:
        return '\n'.join(path.read_text(errors='replace').splitlines()[-lines:])
    except OSError:
        return ''


@dataclass(frozen=True)
class _Watched:
    """How a cross-process run went: its wall time, how each process ended (by node name)
    and the predictor's counters as of its last /diagnostics."""

    wall_seconds: float
    ends: dict[str, Stopped]
    predictor: PredictorCounts


class _Watch:
    """Starts the loop's processes (`commands`, by node name; their logs into `folder`) on
    the ROS domain `domain`, and watches them from a node of its own (`_Monitor`)."""

    def __init__(self, commands: dict[str, list[str]], folder: Path, period_ns: int,
                 domain: int) -> None:
        self.commands = commands
        self.logs = {name: folder / f'{name}.log' for name in commands}
        self.period_ns = period_ns
        self.domain = domain
        self.environment = {'ROS_DOMAIN_ID': str(domain),
                            'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
        self.processes: dict[str, subprocess.Popen[bytes]] = {}

    def run(self, run_log: Path, total: int, wall_timeout: float, bar: ProgressBar,
            label: str) -> _Watched:
        """Start the processes and wait until the twin has written `run_log` (a process
        that exits before, or `wall_timeout` seconds, is a `ClosedLoopError`); stop them."""
        context = Context()
        with _environment(self.environment):
            rclpy.init(context=context, args=[], domain_id=self.domain)
        executor = events_executor(context)
        monitor = _Monitor(context, self.period_ns)
        executor.add_node(monitor)
        started = time.monotonic()
        try:
            self._start()
            while not run_log.exists():
                executor.spin_once(timeout_sec=0.1)
                bar.n = min(monitor.samples, total)
                bar.refresh()
                self._check(label, monitor.samples)
                if time.monotonic() - started > wall_timeout:
                    msg = (f'{label}: not finished after {wall_timeout:g} s '
                           f'({monitor.samples} of {total} samples)')
                    raise ClosedLoopError(msg)
            wall_seconds = time.monotonic() - started
            for _ in range(3):  # the last /diagnostics on their way
                executor.spin_once(timeout_sec=0.05)
            bar.n = total
            bar.close()
        finally:
            ends = dict(zip(self.processes, stop_processes(list(self.processes.values()),
                                                           tracebacks=True), strict=True))
            self._report_killed(label, ends)
            executor.remove_node(monitor)
            monitor.destroy_node()
            executor.shutdown()
            context.try_shutdown()
        try:
            return _Watched(wall_seconds, ends, read_counts(monitor.statuses))
        except CountsMissingError as err:
            msg = f'{label}: {err}'
            raise ClosedLoopError(msg) from err

    def _start(self) -> None:
        for name, command in self.commands.items():
            with open(self.logs[name], 'wb') as output:
                self.processes[name] = subprocess.Popen(
                    command, env={**os.environ, **self.environment}, stdout=output,
                    stderr=subprocess.STDOUT)

    def _report_killed(self, label: str, ends: dict[str, Stopped]) -> None:
        """Where each process that outlived SIGTERM hung (its tracebacks, the end of its log,
        which goes with the run's folder), on stderr."""
        for name, end in ends.items():
            if end.signal is signal.SIGKILL:
                sys.stderr.write(f'{label}: {name} did not stop on SIGINT or SIGTERM and was '
                                 f'killed; the end of its log:\n'
                                 f'{_log_tail(self.logs[name], KILLED_LOG_LINES)}\n')

    def _check(self, label: str, samples: int) -> None:
        """A `ClosedLoopError` with the tail of its log if a process has exited."""
        for name, process in self.processes.items():
            if process.poll() is not None:
                msg = (f'{label}: {name} exited with code {process.returncode} after '
                       f'{samples} samples:\n{_log_tail(self.logs[name])}')
                raise ClosedLoopError(msg)
