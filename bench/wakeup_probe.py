# SPDX-License-Identifier: Apache-2.0
"""This machine's wake-up tail, without the nodes: how late a lone SCHED_FIFO thread wakes.

A thread at SCHED_FIFO `--priority` sleeps to a 1 ms grid for `--seconds` and records how
late each wake-up is (a cyclictest in miniature), with nothing beside it, then beside each
load the chaos soak and the node's adaptation put on the machine: a torch training loop
that allocates and frees 80 MB a step at SCHED_IDLE on the last CPU (an adaptation
attempt), two busy loops at the normal policy (the soak's CPU hog), the same torch loop at
nice 10 (a training job). No priority of the nodes' goes below what this thread sees: a
closed loop with one sample of lead is judged against it (docs/lab/soak_chaos.md).
Prints p50 / p99 / p99.9 / max [us] and the wake-ups over 1, 2 and 3 ms per load.
Run: .venv/bin/python bench/wakeup_probe.py (about 3 minutes; root or CAP_SYS_NICE).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np

PERIOD = 0.001  # s: the grid the thread sleeps to
SETTLE = 3.0  # s: a load runs this long before the thread starts

TORCH_LOOP = ('import sys, time, torch\n'
              'torch.set_num_threads(1)\n'
              'net = torch.nn.LSTM(16, 64, batch_first=True)\n'
              'optimiser = torch.optim.Adam(net.parameters())\n'
              'end = time.monotonic() + float(sys.argv[1])\n'
              'while time.monotonic() < end:\n'
              '    y, _ = net(torch.randn(512, 25, 16))\n'
              '    loss = y.pow(2).mean(); optimiser.zero_grad(); loss.backward()\n'
              '    optimiser.step()\n'
              '    del loss, y\n'
              '    big = torch.ones(20_000_000); del big  # 80 MB mapped, touched, freed\n')
BUSY_LOOP = 'import sys, time\nend = time.monotonic() + float(sys.argv[1])\n' \
            'while time.monotonic() < end: pass\n'


def lateness(seconds: float, priority: int) -> np.ndarray:
    """Wake-up lateness [us] of this thread sleeping to the grid for `seconds` at
    SCHED_FIFO `priority` (the normal policy again after: the loads it starts must not
    inherit it)."""
    late = np.empty(int(seconds / PERIOD))
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    try:
        target = time.monotonic() + PERIOD
        for i in range(len(late)):
            wait = target - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            late[i] = time.monotonic() - target
            target = max(target + PERIOD, time.monotonic())  # no pile-up after a delay
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return late * 1e6


@contextlib.contextmanager
def load(kind: str, seconds: float) -> Iterator[None]:
    """The load `kind` running for `seconds` (+ the settling time) beside this process."""
    last_cpu = str((os.cpu_count() or 1) - 1)
    python = [sys.executable, '-c']
    commands = {
        'nothing': [],
        'torch loop, SCHED_IDLE, last CPU': [
            ['chrt', '--idle', '0', 'taskset', '-c', last_cpu, *python, TORCH_LOOP]],
        'two busy loops, normal policy': [[*python, BUSY_LOOP]] * 2,
        'torch loop, nice 10': [['nice', '-n', '10', *python, TORCH_LOOP]],
    }[kind]
    processes = [subprocess.Popen([*c, str(seconds + SETTLE)]) for c in commands]
    try:
        time.sleep(SETTLE if processes else 0.0)
        yield
    finally:
        for process in processes:
            process.kill()
            process.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--seconds', type=float, default=40.0, help='per load [s]')
    parser.add_argument('--priority', type=int, default=50, help='SCHED_FIFO priority')
    args = parser.parse_args()
    print(f'{"beside it":34s} {"p50":>6s} {"p99":>6s} {"p99.9":>7s} {"max":>7s} us  '
          'wake-ups over 1 / 2 / 3 ms')
    for kind in ('nothing', 'torch loop, SCHED_IDLE, last CPU',
                 'two busy loops, normal policy', 'torch loop, nice 10'):
        with load(kind, args.seconds):
            late = lateness(args.seconds, args.priority)
        p50, p99, p999 = np.percentile(late, [50, 99, 99.9])
        over = ' / '.join(str(int((late > ms * 1000).sum())) for ms in (1, 2, 3))
        print(f'{kind:34s} {p50:6.0f} {p99:6.0f} {p999:7.0f} {late.max():7.0f}     '
              f'{over} of {len(late)}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
