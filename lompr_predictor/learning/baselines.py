"""Reference baselines on the BO-LSTM's own windows: ridge and boosted trees.

Both see exactly what the networks see, the learning problem's windows of feature rows, as
one flattened vector per window (error columns relative to the window's last row, as the
networks take them, plus the last error itself), and predict the change of the error over
the horizon, e(t+h) - e(t); the prediction is e(t) plus that change:

- ridge: a linear map of the standardised vector; its penalty is chosen on the validation
  part from a fixed grid, then it is fitted again on train + validation. It is what a
  linear filter can learn from the window: a network that does not beat it learns nothing
  non-linear.
- boosted trees: scikit-learn's `HistGradientBoostingRegressor` with its default settings
  (one model per axis, seeded), fitted on train + validation. A strong non-linear reference
  that needs no tuning.

They are reference points in the report, not models the node loads. scikit-learn is
imported inside the functions: the command line's help and the node never load it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from lompr_predictor.data.features import TARGETS
from lompr_predictor.data.problem import LearningProblem, without_preview
from lompr_predictor.learning.models import error_columns, gather_windows

#: Ridge penalties tried on the validation part (on standardised inputs, targets in um).
RIDGE_ALPHAS = tuple(10.0 ** k for k in range(-3, 5))
#: Baselines in the report, by key; the BO-LSTM is compared with each.
BASELINES = ('ridge', 'hgb')
#: Suffix of a baseline's key fitted without the reference preview, beside a preview model.
NO_PREVIEW = '_no_preview'


@dataclass(frozen=True)
class BaselinePrediction:
    """One baseline's prediction of the test part and what fitting it took."""

    predicted: np.ndarray  # (B, 2) plant error [m] at the test windows' predicted instants
    seconds: float  # fitting and predicting
    settings: dict[str, object]


def flat_windows(problem: LearningProblem, ends: np.ndarray) -> np.ndarray:
    """(B, window * F + 2) inputs of the windows ending at `ends`: the flattened window,
    error columns relative to its last row, then the last row's error."""
    windows = gather_windows(problem.rows, ends, problem.window).copy()
    columns = error_columns(problem.features)
    last = windows[:, -1, columns].copy()
    windows[:, :, columns] -= last[:, None, :]
    return np.concatenate([windows.reshape(len(ends), -1), last], axis=1)


def _fit_parts(problem: LearningProblem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    split = problem.split
    fit = np.concatenate([split.train, split.validation])
    return fit, flat_windows(problem, fit), problem.targets(fit, True)


def ridge_baseline(problem: LearningProblem) -> BaselinePrediction:
    """Ridge on the standardised flattened window, penalty chosen on validation."""
    from sklearn.linear_model import Ridge

    started = time.perf_counter()
    split = problem.split
    train_x, validation_x = (flat_windows(problem, e) for e in (split.train, split.validation))
    train_y, validation_y = (problem.targets(e, True) * 1e6
                             for e in (split.train, split.validation))
    centre, scale = train_x.mean(axis=0), train_x.std(axis=0)
    scale[scale == 0] = 1.0

    def standard(x: np.ndarray) -> np.ndarray:
        return (x - centre) / scale

    scores = {}
    for alpha in RIDGE_ALPHAS:
        fitted = Ridge(alpha=alpha).fit(standard(train_x), train_y)
        scores[alpha] = float(np.mean((fitted.predict(standard(validation_x)) - validation_y)
                                      ** 2))
    alpha = min(scores, key=lambda a: scores[a])
    _, fit_x, fit_y = _fit_parts(problem)
    model = Ridge(alpha=alpha).fit(standard(fit_x), fit_y * 1e6)
    test = split.test
    change = model.predict(standard(flat_windows(problem, test))) * 1e-6
    return BaselinePrediction(predicted=problem.error[test] + change,
                              seconds=time.perf_counter() - started,
                              settings={'alpha': alpha, 'alphas_tried': list(RIDGE_ALPHAS)})


def hgb_baseline(problem: LearningProblem, seed: int = 0) -> BaselinePrediction:
    """scikit-learn's `HistGradientBoostingRegressor`, default settings, one per axis."""
    from sklearn.ensemble import HistGradientBoostingRegressor

    started = time.perf_counter()
    _, fit_x, fit_y = _fit_parts(problem)
    test_x = flat_windows(problem, problem.split.test)
    change = np.stack([HistGradientBoostingRegressor(random_state=seed)
                       .fit(fit_x, fit_y[:, i] * 1e6).predict(test_x) * 1e-6
                       for i in range(len(TARGETS))], axis=-1)
    return BaselinePrediction(predicted=problem.error[problem.split.test] + change,
                              seconds=time.perf_counter() - started,
                              settings={'model': 'HistGradientBoostingRegressor (defaults)',
                                        'random_state': seed})


def fit_baselines(problem: LearningProblem, seed: int = 0) -> dict[str, BaselinePrediction]:
    """The report's baselines (`BASELINES`) on the problem's windows; with a reference preview
    also on the same windows without it (keys ending in `NO_PREVIEW`), so that the report
    says what the preview gives."""
    fitted = {'ridge': ridge_baseline(problem), 'hgb': hgb_baseline(problem, seed)}
    if problem.preview:
        plain = without_preview(problem)
        fitted |= {'ridge' + NO_PREVIEW: ridge_baseline(plain),
                   'hgb' + NO_PREVIEW: hgb_baseline(plain, seed)}
    return fitted


def beats(metrics: dict[str, dict[str, float]],
          baseline: dict[str, dict[str, float]]) -> dict[str, dict[str, bool]]:
    """Per axis and metric: is `metrics` strictly below the baseline's (lower is better)."""
    return {axis: {name: bool(value < baseline[axis][name]) for name, value in values.items()}
            for axis, values in metrics.items()}
