"""Child processes stopped the way `ros2 launch` stops them: SIGINT, then SIGTERM, then SIGKILL.

Why three steps and not SIGINT then SIGKILL: a SIGINT can be lost. A process started by a job
that runs in the background inherits SIGINT ignored, so one that arrives while a node is still
importing (before it installs its own handler) does nothing, and the node then runs on. SIGTERM
is never inherited ignored, and a running node stops on it as cleanly as on SIGINT. SIGKILL is
for a process that still hangs (a Fast DDS participant can hang at exit).
"""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Sequence
from typing import Any, NamedTuple

#: Seconds a process gets to exit after SIGINT before it is sent SIGTERM (`ros2 launch`'s
#: `sigterm_timeout`).
INTERRUPT_TIMEOUT = 5.0
#: Seconds a process gets to exit after SIGTERM before it is killed (`sigkill_timeout`).
TERMINATE_TIMEOUT = 5.0


class Stopped(NamedTuple):
    """How a process ended: its output (None for a stream that was not piped), exit code, and
    the signal that stopped it (None: it had exited before)."""

    stdout: Any
    stderr: Any
    returncode: int
    signal: signal.Signals | None


def stop_processes(
    processes: Sequence[subprocess.Popen[Any]],
    *,
    interrupt_timeout: float = INTERRUPT_TIMEOUT,
    terminate_timeout: float = TERMINATE_TIMEOUT,
) -> list[Stopped]:
    """Stop every process still running, all at once (each step signals all that remain, then
    waits one deadline for them), reading each one's piped output while waiting for it (a
    child blocked on a full pipe would not exit); one `Stopped` per process, in order."""
    outputs: list[tuple[Any, Any]] = [(None, None)] * len(processes)
    sent: list[signal.Signals | None] = [None] * len(processes)
    pending = list(range(len(processes)))
    steps = ((signal.SIGINT, interrupt_timeout), (signal.SIGTERM, terminate_timeout),
             (signal.SIGKILL, None))
    for number, timeout in steps:
        for index in pending:
            if processes[index].poll() is None:
                processes[index].send_signal(number)
                sent[index] = number
        deadline = None if timeout is None else time.monotonic() + timeout
        remaining = []
        for index in pending:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                outputs[index] = processes[index].communicate(timeout=left)
            except subprocess.TimeoutExpired:
                remaining.append(index)
        pending = remaining
        if not pending:
            break
    return [Stopped(out, err, process.returncode, number)
            for (out, err), process, number in zip(outputs, processes, sent, strict=True)]
