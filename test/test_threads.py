# SPDX-License-Identifier: Apache-2.0
"""The cores a process used (`CoreUse`): in all and the most of any interval, on driven
clocks, and a real thread of its own around one busy thread."""

from __future__ import annotations

import hashlib
import threading

import pytest

from lompr_predictor.threads import CoreUse


class Clocks:
    """Wall and CPU seconds the test sets."""

    def __init__(self) -> None:
        self.wall = 100.0
        self.cpu = 5.0

    def advance(self, wall: float, cpu: float) -> None:
        self.wall += wall
        self.cpu += cpu


def test_the_peak_is_the_busiest_interval_and_the_mean_is_over_the_whole_block() -> None:
    clocks = Clocks()
    use = CoreUse(1.0, wall=lambda: clocks.wall, cpu=lambda: clocks.cpu)
    for wall, cpu in ((1.0, 0.5), (1.0, 1.8), (2.0, 1.0)):  # a late sample: 2 s
        clocks.advance(wall, cpu)
        use.sample()
    clocks.advance(0.5, 0.1)  # an interval not ended: only in the totals
    summary = use.summary()
    assert summary['wall_seconds'] == pytest.approx(4.5)
    assert summary['cpu_seconds'] == pytest.approx(3.4)
    assert summary['mean_cores'] == pytest.approx(3.4 / 4.5)
    assert summary['peak_cores'] == pytest.approx(1.8)


def test_a_block_shorter_than_an_interval_has_its_mean_as_peak() -> None:
    clocks = Clocks()
    use = CoreUse(1.0, wall=lambda: clocks.wall, cpu=lambda: clocks.cpu)
    clocks.advance(0.4, 0.3)
    assert use.summary()['peak_cores'] == pytest.approx(0.75)
    with pytest.raises(ValueError, match='interval must be > 0 s, got 0'):
        CoreUse(0.0)


def test_one_busy_thread_uses_one_core_at_most() -> None:
    # intervals long against the skew between reading the wall and the CPU clock (a 50 ms
    # interval read 1.038 cores once on a loaded machine)
    with CoreUse(0.25) as use:
        data = b'x' * 10**6
        for _ in range(1000):  # about 1-3 s of CPU
            data = hashlib.sha256(data).digest() * 31250
    summary = use.summary()
    assert summary['cpu_seconds'] > 0.5
    assert 0.0 < summary['mean_cores'] <= summary['peak_cores'] <= 1.02, summary
    assert not any(t.name == 'core use' for t in threading.enumerate())  # stopped at exit
