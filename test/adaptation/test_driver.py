# SPDX-License-Identifier: Apache-2.0
"""adaptation.driver: the node's adaptation on its clock, ROS-free: an outcome recorded with
what the node knows of it, an accepted model swapped in through the node's own change of
parameters as the model manager offers it, or not swapped and why."""

from __future__ import annotations

import time
from pathlib import Path

from model_helpers import save_constant

from lompr_predictor.adaptation.driver import AdaptationDriver, NodeHooks, tick_period
from lompr_predictor.adaptation.outcome import AttemptOutcome, AttemptResult, Decision
from lompr_predictor.adaptation.scheduler import AdaptationSettings, ModelInForce
from lompr_predictor.monitoring import Level
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.model_loader import ModelRequest, expected_metadata
from lompr_predictor.online.model_manager import Configured, ModelManager, SwapOrigin
from lompr_predictor.online.sample_store import SampleStore
from lompr_predictor.robot.description import load_robot_description

SECOND = 10**9


def settings(folder: Path, period: float = 30.0) -> AdaptationSettings:
    return AdaptationSettings(minutes=0.1, period=period, margin=0.05, folder=str(folder),
                              keep=3, max_epochs=2, nice=19, idle=True)


def sample(k: int) -> AlignedSample:
    return AlignedSample(stamp_ns=10**12 + k * 40_000_000, x=0.0, y=0.0, reference_x=0.0,
                         reference_y=0.0, reference_z=1.0)


class Node:
    """What the driver is given of a node: its log, and its change of model parameters
    (here: straight to the model manager, as a node's validate and apply do)."""

    def __init__(self, models: ModelManager) -> None:
        self.models = models
        self.lines: list[tuple[Level, str]] = []
        self.swaps: list[SwapOrigin] = []

    def set_model(self, path: str, sha256: str) -> str | None:
        reason = self.models.validate(path, sha256)
        swap = self.models.take()
        if swap is not None:
            self.swaps.append(swap.origin)
        return reason

    def hooks(self) -> NodeHooks:
        return NodeHooks(lambda: ModelInForce('m.pt', 'ab', None, 'lompr_base'), dict,
                         self.set_model, lambda level, text: self.lines.append((level, text)))


def test_the_tick_period_follows_the_attempts_period_within_bounds() -> None:
    assert tick_period(settings(Path('.'), period=30.0)) == 1.0
    assert tick_period(settings(Path('.'), period=0.4)) == 0.1
    assert tick_period(settings(Path('.'), period=0.01)) == 0.05


def test_an_attempt_that_failed_across_a_reset_of_the_sample_time_names_it(
        tmp_path: Path) -> None:
    """A failed attempt while the store restarted (the sample time went back: a simulator
    reset) says so before its own reason; one without a restart says its reason alone."""
    store = SampleStore.for_minutes(0.1, 0.04)
    node = Node(ModelManager())
    try:
        driver = AdaptationDriver(settings(tmp_path), store, node.models, 0.04, node.hooks())
        failed = AttemptResult(Decision.FAILED, 'the machine map needs 120 instants')
        driver.collect(AttemptOutcome(1, 0, SECOND, failed), SECOND)
        assert driver.adaptation.state.last['reason'] == 'the machine map needs 120 instants'
        store.observe(sample(10), (0.0, 0.0), None)
        store.observe(sample(0), (0.0, 0.0), None)  # back in sample time: a restart
        assert store.restarts == 1
        driver.collect(AttemptOutcome(2, 0, SECOND, failed), SECOND)
        assert driver.adaptation.state.last['reason'] == (
            'the sample time went back while it ran (a simulator reset?): the machine map '
            'needs 120 instants')
        assert node.lines[-1] == (Level.WARN, 'adaptation attempt 2 failed: the sample time '
                                  'went back while it ran (a simulator reset?): the machine '
                                  'map needs 120 instants')
    finally:
        store.close()


def test_an_accepted_model_is_swapped_in_as_the_adaptations_or_said_why_not(
        tmp_path: Path) -> None:
    """Accepted from the model in force: prepared beside, then swapped in through the
    node's change of parameters, which takes it as the adaptation's; accepted from another
    parent: recorded failed, not swapped."""
    models = ModelManager()
    loaded = models.configure(ModelRequest(str(save_constant(tmp_path / 'a.pt')),
                                           expected_metadata(load_robot_description().sha256)))
    assert isinstance(loaded, Configured)
    adapted = save_constant(tmp_path / 'adapted.pt', (1e-6, 0.0))
    node = Node(models)
    (tmp_path / 'models').mkdir()  # an attempt's start makes it
    store = SampleStore.for_minutes(0.1, 0.04)
    try:
        driver = AdaptationDriver(settings(tmp_path / 'models'), store, models, 0.04,
                                  node.hooks())
        other = AttemptResult(Decision.ACCEPTED, 'better', parent_sha256='cd' * 32,
                              model_path=str(adapted))
        driver.collect(AttemptOutcome(1, 0, SECOND, other), SECOND)
        assert not driver.swapping and node.swaps == []
        assert driver.adaptation.state.last['reason'] == (
            f'not swapped in: the model in force changed during the attempt (now '
            f'{tmp_path / "a.pt"})')
        ours = AttemptResult(Decision.ACCEPTED, 'better', parent_sha256=loaded.model.model.sha256,
                             model_path=str(adapted))
        driver.collect(AttemptOutcome(2, 0, SECOND, ours), SECOND)
        deadline = time.monotonic() + 30
        while driver.swapping and time.monotonic() < deadline:
            driver.tick(2 * SECOND, active=False)
            time.sleep(0.01)
        assert node.swaps == [SwapOrigin.ADAPTATION]
        assert models.running is not None and models.running.model.path == str(adapted)
        state = driver.adaptation.state
        assert (state.accepted, state.failed, state.swaps) == (1, 1, 1)
        assert node.lines[-1] == (Level.OK, 'adaptation attempt 2 accepted: better')
    finally:
        driver.close()
        store.close()
