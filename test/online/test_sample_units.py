# SPDX-License-Identifier: Apache-2.0
"""The chain of units the core hands every aligned sample and prediction: the live accuracy,
and units plugged in from outside (a persistence stand-in, one that withholds, a recorder)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fake_clock import FakeClock
from model_helpers import save_linear
from test_predictor import (
    HORIZON,
    NEEDED,
    PERIOD_NS,
    WINDOW,
    feed,
    limits,
    predicted,
    spiral,
    stream,
)

from lompr_predictor.learning.model_file import LoadedModel, load_model
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.model_slot import ModelSlot
from lompr_predictor.online.offset import XY
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.sample_units import LiveAccuracy, SampleUnit


@pytest.fixture
def linear_model(tmp_path: Path) -> LoadedModel:
    return load_model(save_linear(tmp_path / 'linear.pt', window=WINDOW, horizon=HORIZON))


class Recorder:
    """Writes down what it is shown; changes nothing."""

    def __init__(self) -> None:
        self.observed: list[tuple[int, XY, XY | None]] = []
        self.revised: list[tuple[int, XY, ModelSlot]] = []
        self.cleared = 0

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        self.observed.append((sample.stamp_ns, error, published))

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        self.revised.append((instant_ns, prediction, slot))
        return prediction

    def clear(self) -> None:
        self.cleared += 1


class Persistence:
    """Replaces every prediction by the plant error last observed (the persistence
    prediction): a stand-in for a guard that chooses persistence."""

    def __init__(self) -> None:
        self.last: XY | None = None

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        self.last = error

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        return self.last

    def clear(self) -> None:
        self.last = None


class EveryOther:
    """Withholds every other prediction."""

    def __init__(self) -> None:
        self.count = 0

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        pass

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        self.count += 1
        return prediction if self.count % 2 else None

    def clear(self) -> None:
        pass


def core_with(model: LoadedModel, *units: SampleUnit, enabled: bool = False) -> OnlinePredictor:
    return OnlinePredictor(model, stream(), limits(enabled=enabled), clock=FakeClock().ns,
                           units=units)


def test_live_accuracy_is_the_rms_of_truth_minus_prediction() -> None:
    accuracy = LiveAccuracy(samples=2)
    rms, count = accuracy.rms()
    assert count == 0 and np.isnan(rms).all()
    sample = AlignedSample(0, 0.0, 0.0, 0.0, 0.0, 0.0)
    accuracy.observe(sample, (9e-6, 0.0), (0.0, 0.0))  # pushed out by the next two
    accuracy.observe(sample, (5e-6, 5e-6), None)  # no prediction for its instant: no residual
    accuracy.observe(sample, (3e-6, 1e-6), (0.0, 2e-6))
    accuracy.observe(sample, (-1e-6, 0.0), (3e-6, 1e-6))
    accuracy.clear()  # a fault does not forget how good the model was
    rms, count = accuracy.rms()
    assert count == 2
    np.testing.assert_allclose(rms, [np.sqrt((9 + 16) / 2) * 1e-6, 1e-6], rtol=1e-12)


def test_a_unit_sees_every_sample_with_its_plant_error_and_the_prediction_for_it(
        linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(40)
    recorder = Recorder()
    core = core_with(linear_model, recorder)
    outputs = feed(core, stamps, reference, tips)
    assert [stamp for stamp, _, _ in recorder.observed] == stamps.tolist()
    # shadow mode: no offset applied, the plant error is measured - reference
    np.testing.assert_allclose([error for _, error, _ in recorder.observed],
                               tips - reference[:, :2], rtol=0, atol=1e-15)
    published = {output.instant_ns: output.prediction for output in outputs}
    assert len(published) == 40 - NEEDED + 1
    for stamp, _, prediction in recorder.observed:  # what was published for its instant
        assert prediction == published.get(stamp)
    assert sum(prediction is not None for _, _, prediction in recorder.observed) == (
        40 - NEEDED + 1 - HORIZON)
    assert [(instant, prediction) for instant, prediction, _ in recorder.revised] == [
        (o.instant_ns, o.prediction) for o in outputs]
    assert all(slot is core.primary for _, _, slot in recorder.revised)


def test_a_unit_can_replace_the_prediction_the_gate_publishes(
        linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(40)
    core = core_with(linear_model, Persistence())
    outputs = feed(core, stamps, reference, tips)
    # each output predicts, for stamp + horizon, the plant error measured at its stamp
    errors = tips - reference[:, :2]
    assert [o.sample_stamp_ns for o in outputs] == stamps[NEEDED - 1:].tolist()
    np.testing.assert_allclose([predicted(o) for o in outputs], errors[NEEDED - 1:],
                               rtol=0, atol=1e-15)
    assert all(o.instant_ns == o.sample_stamp_ns + HORIZON * PERIOD_NS for o in outputs)
    # the live accuracy judges what was published: persistence's residuals
    rms, count = core.accuracy.rms()
    residuals = errors[NEEDED - 1 + HORIZON:] - errors[NEEDED - 1:-HORIZON]
    assert count == len(residuals)
    np.testing.assert_allclose(rms, np.sqrt(np.mean(residuals ** 2, axis=0)), rtol=1e-9)


def test_a_withheld_prediction_leaves_its_instant_without_an_offset(
        linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(40)
    plain = feed(core_with(linear_model, enabled=True), stamps, reference, tips)
    halved = feed(core_with(linear_model, EveryOther(), enabled=True), stamps, reference, tips)
    assert [o.instant_ns for o in halved] == [o.instant_ns for o in plain][::2]
    assert halved[0] == plain[0]


def test_units_are_cleared_with_the_window(linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(NEEDED + 4)
    recorder = Recorder()
    core = core_with(linear_model, recorder)
    feed(core, stamps[:NEEDED], reference[:NEEDED], tips[:NEEDED])
    assert recorder.cleared == 0
    gap = 5 * PERIOD_NS  # beyond gap_factor periods: a fault empties the window
    feed(core, stamps[NEEDED:] + gap, reference[NEEDED:], tips[NEEDED:])
    assert recorder.cleared == 1 and core.faults['gap'] == 1
    core.reset()
    assert recorder.cleared == 2
