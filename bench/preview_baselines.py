"""Would a reference preview help? The report's baselines with and without look-ahead inputs.

    python bench/preview_baselines.py [--presets P ...] [--horizons 1 25] [--bags DIR]

For each twin preset and horizon h, on the recordings `bench_train.py` uses (train `--seed 1`,
test `--seed 2`, `--machine-seed 1`, recorded into --bags when missing), ridge and boosted
trees (HGB) as the report fits them (`learning.baselines`: the flattened window, the change
of the error over the horizon), once as they are (K = 0) and once given the commanded path
up to the predicted instant (K = h): the reference-derived feature columns of the predicted
instant's row (reference position, velocity, acceleration, branch velocities and
accelerations) and the reference's displacement from the window's last row to it. Prints the
test RMSE per axis [um] and the ratio K = h / K = 0. A first look before the trainer has a
`--preview`: ridge's penalty is fixed (alpha 10 on standardised inputs), not chosen on
validation.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_train import PRESETS, TEST_SEED, TRAIN_SEED, recording

from lompr_predictor.data.features import FEATURES
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.data.problem import LearningProblem, train_test_problem
from lompr_predictor.learning.baselines import flat_windows
from lompr_predictor.robot.description import load_robot_description

#: The columns a preview gives for an instant: all but the measured error.
COMMANDED = [i for i, name in enumerate(FEATURES) if not name.startswith('error_')]
REFERENCE_XY = [FEATURES.index('ref_x'), FEATURES.index('ref_y')]


def inputs(problem: LearningProblem, ends: np.ndarray, preview: bool) -> np.ndarray:
    """The baselines' inputs of the windows ending at `ends`, with the preview block."""
    flat = flat_windows(problem, ends)
    if not preview:
        return flat
    ahead = problem.rows[ends + problem.horizon]
    moved = ahead[:, REFERENCE_XY] - problem.rows[ends][:, REFERENCE_XY]
    return np.concatenate([flat, ahead[:, COMMANDED], moved], axis=1)


def test_rmse(problem: LearningProblem, preview: bool) -> dict[str, np.ndarray]:
    """Test RMSE per axis [um] of ridge and HGB, fitted on train + validation."""
    from sklearn.ensemble import HistGradientBoostingRegressor
    from sklearn.linear_model import Ridge

    split = problem.split
    fit = np.concatenate([split.train, split.validation])
    fit_x, test_x = inputs(problem, fit, preview), inputs(problem, split.test, preview)
    fit_y = problem.targets(fit, True) * 1e6
    centre, scale = fit_x.mean(axis=0), fit_x.std(axis=0)
    scale[scale == 0] = 1.0
    changes = {
        'ridge': Ridge(alpha=10.0).fit((fit_x - centre) / scale, fit_y)
        .predict((test_x - centre) / scale),
        'hgb': np.stack([HistGradientBoostingRegressor(random_state=0).fit(fit_x, fit_y[:, i])
                         .predict(test_x) for i in range(2)], axis=-1)}
    now = problem.error[split.test] * 1e6
    truth = problem.error[split.test + problem.horizon] * 1e6
    return {name: np.sqrt(np.mean((now + change - truth) ** 2, axis=0))
            for name, change in changes.items()}


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
    geometry = load_robot_description().geometry
    print(f'{"preset":<16}{"h":>3}  {"model":<6}{"K = 0, um":>14}{"K = h, um":>14}'
          f'{"ratio":>14}   (X / Y)')
    for preset in args.presets:
        data = [load_clean_data(BagInputs(bags=(str(recording(bags, preset, seed, 1)),)),
                                geometry)[0] for seed in (TRAIN_SEED, TEST_SEED)]
        for horizon in args.horizons:
            problem = train_test_problem(data[0], data[1], horizon=horizon)
            without, with_preview = test_rmse(problem, False), test_rmse(problem, True)
            for name in ('ridge', 'hgb'):
                a, b = without[name], with_preview[name]
                print(f'{preset:<16}{horizon:>3}  {name:<6}{a[0]:7.2f}/{a[1]:<6.2f}'
                      f'{b[0]:7.2f}/{b[1]:<6.2f}{b[0] / a[0]:7.2f}/{b[1] / a[1]:<6.2f}',
                      flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
