# SPDX-License-Identifier: Apache-2.0
"""The guard replayed offline publishes what the predictor node's guard publishes online."""

from __future__ import annotations

import numpy as np
import pytest
from guard_streams import HORIZON, LEAD, PERIOD, guard_rules, random_walk, run_guard

from lompr_predictor.online.guard import GuardState, LiveGuard
from lompr_predictor.scoring.guard_replay import ANSWERING, replay_guard


def _instants(truth: np.ndarray, model_error: np.ndarray, start_ns: int = 0
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The predicted instants of `_run`'s stream: stamps, truth, model's and persistence's
    predictions."""
    stamps = start_ns + np.arange(HORIZON, len(truth)) * PERIOD
    return (stamps, truth[HORIZON:], (truth + model_error)[HORIZON:], truth[:-HORIZON])


def test_replay_publishes_what_the_guard_publishes_sample_by_sample() -> None:
    """A model better than persistence, then worse on X for a while, then better again: the
    replay hands to the model, over and back at the same instants as the guard fed in the
    node's order (a sample's truth, then the prediction from its window)."""
    truth = random_walk(900, seed=11)
    model_error = np.random.default_rng(12).normal(0.0, 0.3e-6, truth.shape)
    model_error[100:400, 0] = 4e-6
    settings = guard_rules(window_instants=40, min_scored=20, dwell_instants=30)
    online = run_guard(LiveGuard(settings, LEAD, PERIOD), truth, model_error)[:-HORIZON]
    replay = replay_guard(LiveGuard(settings, LEAD, PERIOD), *_instants(truth, model_error))
    np.testing.assert_array_equal(replay.published, online)
    assert replay.hand_overs == (1, 0) and replay.hand_backs == (2, 1)
    held_x, held_y = replay.held_back.T
    np.testing.assert_array_equal(held_x, online[:, 0] == truth[:-HORIZON, 0])
    # unproven until the first decision the dwell allows (its 30th), then the model on Y
    earned = 29
    assert held_y[:earned].all() and not held_y[earned:].any()
    assert held_x[:earned].all() and not held_x[earned:100].any()
    assert 0.2 < held_x.mean() < 0.5


def test_a_gap_forgets_the_predictions_awaiting_their_truth() -> None:
    """Two runs 10 s apart: the predictions of the first run's last instants never meet a
    truth, the second run's are scored from its own truths on, and the live scores carry
    over (a model worse on X is still held back right after the gap)."""
    truth = random_walk(600, seed=13)
    model_error = np.zeros_like(truth)
    model_error[:, 0] = 5e-6
    settings = guard_rules(min_scored=20, dwell_instants=10)
    first = _instants(truth[:300], model_error[:300])
    second = _instants(truth[300:], model_error[300:], start_ns=310 * PERIOD + 10**10)
    guard = LiveGuard(settings, LEAD, PERIOD)
    replay = replay_guard(guard, *(np.concatenate(pair) for pair in zip(first, second,
                                                                          strict=True)))
    count = len(first[0])
    assert replay.held_back[count:, 0].all()  # held back from the second run's first instant
    np.testing.assert_array_equal(replay.published[count:, 0], second[3][:, 0])
    assert guard.scored == 2 * (count - HORIZON)  # each run's last HORIZON instants: none
    assert guard.status()[0].state is GuardState.PERSISTENCE


def test_rows_outside_the_envelope_are_counted_and_held_back() -> None:
    truth = random_walk(300, seed=14)
    inside = np.ones(len(truth) - HORIZON, dtype=bool)
    inside[100:160] = False
    settings = guard_rules(window_instants=10, envelope_fraction=0.5, dwell_instants=0)
    replay = replay_guard(LiveGuard(settings, LEAD, PERIOD),
                          *_instants(truth, np.zeros_like(truth)), inside)
    assert replay.outside_envelope == 60
    earned = settings.min_scored + HORIZON - 1  # unproven until the 50th score
    assert replay.held_back[:earned].all() and not replay.held_back[earned:100].any()
    assert replay.held_back[110:160].all()
    summary = replay.summary()
    assert summary['rows_outside_envelope'] == 60
    assert summary['x'] == {'held_back_fraction': float(replay.held_back[:, 0].mean()),
                            'prior_fraction': 0.0, 'hand_overs': 1, 'hand_backs': 2}


def test_replay_with_a_prior_publishes_what_the_guard_publishes() -> None:
    """The model worse on X for a while, its prior better than persistence throughout: the
    replay hands X to the prior and back at the node's instants, and counts the prior's
    share."""
    truth = random_walk(900, seed=15)
    rng = np.random.default_rng(16)
    model_error = rng.normal(0.0, 0.2e-6, truth.shape)
    model_error[100:400, 0] = 4e-6
    prior_error = rng.normal(0.0, 0.5e-6, truth.shape)
    settings = guard_rules(window_instants=40, min_scored=20, dwell_instants=30)
    online = run_guard(LiveGuard(settings, LEAD, PERIOD), truth, model_error,
                       prior_error=prior_error)[:-HORIZON]
    replay = replay_guard(LiveGuard(settings, LEAD, PERIOD), *_instants(truth, model_error),
                          prior=(truth + prior_error)[HORIZON:])
    np.testing.assert_array_equal(replay.published, online)
    on_prior = replay.answering[:, 0] == ANSWERING[GuardState.PRIOR]
    # persistence answers until the first decision (the 30th: the dwell), then the model
    # and the prior by turns
    earned = 29
    assert replay.held_back[:earned].all() and not on_prior[:earned].any()
    np.testing.assert_array_equal(on_prior[earned:], replay.held_back[earned:, 0])
    np.testing.assert_array_equal(replay.published[on_prior, 0],
                                  (truth + prior_error)[HORIZON:][on_prior, 0])
    x = replay.summary()['x']
    assert isinstance(x, dict)
    assert x['held_back_fraction'] == pytest.approx(x['prior_fraction'] + earned / len(on_prior),
                                                   rel=1e-12)
    assert 0.3 < x['prior_fraction'] < 0.6
    assert replay.hand_overs == (1, 0) and replay.hand_backs == (2, 1)


def test_replay_hands_on_persistence_where_the_node_finds_a_change_implausible() -> None:
    """What the guard publishes meets the node's last check offline too: a predicted change
    beyond the model's limit on an axis is persistence there, counted, the other axis kept."""
    truth = random_walk(300, seed=21)
    model_error = np.zeros_like(truth)
    model_error[150, 0] = 5e-3  # one prediction 5 mm off on X
    settings = guard_rules(window_instants=40, min_scored=20, dwell_instants=30, enabled=False)
    stamps, actual, model, persistence = _instants(truth, model_error)
    limits = (1e-3, 1e-3)  # 1 mm per axis over the horizon
    replay = replay_guard(LiveGuard(settings, LEAD, PERIOD), stamps, actual, model,
                          persistence, limits=limits)
    jump = 150 - HORIZON
    assert replay.implausible == 1 and replay.summary()['implausible_predictions'] == 1
    assert replay.published[jump, 0] == persistence[jump, 0]
    assert replay.published[jump, 1] == model[jump, 1]
    others = np.arange(len(stamps)) != jump
    np.testing.assert_array_equal(replay.published[others], model[others])
    unchecked = replay_guard(LiveGuard(settings, LEAD, PERIOD), stamps, actual, model,
                             persistence)
    assert unchecked.implausible == 0 and unchecked.published[jump, 0] == model[jump, 0]
