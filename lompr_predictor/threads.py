"""Thread counts of the numeric libraries, set once by an entry point (a CLI command, a node's
`main`, a bench), never by library code: torch's intra-op thread count is process-wide, so
the last caller would win for everyone.

Why it matters here: on 2 cores, torch at its default thread count inside an rclpy callback
loses 4-15 % of messages at 1 kHz (one thread: < 0.4 %), and small LSTM training steps are
faster on one thread when another job shares the machine.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


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
