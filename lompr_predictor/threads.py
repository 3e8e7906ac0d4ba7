# SPDX-License-Identifier: Apache-2.0
"""Thread counts of the numeric libraries, set once by an entry point (a CLI command, a node's
`main`, a bench), never by library code: torch's intra-op thread count is process-wide, so
the last caller would win for everyone. Also how many cores a process may use, which sets
`lompr train`'s default number of tuning processes, and how many it did use (`CoreUse`: a
process held to one thread, an adaptation attempt beside the nodes, shows that it never took
more than one core).

Why it matters here: on 2 cores, torch at its default thread count inside an rclpy callback
loses 4-15 % of messages at 1 kHz (one thread: < 0.4 %), and small LSTM training steps are
faster on one thread when another job shares the machine.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import TracebackType

#: `lompr train` runs one tuning process per available core, but at most this many: each
#: holds torch and the data (a few hundred MB), and with a 20-trial budget more concurrent
#: trials leave the Gaussian process fewer results to choose each next point from.
MAX_DEFAULT_WORKERS = 4


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, e.g. a container's cpuset)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def default_workers() -> int:
    """`lompr train`'s default `--workers`: the available cores, at most
    `MAX_DEFAULT_WORKERS`."""
    return max(1, min(available_cores(), MAX_DEFAULT_WORKERS))


def set_torch_threads(threads: int) -> None:
    """torch intra-op threads for this process (torch is imported here, on first use)."""
    import torch

    if threads < 1:
        msg = f'threads must be >= 1, got {threads}'
        raise ValueError(msg)
    torch.set_num_threads(threads)


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """`set_torch_threads(threads)` for the `with` block, the previous count restored after:
    for an entry point that runs inside a longer process (a closed loop within the demo)."""
    import torch

    previous = torch.get_num_threads()
    set_torch_threads(threads)
    try:
        yield
    finally:
        set_torch_threads(previous)


class CoreUse:
    """The cores this process uses while a `with` block runs: its CPU time (all its threads)
    over wall time, in all and at most over any `interval` of wall time (a thread of its own
    samples both each interval: an average over the whole block would hide a burst of two
    threads). The clocks are injectable, so tests drive `sample` with exact numbers."""

    def __init__(self, interval: float = 1.0, *, wall: Callable[[], float] = time.monotonic,
                 cpu: Callable[[], float] = time.process_time) -> None:
        if not interval > 0:
            msg = f'interval must be > 0 s, got {interval}'
            raise ValueError(msg)
        self.interval = interval
        self._wall, self._cpu = wall, cpu
        self._start = self._last = (wall(), cpu())
        self.peak = 0.0  # the most cores of a whole interval so far
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='core use', daemon=True)

    def sample(self) -> None:
        """An interval ends now (called by the thread)."""
        now = (self._wall(), self._cpu())
        wall = now[0] - self._last[0]
        if wall > 0:
            self.peak = max(self.peak, (now[1] - self._last[1]) / wall)
        self._last = now

    def summary(self) -> dict[str, float]:
        """Wall and CPU seconds since the start, the mean cores, and the peak cores: the most
        of any whole interval (the mean, if more, or if no interval has ended)."""
        wall = self._wall() - self._start[0]
        cpu = self._cpu() - self._start[1]
        mean = cpu / wall if wall > 0 else 0.0
        return {'wall_seconds': wall, 'cpu_seconds': cpu, 'mean_cores': mean,
                'peak_cores': max(self.peak, mean), 'interval_seconds': self.interval}

    def __enter__(self) -> CoreUse:
        self._start = self._last = (self._wall(), self._cpu())
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.sample()
