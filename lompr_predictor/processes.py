# SPDX-License-Identifier: Apache-2.0
"""Processes that stop when told: child processes stopped the way `ros2 launch` stops them
(SIGINT, then SIGTERM, then SIGKILL: `stop_processes`), and a command that stops on SIGTERM
as on Ctrl-C (`stop_on_signals`), and a child that ends with its parent (`end_with_parent`).

A process that hangs instead says where: one that called `dump_tracebacks_on_signal` (every
node executable) writes each thread's Python traceback to its stderr on `TRACEBACK_SIGNAL`,
which `stop_processes(..., tracebacks=True)` sends before SIGKILL. The dump comes from
faulthandler's C signal handler, so it is written also while the main thread is stuck in a
library call (a middleware that hangs at exit); a hang below Python shows as such.

Why three steps and not SIGINT then SIGKILL: a SIGINT can be lost. A process started by a job
that runs in the background inherits SIGINT ignored, so one that arrives while a node is still
importing (before it installs its own handler) does nothing, and the node then runs on. SIGTERM
is never inherited ignored, and a running node stops on it as cleanly as on SIGINT. SIGKILL is
for a process that still hangs (a Fast DDS participant can hang at exit).
"""

from __future__ import annotations

import contextlib
import faulthandler
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from types import FrameType
from typing import Any, NamedTuple

#: Seconds a process gets to exit after SIGINT before it is sent SIGTERM (`ros2 launch`'s
#: `sigterm_timeout`).
INTERRUPT_TIMEOUT = 5.0
#: Seconds a process gets to exit after SIGTERM before it is killed (`sigkill_timeout`).
TERMINATE_TIMEOUT = 5.0
#: The signal on which a process that called `dump_tracebacks_on_signal` writes every
#: thread's Python traceback to stderr.
TRACEBACK_SIGNAL = signal.SIGUSR1
#: Seconds a hung process gets to write its tracebacks before it is killed.
TRACEBACK_TIMEOUT = 1.0


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
    tracebacks: bool = False,
) -> list[Stopped]:
    """Stop every process still running, all at once (each step signals all that remain, then
    waits one deadline for them), reading each one's piped output while waiting for it (a
    child blocked on a full pipe would not exit); one `Stopped` per process, in order. With
    `tracebacks` (processes that called `dump_tracebacks_on_signal`: to any other the signal
    is fatal) one that outlived SIGTERM is asked for its tracebacks before SIGKILL."""
    outputs: list[tuple[Any, Any]] = [(None, None)] * len(processes)
    sent: list[signal.Signals | None] = [None] * len(processes)
    pending = list(range(len(processes)))
    steps = ((signal.SIGINT, interrupt_timeout), (signal.SIGTERM, terminate_timeout),
             *(((TRACEBACK_SIGNAL, TRACEBACK_TIMEOUT),) if tracebacks else ()),
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


def dump_tracebacks_on_signal() -> None:
    """From now on `TRACEBACK_SIGNAL` makes this process write every thread's Python
    traceback to its standard error (module docstring); nothing where it has none."""
    stream = sys.__stderr__
    with contextlib.suppress(AttributeError, ValueError, OSError):
        if stream is not None:
            faulthandler.register(TRACEBACK_SIGNAL, file=stream, all_threads=True)


class StopSignal(KeyboardInterrupt):
    """SIGINT or SIGTERM asked this process to stop (`stop_on_signals`). A KeyboardInterrupt,
    so that whatever cleans up after Ctrl-C cleans up after a supervisor's SIGTERM too."""

    def __init__(self, number: signal.Signals) -> None:
        self.signal = number
        super().__init__(number.name)

    @property
    def exit_code(self) -> int:
        """The shell's code of a process ended by this signal: 128 + its number."""
        return 128 + int(self.signal)


#: The signal that stopped the current `stop_on_signals` block, once one has.
_stopped_by: signal.Signals | None = None


def stop_signal() -> signal.Signals | None:
    """The signal that stopped the current `stop_on_signals` block, if one did (None outside
    a block). An error raised after it may be the stop itself, come out as another exception
    from library code it landed in (a clean-up there that raised its own error): code inside
    the block that handles errors takes it as the stop; the block itself lets it out as the
    `StopSignal`."""
    return _stopped_by


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """Inside, the first SIGINT or SIGTERM raises `StopSignal` in the main thread and later
    ones are ignored, so that the clean-up the first one starts (stopping child processes,
    recording their work) is not itself cut short. A signal the process inherited ignored
    (SIGINT in a job a shell script started in the background) stays ignored. The previous
    handlers come back after the block; outside the main thread (no handlers there) this
    does nothing. An error (an `Exception`) that leaves the block after a stop leaves it as
    that stop's `StopSignal`, chained from the error: whoever cleans up after a stop does
    after this one too."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    global _stopped_by
    outer, _stopped_by = _stopped_by, None

    def stop(number: int, frame: FrameType | None) -> None:
        del frame
        global _stopped_by
        if _stopped_by is None:
            _stopped_by = signal.Signals(number)
            raise StopSignal(_stopped_by)

    wanted = [number for number in (signal.SIGINT, signal.SIGTERM)
              if signal.getsignal(number) is not signal.SIG_IGN]
    previous = {number: signal.signal(number, stop) for number in wanted}
    try:
        yield
    except Exception as error:
        if _stopped_by is not None:  # the stop, come out of library code as another error
            raise StopSignal(_stopped_by) from error
        raise
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        _stopped_by = outer


#: Seconds between a child's looks at whether its parent still runs (`end_with_parent`).
PARENT_CHECK_PERIOD = 0.25
#: The exit code of a child that ended because its parent had ended.
PARENT_GONE_EXIT = 3


def end_with_parent(period: float = PARENT_CHECK_PERIOD,
                    parent: int | None = None) -> threading.Thread:
    """End this process (at once, `PARENT_GONE_EXIT`) once the process that started it has
    ended, whatever ended it: a daemon thread that looks every `period` seconds whether this
    process was handed to another parent. For a child in its own session (no signal of the
    parent's group reaches it) whose work is worth nothing without its parent: a node
    killed with SIGKILL leaves no orphan working on, nor its output behind. `parent`: the
    pid the parent gave the child (its own), so that a parent that ended before this call
    (while the child imported its libraries: seconds) ends the child at once; None: the
    parent this process has now."""
    if parent is None:
        parent = os.getppid()
    elif os.getppid() != parent:
        os._exit(PARENT_GONE_EXIT)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period)
        os._exit(PARENT_GONE_EXIT)

    thread = threading.Thread(target=watch, name='end-with-parent', daemon=True)
    thread.start()
    return thread
