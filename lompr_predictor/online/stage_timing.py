# SPDX-License-Identifier: Apache-2.0
"""Timing the stages of the predictor core's input calls, from outside the core (ROS-free).

`time_stages(core, timer)` wraps, on that one core object, its two input calls (`begin`)
and the call each stage ends with (`end(stage)`), as the core lists them
(`OnlinePredictor.stage_steps`): the core holds no hook for a profiler and pays nothing
when none listens. A stage runs from the input call's beginning or the previous stage's
end, so the stages of an input call add up to the call. `StageHistograms` is the timer a
node uses: each stage's wall time into a row 'stage <name>' of its `CallbackTimes`.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterable
from typing import Any, Protocol

from lompr_predictor.monitoring import CallbackTimes

#: The stages of an input call a `StageTimer` hears the end of, in the order they run:
#: checking and converting the stamp, aligning pose and reference, the plant error (the
#: offset and prediction published for the instant, the units' observation), the windows'
#: feature rows, the overrun policy, the network, the offset gate.
STAGES = ('stamp', 'alignment', 'plant error', 'feature rows', 'overrun', 'inference',
          'offset gate')


class StageTimer(Protocol):
    """Told where an input call is (`time_stages`), to time its stages."""

    def begin(self) -> None:
        """An input call (`add_pose`, `add_reference`) begins."""
        ...

    def end(self, stage: str) -> None:
        """The stage `stage` (one of `STAGES`) ended."""
        ...


class StageHistograms:
    """A `StageTimer` recording each stage's wall time into `times`, row 'stage <name>'
    (a perf_counter_ns reading per stage, no CPU time: the callback's row has that)."""

    def __init__(self, times: CallbackTimes) -> None:
        self._times = times
        self._rows = {stage: f'stage {stage}' for stage in STAGES}
        self._last = 0

    def begin(self) -> None:
        self._last = time.perf_counter_ns()

    def end(self, stage: str) -> None:
        now = time.perf_counter_ns()
        self._times.record(self._rows[stage], now - self._last)
        self._last = now


class StagedCore(Protocol):
    """What `time_stages` needs of a core (`predictor.OnlinePredictor`): its input calls
    and the steps that end its stages."""

    def add_pose(self, *args: Any) -> Any: ...

    def add_reference(self, *args: Any) -> Any: ...

    def stage_steps(self) -> Iterable[tuple[str, object, str]]:
        """(stage, object, method name): the method call each of `STAGES` ends with."""
        ...


def time_stages(core: StagedCore, timer: StageTimer) -> None:
    """From now on tell `timer` where each input call of `core` is (module docstring)."""
    for name in ('add_pose', 'add_reference'):
        _wrap(core, name, before=timer.begin)
    for stage, owner, name in core.stage_steps():
        if stage not in STAGES:
            msg = f'{type(owner).__name__}.{name} ends an unknown stage {stage!r}'
            raise ValueError(msg)
        _wrap(owner, name, after=functools.partial(timer.end, stage))


def _wrap(owner: object, name: str, *, before: Callable[[], None] | None = None,
          after: Callable[[], None] | None = None) -> None:
    """Replace the method `name` of the object `owner` (on the instance) by one that calls
    `before`, the method, then `after`."""
    method: Callable[..., Any] = getattr(owner, name)

    @functools.wraps(method)
    def timed(*args: Any, **kwargs: Any) -> Any:
        if before is not None:
            before()
        result = method(*args, **kwargs)
        if after is not None:
            after()
        return result

    setattr(owner, name, timed)
