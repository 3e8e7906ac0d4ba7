# SPDX-License-Identifier: Apache-2.0
"""Where a trained model loses to the boosted trees: the test samples that carry the gap.

    python bench/error_concentration.py MODEL --train-bags DIR --test-bags DIR [--top N]

Rebuilds `lompr train --test-bags`'s problem for the model's window and horizon, fits the
boosted-tree baseline (`baselines.HGB`, as the report does) and scores both on every
test window. It prints per axis the test RMSE of each, the mean squared error the model's
`--top` worst samples (by squared error above the trees') contribute, and the RMSE of both
without them; then those samples, each with the measured error's step into the predicted
instant and the reference velocity's step there, which no window can show (the reference comes
at its instant, docs/interface.md, topics). The high-rate preset's miss at horizon 1 was found
this way: one sample per pass, where the spiral meets the disk's rim.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.data.problem import train_test_problem
from lompr_predictor.learning.baselines import HGB, FitContext
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.learning.models import predict_rows
from lompr_predictor.robot.chain import load_chain
from lompr_predictor.threads import set_torch_threads

UM = 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('model', type=Path, help='model file written by lompr train')
    parser.add_argument('--train-bags', type=Path, nargs='+', required=True,
                        help='the recordings the model was trained on')
    parser.add_argument('--test-bags', type=Path, nargs='+', required=True,
                        help='the recordings it was tested on')
    parser.add_argument('--top', type=int, default=20,
                        help='worst samples (by squared error above the trees) to single out')
    args = parser.parse_args()
    set_torch_threads(1)
    model = load_model(args.model, expected={'targets': TARGETS})
    window, horizon = model.metadata.window, model.metadata.horizon
    chain = load_chain()
    train, _ = load_clean_data(BagInputs(bags=tuple(map(str, args.train_bags))), chain)
    test, _ = load_clean_data(BagInputs(bags=tuple(map(str, args.test_bags))), chain)
    problem = train_test_problem(train, test, window, horizon, preview=model.metadata.preview)
    ends = problem.split.test
    actual = problem.error[ends + horizon]
    residuals = {'model': predict_rows(model.module, problem.rows, ends, window) - actual,
                 'trees': HGB.fit(problem, FitContext()).predict(ends) - actual}
    velocity = problem.rows[:, [FEATURES.index('ref_vx'), FEATURES.index('ref_vy')]]
    seconds = (problem.stamps[ends] - problem.stamps[ends[0]]) * 1e-9
    print(f'{args.model.name}: window {window}, horizon {horizon}, preview '
          f'{model.metadata.preview}, {len(ends)} test windows (the trees given the same rows)')
    for axis, name in enumerate(TARGETS):
        squared = {key: (r[:, axis] * UM) ** 2 for key, r in residuals.items()}
        worst = np.argsort(squared['model'] - squared['trees'])[-args.top:]
        rest = np.ones(len(ends), dtype=bool)
        rest[worst] = False
        print(f'\naxis {name}: RMSE model {np.sqrt(squared["model"].mean()):.3f} um, trees '
              f'{np.sqrt(squared["trees"].mean()):.3f} um; {args.top} samples where the model '
              f'is worst add {squared["model"][worst].sum() / len(ends):.4f} um^2 (trees '
              f'{squared["trees"][worst].sum() / len(ends):.4f}); without them RMSE model '
              f'{np.sqrt(squared["model"][rest].mean()):.3f}, trees '
              f'{np.sqrt(squared["trees"][rest].mean()):.3f} um')
        print('   t [s]  model err  trees err  error step [um]  reference velocity step [mm/s]')
        for i in sorted(worst):
            step = (actual[i, axis] - problem.error[ends[i] + horizon - 1, axis]) * UM
            velocity_step = np.linalg.norm(velocity[ends[i] + horizon]
                                           - velocity[ends[i] + horizon - 1]) * 1e3
            print(f'{seconds[i]:8.3f} {residuals["model"][i, axis] * UM:10.2f} '
                  f'{residuals["trees"][i, axis] * UM:10.2f} {step:11.2f} {velocity_step:12.2f}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
