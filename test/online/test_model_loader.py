# SPDX-License-Identifier: Apache-2.0
"""online.model_loader: a model file loaded, checked and warmed up, or the reason why not;
a swap prepared beside the sample path."""

from __future__ import annotations

import time
from pathlib import Path

from model_helpers import save_constant

from lompr_predictor.learning.model_file import MetadataMismatchError, ModelFileError
from lompr_predictor.online.model_loader import (
    LoadOutcome,
    ModelRequest,
    SwapInBackground,
    expected_metadata,
    load_ready_model,
    prepare_swap,
)
from lompr_predictor.robot.description import load_robot_description

SHA = load_robot_description().sha256


def refusal(outcome: LoadOutcome) -> str:
    """Why `outcome` is a refusal (it must be one)."""
    assert outcome.reason is not None
    return outcome.reason


def request(path: Path | str, sample_period: float = 0.0) -> ModelRequest:
    return ModelRequest(str(path), expected_metadata(SHA), sample_period)


def test_a_good_file_is_loaded_verified_and_warmed_up(tmp_path: Path) -> None:
    outcome = load_ready_model(request(save_constant(tmp_path / 'c.pt', (1e-6, 2e-6))))
    assert outcome.ready is not None and outcome.error is None and outcome.reason is None
    ready = outcome.ready
    assert ready.sample_period == 0.04  # the model's, none asked for
    assert ready.model.verified_by == 'sidecar' and ready.warm_up_seconds > 0.0
    assert ready.describe().startswith(f'linear model {tmp_path / "c.pt"} (sha256 ')


def test_every_refusal_is_a_reason_not_an_exception(tmp_path: Path) -> None:
    assert refusal(load_ready_model(request(''))).startswith('parameter model_path is empty')
    missing = load_ready_model(request(tmp_path / 'missing.pt'))
    assert missing.ready is None and 'no such file' in refusal(missing)
    model = save_constant(tmp_path / 'c.pt')
    window = load_ready_model(ModelRequest(str(model), {'window': 9}))
    assert isinstance(window.error, MetadataMismatchError) and 'window' in refusal(window)
    period = load_ready_model(request(model, sample_period=0.01))
    assert isinstance(period.error, ModelFileError) and '0.01' in refusal(period)
    nan = load_ready_model(request(save_constant(tmp_path / 'nan.pt', (float('nan'), 0.0))))
    assert refusal(nan).endswith('warm-up on onnxruntime gave (nan, 0.0), not a finite prediction')


def test_expected_metadata_leaves_out_what_the_configuration_leaves_open() -> None:
    assert expected_metadata('abc') == {'robot_description_sha256': 'abc'}
    assert expected_metadata('abc', window=8, horizon=0)['horizon'] == 0


def test_a_swap_keeps_the_running_window_and_horizon(tmp_path: Path) -> None:
    running = load_ready_model(request(save_constant(tmp_path / 'a.pt'))).ready
    assert running is not None
    assert prepare_swap(running, None, '').ready is None  # nothing to do
    assert prepare_swap(running, None, running.model.sha256.upper()).error is None
    pin = prepare_swap(running, None, 'f' * 64)
    assert refusal(pin).startswith(f'the running model {running.model.path} has sha256 ')
    other = save_constant(tmp_path / 'b.pt', (3e-6, 0.0))
    swapped = prepare_swap(running, str(other), '').ready
    assert swapped is not None and swapped.model.path == str(other)
    longer = save_constant(tmp_path / 'w.pt', window=6)
    refused = prepare_swap(running, str(longer), '')
    assert refused.ready is None and 'window' in refusal(refused)
    assert refusal(refused).endswith(f'; still running {running.model.path}')


def test_a_swap_prepared_beside_the_sample_path_is_taken_only_for_its_own_change(
        tmp_path: Path) -> None:
    running = load_ready_model(request(save_constant(tmp_path / 'a.pt'))).ready
    assert running is not None
    other = str(save_constant(tmp_path / 'b.pt', (3e-6, 0.0)))
    prepared = SwapInBackground(running, other, '')
    deadline = time.monotonic() + 60.0
    while not prepared.done and time.monotonic() < deadline:
        time.sleep(0.01)
    ready = prepared.outcome.ready
    assert ready is not None and ready.model.path == other
    assert prepare_swap(running, other, '', prepared) is prepared.outcome
    # another change, or the same one of a model swapped in meanwhile, loads afresh
    pinned = prepare_swap(running, other, 'f' * 64, prepared)
    assert pinned.ready is None and 'f' * 64 in refusal(pinned)
    again = load_ready_model(request(tmp_path / 'a.pt')).ready
    assert again is not None
    fresh = prepare_swap(again, other, '', prepared).ready
    assert fresh is not None and fresh is not ready and fresh.model.path == other
