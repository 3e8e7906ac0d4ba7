# SPDX-License-Identifier: Apache-2.0
"""Digital twin speed against its targets; prints figures and PASS/FAIL.

- step: `DigitalTwin.step(1, offset)` as twin_node calls it in a closed loop (IK, plant,
  true tool tip by FK), per-call time p50/p99 [us]; target p99 under 1 ms.
- simulate: `simulate` of 20 spiral passes (22,000 samples, 880 s simulated), wall time
  and speed-up over real time (best of 3).

Both on one core (BLAS/OpenMP threads set to 1 before NumPy loads).
Run: .venv/bin/python bench/bench_twin.py   (exit code 1 if a target is missed)
"""

from __future__ import annotations

import os

for _variable in ('OMP_NUM_THREADS', 'MKL_NUM_THREADS', 'OPENBLAS_NUM_THREADS'):
    os.environ[_variable] = '1'

import sys
import time

import numpy as np

from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.twin import DigitalTwin, load_twin_parameters, simulate

STEP_P99_TARGET_US = 1000.0
STEPS = 3000
WARMUP = 100
PASSES = 20


def main() -> int:
    description = load_robot_description()
    params = load_twin_parameters()
    twin = DigitalTwin(description, params, seed=1)
    offset = np.array([[10e-6, -5e-6, 0.0]])
    times = np.empty(STEPS)
    for i in range(WARMUP + STEPS):
        started = time.perf_counter()
        twin.step(1, offset)
        if i >= WARMUP:
            times[i - WARMUP] = time.perf_counter() - started
    p50, p99 = np.percentile(times, [50, 99]) * 1e6
    step_ok = p99 < STEP_P99_TARGET_US
    print(f'step (1 sample, closed loop): p50 {p50:.0f} us, p99 {p99:.0f} us '
          f'(target p99 < {STEP_P99_TARGET_US:.0f} us) {"PASS" if step_ok else "FAIL"}')
    best = np.inf
    for _ in range(3):
        started = time.perf_counter()
        sim = simulate(description, params, passes=PASSES, seed=1)
        best = min(best, time.perf_counter() - started)
    simulated = len(sim.stamps) * params.sample_period
    print(f'simulate {PASSES} passes ({len(sim.stamps)} samples, {simulated:.0f} s): '
          f'{best:.2f} s, {simulated / best:.0f}x real time')
    return 0 if step_ok else 1


if __name__ == '__main__':
    sys.exit(main())
