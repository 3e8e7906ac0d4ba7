# SPDX-License-Identifier: Apache-2.0
"""learning.linear_start: the ridge over the flattened windows against scikit-learn's at the
same penalty (1e-9), its penalty the validation part's choice, a network started from it
predicting what it predicts, a trained network never worse on validation than it, a
fine-tuned one starting from its highways fitted again where that validates better, and a
study's trainings on the same data fitting it once."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch
from sklearn.linear_model import Ridge
from trainer_data import lissajous_reference, synthetic_recording

from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.problem import LearningProblem, build_problem
from lompr_predictor.learning import linear_start, training
from lompr_predictor.learning.linear_start import (
    RELATIVE_PENALTIES,
    LinearFit,
    RidgeFits,
    fit_ridge,
    holds_highway,
    refit_highways,
    start_from,
)
from lompr_predictor.learning.models import LstmNet, PairedNet, error_columns, gather_windows
from lompr_predictor.learning.options import HOLD_BELOW_WINDOWS_PER_INPUT
from lompr_predictor.learning.training import TrainSettings, train_network
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription

WINDOW, FEATURES = 6, 3


def windows_of(rows: torch.Tensor) -> Callable[[np.ndarray], torch.Tensor]:
    """The windows of `rows` ending at given rows, as `fit_ridge` reads them."""
    return lambda ends: gather_windows(rows, ends, WINDOW)


def noisy_linear_data(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Rows of random features and targets linear in each window plus noise (true weights
    returned), so that the penalty matters and the fit can be checked against sklearn."""
    rng = np.random.default_rng(seed)
    rows = torch.from_numpy(rng.normal(size=(600, FEATURES)).astype(np.float32))
    weight = rng.normal(size=(2, WINDOW * FEATURES))
    flat = gather_windows(rows, np.arange(WINDOW - 1, 600), WINDOW).flatten(1).double().numpy()
    targets = flat @ weight.T + 0.3 + rng.normal(scale=2.0, size=(len(flat), 2))
    return rows, torch.from_numpy(targets.astype(np.float32)), weight


def test_the_fit_is_scikit_learns_ridge_at_the_chosen_penalty() -> None:
    rows, targets, _ = noisy_linear_data()
    train, validation = np.arange(WINDOW - 1, 400), np.arange(400, 600)
    train_y, validation_y = targets[train - WINDOW + 1], targets[validation - WINDOW + 1]
    fit = fit_ridge(windows_of(rows), train, train_y, validation, validation_y)
    assert fit is not None
    x = gather_windows(rows, train, WINDOW).flatten(1).double().numpy()
    centred = x - x.mean(0)
    scale = np.mean(np.linalg.eigvalsh(centred.T @ centred))
    x_validation = gather_windows(rows, validation, WINDOW).flatten(1).double().numpy()
    losses = []
    for penalty in RELATIVE_PENALTIES:
        reference = Ridge(alpha=penalty * scale).fit(x, train_y.double().numpy())
        losses.append(np.mean((reference.predict(x_validation)
                               - validation_y.double().numpy()) ** 2))
        if penalty == fit.penalty:
            np.testing.assert_allclose(fit.weight, reference.coef_, rtol=0, atol=1e-9)
            np.testing.assert_allclose(fit.bias, reference.intercept_, rtol=0, atol=1e-9)
    assert fit.penalty == RELATIVE_PENALTIES[int(np.argmin(losses))]
    assert fit.validation_loss == pytest.approx(min(losses), rel=1e-9)
    # noise this large wants shrinkage: neither end of the grid
    assert RELATIVE_PENALTIES[0] < fit.penalty


def test_a_network_started_from_the_fit_predicts_the_ridge() -> None:
    rows, targets, _ = noisy_linear_data(1)
    ends = np.arange(WINDOW - 1, 600)
    fit = fit_ridge(windows_of(rows), ends[:400], targets[:400], ends[400:], targets[400:])
    assert fit is not None
    net = LstmNet(FEATURES, WINDOW, hidden=4)
    start_from(net, fit)
    x = gather_windows(rows, ends, WINDOW)
    expected = x.flatten(1).double().numpy() @ fit.weight.T + fit.bias
    with torch.no_grad():
        np.testing.assert_allclose(net(x).double().numpy(), expected, rtol=0, atol=1e-5)


def test_inputs_that_never_vary_have_no_fit() -> None:
    rows = torch.ones(50, FEATURES)
    ends = np.arange(WINDOW - 1, 50)
    targets = torch.randn(len(ends), 2)
    assert fit_ridge(windows_of(rows), ends[:30], targets[:30], ends[30:], targets[30:]) is None


@pytest.fixture(scope='module')
def problem(description: RobotDescription) -> LearningProblem:
    recording, _ = synthetic_recording(description.geometry, 3000, noise=2e-7,
                                       reference=lissajous_reference(3000))
    return build_problem(clean_recordings([recording], LomprChain(description)), window=12,
                         horizon=10)


@pytest.fixture
def fits(monkeypatch: pytest.MonkeyPatch) -> list[LinearFit | None]:
    """Every ridge the training loop fits, in order."""
    made: list[LinearFit | None] = []

    def recorded(*args: object, **kwargs: object) -> object:
        made.append(fit_ridge(*args, **kwargs))  # type: ignore[arg-type]
        return made[-1]

    monkeypatch.setattr(training, 'fit_ridge', recorded)
    return made


def test_a_trained_network_is_never_worse_on_validation_than_its_ridge_start(
        problem: LearningProblem, fits: list[LinearFit | None]) -> None:
    settings = TrainSettings(max_epochs=3, patience=3, seed=3)
    trained = train_network(problem, 'lstm', {'batch_size': 200, 'hidden': 8,
                                              'learning_rate': 0.01}, settings, progress=False)
    assert len(fits) == 1 and fits[0] is not None
    # the start's validation loss is the ridge's (float32 windows against float64)
    assert trained.start_loss == pytest.approx(fits[0].validation_loss, rel=1e-4)
    assert trained.validation_loss <= trained.start_loss
    assert trained.validation_loss == min([trained.start_loss, *trained.history])
    # a learning rate that ruins every epoch leaves the ridge in place
    ruined = train_network(problem, 'lstm', {'batch_size': 200, 'hidden': 8,
                                             'learning_rate': 50.0},
                           dataclasses.replace(settings, max_epochs=1), progress=False)
    assert ruined.best_epoch == 0 and ruined.validation_loss == ruined.start_loss
    net, fit = ruined.module.net, fits[-1]
    assert isinstance(net, LstmNet) and fit is not None
    np.testing.assert_allclose(net.highway.weight.detach().double().numpy(), fit.weight,
                               rtol=0, atol=1e-6)


def test_auto_holds_a_highway_too_wide_for_its_training_windows() -> None:
    net = LstmNet(FEATURES, WINDOW, hidden=4)
    enough = HOLD_BELOW_WINDOWS_PER_INPUT * WINDOW * FEATURES
    assert holds_highway(net, enough - 1, 'auto') and not holds_highway(net, enough, 'auto')
    assert holds_highway(net, 10 ** 9, 'held') and not holds_highway(net, 1, 'trained')


def test_a_held_highway_stays_at_its_ridge_start_while_the_lstm_and_head_train(
        problem: LearningProblem, fits: list[LinearFit | None],
        monkeypatch: pytest.MonkeyPatch) -> None:
    highway_trains = []
    fit_epochs = training._fit

    def spied(net: LstmNet, *args: Any, **kwargs: Any) -> None:
        highway_trains.append(net.highway.weight.requires_grad)
        fit_epochs(net, *args, **kwargs)

    monkeypatch.setattr(training, '_fit', spied)
    trained = {rule: train_network(problem, 'lstm', {'batch_size': 200, 'hidden': 8,
                                                     'learning_rate': 0.01},
                                   TrainSettings(max_epochs=3, patience=3, seed=3,
                                                 highway=rule), progress=False)
               for rule in ('held', 'trained')}
    assert highway_trains == [False, True] and len(fits) == 2
    held, fit = trained['held'], fits[0]
    assert held.highway_held and not trained['trained'].highway_held
    net = held.module.net
    assert isinstance(net, LstmNet) and held.best_epoch > 0 and fit is not None
    np.testing.assert_allclose(net.highway.weight.detach().double().numpy(), fit.weight,
                               rtol=0, atol=1e-6)
    last = net.head[-1]  # the head left its zero start
    assert isinstance(last, torch.nn.Linear) and last.weight.abs().max() > 1e-3
    # held for that training only: a fine-tuning of it trains every weight
    assert all(parameter.requires_grad for parameter in net.parameters())


def test_a_refit_fits_each_highway_to_what_its_lstm_leaves() -> None:
    """Targets that are the specialist's LSTM part plus a linear map of the window: refitted,
    its highway is that map (its output the targets); the generalist's highway is fitted on
    the columns it reads; the LSTM parts stay."""
    rows, _, weight = noisy_linear_data(2)
    ends = np.arange(WINDOW - 1, 600)
    net = PairedNet(FEATURES, WINDOW, hidden=4, machine_columns=[1, 2])
    x = gather_windows(rows, ends, WINDOW)
    with torch.no_grad():
        targets = ((net.specialist(x) - net.specialist.highway(x.flatten(1))).double()
                   + torch.from_numpy(x.flatten(1).double().numpy() @ weight.T + 0.3)).float()
    lstm_parts = {k: v.clone() for k, v in net.state_dict().items() if 'highway' not in k}
    refit_highways(net, windows_of(rows), ends[:400], targets[:400], ends[400:], targets[400:])
    with torch.no_grad():
        np.testing.assert_allclose(net.specialist(x).numpy(), targets.numpy(), rtol=0,
                                   atol=1e-3 * float(targets.abs().max()))
        reads = x.index_select(2, net.machine_columns)
        left = targets - (net.generalist(reads) - net.generalist.highway(reads.flatten(1)))
    generalist = fit_ridge(lambda e: windows_of(rows)(e).index_select(2, net.machine_columns),
                           ends[:400], left[:400], ends[400:], left[400:])
    assert generalist is not None
    np.testing.assert_allclose(net.generalist.highway.weight.detach().double().numpy(),
                               generalist.weight, rtol=1e-6, atol=1e-6)
    assert all(torch.equal(net.state_dict()[k], v) for k, v in lstm_parts.items())


def test_fine_tuning_starts_from_the_refit_where_it_validates_better(
        problem: LearningProblem) -> None:
    """A parent fine-tuned on data it does not know: epochs that cannot move (a learning rate
    of 1e-12) leave the refitted highways, which predict the validation part better than
    the parent; without the ridge start, the parent's weights."""
    hyper = {'batch_size': 200, 'hidden': 8, 'learning_rate': 0.01}
    settings = TrainSettings(max_epochs=2, patience=3, seed=3)
    parent = train_network(problem, 'lstm', hyper, settings, progress=False).module
    # another plant: its error twice the parent's along the same path
    other = dataclasses.replace(problem, error=2.0 * problem.error,
                                rows=problem.rows * np.where(
                                    np.isin(np.arange(problem.rows.shape[1]),
                                            error_columns(problem.features)), 2.0, 1.0))
    frozen = {**hyper, 'learning_rate': 1e-12}
    refitted = train_network(other, 'lstm', frozen, settings, progress=False, init=parent)
    assert refitted.highway_refitted and refitted.best_epoch == 0
    assert refitted.validation_loss < 0.9 * refitted.start_loss
    kept = train_network(other, 'lstm', frozen, dataclasses.replace(settings, linear_start=False),
                         progress=False, init=parent)
    assert not kept.highway_refitted and kept.validation_loss == kept.start_loss
    assert kept.start_loss == pytest.approx(refitted.start_loss, rel=1e-9)


def test_a_studys_trainings_on_the_same_data_fit_their_ridge_once(
        monkeypatch: pytest.MonkeyPatch) -> None:
    rows, targets, _ = noisy_linear_data(3)
    ends = np.arange(WINDOW - 1, 600)
    calls = []

    def counted(*args: object) -> object:
        calls.append(args)
        return fit_ridge(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(linear_start, 'fit_ridge', counted)
    fits = RidgeFits(kept=2)
    data = (windows_of(rows), ends[:400], targets[:400], ends[400:], targets[400:])
    first = fits.fit(*data, rows=rows)
    assert fits.fit(*data, rows=rows) is first and len(calls) == 1
    direct = fit_ridge(*data)
    assert first is not None and direct is not None
    np.testing.assert_array_equal(first.weight, direct.weight)
    # other targets, other rows, other ends: fitted anew
    fits.fit(*data[:2], 2 * targets[:400], *data[3:], rows=rows)
    fits.fit(windows_of(rows + 1), *data[1:], rows=rows + 1)
    fits.fit(data[0], ends[:300], targets[:300], *data[3:], rows=rows)
    assert len(calls) == 4
    assert fits.fit(*data, rows=rows) is not first and len(calls) == 5  # kept: the latest two
