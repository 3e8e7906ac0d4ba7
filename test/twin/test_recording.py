# SPDX-License-Identifier: Apache-2.0
"""twin.recording: a simulation as the bag content a machine records (its measured joints
and the reference, unchanged without faults), the path generator's preview of the next
samples, and an existing output refused (the bag itself and its ground truth:
test/cli/test_simulate)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lompr_predictor.robot.description import MEASURED_JOINTS, RobotDescription
from lompr_predictor.twin import load_twin_parameters, simulate
from lompr_predictor.twin.recording import (
    RecordingExistsError,
    planned_preview,
    to_recording,
    write_simulation,
)

PARAMS = load_twin_parameters()


def test_a_run_is_recorded_as_measured_and_its_preview_is_the_next_samples(
        description: RobotDescription, tmp_path: Path) -> None:
    sim = simulate(description, PARAMS, passes=1, seed=2)
    recording, logs = to_recording(sim)
    assert logs == {} and recording.preview is None
    np.testing.assert_array_equal(recording.joints.stamps, sim.stamps)
    np.testing.assert_array_equal(recording.joints.positions, sim.joints_measured)
    assert recording.joints.names == MEASURED_JOINTS
    np.testing.assert_array_equal(recording.reference.positions, sim.reference)
    preview = planned_preview(sim, 3)
    count = len(sim.stamps)
    np.testing.assert_array_equal(preview.stamps, sim.stamps)
    np.testing.assert_array_equal(np.diff(preview.starts), [3] * (count - 3) + [2, 1, 0])
    first = slice(preview.starts[0], preview.starts[1])
    np.testing.assert_array_equal(preview.pose_stamps[first], sim.stamps[1:4])
    np.testing.assert_array_equal(preview.positions[first], sim.reference[1:4])
    assert to_recording(sim, preview_samples=3)[0].preview is not None
    (tmp_path / 'bag').mkdir()
    with pytest.raises(RecordingExistsError, match='already exists; choose a new directory'):
        write_simulation(tmp_path / 'bag', sim, PARAMS, description.sha256, plot=False)
