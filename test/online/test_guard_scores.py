# SPDX-License-Identifier: Apache-2.0
"""online.guard_scores: predictions meet their truth by instant (a dropped one forgotten, a
newer one for the same instant replacing the older), the mean squares a plain mean at first
and then exponentially weighted, against hand-computed values; a restart keeps or forgets
whose prediction each axis publishes."""

from __future__ import annotations

import math

import pytest

from lompr_predictor.online.guard_scores import UNSCORED, GuardReason, GuardState, LiveScores

PERIOD = 4_000_000
NAN2 = (math.nan, math.nan)


def test_predictions_meet_their_truth_by_instant_and_are_averaged_by_hand() -> None:
    scores = LiveScores(PERIOD)
    scores.weight = 0.01  # a plain mean over the first 100 instants (1: the newest alone)
    scores.expect(1 * PERIOD, (1.0, 0.0), (0.0, 0.0), NAN2, NAN2)
    scores.expect(2 * PERIOD, (9.0, 9.0), (9.0, 9.0), NAN2, NAN2)
    scores.expect(2 * PERIOD + 1, (2.0, 1.0), (1.0, 1.0), (3.0, 3.0), NAN2)  # replaces it
    scores.expect(3 * PERIOD, (5.0, 5.0), (5.0, 5.0), NAN2, NAN2)  # its truth never comes
    scores.expect(4 * PERIOD, (4.0, 0.0), (2.0, 0.0), (4.0, 0.0), (4.0, 1.0))
    scores.observe(1 * PERIOD, (3.0, 0.0))  # model residual 2, persistence 3
    scores.observe(2 * PERIOD + PERIOD // 2, (2.0, 0.0))  # within half a period: 0, 1
    scores.observe(4 * PERIOD - 5, (4.0, 2.0))  # the instant 3 is forgotten: 0, 2
    x, y = scores.axes
    assert scores.scored == 3
    assert x.model_ms == pytest.approx((4 + 0 + 0) / 3, abs=1e-15)
    assert x.persistence_ms == pytest.approx((9 + 1 + 4) / 3, abs=1e-15)
    assert y.model_ms == pytest.approx((0 + 1 + 4) / 3, abs=1e-15)
    # a prior is scored from its first residual on: (2 - 3)^2, then 1/3 of the way to 0
    assert x.prior_ms == pytest.approx(1.0 - (1.0 - 0.0) / 3, abs=1e-15)
    assert x.map_ms == 0.0 and y.map_ms == 1.0
    scores.observe(5 * PERIOD, (0.0, 0.0))  # nothing was expected for it
    assert scores.scored == 3


def test_past_the_plain_mean_the_newest_square_weighs_the_set_weight() -> None:
    scores = LiveScores(PERIOD)
    scores.weight = 0.25
    for k, residual in enumerate((1.0, 1.0, 1.0, 1.0, 3.0)):
        scores.expect(k * PERIOD, (0.0, 0.0), (0.0, 0.0), NAN2, NAN2)
        scores.observe(k * PERIOD, (residual, 0.0))
    # four plain-mean steps (weights 1, 1/2, 1/3, 1/4) leave 1, then 1 + 0.25 (9 - 1)
    assert scores.axes[0].model_ms == pytest.approx(3.0, abs=1e-15)
    status = scores.axes[0].status(scored=True)
    assert status.model_rms == pytest.approx(math.sqrt(3.0), abs=1e-15)
    assert math.isnan(status.prior_rms) and scores.axes[0].prior_ms == UNSCORED


def test_a_restart_forgets_the_scores_and_keeps_the_state_only_if_asked() -> None:
    scores = LiveScores(PERIOD)
    scores.axes[0].state, scores.axes[0].reason = GuardState.MODEL, None
    scores.axes[1].state = GuardState.PRIOR
    scores.axes[1].reason = GuardReason.WORSE_THAN_PRIOR
    scores.expect(PERIOD, (1.0, 1.0), (0.0, 0.0), NAN2, NAN2)
    scores.restart(7, inherit=True)
    assert [(a.state, a.reason, a.switched_at) for a in scores.axes] == [
        (GuardState.MODEL, None, 7), (GuardState.PRIOR, GuardReason.WORSE_THAN_PRIOR, 7)]
    scores.observe(PERIOD, (1.0, 1.0))  # the prediction awaiting its truth went too
    assert scores.scored == 0 and scores.axes[0].model_ms == 0.0
    scores.restart(9)
    assert [(a.state, a.reason) for a in scores.axes] == [
        (GuardState.PERSISTENCE, GuardReason.UNPROVEN)] * 2
    assert math.isnan(scores.axes[0].status(scored=False).model_rms)
