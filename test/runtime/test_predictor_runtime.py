# SPDX-License-Identifier: Apache-2.0
"""runtime.predictor_runtime: what a predictor node runs, without ROS: configured from the
node's settings snapshot, driven by its clock, a swap taken, the store written and let go,
the clock's jumps and staleness as the node hears them."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
from fake_clock import FakeClock
from model_helpers import save_constant

from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import Level
from lompr_predictor.online.alignment import DropReason
from lompr_predictor.online.faults import FaultReason
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings
from lompr_predictor.runtime.predictor_runtime import PredictorRuntime, RuntimeHooks

PERIOD_NS = 40_000_000


class Node:
    """What a node hands the runtime: its clock, name and log, its model parameters."""

    def __init__(self) -> None:
        self.clock = FakeClock(0.0)
        self.lines: list[tuple[Level, str]] = []
        self.runtime = PredictorRuntime(RuntimeHooks(
            self.clock.ns, lambda: '/cell1/predictor_node', lambda: True, self.set_model,
            lambda level, text: self.lines.append((level, text))))

    def set_model(self, path: str, sha256: str) -> str | None:
        return self.runtime.validate(path, sha256)


def settings(model: Path, **changes: Any) -> PredictorNodeSettings:
    return dataclasses.replace(PredictorNodeSettings(), model_path=str(model), **changes)


def test_configured_from_the_settings_it_runs_the_model_with_its_guard_and_store(
        tmp_path: Path) -> None:
    node = Node()
    assert node.runtime.configure(settings(save_constant(tmp_path / 'c.pt'), store_minutes=0.5,
                                           store_folder=str(tmp_path / 'bags'))) is None
    runtime = node.runtime
    assert runtime.core is not None and runtime.guard is not None and runtime.adaptation is None
    assert runtime.sample_period == 0.04 and runtime.store is not None
    assert runtime.store.capacity == 750  # half a minute at 25 Hz
    node.clock.now = 5.0
    for k in range(3):
        runtime.core.add_reference(10**9 + k * PERIOD_NS, 0.0, 0.0, 1.1)
        runtime.core.add_pose(10**9 + k * PERIOD_NS, 0.0, 0.0)
    provenance = runtime.provenance()
    assert provenance['node'] == '/cell1/predictor_node' and provenance['use_sim_time']
    assert provenance['model_path'] == str(tmp_path / 'c.pt')
    assert provenance['store_minutes'] == 0.5 and provenance['sample_period'] == 0.04
    path = runtime.write_samples()
    assert path.parent == tmp_path / 'bags'
    assert runtime.export is not None and runtime.export.wait(60)
    runtime.release()
    assert runtime.core is None and runtime.store is None and runtime.models.running is None


def test_a_model_that_cannot_load_is_said_and_nothing_runs(tmp_path: Path) -> None:
    node = Node()
    error = node.runtime.configure(settings(tmp_path / 'missing.pt'))
    assert isinstance(error, LomprError) and 'no such file' in str(error)
    assert node.runtime.core is None
    with pytest.raises(LomprError, match='no sample store is kept'):
        node.runtime.write_samples()


def test_an_operators_swap_is_taken_and_the_new_model_earns_its_place(tmp_path: Path) -> None:
    node = Node()
    first = settings(save_constant(tmp_path / 'a.pt'))
    assert node.runtime.configure(first) is None
    runtime = node.runtime
    new = save_constant(tmp_path / 'b.pt', (1e-6, 0.0))
    assert runtime.validate(str(tmp_path / 'missing.pt'), '') is not None
    assert node.lines[-1][0] is Level.ERROR and 'model not swapped' in node.lines[-1][1]
    assert runtime.validate(str(new), '') is None
    assert runtime.apply(dataclasses.replace(first, model_path=str(new)), True) == []
    assert runtime.core is not None and runtime.core.model.path == str(new)
    assert runtime.models.history.swaps == 1
    assert node.lines[-1] == (Level.OK, f'model swapped: now {new} (sha256 '
                                        f'{runtime.core.model.sha256[:16]})')


def test_the_clock_going_back_cancels_and_the_first_tick_restarts_staleness(
        tmp_path: Path) -> None:
    node = Node()
    assert node.runtime.configure(settings(save_constant(tmp_path / 'c.pt'))) is None
    runtime = node.runtime
    runtime.activate()  # the clock reads 0: no /clock yet
    assert runtime.check_stale() == []  # the first tick: idle time counts from now
    node.clock.now = 3.0
    text, outputs = runtime.clock_jumped(False, 2 * 10**9, active=True)
    assert text == ('the clock went back by 2.000 s to 3.000 s (a simulator reset?): window '
                    'emptied, offset cancelled; output resumes once the window has refilled')
    assert outputs == [] and runtime.clock_jumps_back == 1  # nothing was in force
    assert runtime.core is not None and runtime.core.faults[FaultReason.CLOCK_JUMP] == 1
    text, _ = runtime.clock_jumped(True, 0, active=False)
    assert text.startswith('the clock changed source (now 3.000 s)')
    assert runtime.core.dropped[DropReason.CLOCK_JUMP] == 0
