# SPDX-License-Identifier: Apache-2.0
"""ros.predictor_diagnostics, without a node: the statuses it registers, and the warnings
about what happened since the last report (faults, late outputs), read from a real runtime
each report and quiet again at the next."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import pytest
from fake_clock import FakeClock
from model_helpers import save_constant

from lompr_predictor.monitoring import LatencyRecorder, Level, RateMeter, Status
from lompr_predictor.online.predictor_status import Lifecycle
from lompr_predictor.ros.predictor_diagnostics import (
    PredictorDiagnostics,
    PredictorMeters,
    PredictorReadings,
)
from lompr_predictor.ros.predictor_outputs import OutputPublisher
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings
from lompr_predictor.runtime.predictor_runtime import PredictorRuntime, RuntimeHooks


class Statuses:
    """Stands for the node's diagnostics publisher: the statuses added, by name."""

    def __init__(self) -> None:
        self.read: dict[str, Callable[[], Status]] = {}
        self.watched: dict[str, Callable[[], bool]] = {}
        self.told_between_samples = 0

    def add(self, name: str, status: Callable[[], Status]) -> None:
        self.read[name] = status

    def watch(self, name: str, changed: Callable[[], bool]) -> None:
        self.watched[name] = changed

    def between_samples(self) -> None:
        self.told_between_samples += 1


def diagnostics_of(tmp_path: Path) -> tuple[Statuses, PredictorRuntime, PredictorMeters]:
    """The statuses of an active node running a constant model, and what they read."""
    clock = FakeClock(5.0)
    runtime = PredictorRuntime(RuntimeHooks(clock.ns, lambda: '/predictor_node', lambda: False,
                                            lambda _path, _sha: None, lambda _level, _text: None))
    settings = dataclasses.replace(PredictorNodeSettings(),
                                   model_path=str(save_constant(tmp_path / 'c.pt')))
    assert runtime.configure(settings) is None
    meters = PredictorMeters(RateMeter(), RateMeter(), RateMeter(), OutputPublisher(
        'lompr_base', RateMeter(), LatencyRecorder(100), lambda _key, _text: None))
    statuses = Statuses()
    PredictorDiagnostics(statuses, meters, lambda: PredictorReadings(  # type: ignore[arg-type]
        Lifecycle('active', True, None), settings, runtime, {}, {}, clock.ns()))
    return statuses, runtime, meters


def test_the_statuses_are_registered_in_the_order_an_operator_reads_them(
        tmp_path: Path) -> None:
    statuses, _, meters = diagnostics_of(tmp_path)
    assert list(statuses.read) == ['model', 'inputs', 'reference preview', 'prediction',
                                   'guard', 'sample store', 'adaptation']
    assert statuses.read['adaptation']().message.startswith('off')
    assert list(statuses.watched) == ['adaptation'] and not statuses.watched['adaptation']()
    meters.outputs.between_samples()  # outputs sent: the statuses hear it
    assert statuses.told_between_samples == 1


def test_an_adaptation_attempt_that_ended_is_watched_for_at_every_tick(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    statuses, runtime, _ = diagnostics_of(tmp_path)
    ended = [True]
    monkeypatch.setattr(runtime, 'adaptation', SimpleNamespace(
        adaptation=SimpleNamespace(ended=lambda: ended[0])))
    assert statuses.watched['adaptation']()
    ended[0] = False
    assert not statuses.watched['adaptation']()


def test_faults_and_late_outputs_warn_for_the_report_they_happened_in(tmp_path: Path) -> None:
    statuses, runtime, meters = diagnostics_of(tmp_path)
    core = runtime.core
    assert core is not None
    meters.end_pose.tick()
    inputs, prediction = statuses.read['inputs'], statuses.read['prediction']
    assert inputs().message == 'filling the window 0/6'
    quiet = prediction()
    assert (quiet.level, quiet.message) == (Level.OK, 'shadow mode; 0 predictions')
    core.abort()
    core.abort()
    core.overrun.outputs_after_instant += 2
    core.overrun.inference_skipped_late += 1
    warned = inputs()
    assert (warned.level, warned.message) == (
        Level.WARN, '2 faults since the last report (last: internal); window 0/6')
    assert prediction().message == ('shadow mode; 3 outputs after their instant or skipped '
                                    'since the last report (the input came late, or the '
                                    'inference was slower than it)')
    assert inputs().message == 'filling the window 0/6'  # nothing new since
    assert prediction().level == Level.OK
