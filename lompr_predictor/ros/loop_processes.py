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

import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lompr_predictor.online.predictor_counts import (
    CountsMissingError,
    PredictorCounts,
    read_counts,
)
from lompr_predictor.processes import Stopped, stop_processes
from lompr_predictor.progress import ProgressBar, progress_bar
from lompr_predictor.robot.paths import build_cycle
from lompr_predictor.ros.common import events_executor
from lompr_predictor.ros.loop_settings import (
    ClosedLoopError,
    LoopRun,
    LoopSettings,
    loop_counts,
    loop_parameters,
)
from lompr_predictor.ros.loop_watch import (
    LoopMonitor,
    loop_context,
    loop_domain_id,
    loop_environment,
)
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


def ros_value(value: Any) -> str:
    """A parameter value as `-p name:=value` writes it."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def loop_commands(settings: LoopSettings, horizon: int, period: float,
                  run_log: Path) -> dict[str, list[str]]:
    """The three executables of a cross-process loop, as `python -m` commands (the same
    `main()` as the console scripts)."""
    return {node: [sys.executable, '-m', f'lompr_predictor.ros.{node}', '--ros-args',
                   *(item for name, value in values.items()
                     for item in ('-p', f'{name}:={ros_value(value)}'))]
            for node, values in loop_parameters(settings, horizon, period, run_log).items()}


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
    the ROS domain `domain`, and watches them from a node of its own (`LoopMonitor`)."""

    def __init__(self, commands: dict[str, list[str]], folder: Path, period_ns: int,
                 domain: int) -> None:
        self.commands = commands
        self.logs = {name: folder / f'{name}.log' for name in commands}
        self.period_ns = period_ns
        self.domain = domain
        self.environment = loop_environment(domain)
        self.processes: dict[str, subprocess.Popen[bytes]] = {}

    def run(self, run_log: Path, total: int, wall_timeout: float, bar: ProgressBar,
            label: str) -> _Watched:
        """Start the processes and wait until the twin has written `run_log` (a process
        that exits before, or `wall_timeout` seconds, is a `ClosedLoopError`); stop them."""
        context = loop_context(self.domain)
        executor = events_executor(context)
        monitor = LoopMonitor(context, self.period_ns)
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
