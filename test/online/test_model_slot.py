# SPDX-License-Identifier: Apache-2.0
"""online.model_slot: a model refused for another robot, features or window before it
serves; a slot's window fills before it answers, a model that raises is no prediction, and
of two slots the first full one answers."""

from __future__ import annotations

from pathlib import Path

import pytest
from model_helpers import FailingModel, metadata, save_constant

from lompr_predictor.learning.model_file import MetadataMismatchError, load_model, save_model
from lompr_predictor.monitoring import LatencyRecorder
from lompr_predictor.online.model_slot import (
    ModelSlot,
    ModelSlots,
    check_fallback,
    check_model,
    check_replacement,
)
from lompr_predictor.robot.chain import load_chain

REFERENCE = (0.1, -0.05, 1.097)


def test_a_model_for_another_robot_window_or_horizon_is_refused(tmp_path: Path) -> None:
    chain = load_chain()
    model = load_model(save_constant(tmp_path / 'm.pt', (1e-6, 2e-6)))
    check_model(model, chain)
    other = load_model(save_constant(tmp_path / 'o.pt', robot_sha256='0' * 64))
    with pytest.raises(MetadataMismatchError, match="'robot_description_sha256' is '0000"):
        check_model(other, chain)
    wider = load_model(save_constant(tmp_path / 'w.pt', window=6))
    with pytest.raises(ValueError, match='has window 6, horizon 3 and preview 0; the running '
                                         'one 4, 3 and 0'):
        check_replacement(model, wider, chain)
    sooner = load_model(save_constant(tmp_path / 's.pt', horizon=1))
    with pytest.raises(MetadataMismatchError, match="'horizon' is 1"):
        check_fallback(sooner, chain, horizon=3)


def test_slots_answer_once_full_and_a_model_that_raises_is_no_prediction(
        tmp_path: Path) -> None:
    chain = load_chain()
    times = LatencyRecorder(10)
    constant = load_model(save_constant(tmp_path / 'm.pt', (1e-6, 2e-6)))
    failing = load_model(save_model(tmp_path / 'f.pt', FailingModel(threshold=0.05),
                                    metadata()))
    slots = ModelSlots(constant, None, None, chain, times)
    answered = [slots.push(k * 40_000_000, (0.0, 0.0), REFERENCE, None) for k in range(8)]
    first = next(k for k, slot in enumerate(answered) if slot is not None)
    assert answered[first] is slots.primary and all(answered[first:])
    assert slots.primary.predict() == pytest.approx((1e-6, 2e-6), abs=1e-18)
    assert (slots.predictions, slots.primary.answers) == (1, 8 - first)
    broken = ModelSlot(failing, None, chain, times)
    for k in range(8):
        broken.window.push(k * 40_000_000, 0.0, 0.0, *REFERENCE, None)
    assert broken.predict() is None and broken.predictions == 0  # |ref x| 0.1 > 0.05: raised
    assert times.summary().samples == 2  # both calls timed
    slots.clear()
    assert slots.push(9 * 40_000_000, (0.0, 0.0), REFERENCE, None) is None  # refilling
