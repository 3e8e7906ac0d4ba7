# SPDX-License-Identifier: Apache-2.0
"""The live guard: the model compensates an axis only while it beats its fallbacks there (its
map prior, persistence), and not while its inputs lie outside what it was trained on."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import random
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from guard_streams import HORIZON, LEAD, PERIOD, guard_rules, random_walk, run_guard

from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.guard import (
    AxisStatus,
    GuardReason,
    GuardState,
    LiveGuard,
)


def test_a_model_better_than_persistence_earns_both_axes_and_keeps_them() -> None:
    """Persistence answers until the first decision (`min_scored` scores, `min_dwell` from
    the start), then the model, better by far, on both axes to the end."""
    settings = guard_rules(min_scored=50, dwell_instants=50)
    guard = LiveGuard(settings, LEAD, PERIOD)
    x, y = guard.status()
    assert x.state is y.state is GuardState.PERSISTENCE and guard.holding
    assert x.reason is y.reason is GuardReason.UNPROVEN
    truth = random_walk(600)
    model_error = np.random.default_rng(1).normal(0.0, 0.2e-6, truth.shape)
    published = run_guard(guard, truth, model_error)
    # scored from the instant HORIZON on: the first decision comes with the 50th score
    earned = settings.min_scored + HORIZON - 1
    np.testing.assert_array_equal(published[:earned], truth[:earned])
    np.testing.assert_array_equal(published[earned:-HORIZON],
                                  (truth + model_error)[earned + HORIZON:])
    x, y = guard.status()
    assert x.state is y.state is GuardState.MODEL and x.hand_overs == y.hand_overs == 0
    assert x.hand_backs == y.hand_backs == 1 and x.reason is y.reason is None
    assert not guard.holding and guard.published_fallback == earned
    assert math.isnan(x.prior_rms)  # a model without a map has no prior
    # both scored on the same instants: the model's live RMS near its 0.2 um, persistence's
    # near the walk's sqrt(2) um
    assert 0.15e-6 < x.model_rms < 0.25e-6 and 1.2e-6 < x.persistence_rms < 1.6e-6


def test_an_axis_where_the_model_is_worse_stays_with_persistence() -> None:
    """X of the model misses by 5 um, Y by 0.2 um: X never earns control (the first
    decision names the reason), Y does; the published X is the last plant error
    (persistence's) throughout."""
    settings = guard_rules(min_scored=50, dwell_instants=50)
    guard = LiveGuard(settings, LEAD, PERIOD)
    truth = random_walk(400, seed=2)
    model_error = np.random.default_rng(3).normal(0.0, 0.2e-6, truth.shape)
    model_error[:, 0] = 5e-6
    published = run_guard(guard, truth, model_error)
    x, y = guard.status()
    assert x.state is GuardState.PERSISTENCE and x.reason is GuardReason.WORSE_THAN_PERSISTENCE
    assert y.state is GuardState.MODEL and y.reason is None
    assert x.hand_overs == x.hand_backs == 0 and guard.holding
    np.testing.assert_array_equal(published[:-HORIZON, 0], truth[:-HORIZON, 0])
    earned = settings.min_scored + HORIZON - 1
    np.testing.assert_array_equal(published[earned:-HORIZON, 1],
                                  (truth + model_error)[earned + HORIZON:, 1])
    # the live figures: a constant 5 um miss has an RMS of 5 um exactly
    assert math.isclose(x.model_rms, 5e-6, rel_tol=1e-9)


@pytest.mark.parametrize(('ratio', 'reason'), [(1.03, GuardReason.WORSE_THAN_PERSISTENCE),
                                               (0.97, GuardReason.UNPROVEN)])
def test_a_model_within_the_margin_of_persistence_never_earns_control(
        ratio: float, reason: GuardReason) -> None:
    """A model whose every residual is `ratio` x persistence's, inside the margin: the
    model never answers; the reason says whether it is worse or only not better enough."""
    settings = guard_rules(margin=0.05, min_scored=50, dwell_instants=50)
    guard = LiveGuard(settings, LEAD, PERIOD)
    truth = random_walk(300, seed=7)
    model_error = np.zeros_like(truth)
    model_error[HORIZON:] = -ratio * (truth[HORIZON:] - truth[:-HORIZON])
    published = run_guard(guard, truth, model_error)
    np.testing.assert_array_equal(published[:-HORIZON], truth[:-HORIZON])
    x, y = guard.status()
    assert x.state is y.state is GuardState.PERSISTENCE and x.reason is y.reason is reason
    assert x.hand_overs == y.hand_overs == x.hand_backs == y.hand_backs == 0
    assert math.isclose(x.model_rms / x.persistence_rms, ratio, rel_tol=1e-9)


def test_hand_over_is_at_once_and_hand_back_needs_the_margin_and_the_dwell() -> None:
    """Better, worse, better: the axis is handed over as soon as the model's weighted RMS
    exceeds persistence's (the dwell since it earned control has passed) and comes back
    once below (1 - margin) x persistence's and `min_dwell` has passed, not before."""
    settings = guard_rules(window_instants=20, margin=0.1, min_scored=10, dwell_instants=100)
    guard = LiveGuard(settings, LEAD, PERIOD)
    truth = random_walk(1000, seed=4)
    model_error = np.zeros_like(truth)
    model_error[300:600] = 6e-6  # far worse than persistence (~1.4 um)
    published = run_guard(guard, truth, model_error)
    x, _ = guard.status()
    assert x.hand_overs == 1 and x.hand_backs == 2 and x.state is GuardState.MODEL
    from_model = published[:-HORIZON, 0] == (truth + model_error)[HORIZON:, 0]
    # earned with the first decision the dwell allows (the 100th)
    assert not from_model[:99].any() and from_model[99:300 - HORIZON].all()
    over = 300 - HORIZON + int(np.argmin(from_model[300 - HORIZON:]))
    back = over + int(np.argmax(from_model[over:]))
    # handed over within a few instants of the first miss scored (instant 300, predicted
    # HORIZON samples earlier); held at least the dwell, and only after the misses stopped
    # (instant 600) and the weighted mean forgot them
    assert over <= 300 + HORIZON
    assert back - over >= 100
    assert back > 600


def test_the_prior_answers_where_the_model_is_worse_and_it_is_better_than_persistence() -> None:
    """X of the model misses by 5 um, its prior by 0.3 um, persistence by ~1.4 um: X goes to
    the prior (its value published, the reason naming it); Y, where the model beats both,
    stays with the model."""
    settings = guard_rules(min_scored=50, dwell_instants=50)
    guard = LiveGuard(settings, LEAD, PERIOD)
    truth = random_walk(400, seed=8)
    rng = np.random.default_rng(9)
    model_error = rng.normal(0.0, 0.1e-6, truth.shape)
    model_error[:, 0] = 5e-6
    prior_error = rng.normal(0.0, 0.3e-6, truth.shape)
    published = run_guard(guard, truth, model_error, prior_error=prior_error)
    x, y = guard.status()
    assert x.state is GuardState.PRIOR and x.reason is GuardReason.WORSE_THAN_PRIOR
    assert y.state is GuardState.MODEL and x.hand_overs == y.hand_overs == 0
    assert x.hand_backs == 0 and y.hand_backs == 1
    assert guard.answering == (GuardState.PRIOR, GuardState.MODEL)
    np.testing.assert_array_equal(published[-100:-HORIZON, 0],
                                  (truth + prior_error)[-100 + HORIZON:, 0])
    earned = settings.min_scored + HORIZON - 1
    np.testing.assert_array_equal(published[earned:-HORIZON, 1],
                                  (truth + model_error)[earned + HORIZON:, 1])
    assert 0.2e-6 < x.prior_rms < 0.4e-6 < 1.2e-6 < x.persistence_rms


def test_of_a_paired_models_two_priors_the_better_live_answers() -> None:
    """The model misses by 5 um; its generalist (the prior) by 1.0 um on X and 0.3 um on Y,
    its map prior by 0.3 um on X and 1.0 um on Y, persistence by ~1.4 um: X is answered by
    the map prior, Y by the generalist, each the value published; both scored."""
    guard = LiveGuard(guard_rules(min_scored=50, dwell_instants=50), LEAD, PERIOD)
    truth = random_walk(400, seed=8)
    rng = np.random.default_rng(11)
    model_error = np.full(truth.shape, 5e-6)
    prior_error = rng.normal(0.0, 1.0, truth.shape) * np.array([1.0e-6, 0.3e-6])
    map_error = rng.normal(0.0, 1.0, truth.shape) * np.array([0.3e-6, 1.0e-6])
    published = run_guard(guard, truth, model_error, prior_error=prior_error, map_error=map_error)
    x, y = guard.status()
    assert x.state is y.state is GuardState.PRIOR
    assert x.reason is y.reason is GuardReason.WORSE_THAN_PRIOR
    np.testing.assert_array_equal(published[-100:-HORIZON, 0],
                                  (truth + map_error)[-100 + HORIZON:, 0])
    np.testing.assert_array_equal(published[-100:-HORIZON, 1],
                                  (truth + prior_error)[-100 + HORIZON:, 1])
    assert 0.2e-6 < x.map_prior_rms < 0.4e-6 and 0.8e-6 < x.prior_rms < 1.2e-6
    assert 0.2e-6 < y.prior_rms < 0.4e-6 and 0.8e-6 < y.map_prior_rms < 1.2e-6


def test_a_model_better_than_persistence_but_worse_than_its_prior_is_handed_to_it() -> None:
    """The model's network adds 0.6 um of misses to a prior that misses by 0.2 um, both far
    better than persistence: the prior takes both axes (what the network learned does not
    hold here)."""
    guard = LiveGuard(guard_rules(min_scored=50, dwell_instants=50), LEAD, PERIOD)
    truth = random_walk(400, seed=10)
    rng = np.random.default_rng(11)
    prior_error = rng.normal(0.0, 0.2e-6, truth.shape)
    model_error = prior_error + rng.normal(0.0, 0.6e-6, truth.shape)
    run_guard(guard, truth, model_error, prior_error=prior_error)
    x, y = guard.status()
    assert x.state is y.state is GuardState.PRIOR
    assert x.model_rms < x.persistence_rms and x.prior_rms < x.model_rms


def test_a_prior_no_better_than_persistence_is_passed_over_and_left_when_worse() -> None:
    """The model misses by 5 um throughout. First its prior misses by 1.4 um, about as
    persistence does (~1.4 um), so persistence answers (the prior must be better by the
    margin); then the prior misses by 0.2 um and takes over; then by 4 um and persistence
    takes back. Switches between the fallbacks are no hand-backs to the model."""
    settings = guard_rules(window_instants=20, min_scored=10, dwell_instants=20)
    guard = LiveGuard(settings, LEAD, PERIOD)
    truth = random_walk(900, seed=12)
    rng = np.random.default_rng(13)
    model_error = np.full_like(truth, 5e-6)
    prior_error = np.empty_like(truth)
    prior_error[:300] = (np.roll(truth, HORIZON, axis=0) - truth)[:300]  # persistence itself
    prior_error[300:600] = rng.normal(0.0, 0.2e-6, (300, 2))
    prior_error[600:] = 4e-6
    answering = []
    for k in range(len(truth) - HORIZON):
        stamp = k * PERIOD
        error = (float(truth[k, 0]), float(truth[k, 1]))
        guard.observe(AlignedSample(stamp, *error, 0.0, 0.0, 1.1), error, None)
        target = truth[k + HORIZON] + model_error[k + HORIZON]
        prior = truth[k + HORIZON] + prior_error[k + HORIZON]
        guard.choose(stamp + LEAD, (float(target[0]), float(target[1])), error, True,
                     (float(prior[0]), float(prior[1])))
        answering.append(guard.answering[0])
    assert set(answering[100:300]) == {GuardState.PERSISTENCE}
    assert set(answering[400:600]) == {GuardState.PRIOR}
    assert set(answering[700:]) == {GuardState.PERSISTENCE}
    x, _ = guard.status()
    assert x.hand_overs == x.hand_backs == 0  # the model never had control
    assert x.reason is GuardReason.WORSE_THAN_PERSISTENCE


def test_rows_outside_the_envelope_hold_the_model_back() -> None:
    settings = guard_rules(window_instants=10, envelope_fraction=0.5, dwell_instants=0)
    guard = LiveGuard(settings, LEAD, PERIOD)
    truth = random_walk(200, seed=5)
    inside = np.ones(len(truth), dtype=bool)
    inside[100:150] = False
    published = run_guard(guard, truth, np.zeros_like(truth), inside)
    held = published[:-HORIZON, 0] == truth[:-HORIZON, 0]
    # unproven until the first decision (the 50th score, instant 51), then the model
    earned = settings.min_scored + HORIZON - 1
    assert held[:earned].all() and not held[earned:100].any()
    assert held[110:150].all() and not held[170:].any()
    assert guard.envelope.rows_outside == 50
    x, _ = guard.status()
    assert x.hand_overs == 1 and x.hand_backs == 2


def test_disabled_guard_publishes_the_model_and_still_reports() -> None:
    guard = LiveGuard(guard_rules(enabled=False, min_scored=10, dwell_instants=10), LEAD, PERIOD)
    truth = random_walk(200, seed=6)
    model_error = np.full_like(truth, 5e-6)
    published = run_guard(guard, truth, model_error)
    np.testing.assert_array_equal(published[:-HORIZON], (truth + model_error)[HORIZON:])
    assert guard.holding  # what the guard would do, for diagnostics
    assert guard.published_fallback == 0
    assert guard.answering == (GuardState.MODEL, GuardState.MODEL)


def test_a_new_model_starts_unproven_and_an_adapted_one_inherits_the_choice() -> None:
    """X with the model (better), Y with persistence (the model worse). A new model: both
    axes back on persistence, unproven, scores fresh. An adapted model (`inherit`): X stays
    with the model, Y with persistence for the reason it had, scores fresh; the first
    predictions after it are published accordingly."""
    settings = guard_rules(min_scored=50, dwell_instants=50)
    truth = random_walk(300, seed=22)
    model_error = np.random.default_rng(23).normal(0.0, 0.2e-6, truth.shape)
    model_error[:, 1] = 5e-6
    guards = []
    for inherit in (False, True):
        guard = LiveGuard(settings, LEAD, PERIOD)
        run_guard(guard, truth, model_error)
        assert guard.answering == (GuardState.MODEL, GuardState.PERSISTENCE)
        guard.restart(inherit=inherit)
        assert guard.scored == 0 and guard.holding
        guards.append(guard)
    fresh, adapted = guards
    x, y = fresh.status()
    assert x.state is y.state is GuardState.PERSISTENCE
    assert x.reason is y.reason is GuardReason.UNPROVEN
    x, y = adapted.status()
    assert (x.state, x.reason) == (GuardState.MODEL, None)
    assert (y.state, y.reason) == (GuardState.PERSISTENCE, GuardReason.WORSE_THAN_PERSISTENCE)
    assert math.isnan(x.model_rms)  # scores start from nothing
    last = (float(truth[-1, 0]), float(truth[-1, 1]))
    instant = (len(truth) - 1) * PERIOD + LEAD
    error = (float(truth[-1, 0]), float(truth[-1, 1]))
    adapted.observe(AlignedSample((len(truth) - 1) * PERIOD, *error, 0.0, 0.0, 1.1), error, None)
    assert adapted.choose(instant, (1e-6, 2e-6), last, True) == (1e-6, last[1])
    assert fresh.choose(instant, (1e-6, 2e-6), last, True) == last


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match='margin'):
        guard_rules(margin=1.0)
    with pytest.raises(ValueError, match='window'):
        guard_rules(window_instants=0)


def _mixed_run(guard: LiveGuard) -> list[Any]:
    """A long stream through the core's calls (`observe`, `revise` on a slot): the model
    better then worse per axis in stretches, bursts of rows outside the envelope, dropped
    samples, a cleared window, a new model, the guard off for a while and its rules
    changed. Returns the guard's status and counters before the new model, every published
    prediction, then its status and counters at the end."""
    rng = random.Random(30)
    features = ('error_x', 'error_y', 'ref_x', 'ref_y', 'ups1_v')
    model = SimpleNamespace(metadata=SimpleNamespace(
        features=features, envelope={'margin': 0.1, 'ranges': {
            'ref_x': [-1.0, 1.0], 'ref_y': [-1.0, 1.0], 'ups1_v': [-0.5, 0.5]}}))
    errors, published = [(0.0, 0.0)], []
    while len(errors) < 8000 + HORIZON:
        step = 1e-6 * (rng.random() - 0.5)
        errors.append((errors[-1][0] + step, errors[-1][1] + 1e-6 * (rng.random() - 0.5)))
    for k in range(1, 8000):
        if k == 4000:
            before = [*map(_as_first_written, guard.status()), guard.scored,
                      guard.published_fallback]
            guard.restart()
            model = SimpleNamespace(metadata=SimpleNamespace(features=features, envelope={}))
        if k in {2500, 6000}:
            guard.clear()
        if k == 3000:
            guard.settings = guard_rules(enabled=False, window_instants=40, dwell_instants=15)
        if k == 3500:
            guard.settings = guard_rules(window_instants=80, margin=0.2, dwell_instants=30)
        if rng.random() < 0.02:
            continue  # a dropped sample: its instant never meets its truth
        stamp = k * PERIOD
        guard.observe(AlignedSample(stamp, *errors[k], 0.0, 0.0, 1.1), errors[k], None)
        worse_x, worse_y = (k // 700) % 2, (k // 1100) % 3 == 1
        miss = (3e-6 * worse_x + 0.3e-6 * rng.random(), 3e-6 * worse_y + 0.3e-6 * rng.random())
        burst = 1.7 if (k // 300) % 5 == 3 else 0.0
        row = (*errors[k], rng.random() - 0.5, rng.random() - 0.5 + burst, 0.4 * rng.random())
        slot = SimpleNamespace(model=model, window=SimpleNamespace(newest=row), prior=None,
                               map_prior=None)
        truth = errors[k + HORIZON]
        prediction = (truth[0] + miss[0], truth[1] + miss[1])
        published.append(guard.revise(stamp + LEAD, prediction, slot))  # type: ignore[arg-type]
    return [*before, *published, *map(_as_first_written, guard.status()), guard.scored,
            guard.envelope.rows_outside, guard.envelope.last_outside, guard.published_fallback,
            guard.envelope.fraction, guard.holding]


def _as_first_written(status: AxisStatus) -> tuple[object, ...]:
    """An axis's status as the guard first reported it (no prior): what the pin hashed."""
    fields = dataclasses.asdict(status)
    fields.pop('prior_rms', None)
    fields.pop('map_prior_rms', None)
    return tuple(fields.values())


def test_decisions_on_a_long_mixed_stream_are_those_pinned() -> None:
    """Every prediction published, the switches and counters over 8000 samples of
    `_mixed_run`, bit for bit those pinned when each model began to earn control (computed
    with the guard then, whose decisions had been pinned against the guard as first written:
    one method call per axis and sample, the envelope compared through `operator.le`; the
    hash taken over the statuses' fields of then): a faster guard, and the guard of a model
    without a prior, must decide alike."""
    outcome = _mixed_run(LiveGuard(guard_rules(window_instants=60, dwell_instants=20), LEAD,
                                   PERIOD))
    held_x, held_y, scored, persisted = outcome[:4]  # before the new model
    assert held_x[0] is held_y[0] is GuardState.PERSISTENCE
    assert held_x[1] is held_y[1] is GuardReason.OUTSIDE_ENVELOPE
    # hand-overs, hand-backs: each model's first hand-back is the control it earned
    assert (*held_x[-2:], *held_y[-2:], scored, persisted) == (3, 3, 2, 2, 3777, 2780)
    x, y = outcome[-8], outcome[-7]
    assert (*x[-2:], *y[-2:]) == (3, 3, 2, 2)
    assert outcome[-6:] == [3827, 684, 'ref_y', 6123, 0.0, True]
    assert hashlib.sha256(repr(outcome).encode()).hexdigest() == (
        'da358b9da96bbaca1f97bee8ecc61f2a749c60dd45bec79d3a844fcbbea5781c')
