# SPDX-License-Identifier: Apache-2.0
"""Forward kinematics speed against its targets; prints figures and PASS/FAIL.

- single: `ForwardKinematics.solve` as the kinematics node calls it, one sample after the
  other along the paper's spiral at 25 Hz (warm-started), per-call time p50/p99 [us].
- batch: `batch_forward_kinematics` on 100,000 spiral samples, samples/s (best of 3).

Both on one core (BLAS/OpenMP threads set to 1 before NumPy loads).
Run: .venv/bin/python bench/bench_fk.py   (exit code 1 if a target is missed)
"""

from __future__ import annotations

import os

for _variable in ('OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'OPENBLAS_NUM_THREADS'):
    os.environ[_variable] = '1'

import sys
import time

import numpy as np

from lompr_predictor.robot.description import LomprGeometry, load_robot_description
from lompr_predictor.robot.kinematics import (
    ForwardKinematics,
    batch_forward_kinematics,
    inverse_kinematics,
)
from lompr_predictor.robot.paths import build_cycle
from lompr_predictor.twin.parameters import load_twin_parameters

SINGLE_P99_TARGET_US = 100.0
BATCH_TARGET_PER_S = 1_000_000.0
BATCH_SAMPLES = 100_000
SINGLE_SAMPLES = 10_000  # ten 40 s spiral passes at 25 Hz
WARMUP = 200


def bench_single(fk: ForwardKinematics, joints: np.ndarray) -> np.ndarray:
    """Per-call times [s] of `fk.solve`, rows given as Python lists as the node does."""
    rows = joints.tolist()
    for row in rows[:WARMUP]:
        fk.solve(row)
    fk.reset()
    times = np.empty(len(rows))
    clock = time.perf_counter
    for i, row in enumerate(rows):
        start = clock()
        fk.solve(row)
        times[i] = clock() - start
    return times


def bench_batch(geometry: LomprGeometry, joints: np.ndarray) -> float:
    """Best samples/s of three `batch_forward_kinematics` runs."""
    best = float('inf')
    for _ in range(3):
        start = time.perf_counter()
        poses = batch_forward_kinematics(geometry, joints)
        best = min(best, time.perf_counter() - start)
    assert poses.valid.all(), 'every spiral sample must solve'
    return len(joints) / best


def spiral(samples: int) -> np.ndarray:
    """(N, 3) tool-tip positions along the paper's spiral passes and their returns."""
    params = load_twin_parameters()
    return build_cycle('spiral', params.path, params.sample_period).sample(0, samples)


def verdict(ok: bool) -> str:
    return 'PASS' if ok else 'FAIL'


def main() -> int:
    description = load_robot_description()
    geometry = description.geometry
    single_joints = inverse_kinematics(geometry, spiral(SINGLE_SAMPLES)).joints
    times_us = bench_single(ForwardKinematics(description), single_joints) * 1e6
    p50, p99 = np.percentile(times_us, [50.0, 99.0])
    batch_joints = inverse_kinematics(geometry, spiral(BATCH_SAMPLES)).joints
    rate = bench_batch(geometry, batch_joints)

    single_ok, batch_ok = p99 < SINGLE_P99_TARGET_US, rate >= BATCH_TARGET_PER_S
    print(f'single-sample FK ({len(times_us)} spiral samples, warm-started): '
          f'p50 {p50:.1f} us, p99 {p99:.1f} us, max {times_us.max():.1f} us '
          f'(target p99 < {SINGLE_P99_TARGET_US:.0f} us) {verdict(single_ok)}')
    print(f'batch FK ({BATCH_SAMPLES} samples, one thread): {rate / 1e6:.2f} M samples/s '
          f'(target >= {BATCH_TARGET_PER_S / 1e6:.1f} M/s) {verdict(batch_ok)}')
    return 0 if single_ok and batch_ok else 1


if __name__ == '__main__':
    sys.exit(main())
