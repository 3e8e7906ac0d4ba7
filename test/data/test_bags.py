# SPDX-License-Identifier: Apache-2.0
"""Recordings made with compensation on: the trainer and `lompr evaluate` read the offsets
recorded on /lompr/compensation and learn the plant error, tool tip - (reference + offset)
(docs/interface.md, the error); a bag without the topic reads as before (no offset)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from model_helpers import save_linear
from trainer_data import EPOCH_NS, PERIOD_NS, lissajous_reference, synthetic_recording

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.data.bags import (
    BagTopics,
    CompensationSamples,
    Recording,
    read_recording,
    write_recording,
)
from lompr_predictor.data.cleaning import CleaningConfig
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription

SAMPLES = 600
NO_SPIKES = CleaningConfig(hampel_threshold=1e12)


def offsets(samples: int) -> np.ndarray:
    """(N, 2) a compensation of tens of micrometres that changes every sample, zero for the
    first 20 samples (the predictor's window filling)."""
    k = np.arange(samples)
    offset = np.stack([30e-6 * np.sin(0.05 * k), -25e-6 * np.cos(0.03 * k)], -1)
    offset[:20] = 0.0
    return offset


def compensated_recording(description: RobotDescription) -> tuple[Recording, np.ndarray,
                                                                 np.ndarray]:
    """(recording, plant error, offset in force): the robot commanded reference + offset,
    the offsets on the bag as a predictor publishes them, and the noise a recorder adds:
    for every instant first a stale guess (superseded by the newest), the offset itself,
    NaNs (which a controller refuses), one stamped between two instants and one for an
    instant without a sample."""
    offset = offsets(SAMPLES)
    recording, error = synthetic_recording(description.geometry, SAMPLES,
                                           reference=lissajous_reference(SAMPLES), offset=offset)
    stamps = recording.joints.stamps
    extra = np.array([stamps[100] + PERIOD_NS // 2, stamps[-1] + 5 * PERIOD_NS])
    recording = dataclasses.replace(recording, compensation=CompensationSamples(
        stamps=np.concatenate([stamps, stamps, stamps[::7], extra]),
        offsets=np.concatenate([2.0 * offset + 1e-5, offset,
                                np.full((len(stamps[::7]), 2), np.nan),
                                np.full((2, 2), 4e-4)])))
    return recording, error, offset


def test_the_plant_error_is_the_tool_tip_less_reference_and_newest_offset(
        tmp_path: Path, description: RobotDescription) -> None:
    recording, error, offset = compensated_recording(description)
    bag = write_recording(tmp_path / 'compensated', recording)
    read = read_recording(bag)
    assert read.compensation is not None and len(read.compensation.stamps) == 2 * SAMPLES + 88
    data, _ = load_clean_data(BagInputs((str(bag),), cleaning=NO_SPIKES), LomprChain(description))
    assert data.compensation is not None and len(data) == SAMPLES
    np.testing.assert_allclose(data.compensation, offset, rtol=0, atol=1e-15)
    np.testing.assert_allclose(data.error, error, rtol=0, atol=1e-9)  # IK -> FK round trip
    np.testing.assert_allclose(data.tool_error, error + offset, rtol=0, atol=1e-9)
    counts = data.counts
    assert counts['compensation_read'] == 2 * SAMPLES + 88
    assert counts['compensation_nonfinite'] == 86
    assert counts['compensation_no_sample'] == 2 and counts['compensated'] == SAMPLES
    # the same bag with the topic read under another name: read as without compensation
    plain, _ = load_clean_data(BagInputs((str(bag),), cleaning=NO_SPIKES,
                                         topics=BagTopics(compensation='/other')),
                               LomprChain(description))
    assert plain.compensation is None and 'compensated' not in plain.counts
    np.testing.assert_allclose(plain.error, error + offset, rtol=0, atol=1e-9)


def test_evaluate_scores_a_compensated_recording_on_its_plant_error(
        tmp_path: Path, description: RobotDescription,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The same plant, recorded once with compensation on and once without: `lompr
    evaluate` scores the model alike on both (and unlike on the compensated error)."""
    compensated, _, _ = compensated_recording(description)
    plain, _ = synthetic_recording(description.geometry, SAMPLES,
                                   reference=lissajous_reference(SAMPLES))
    model = save_linear(tmp_path / 'model.pt', normalisation={'error_low': [-1e-4, -1e-4],
                                                              'error_high': [1e-4, 1e-4]})
    reports = {}
    for name, recording in (('on', compensated), ('off', plain)):
        bag = write_recording(tmp_path / name, recording)
        report = tmp_path / f'report_{name}'
        assert lompr_main(['evaluate', str(model), str(bag), '--report', str(report),
                           '--quiet']) == 0
        reports[name] = json.loads((report / 'report.json').read_text())['models']
    capsys.readouterr()
    for model_name in ('model', 'persistence'):
        for axis in 'xy':
            on, off = (reports[n][model_name]['metrics'][axis]['rmse_um'] for n in ('on', 'off'))
            assert on == pytest.approx(off, rel=1e-6, abs=1e-6)
    assert reports['off']['persistence']['metrics']['x']['rmse_um'] > 0.1  # not vacuous


def test_a_bag_without_the_topic_reads_as_before(tmp_path: Path,
                                                 description: RobotDescription) -> None:
    recording, error = synthetic_recording(description.geometry, 200,
                                           reference=lissajous_reference(200))
    bag = write_recording(tmp_path / 'plain', recording)
    assert read_recording(bag).compensation is None
    data, _ = load_clean_data(BagInputs((str(bag),)), LomprChain(description))
    assert data.compensation is None and 'compensation_read' not in data.counts
    np.testing.assert_allclose(data.error, error, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(data.tool_error, data.error)
    assert data.stamps[0] == EPOCH_NS
