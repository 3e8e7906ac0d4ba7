# SPDX-License-Identifier: Apache-2.0
"""online.model_manager: the model running, a change validated then taken, an adaptation's
model offered beside the sample path, and the history of swaps (ROS-free)."""

from __future__ import annotations

import time
from pathlib import Path

from model_helpers import save_constant

from lompr_predictor.errors import LomprError
from lompr_predictor.online.model_loader import ModelRequest, SwapInBackground, expected_metadata
from lompr_predictor.online.model_manager import Configured, ModelManager, SwapOrigin
from lompr_predictor.robot.description import load_robot_description

SHA = load_robot_description().sha256


def configured(tmp_path: Path) -> ModelManager:
    models = ModelManager()
    loaded = models.configure(ModelRequest(str(save_constant(tmp_path / 'a.pt', (1e-6, 0.0))),
                                           expected_metadata(SHA)))
    assert isinstance(loaded, Configured) and loaded.fallback is None
    assert models.running is loaded.model and models.history.warm_up_seconds > 0
    return models


def test_an_operators_change_is_validated_then_taken_and_counted(tmp_path: Path) -> None:
    models = configured(tmp_path)
    first = models.running
    new = save_constant(tmp_path / 'b.pt', (2e-6, 0.0))
    assert models.take() is None  # nothing validated yet
    assert models.validate(str(new), '') is None
    assert models.running is first  # not before it is taken
    swap = models.take()
    assert swap is not None and swap.origin is SwapOrigin.OPERATOR
    assert models.running is swap.ready and swap.ready.model.path == str(new)
    assert models.history.swaps == 1 and models.take() is None


def test_a_refused_change_keeps_the_model_and_says_why(tmp_path: Path) -> None:
    models = configured(tmp_path)
    first = models.running
    reason = models.validate(str(tmp_path / 'missing.pt'), '')
    assert reason is not None and 'no such file' in reason
    assert reason.endswith(f'still running {tmp_path / "a.pt"}')
    assert models.history.reload_error == reason
    assert models.take() is None and models.running is first
    # a pin of the running model that is not its digest, the path unchanged
    assert models.validate(None, 'ab' * 32) is not None and models.take() is None
    assert models.validate(None, '') is None and models.take() is None  # no change at all


def test_an_adaptations_model_offered_is_taken_as_prepared_and_named_so(
        tmp_path: Path) -> None:
    models = configured(tmp_path)
    assert models.running is not None
    adapted = save_constant(tmp_path / 'adapted.pt', (3e-6, 0.0))
    prepared = SwapInBackground(models.running, str(adapted), '')
    deadline = time.monotonic() + 30
    while not prepared.done and time.monotonic() < deadline:
        time.sleep(0.01)
    models.offer(prepared)
    assert models.validate(str(adapted), '') is None
    swap = models.take()
    assert swap is not None and swap.origin is SwapOrigin.ADAPTATION
    assert swap.ready is prepared.outcome.ready  # the model loaded beside, not again
    models.offer(None)
    # the same file set by hand afterwards is an operator's change
    assert models.validate(str(tmp_path / 'a.pt'), '') is None
    swap = models.take()
    assert swap is not None and swap.origin is SwapOrigin.OPERATOR


def test_unconfigured_any_change_waits_for_configure_which_says_why_it_fails(
        tmp_path: Path) -> None:
    models = ModelManager()
    assert models.validate(str(tmp_path / 'missing.pt'), '') is None and models.take() is None
    failed = models.configure(ModelRequest(str(tmp_path / 'missing.pt'), expected_metadata(SHA)))
    assert isinstance(failed, LomprError) and 'no such file' in str(failed)
    assert models.running is None
    configured(tmp_path).release()
