# SPDX-License-Identifier: Apache-2.0
"""online.timing through the core: a slow model publishes nothing late, builds no backlog
and is not stopped by one stall; and the guard alone: an instant read on the node's clock
when the stamps are on it (a wait for the CPU counts), else against the best-case delay."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import cast

import pytest
import torch
from model_helpers import save_constant
from test_predictor import HORIZON, PERIOD_NS, T0, WINDOW, Z, spiral_xy, stream

from lompr_predictor.learning.model_file import (
    ExportedModule,
    LoadedModel,
    load_model,
)
from lompr_predictor.online.offset import CompensationLimits, Output
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.timing import OverrunGuard

# -- faults: a slow model skips to the newest sample instead of building a backlog ---------

class NodeClock:
    """The node's clock [ns], shared by the core and a model that takes time."""

    def __init__(self) -> None:
        self.ns = T0

    def now(self) -> int:
        return self.ns


def slow(model: LoadedModel, clock: NodeClock, durations: Iterator[int]) -> LoadedModel:
    """`model` whose every inference advances `clock` by the next of `durations` [ns]."""
    module = model.module

    def run(windows: torch.Tensor) -> torch.Tensor:
        clock.ns += next(durations)
        return cast(torch.Tensor, module(windows))

    return dataclasses.replace(model, compiled=cast(ExportedModule, run))


def stream_through(core: OnlinePredictor, clock: NodeClock, samples: int, period_ns: int,
                   delay_ns: int = 1_000_000) -> list[tuple[int, Output]]:
    """Samples arriving `delay_ns` after their stamp, handled one after the other as an
    executor does (a sample that arrives while the node is busy waits): (publish time,
    output) of every output."""
    published = []
    for k in range(samples):
        stamp = T0 + k * period_ns
        clock.ns = max(clock.ns, stamp + delay_ns)
        x, y = spiral_xy(k)
        for output in core.add_reference(stamp, x, y, Z) + core.add_pose(stamp, x + 1e-5, y):
            published.append((clock.ns, output))
    return published


@pytest.mark.faults
@pytest.mark.parametrize('horizon', [1, 5])
def test_a_slow_model_publishes_nothing_late_and_no_burst(tmp_path: Path, horizon: int) -> None:
    """100 ms per inference, 25 Hz input."""
    clock = NodeClock()
    model = load_model(save_constant(tmp_path / 'm.pt', (1e-5, 0.0), window=WINDOW,
                                     horizon=horizon))
    core = OnlinePredictor(slow(model, clock, iter(lambda: 100_000_000, None)), stream(),
                           CompensationLimits(1e-3, 1e-3, True), clock=clock.now)
    published = stream_through(core, clock, 100, PERIOD_NS)
    lead, tolerance, delay = horizon * PERIOD_NS, 5_000_000, 1_000_000
    predictions = [(at, o) for at, o in published if not o.reason]
    for at, output in predictions:  # none for an instant already past
        assert at <= output.instant_ns + delay + tolerance
    overrun = core.overrun
    assert overrun.inference_skipped_late + overrun.late_outputs_dropped > 0
    last_arrival = T0 + 99 * PERIOD_NS + delay
    # no backlog: done within one inference or the lead after the input stopped (not 4 s)
    assert clock.ns - last_arrival <= max(100_000_000, lead + tolerance)
    if horizon == 5:  # 200 ms lead covers one inference: most samples are answered in time
        assert len(predictions) >= 25
    else:  # 40 ms cannot: nothing is published late
        assert predictions == [] and overrun.late_outputs_dropped > 0


@pytest.mark.faults
def test_one_stall_does_not_stop_the_answers(tmp_path: Path) -> None:
    clock = NodeClock()
    durations = iter([0, 0, 1_000_000_000] + [0] * 1000)  # the third inference stalls 1 s
    model = load_model(save_constant(tmp_path / 'm.pt', (1e-5, 0.0), window=WINDOW,
                                     horizon=HORIZON))
    core = OnlinePredictor(slow(model, clock, durations), stream(),
                           CompensationLimits(1e-3, 1e-3, True), clock=clock.now)
    published = stream_through(core, clock, 120, PERIOD_NS)
    late_part = [o for _, o in published
                 if not o.reason and o.sample_stamp_ns > T0 + 60 * PERIOD_NS]
    assert len(late_part) == 120 - 61  # every sample after the stall's backlog is answered
    assert core.overrun.late_outputs_dropped == 1 and core.overrun.inference_skipped_late > 0


# -- the overrun guard itself: which clock an instant is read on --------------------------

LEAD, TOLERANCE, MS = 5_000_000, 5_000_000, 1_000_000


def idle_then_waited(clock_offset_ns: int) -> tuple[OverrunGuard, int, int]:
    """Ten samples 1 ms apart arriving 1 ms after their stamps (plus `clock_offset_ns`, the
    node's clock ahead of the stamps'), each inferred in 0.1 ms; then 100 ms of silence and
    a sample whose callback ran 30 ms after its stamp (it waited for the CPU): the guard, the
    last stamp and the node time after that sample's arrival."""
    guard = OverrunGuard(LEAD, TOLERANCE)
    for k in range(10):
        stamp = T0 + k * MS
        guard.arrival(stamp, stamp + MS + clock_offset_ns)
        guard.inference_took(stamp + MS + clock_offset_ns, stamp + MS + clock_offset_ns + MS // 10)
    stamp = T0 + 110 * MS
    now = stamp + 30 * MS + clock_offset_ns
    guard.arrival(stamp, now)
    return guard, stamp, now


def test_on_the_nodes_clock_a_wait_for_the_cpu_counts_as_late() -> None:
    """Stamps on the node's clock: the 30 ms wait puts the output 25 ms past its instant
    (30 ms - the 5 ms lead), late beyond the 5 ms tolerance, though the node was idle."""
    guard, stamp, now = idle_then_waited(0)
    assert guard.same_clock is True
    assert guard.lateness_ns(stamp, now) == 25 * MS
    assert guard.late(stamp, now) and guard.skip(stamp, now)


@pytest.mark.parametrize('clock_offset_ns', [10**15, -20 * MS])
def test_stamps_on_another_clock_are_judged_against_the_best_case_delay(
        clock_offset_ns: int) -> None:
    """A recording's epoch (the node 11.6 days ahead) or a node clock 20 ms behind the
    stamps (beyond the tolerance): the same wait is read as input delay while the node was
    idle, the output in time by its lead."""
    guard, stamp, now = idle_then_waited(clock_offset_ns)
    assert guard.same_clock is False
    assert guard.lateness_ns(stamp, now) == -LEAD
    assert not guard.late(stamp, now)


def test_a_restart_forgets_which_clock_the_stamps_were_on() -> None:
    """Stamps going back (a bag looped) restart the estimate: no reading before the next
    sample, then the new stamps' own."""
    guard, stamp, now = idle_then_waited(10**15)
    guard.arrival(T0, now + MS)  # back to the first stamp, on the node's clock now
    assert guard.same_clock is False  # its delay is 10**15 + ...: still another clock
    guard.restart()
    assert guard.same_clock is None and guard.lateness_ns(stamp, now) == 0
    guard.arrival(T0, T0 + MS)
    assert guard.same_clock is True
