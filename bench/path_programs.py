# SPDX-License-Identifier: Apache-2.0
"""What each of the twin's programs asks of the machine, from recordings of them.

    python bench/path_programs.py DIR [DIR ...]

Each DIR is a `lompr simulate` recording (its ground truth is read, not the bag). Prints per
recording: the program, samples per pass (its return included) and the pass's duration,
the RMS and peak of the measured X/Y error, the commanded tool tip's peak speed,
acceleration and jerk (by differences of the reference), and how often per pass a branch's
commanded velocity reverses (from above +`--reversal-speed` to below minus it, or back):
where friction changes sign. docs/twin.md has the table for the six programs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from lompr_predictor.twin.recording import read_ground_truth

UM = 1e6
BRANCHES = 3  # the first three joints are the UPS branch lengths


def reversals(lengths: np.ndarray, period: float, threshold: float) -> int:
    """Times any of the branches' velocities (from (N, B) lengths [m]) changes sign, with
    hysteresis: counted once it has passed +-`threshold` [m/s] the other way."""
    velocity = np.diff(lengths, axis=0) / period
    count = 0
    for branch in velocity.T:
        signs = np.sign(branch[np.abs(branch) > threshold])
        count += int(np.count_nonzero(np.diff(signs)))
    return count


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('recordings', type=Path, nargs='+', metavar='DIR',
                        help='recordings written by lompr simulate')
    parser.add_argument('--reversal-speed', type=float, default=1e-4,
                        help='branch speed a reversal must pass both ways [m/s] (default 1e-4)')
    args = parser.parse_args()
    print('| program | samples per pass + return (s) | RMS error X / Y (um) | '
          'peak error X / Y (um) | peak speed (m/s) | peak acceleration (m/s^2) | '
          'peak jerk (m/s^3) | branch reversals per pass |')
    print('|---|---|---|---|---|---|---|---|')
    for folder in args.recordings:
        truth, document = read_ground_truth(folder)
        period, passes = document['sample_period'], document['passes']
        per_pass = len(truth['stamps']) // passes
        error = truth['error_measured'][:, :2] * UM
        rms = np.sqrt(np.mean(error ** 2, axis=0))
        peak = np.abs(error).max(axis=0)
        velocity = np.diff(truth['reference'][:, :2], axis=0) / period
        acceleration = np.diff(velocity, axis=0) / period
        jerk = np.diff(acceleration, axis=0) / period
        speed, accel, jerks = (np.linalg.norm(d, axis=1).max()
                               for d in (velocity, acceleration, jerk))
        turns = reversals(truth['joints_commanded'][:, :BRANCHES], period, args.reversal_speed)
        print(f'| {document["path"]} | {per_pass} ({per_pass * period:.0f}) | '
              f'{rms[0]:.1f} / {rms[1]:.1f} | {peak[0]:.1f} / {peak[1]:.1f} | {speed:.3f} | '
              f'{accel:.3f} | {jerks:.2f} | {turns / passes:.0f} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
