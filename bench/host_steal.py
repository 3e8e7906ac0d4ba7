# SPDX-License-Identifier: Apache-2.0
"""The host's CPU steal beside a timing run, by the samples that ran while it was taken.

On a virtual machine an answer can come late because the hypervisor gave the CPUs to other
guests (the steal column of /proc/stat), not because of the code. A soak records the steal
about once a second with the sample index it had reached (`HostSteal.record`) and reports
its in-time share outside the intervals whose steal is over `BURST_PERCENT` beside the share
over all samples, so that a miss by the host and a miss by the nodes read apart. Without
a readable /proc/stat (not Linux) or two readings, nothing is recorded and the report says so.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

#: An interval with more of its CPU time stolen than this is a burst [%].
BURST_PERCENT = 5.0


def cpu_jiffies(stat: str) -> tuple[int, int]:
    """(all, steal) jiffies of the first line of /proc/stat's text (every CPU together):
    user, nice, system, idle, iowait, irq, softirq and steal (guest time is counted in
    user's already)."""
    fields = stat.split('\n', 1)[0].split()
    if not fields or fields[0] != 'cpu' or len(fields) < 9:
        raise ValueError(f'not the cpu line of /proc/stat: {stat[:80]!r}')
    values = [int(value) for value in fields[1:9]]
    return sum(values), values[7]


class HostSteal:
    """Steal per interval between calls of `record`, by the samples that ran in it."""

    def __init__(self, stat: Path = Path('/proc/stat')) -> None:
        self.stat = stat
        #: (first sample, end sample, steal %) per interval, in order
        self.intervals: list[tuple[int, int, float]] = []
        self._last: tuple[int, int, int] | None = None  # sample, all and steal jiffies

    def record(self, sample: int) -> None:
        """Read the jiffies now; the interval since the last call ends at `sample`."""
        try:
            total, steal = cpu_jiffies(self.stat.read_text())
        except (OSError, ValueError):
            return
        if self._last is not None:
            first, total_before, steal_before = self._last
            if total > total_before and sample > first:
                self.intervals.append(
                    (first, sample, 100.0 * (steal - steal_before) / (total - total_before)))
        self._last = (sample, total, steal)

    def bursts(self, samples: int) -> np.ndarray:
        """(samples,) bool: the samples that ran in an interval of steal over
        `BURST_PERCENT`."""
        inside = np.zeros(samples, dtype=bool)
        for first, end, percent in self.intervals:
            if percent > BURST_PERCENT:
                inside[first:end] = True
        return inside

    def summary(self, answered: np.ndarray, quiet: np.ndarray) -> dict[str, Any]:
        """The steal's mean and largest interval [%], the intervals over `BURST_PERCENT`,
        and the quiet samples outside them and how many of those were answered."""
        if not self.intervals:
            return {'recorded': False}
        percent = np.array([interval[2] for interval in self.intervals])
        outside = quiet & ~self.bursts(len(answered))
        return {'recorded': True, 'steal_mean_percent': float(percent.mean()),
                'steal_max_percent': float(percent.max()),
                'burst_intervals': int((percent > BURST_PERCENT).sum()),
                'intervals': len(percent), 'quiet_samples_outside_bursts': int(outside.sum()),
                'quiet_answered_outside_bursts': int(answered[outside].sum())}


def steal_line(summary: dict[str, Any]) -> str:
    """The report's line of `HostSteal.summary`."""
    if not summary.get('recorded'):
        return '  host steal: not recorded (no readable /proc/stat, or under two readings)'
    outside = max(summary['quiet_samples_outside_bursts'], 1)
    return (f'  host steal: mean {summary["steal_mean_percent"]:.2f} %, largest '
            f'{summary["steal_max_percent"]:.1f} % of an interval; '
            f'{summary["burst_intervals"]} of {summary["intervals"]} intervals over '
            f'{BURST_PERCENT:g} %; outside them answered in time '
            f'{summary["quiet_answered_outside_bursts"]} of '
            f'{summary["quiet_samples_outside_bursts"]} '
            f'({summary["quiet_answered_outside_bursts"] / outside:.4%})')
