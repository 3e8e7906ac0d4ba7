# SPDX-License-Identifier: Apache-2.0
"""The baselines a trained model is scored against, behind one seam: a `Baseline` has a
`name` (its key in the report), a `label` (its name in report.md and the plots) and
`fit(problem, context)`, which returns something that predicts any window ends (`Fitted`),
or None where it does not apply. The pipeline, the fine-tuning, the report and the benches
iterate `BASELINES`; a new baseline is one class and its place in that tuple.

- persistence: e(t+h) = e(t), the floor.
- BP: the paper's baseline, an MLP on the flattened window predicting e(t+h), with the
  paper's budget (`training.BP_MAX_EPOCHS`, a budget shrunk below the default shrinks it).
- ridge and boosted trees see exactly what the networks see, the learning problem's windows
  of feature rows, as one flattened vector per window (error columns relative to the
  window's last row, as the networks take them, plus the last error itself), and predict
  the change of the error over the horizon, e(t+h) - e(t); the prediction is e(t) plus that
  change. Ridge is a linear map of the standardised vector, its penalty chosen on the
  validation part from a fixed grid, then fitted again on train + validation: what a linear
  filter can learn from the window (a network that does not beat it learns nothing
  non-linear). Boosted trees are scikit-learn's `HistGradientBoostingRegressor` with its
  default settings (one model per axis, seeded), fitted on train + validation: a strong
  non-linear reference that needs no tuning.
- with a reference preview, ridge and the trees again on the same windows without it (keys
  ending in `NO_PREVIEW`): what the preview gives.
- the machine map's prior alone, e(t) + g(t+h) - g(t), where the run fitted a map.

They are reference points in the report, not models the node loads. scikit-learn is
imported inside the fits: the command line's help and the node never load it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from lompr_predictor.data.features import TARGETS
from lompr_predictor.data.problem import LearningProblem, without_preview
from lompr_predictor.learning.machine_map import MachineMap, map_prior
from lompr_predictor.learning.metrics import score_predictions
from lompr_predictor.learning.models import (
    BP_HYPERPARAMETERS,
    error_columns,
    gather_windows,
    persistence,
    predict_rows,
)
from lompr_predictor.learning.options import MAX_EPOCHS, TrainSettings
from lompr_predictor.learning.publishing import RidgeModule, rmse_um
from lompr_predictor.learning.training import BP_MAX_EPOCHS, BP_PATIENCE, train_network
from lompr_predictor.stamps import seconds_since

#: Ridge penalties tried on the validation part (on standardised inputs, targets in um).
RIDGE_ALPHAS = tuple(10.0 ** k for k in range(-3, 5))
#: Suffix of a baseline's key fitted without the reference preview, beside a preview model.
NO_PREVIEW = '_no_preview'
#: What the baselines that predict the change of the error predict.
RESIDUAL_TARGET = 'residual (e(t+h) - e(t))'


@dataclass(frozen=True)
class FitContext:
    """What a baseline may need beyond the problem: the run's training settings (seed,
    budget), progress bars, the machine map the run fitted (None: none)."""

    settings: TrainSettings = TrainSettings()
    progress: bool = False
    machine_map: MachineMap | None = None


@dataclass(frozen=True)
class Fitted:
    """A fitted baseline: `predict(ends)` is its (B, 2) plant error [m] at the predicted
    instants of the windows ending at `ends`; `details` what the report says of it
    (training_seconds, hyperparameters, target, ...)."""

    predict: Callable[[np.ndarray], np.ndarray]
    details: dict[str, Any] = field(default_factory=dict)
    #: the same predictor as a raw-SI module of the model file's contract, where it has one
    #: (the ridge: `publishing.RidgeModule`), which `lompr train` may publish
    module: RidgeModule | None = None
    #: (B, 2) [m] its prediction of the validation part as fitted on the training part
    #: alone, where `lompr train` may publish it (what `publishing.choose` compares)
    validation_prediction: np.ndarray | None = field(default=None, repr=False)


class Baseline(Protocol):
    """A reference the model is scored against (module docstring)."""

    @property
    def name(self) -> str: ...

    @property
    def label(self) -> str: ...

    def fit(self, problem: LearningProblem, context: FitContext) -> Fitted | None: ...


@dataclass(frozen=True)
class FittedBaseline:
    """A baseline as a run fitted it: its label, its `Fitted`, and the wall time fitting
    it took."""

    label: str
    fitted: Fitted
    seconds: float

    def report(self) -> dict[str, Any]:
        """Its fields in the report's entry of it (beside the metrics)."""
        return {'label': self.label, **self.fitted.details}


def flat_windows(problem: LearningProblem, ends: np.ndarray) -> np.ndarray:
    """(B, window * F + 2) inputs of the windows ending at `ends`: the flattened window,
    error columns relative to its last row, then the last row's error."""
    windows = gather_windows(problem.rows, ends, problem.window).copy()
    columns = error_columns(problem.features)
    last = windows[:, -1, columns].copy()
    windows[:, :, columns] -= last[:, None, :]
    return np.concatenate([windows.reshape(len(ends), -1), last], axis=1)


def _fit_parts(problem: LearningProblem) -> tuple[np.ndarray, np.ndarray]:
    """The flattened windows of train + validation and their targets."""
    split = problem.split
    fit = np.concatenate([split.train, split.validation])
    return flat_windows(problem, fit), problem.targets(fit, True)


@dataclass(frozen=True)
class Persistence:
    """e(t+h) = e(t)."""

    name: str = 'persistence'
    label: str = 'Persistence'

    def fit(self, problem: LearningProblem, context: FitContext) -> Fitted:
        return Fitted(predict=lambda ends: persistence(problem.error, ends))


@dataclass(frozen=True)
class BackPropagation:
    """The paper's BP: an MLP on the flattened window, min-max inputs, its own budget."""

    name: str = 'bp'
    label: str = 'BP'

    def fit(self, problem: LearningProblem, context: FitContext) -> Fitted:
        run = context.settings
        settings = TrainSettings(
            max_epochs=BP_MAX_EPOCHS if run.max_epochs >= MAX_EPOCHS else run.max_epochs,
            patience=BP_PATIENCE, seed=run.seed, epoch_windows=run.epoch_windows)
        trained = train_network(problem, 'mlp', BP_HYPERPARAMETERS, settings, residual=False,
                                progress=context.progress, label=self.label)
        return Fitted(
            predict=lambda ends: predict_rows(trained.module, problem.rows, ends,
                                              problem.window),
            details={'training_seconds': trained.seconds,
                     'hyperparameters': dict(BP_HYPERPARAMETERS), 'target': 'error',
                     'epochs': trained.epochs})


@dataclass(frozen=True)
class Ridge:
    """Ridge on the standardised flattened window, penalty chosen on validation."""

    name: str = 'ridge'
    label: str = 'Ridge'

    def fit(self, problem: LearningProblem, context: FitContext) -> Fitted:
        from sklearn.linear_model import Ridge as RidgeRegression

        started = time.perf_counter()
        split = problem.split
        train_x, validation_x = (flat_windows(problem, e)
                                 for e in (split.train, split.validation))
        train_y, validation_y = (problem.targets(e, True) * 1e6
                                 for e in (split.train, split.validation))
        centre, scale = train_x.mean(axis=0), train_x.std(axis=0)
        scale[scale == 0] = 1.0

        def standard(x: np.ndarray) -> np.ndarray:
            return (x - centre) / scale

        fits = {alpha: RidgeRegression(alpha=alpha).fit(standard(train_x), train_y)
                for alpha in RIDGE_ALPHAS}
        validation = {alpha: fitted.predict(standard(validation_x))
                      for alpha, fitted in fits.items()}
        alpha = min(validation, key=lambda a: float(np.mean((validation[a] - validation_y) ** 2)))
        fit_x, fit_y = _fit_parts(problem)
        model = RidgeRegression(alpha=alpha).fit(standard(fit_x), fit_y * 1e6)

        def predict(ends: np.ndarray) -> np.ndarray:
            change = model.predict(standard(flat_windows(problem, ends))) * 1e-6
            return problem.error[ends] + change

        module = RidgeModule(centre, scale, model.coef_, model.intercept_,
                             error_columns(problem.features), len(problem.features))
        return Fitted(predict=predict, module=module, validation_prediction=(
            problem.error[split.validation] + validation[alpha] * 1e-6), details={
            'training_seconds': time.perf_counter() - started,
            'hyperparameters': {'alpha': alpha, 'alphas_tried': list(RIDGE_ALPHAS)},
            # of the fit on the training part alone, at the penalty chosen
            'validation_rmse_um': rmse_um(validation[alpha] * 1e-6, validation_y * 1e-6),
            'target': RESIDUAL_TARGET})


@dataclass(frozen=True)
class BoostedTrees:
    """scikit-learn's `HistGradientBoostingRegressor`, default settings, one per axis,
    seeded with the run's seed."""

    name: str = 'hgb'
    label: str = 'HGB'

    def fit(self, problem: LearningProblem, context: FitContext) -> Fitted:
        from sklearn.ensemble import HistGradientBoostingRegressor

        started = time.perf_counter()
        seed = context.settings.seed
        fit_x, fit_y = _fit_parts(problem)
        models = [HistGradientBoostingRegressor(random_state=seed).fit(fit_x, fit_y[:, i] * 1e6)
                  for i in range(len(TARGETS))]

        def predict(ends: np.ndarray) -> np.ndarray:
            inputs = flat_windows(problem, ends)
            change = np.stack([m.predict(inputs) * 1e-6 for m in models], axis=-1)
            return problem.error[ends] + change

        return Fitted(predict=predict, details={
            'training_seconds': time.perf_counter() - started,
            'hyperparameters': {'model': 'HistGradientBoostingRegressor (defaults)',
                                'random_state': seed},
            'target': RESIDUAL_TARGET})


@dataclass(frozen=True)
class WithoutPreview:
    """`base` fitted on the same windows without the reference preview; only beside a
    problem that has one."""

    base: Baseline

    @property
    def name(self) -> str:
        return self.base.name + NO_PREVIEW

    @property
    def label(self) -> str:
        return f'{self.base.label} (no preview)'

    def fit(self, problem: LearningProblem, context: FitContext) -> Fitted | None:
        if not problem.preview:
            return None
        return self.base.fit(without_preview(problem), context)


@dataclass(frozen=True)
class MapPrior:
    """The machine map's prior alone, e(t) + g(t+h) - g(t); only where the run fitted a
    map (`FitContext.machine_map`)."""

    name: str = 'machine_map'
    label: str = 'Machine map (prior)'

    def fit(self, problem: LearningProblem, context: FitContext) -> Fitted | None:
        machine_map = context.machine_map
        if machine_map is None:
            return None
        return Fitted(predict=lambda ends: map_prior(machine_map, problem, ends),
                      details={'target': 'e(t) + g(t+h) - g(t)',
                               'map_fit_rms_um': machine_map.fit_rms * 1e6})


PERSISTENCE, BP, RIDGE, HGB, MAP_PRIOR = (Persistence(), BackPropagation(), Ridge(),
                                          BoostedTrees(), MapPrior())
#: Every baseline of a training's report, in the report's order.
BASELINES: tuple[Baseline, ...] = (PERSISTENCE, BP, RIDGE, HGB, WithoutPreview(RIDGE),
                                   WithoutPreview(HGB), MAP_PRIOR)


def fit_baselines(problem: LearningProblem, context: FitContext,
                  baselines: Sequence[Baseline] = BASELINES) -> dict[str, FittedBaseline]:
    """Each of `baselines` that applies to the problem, fitted, by name, in order."""
    fitted = {}
    for baseline in baselines:
        started = time.perf_counter()
        result = baseline.fit(problem, context)
        if result is not None:
            fitted[baseline.name] = FittedBaseline(baseline.label, result,
                                                   time.perf_counter() - started)
    return fitted


@dataclass(frozen=True)
class ScoredPredictions:
    """Each model's prediction of the test part and the actual error, for the plots."""

    seconds: np.ndarray  # (B,) predicted instants [s] from the first one
    actual: np.ndarray  # (B, 2) plant error [m]
    predictions: dict[str, np.ndarray]  # model name -> (B, 2) [m]


def score_test_part(problem: LearningProblem, baselines: Mapping[str, FittedBaseline],
                    predicted: Mapping[str, np.ndarray], gap_factor: float
                    ) -> tuple[ScoredPredictions, dict[str, dict[str, Any]]]:
    """The fitted baselines' predictions of the problem's test part, then the models'
    (`predicted`), and the report's entry of each: its metrics (a step over `gap_factor`
    sample periods ends a run of the integral metrics) and what a baseline says of itself."""
    test = problem.split.test
    targets = test + problem.horizon
    actual, stamps = problem.error[targets], problem.stamps[targets]
    predictions = {**{name: fitted.fitted.predict(test) for name, fitted in baselines.items()},
                   **predicted}
    models = score_predictions(predictions, actual, stamps, problem.error_low,
                               problem.error_high, gap_factor * problem.sample_period)
    for name, fitted in baselines.items():
        models[name].update(fitted.report())
    return ScoredPredictions(seconds=seconds_since(stamps), actual=actual,
                             predictions=predictions), models


def beats(metrics: dict[str, dict[str, float]],
          baseline: dict[str, dict[str, float]]) -> dict[str, dict[str, bool]]:
    """Per axis and metric: is `metrics` strictly below the baseline's (lower is better)."""
    return {axis: {name: bool(value < baseline[axis][name]) for name, value in values.items()}
            for axis, values in metrics.items()}
