# SPDX-License-Identifier: Apache-2.0
"""The live guard replayed on recorded predictions: what the predictor node would publish.

Offline a model is scored as it is; online the live guard (`online.guard`) hands an axis to
the model's prior or to persistence while the model does worse there, and back when it
does better. To say how a model will compensate a recording of a program it was not trained
on, `lompr evaluate` (and the transfer bench) runs the same guard over the model's, its
prior's and persistence's predictions of every window, in stamp order, with the truth of an
instant revealed only `horizon` samples after its prediction was made, as the node sees it.
A gap in the recording empties the node's window; the replay then forgets the predictions
awaiting their truth, as the node does, and keeps the live scores. What the guard publishes
then meets the node's last check, as online: a change beyond the model's trained range is
persistence (`sample_units.plausible`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lompr_predictor.learning.envelope import InputEnvelope
from lompr_predictor.learning.model_file import ModelMetadata
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.guard import DEFAULT_GUARD, GuardSettings, GuardState, LiveGuard
from lompr_predictor.online.sample_units import plausible, plausible_limits

#: What a replay records per instant and axis: whose prediction was published.
ANSWERING = {GuardState.MODEL: 0, GuardState.PRIOR: 1, GuardState.PERSISTENCE: 2}


@dataclass(frozen=True)
class GuardReplay:
    """What the guard published for each predicted instant, and how it got there."""

    published: np.ndarray  # (B, 2) the prediction published for each instant [m]
    answering: np.ndarray  # (B, 2) int8: whose it was, per axis (`ANSWERING`)
    hand_overs: tuple[int, int]  # per axis, switches model -> a fallback
    hand_backs: tuple[int, int]  # per axis, switches a fallback -> model
    outside_envelope: int  # rows outside the model's trained envelope
    implausible: int = 0  # published predictions handed on as persistence (implausible)

    @property
    def held_back(self) -> np.ndarray:
        """(B, 2) bool: a fallback answered on the axis, not the model."""
        return self.answering != ANSWERING[GuardState.MODEL]

    def summary(self) -> dict[str, object]:
        """The report's entry: per axis, the share of instants held back (and of those the
        prior's) and the switches."""
        def share(state: GuardState, k: int) -> float:
            column = self.answering[:, k]
            return float(np.mean(column == ANSWERING[state])) if len(column) else float('nan')
        held = self.held_back
        return {axis: {'held_back_fraction': float(held[:, k].mean())
                       if len(held) else float('nan'),
                       'prior_fraction': share(GuardState.PRIOR, k),
                       'hand_overs': self.hand_overs[k], 'hand_backs': self.hand_backs[k]}
                for k, axis in enumerate(('x', 'y'))} | {
                    'rows_outside_envelope': self.outside_envelope,
                    'implausible_predictions': self.implausible}


def replay_guard(guard: LiveGuard, stamps_ns: np.ndarray, actual: np.ndarray,
                 model: np.ndarray, persistence: np.ndarray,
                 inside: np.ndarray | None = None,
                 prior: np.ndarray | None = None,
                 map_prior: np.ndarray | None = None, *,
                 limits: tuple[float, float] | None = None) -> GuardReplay:
    """Run `guard` over B predicted instants in increasing stamps `stamps_ns` (int64 ns):
    the model's prediction `model` (B, 2), persistence's `persistence` (B, 2: the plant
    error `guard.lead_ns` before each instant), the plant error `actual` (B, 2) at each instant,
    whether the model's newest row lay inside its trained envelope (`inside`, (B,);
    None: always), the model's prior (`prior`, (B, 2); None or NaN rows: none) and a paired
    model's map prior (`map_prior`, alike), and the largest plausible change per axis
    (`limits`, `sample_units.plausible_limits`; None: no check). An instant's truth is
    scored once the stream reaches it; a step between instants longer than the guard's
    sample period and a half is a gap."""
    count = len(stamps_ns)
    published = np.empty((count, 2))
    answering = np.zeros((count, 2), dtype=np.int8)
    priors = [(np.zeros(count, dtype=bool) if values is None
               else np.isfinite(values).all(axis=1), values) for values in (prior, map_prior)]
    gap_ns, lead_ns = guard.period_ns * 3 // 2, guard.lead_ns
    truths = 0  # the next instant whose truth the stream has not reached
    implausible = 0
    for k in range(count):
        now = int(stamps_ns[k]) - lead_ns
        if k and stamps_ns[k] - stamps_ns[k - 1] > gap_ns:
            guard.clear()
            truths = k
        while truths < k and stamps_ns[truths] <= now:
            error = (float(actual[truths, 0]), float(actual[truths, 1]))
            guard.observe(AlignedSample(int(stamps_ns[truths]), *error, 0.0, 0.0, 0.0),
                          error, None)
            truths += 1
        prediction = (float(model[k, 0]), float(model[k, 1]))
        last = (float(persistence[k, 0]), float(persistence[k, 1]))
        prior_xy, map_xy = ((float(values[k, 0]), float(values[k, 1]))
                            if values is not None and finite[k] else None
                            for finite, values in priors)
        chosen = guard.choose(int(stamps_ns[k]), prediction, last,
                              True if inside is None else bool(inside[k]), prior_xy, map_xy)
        if limits is not None:
            kept = plausible(chosen, last, limits)
            implausible += kept != chosen
            chosen = kept
        published[k] = chosen
        state_x, state_y = guard.answering
        answering[k] = ANSWERING[state_x], ANSWERING[state_y]
    x, y = guard.status()
    return GuardReplay(published=published, answering=answering,
                       hand_overs=(x.hand_overs, y.hand_overs),
                       hand_backs=(x.hand_backs, y.hand_backs),
                       outside_envelope=guard.envelope.rows_outside, implausible=implausible)


def replay_model_guard(metadata: ModelMetadata, stamps_ns: np.ndarray, actual: np.ndarray,
                       model: np.ndarray, persistence: np.ndarray, newest_rows: np.ndarray,
                       settings: GuardSettings = DEFAULT_GUARD,
                       prior: np.ndarray | None = None,
                       map_prior: np.ndarray | None = None) -> GuardReplay:
    """`replay_guard` with the guard a predictor node builds for this model (its horizon,
    sample period and trained envelope, the node's default rules unless `settings`), the
    envelope checked on each window's newest feature row (`newest_rows`, (B, features)),
    with the model's prior `prior` (and a paired model's `map_prior`) where it has one, and
    the node's plausibility check of the model's trained range."""
    envelope = InputEnvelope.from_metadata(metadata.envelope, metadata.features)
    inside = (None if envelope is None else
              np.array([envelope.contains(row) for row in newest_rows.tolist()], dtype=bool))
    guard = LiveGuard.for_stream(settings, metadata.horizon, metadata.sample_period)
    return replay_guard(guard, stamps_ns, actual, model, persistence, inside, prior, map_prior,
                        limits=plausible_limits(metadata))
