# SPDX-License-Identifier: Apache-2.0
"""The benches' profiler of the predictor core's stages, from outside the core.

`time_stages(core, timer)` wraps, on that one core object, its two input calls (`begin`)
and the call each stage ends with (`end(stage)`, `core_steps`): the core holds no hook for
a profiler and pays nothing when none listens. A stage runs from the input call's beginning
or the previous stage's end, so the stages of an input call add up to the call. The steps
are the core's own methods and parts, named here: a rename there stops the profile with the
name instead of leaving a stage out (`bench_predictor.py --parts profile`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, Protocol

from lompr_predictor.online.predictor import OnlinePredictor

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


def core_steps(core: OnlinePredictor) -> list[tuple[str, object, str]]:
    """(stage, object, method name) of the call each of `STAGES` ends with, in the order
    they run."""
    return [('stamp', core._stamps, 'pose_ns'), ('stamp', core._stamps, 'reference_ns'),
            ('alignment', core._alignment, 'add_pose'),
            ('alignment', core._alignment, 'add_reference'),
            ('plant error', core._errors, 'of'), ('feature rows', core, '_feature_rows'),
            ('overrun', core._answers, 'worth_inferring'),
            *(('inference', slot, 'predict') for slot in core.slots.all),
            ('offset gate', core._answers, 'publish')]


def time_stages(core: OnlinePredictor, timer: StageTimer) -> None:
    """From now on tell `timer` where each input call of `core` is (module docstring)."""
    for name in ('add_pose', 'add_reference'):
        _wrap(core, name, before=timer.begin)
    for stage, owner, name in core_steps(core):
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
