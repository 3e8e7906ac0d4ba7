# SPDX-License-Identifier: Apache-2.0
"""Without a preview, what does the machine map's prior miss of the next sample, and why?

    python bench/map_extrapolation.py TRAIN_BAG... --test-bag BAG [--horizon 1]

Fits the machine map as `lompr train` does (the training bags' training part) and scores on
the test bag's windows the change of the plant error over the horizon, e(t+h) - e(t),
predicted four ways, as RMSE multiples of persistence's (X / Y):

- the prior as the model has it without a preview, g at the last row extrapolated at
  constant acceleration (`MachineMap.ahead`);
- g at the true commanded row t+h (what a preview of K = h gives);
- the true row's position and velocity with the last row's acceleration held, and the true
  position and acceleration with the velocity extrapolated: which of the commanded motion's
  quantities the extrapolation gets wrong.

The gap between the first two is what a model without a preview can only learn from the
path itself (where the program changes its acceleration next), which is what does not
transfer to another program.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.data.problem import train_test_problem
from lompr_predictor.learning.machine_map import fit_machine_map
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import BRANCH_JOINTS, load_robot_description


def rms(values: np.ndarray) -> np.ndarray:
    finite = values[np.isfinite(values).all(axis=1)]
    return np.sqrt(np.mean(finite ** 2, axis=0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('bags', nargs='+', help='training bags')
    parser.add_argument('--test-bag', required=True)
    parser.add_argument('--horizon', type=int, default=1)
    args = parser.parse_args()
    description = load_robot_description()
    train = load_clean_data(BagInputs(bags=tuple(args.bags)), LomprChain(description))[0]
    test = load_clean_data(BagInputs(bags=(args.test_bag,)), LomprChain(description))[0]
    problem = train_test_problem(train, test, horizon=args.horizon)
    training = problem.split.training_rows()[:len(train)]
    machine_map = fit_machine_map(problem, train.reference[training], LomprChain(description))
    h, names, rows = args.horizon, list(problem.features), problem.rows
    ends = problem.split.test
    ends = ends[ends + h < len(rows)]
    later = ends + h

    def columns(*wanted: str) -> np.ndarray:
        return rows[:, [names.index(name) for name in wanted]]

    position = columns('ref_x', 'ref_y')
    velocity = columns(*(f'{b}_v' for b in BRANCH_JOINTS))
    acceleration = columns(*(f'{b}_a' for b in BRANCH_JOINTS))
    values, ahead = machine_map.values(rows)

    def g(xy: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return machine_map.evaluate(*(torch.from_numpy(np.ascontiguousarray(z)) for z in
                                          (xy, v, a))).numpy()

    lead = h * problem.sample_period
    change = problem.error[later] - problem.error[ends]
    predicted = {
        'prior without preview (constant acceleration)': ahead[ends],
        'g at the true row t+h (a preview of K = h)': values[later],
        'true position and velocity, acceleration held': g(
            position[later], velocity[later], acceleration[ends]),
        'true position and acceleration, velocity extrapolated': g(
            position[later], velocity[ends] + acceleration[ends] * lead, acceleration[later]),
    }
    persistence = rms(change)
    print(f'persistence RMSE {persistence[0] * 1e6:.2f} / {persistence[1] * 1e6:.2f} um '
          f'(horizon {h}, {len(ends)} test windows)')
    for label, g_ahead in predicted.items():
        ratio = rms(change - (g_ahead - values[ends])) / persistence
        print(f'{label:<56}{ratio[0]:6.2f} / {ratio[1]:.2f}')


if __name__ == '__main__':
    main()
