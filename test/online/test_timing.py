# SPDX-License-Identifier: Apache-2.0
"""online.timing through the core: a slow model publishes nothing late, builds no backlog
and is not stopped by one stall."""

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
