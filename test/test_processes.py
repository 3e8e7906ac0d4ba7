"""Stopping child processes: SIGINT, then SIGTERM, then SIGKILL, all processes at once."""

from __future__ import annotations

import signal
import subprocess
import sys

from lompr_predictor.processes import stop_processes

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


def test_a_process_that_has_exited_is_not_signalled() -> None:
    process = subprocess.Popen([sys.executable, '-c', 'print(7)'], stdout=subprocess.PIPE,
                               text=True)
    process.wait()
    (stopped,) = stop_processes([process])
    assert stopped == ('7\n', None, 0, None)
