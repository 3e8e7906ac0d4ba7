# SPDX-License-Identifier: Apache-2.0
"""twin.run_log: a live run's samples and answers counted as the twin saw them, and the file
a twin in another process writes read back exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lompr_predictor.twin.arm_twin import ArmDigitalTwin
from lompr_predictor.twin.run_log import RUN_LOG_FORMAT, RunLog, read_run_log, write_run_log


def test_a_run_is_counted_as_run_and_read_back_exactly(tmp_path: Path) -> None:
    twin = ArmDigitalTwin(seed=1, program='circle')
    log = RunLog(joint_count=len(twin.joint_names))
    answers = [False, False, True, True, False, True]
    offsets = 1e-6 * np.arange(12.0).reshape(6, 2)
    blocks = [twin.step(1, np.array([[x, y, 0.0]])) for x, y in offsets]
    for block, answered in zip(blocks, answers, strict=True):
        log.add(block, answered)
    assert len(log) == 6
    assert log.counts() == {'samples': 6, 'answered': 3, 'first_answered': 2,
                            'unanswered_after_first': 1}
    path = write_run_log(tmp_path / 'run.npz', log, {'robot': 'arm', 'seed': 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == ['run.npz']  # nothing staged left
    arrays, document = read_run_log(path)
    assert document == {'format': 'lompr_twin_run', 'format_version': RUN_LOG_FORMAT,
                        'samples': 6, 'answered': 3, 'first_answered': 2,
                        'unanswered_after_first': 1, 'robot': 'arm', 'seed': 1}
    assert arrays['stamps'].dtype == np.int64
    np.testing.assert_array_equal(arrays['stamps'], [b.stamps[0] for b in blocks])
    np.testing.assert_array_equal(arrays['answered'], answers)
    np.testing.assert_array_equal(arrays['offset'], [b.compensation[0, :2] for b in blocks])
    np.testing.assert_array_equal(arrays['offset'], offsets)
    np.testing.assert_array_equal(arrays['joints'], [b.joints.measured[0] for b in blocks])
    np.testing.assert_array_equal(arrays['true_error'], [b.error_true[0, :2] for b in blocks])
    np.testing.assert_array_equal(arrays['plant_error'],
                                  [b.plant_error_true[0, :2] for b in blocks])
    assert arrays['reference'].shape == (6, 3) and arrays['joints'].shape == (6, 6)


def test_an_empty_run_keeps_its_columns() -> None:
    arrays = RunLog(joint_count=5).arrays()
    assert {name: array.shape for name, array in arrays.items()} == {
        'stamps': (0,), 'reference': (0, 3), 'joints': (0, 5), 'true_error': (0, 2),
        'plant_error': (0, 2), 'offset': (0, 2), 'answered': (0,)}
