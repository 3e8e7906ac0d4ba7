"""Thread counts of the numeric libraries, set once by an entry point (a CLI command, a node's
`main`, a bench), never by library code: torch's intra-op thread count is process-wide, so
the last caller would win for everyone. Also how many cores a process may use, which sets
`lompr train`'s default number of tuning processes.

Why it matters here: on 2 cores, torch at its default thread count inside an rclpy callback
loses 4-15 % of messages at 1 kHz (one thread: < 0.4 %), and small LSTM training steps are
faster on one thread when another job shares the machine.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

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
