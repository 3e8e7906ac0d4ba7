# SPDX-License-Identifier: Apache-2.0
"""Would a reference preview help? The report's baselines with and without the trainer's preview.

    python bench/preview_baselines.py [--presets P ...] [--horizons 1 25] [--bags DIR]

For each twin preset and horizon h, on the recordings `bench_train.py` uses (train `--seed 1`,
test `--seed 2`, `--machine-seed 1`, recorded into --bags when missing), ridge and boosted
trees (HGB) exactly as `lompr train --preview h` fits them (`learning.baselines.WithoutPreview`:
the flattened window, the change of the error over the horizon, ridge's penalty chosen on
validation), with the preview block of K = h samples in every row (`features.with_preview`)
and without it, on the same test windows. Prints the test RMSE per axis [um] and the ratio
K = h / K = 0.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_train import PRESETS, TEST_SEED, TRAIN_SEED, recording

from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.data.problem import LearningProblem, train_test_problem
from lompr_predictor.learning.baselines import BASELINES, FitContext, WithoutPreview, fit_baselines
from lompr_predictor.robot.chain import load_chain

#: The baselines `lompr train --preview` also fits without the preview: (with, without).
PAIRS = tuple((b.base, b) for b in BASELINES if isinstance(b, WithoutPreview))


def test_rmse(problem: LearningProblem) -> dict[str, np.ndarray]:
    """Test RMSE per axis [um] of each baseline of `PAIRS`, with and without the preview,
    as `lompr train` fits them for `problem`."""
    test = problem.split.test
    truth = problem.error[test + problem.horizon]
    fitted = fit_baselines(problem, FitContext(), [b for pair in PAIRS for b in pair])
    return {name: np.sqrt(np.mean((f.fitted.predict(test) - truth) ** 2, axis=0)) * 1e6
            for name, f in fitted.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--presets', nargs='+', default=list(PRESETS), choices=PRESETS)
    parser.add_argument('--horizons', type=int, nargs='+', default=[1, 25])
    parser.add_argument('--bags', default='bench_train_out',
                        help='folder of the {preset}_seed{1,2} recordings (default: '
                             "bench_train.py's)")
    args = parser.parse_args()
    bags = Path(args.bags)
    bags.mkdir(parents=True, exist_ok=True)
    chain = load_chain()
    print(f'{"preset":<16}{"h":>3}  {"model":<6}{"K = 0, um":>14}{"K = h, um":>14}'
          f'{"ratio":>14}   (X / Y)')
    for preset in args.presets:
        data = [load_clean_data(BagInputs(bags=(str(recording(bags, preset, seed, 1)),)),
                                chain)[0] for seed in (TRAIN_SEED, TEST_SEED)]
        for horizon in args.horizons:
            rmse = test_rmse(train_test_problem(data[0], data[1], horizon=horizon,
                                                preview=horizon))
            for base, plain in PAIRS:
                a, b = rmse[plain.name], rmse[base.name]
                print(f'{preset:<16}{horizon:>3}  {base.label:<6}{a[0]:7.2f}/{a[1]:<6.2f}'
                      f'{b[0]:7.2f}/{b[1]:<6.2f}{b[0] / a[0]:7.2f}/{b[1] / a[1]:<6.2f}',
                      flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
