# SPDX-License-Identifier: Apache-2.0
"""Stopping child processes: SIGINT, then SIGTERM, then SIGKILL, all processes at once; and a
command stopped by SIGINT or SIGTERM alike."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from lompr_predictor import cli
from lompr_predictor.processes import StopSignal, stop_on_signals, stop_processes, stop_signal

#: A child that says it is ready, then handles the signals as its argument says: `interrupt`
#: exits 0 on SIGINT; `lost` ignores SIGINT (as one started in the background while still
#: importing) and exits 3 on SIGTERM; `stuck` ignores both.
CHILD = """
import signal, sys, time
mode = sys.argv[1]
def leave(code):
    def handler(number, frame):
        sys.stdout.write(f'bye {number}'); sys.stdout.flush(); sys.exit(code)
    return handler
signal.signal(signal.SIGINT, leave(0) if mode == 'interrupt' else signal.SIG_IGN)
signal.signal(signal.SIGTERM, leave(3) if mode == 'lost' else signal.SIG_IGN
              if mode == 'stuck' else signal.SIG_DFL)
print('ready', flush=True)
sys.stderr.write('x' * 200_000)  # more than a pipe holds: stopping must read it
sys.stderr.flush()
while True:
    time.sleep(0.01)
"""


def start(mode: str) -> subprocess.Popen[str]:
    process = subprocess.Popen([sys.executable, '-c', CHILD, mode], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    return process


def test_each_process_stops_at_the_first_signal_it_obeys() -> None:
    processes = [start(mode) for mode in ('interrupt', 'lost', 'stuck')]
    for process in processes:  # past start-up: the handlers are in place
        assert process.stdout is not None and process.stdout.readline() == 'ready\n'
    stopped = stop_processes(processes, interrupt_timeout=0.5, terminate_timeout=0.5)
    assert [s.signal for s in stopped] == [signal.SIGINT, signal.SIGTERM, signal.SIGKILL]
    assert [s.returncode for s in stopped] == [0, 3, -signal.SIGKILL]
    assert stopped[0].stdout == 'bye 2' and stopped[1].stdout == 'bye 15'
    # read while they ran (the first left while writing it)
    assert [len(s.stderr) for s in stopped[1:]] == [200_000, 200_000]


#: A child stuck in a call that ignores SIGINT and SIGTERM, as a middleware hanging at exit.
HUNG = """
import signal, time
from lompr_predictor.processes import dump_tracebacks_on_signal
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
dump_tracebacks_on_signal()
def destroy_participant():
    print('ready', flush=True)
    time.sleep(60)
destroy_participant()
"""


def test_a_hung_process_says_where_before_it_is_killed() -> None:
    process = subprocess.Popen([sys.executable, '-c', HUNG], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    assert process.stdout is not None and process.stdout.readline() == 'ready\n'
    (stopped,) = stop_processes([process], interrupt_timeout=0.3, terminate_timeout=0.3,
                                tracebacks=True)
    assert stopped.signal is signal.SIGKILL and stopped.returncode == -signal.SIGKILL
    # the main thread's stack, from the call it hangs in out
    assert 'Current thread' in stopped.stderr, stopped.stderr
    assert 'in destroy_participant' in stopped.stderr, stopped.stderr
    assert stopped.stderr.index('in destroy_participant') < stopped.stderr.index('<module>')


def test_a_process_that_has_exited_is_not_signalled() -> None:
    process = subprocess.Popen([sys.executable, '-c', 'print(7)'], stdout=subprocess.PIPE,
                               text=True)
    process.wait()
    (stopped,) = stop_processes([process])
    assert stopped == ('7\n', None, 0, None)


#: A command under `stop_on_signals`: ready, then sleeping until stopped; its clean-up sends
#: itself a second SIGTERM (ignored while it cleans up) and exits with the stop's code.
STOPPABLE = """
import os, signal, sys, time
from lompr_predictor.processes import StopSignal, stop_on_signals
with stop_on_signals():
    try:
        print('ready', flush=True)
        time.sleep(60)
    except StopSignal as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.2)
        print('stopped by', stop.signal.name, flush=True)
        sys.exit(stop.exit_code)
"""


def start_stoppable(preexec_fn: Callable[[], object] | None = None) -> subprocess.Popen[str]:
    process = subprocess.Popen([sys.executable, '-c', STOPPABLE], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, preexec_fn=preexec_fn)
    assert process.stdout is not None and process.stdout.readline() == 'ready\n'
    return process


@pytest.mark.parametrize('number', [signal.SIGINT, signal.SIGTERM], ids=lambda n: n.name)
def test_sigint_and_sigterm_stop_a_command_once(number: signal.Signals) -> None:
    """Either signal raises `StopSignal` once: the clean-up it starts is not cut short by
    another (a supervisor's SIGTERM after a Ctrl-C), and the code is 128 + the signal."""
    process = start_stoppable()
    process.send_signal(number)
    out, _ = process.communicate(timeout=30)
    assert (out, process.returncode) == (f'stopped by {number.name}\n', 128 + number)


def test_a_sigint_inherited_ignored_stays_ignored() -> None:
    """A command a shell script started in the background ignores SIGINT (the script's
    Ctrl-C is not for it); SIGTERM still stops it."""
    process = start_stoppable(preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    process.send_signal(signal.SIGINT)
    with pytest.raises(subprocess.TimeoutExpired):
        process.wait(timeout=1.0)
    process.send_signal(signal.SIGTERM)
    out, _ = process.communicate(timeout=30)
    assert (out, process.returncode) == ('stopped by SIGTERM\n', 128 + signal.SIGTERM)


def stopped_in_library_code() -> None:
    """Work a SIGTERM reaches inside library code whose clean-up raises its own error."""
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)
    except StopSignal:
        msg = 'did not possess lock'  # what Optuna's journal lock once raised here
        raise RuntimeError(msg) from None


def test_a_stop_that_comes_out_as_another_error_leaves_the_block_as_the_stop() -> None:
    """Library code a stop lands in may raise an error of its own in its clean-up: inside the
    block `stop_signal` names the stop, and the error leaves the block as that stop (chained
    from the error); outside a block there is no stop."""
    seen = []

    def stopped_and_seen() -> None:
        try:
            stopped_in_library_code()
        finally:
            seen.append(stop_signal())

    with pytest.raises(StopSignal) as raised, stop_on_signals():
        stopped_and_seen()
    assert seen == [signal.SIGTERM] and raised.value.signal == signal.SIGTERM
    assert isinstance(raised.value.__cause__, RuntimeError)
    assert stop_signal() is None


def test_a_command_stopped_inside_library_code_says_it_was_stopped(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """`lompr`: a stop that reached the command as another error is reported as the stop,
    with its exit code, not as an internal error."""
    parser = argparse.ArgumentParser(prog='lompr')
    parser.add_argument('--debug', action='store_true')
    commands = parser.add_subparsers(dest='command')
    commands.add_parser('work').set_defaults(run=lambda args: stopped_in_library_code())
    monkeypatch.setattr(cli, 'build_parser', lambda: parser)
    assert cli.main(['work']) == 128 + signal.SIGTERM
    assert capsys.readouterr().err == 'lompr work: stopped by SIGTERM\n'



def test_a_child_that_ends_with_its_parent_ends_when_the_parent_is_killed(
        tmp_path: Path) -> None:
    """A parent starts a child in its own session (no signal of the parent's reaches it)
    that calls `end_with_parent` and would sleep a minute; the parent is killed with
    SIGKILL: the child ends too (within seconds; it would sleep on a minute)."""
    child_pid = tmp_path / 'child.pid'
    child = ('import os, pathlib, time; from lompr_predictor.processes import end_with_parent; '
             f'end_with_parent(0.05); pathlib.Path({str(child_pid)!r}).write_text('
             'str(os.getpid())); time.sleep(60)')
    parent = subprocess.Popen([sys.executable, '-c', (
        'import subprocess, sys, time; '
        f'subprocess.Popen([sys.executable, "-c", {child!r}], start_new_session=True); '
        'time.sleep(60)')])
    try:
        deadline = time.monotonic() + 30
        while not child_pid.exists() or not child_pid.read_text():
            assert time.monotonic() < deadline, 'the child did not start'
            time.sleep(0.05)
        pid = int(child_pid.read_text())
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        gone_by = time.monotonic() + 5
        while _running(pid) and time.monotonic() < gone_by:
            time.sleep(0.05)
        assert not _running(pid), 'the child outlived its parent'
    finally:
        parent.kill()
        parent.wait()


def test_a_child_whose_parent_ended_before_it_asked_ends_at_once(tmp_path: Path) -> None:
    """The parent killed while the child still imports (an adaptation attempt takes seconds
    to): the child, told its parent's pid, ends at once when it asks, instead of watching
    the process it was handed to (init, or a subreaper) forever and writing its output."""
    written = tmp_path / 'written'
    child = ('import os, pathlib, sys, time; time.sleep(1.0); '
             'from lompr_predictor.processes import end_with_parent; '
             'end_with_parent(0.05, parent=int(sys.argv[1])); '
             f'pathlib.Path({str(written)!r}).write_text("by an orphan"); time.sleep(60)')
    errors = tmp_path / 'stderr.txt'
    parent = subprocess.Popen([sys.executable, '-c', (
        'import os, subprocess, sys, time; '
        f'c = subprocess.Popen([sys.executable, "-c", {child!r}, str(os.getpid())], '
        f'start_new_session=True, stderr=open({str(errors)!r}, "w")); '
        'print(c.pid, flush=True); time.sleep(60)')],
        stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        pid = int(parent.stdout.readline())
        os.kill(parent.pid, signal.SIGKILL)  # before the child's second of imports is over
        parent.wait()
        gone_by = time.monotonic() + 10
        while _running(pid) and time.monotonic() < gone_by:
            time.sleep(0.05)
        assert not _running(pid), 'the child outlived its parent'
        assert not written.exists() and errors.read_text() == ''  # ended, not failed
    finally:
        parent.kill()
        parent.wait()


def _running(pid: int) -> bool:
    """Whether process `pid` runs (an exited one not yet reaped, a zombie, does not)."""
    try:
        state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != 'Z'
