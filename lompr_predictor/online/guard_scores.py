# SPDX-License-Identifier: Apache-2.0
"""The live guard's scores (ROS-free): per axis, the exponentially weighted mean squares of
the residuals of the model, its priors and persistence, each scored on the same instants as
the truth of its predictions arrives.

A prediction is kept by its instant (`expect`) until the plant error measured at that
instant comes (`observe`); an instant whose truth never came (a dropped sample) is
forgotten. The guard (`guard.LiveGuard`) reads the mean squares to decide whose prediction
an axis publishes; its own state per axis (whose it publishes, why, the switches) lives
beside the scores in the same record, both being one axis of the machine.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import StrEnum

from lompr_predictor.online.offset import XY

#: The live mean square of a candidate not yet scored (a model without a prior): never
#: chosen.
UNSCORED = float('inf')


class GuardState(StrEnum):
    """Whose prediction an axis publishes."""

    MODEL = 'model'
    PRIOR = 'prior'  # the model's prior: what it predicts from the machine alone
    PERSISTENCE = 'persistence'


class GuardReason(StrEnum):
    """Why the guard holds the model back on an axis."""

    WORSE_THAN_PERSISTENCE = 'worse_than_persistence'  # its live RMS; persistence answers
    WORSE_THAN_PRIOR = 'worse_than_prior'  # its live RMS; its prior answers
    OUTSIDE_ENVELOPE = 'outside_envelope'  # the inputs left what training saw
    UNPROVEN = 'unproven'  # not yet better than the fallbacks by the margin, nor worse


@dataclass(frozen=True)
class AxisStatus:
    """One axis of the guard, for diagnostics."""

    state: GuardState
    reason: GuardReason | None  # why the model is held back (None: it is not)
    model_rms: float  # live RMS of the model's residual [m] (NaN before the first)
    persistence_rms: float  # live RMS of persistence's residual [m], same instants
    prior_rms: float  # live RMS of the prior's residual [m] (NaN: no prior)
    map_prior_rms: float  # a paired model's map prior's, its second prior [m] (NaN: none)
    hand_overs: int  # switches model -> a fallback
    hand_backs: int  # switches a fallback -> model


class GuardAxis:
    """One axis: its live mean squares (`LiveScores`) and the guard's state on it. Plain
    slots, updated inline: a method call per axis and sample would be most of the cost."""

    __slots__ = ('hand_backs', 'hand_overs', 'map_ms', 'model_ms', 'on_map', 'persistence_ms',
                 'prior_ms', 'reason', 'state', 'switched_at')

    def __init__(self, instant: int) -> None:
        self.model_ms = 0.0
        self.persistence_ms = 0.0
        self.prior_ms = UNSCORED
        self.map_ms = UNSCORED  # a paired model's map prior, its second prior
        self.on_map = False  # the prior state answers with the map prior (the better)
        self.state = GuardState.PERSISTENCE  # until the model earns control
        self.reason: GuardReason | None = GuardReason.UNPROVEN
        self.switched_at = instant  # the guard's count of decisions at the last switch
        self.hand_overs = 0
        self.hand_backs = 0

    def status(self, scored: bool) -> AxisStatus:
        """The axis for diagnostics (`scored`: any instant was)."""
        nan = float('nan')
        return AxisStatus(state=self.state, reason=self.reason,
                          model_rms=self.model_ms ** 0.5 if scored else nan,
                          persistence_rms=self.persistence_ms ** 0.5 if scored else nan,
                          prior_rms=nan if self.prior_ms == UNSCORED else self.prior_ms ** 0.5,
                          map_prior_rms=nan if self.map_ms == UNSCORED else self.map_ms ** 0.5,
                          hand_overs=self.hand_overs, hand_backs=self.hand_backs)


class LiveScores:
    """The predictions awaiting their truth and the two axes' live mean squares, on a grid
    of instants `period_ns` apart (an instant matches within half a period)."""

    def __init__(self, period_ns: int) -> None:
        self._tolerance_ns = period_ns // 2
        #: (instant, model x, y, persistence x, y, prior x, y, map prior x, y (NaN: none))
        #: awaiting their truth, in increasing instants (a sample's truth arrives in stamp
        #: order)
        self._pending: deque[tuple[int, float, float, float, float, float, float, float,
                                   float]] = deque()
        self.axes = (GuardAxis(0), GuardAxis(0))
        self.weight = 1.0  # of the newest square once past the first 1 / weight instants
        self.scored = 0  # instants where the predictions met their truth

    def expect(self, instant_ns: int, model: XY, persistence: XY, prior: XY, map_prior: XY
               ) -> None:
        """Keep the predictions for `instant_ns` (a prior NaN: none) until its truth comes;
        a newer prediction for the same instant replaces the older."""
        pending = self._pending
        while pending and pending[-1][0] >= instant_ns - self._tolerance_ns:
            pending.pop()
        pending.append((instant_ns, *model, *persistence, *prior, *map_prior))

    def observe(self, stamp_ns: int, error: XY) -> None:
        """The plant error measured at `stamp_ns`: the truth of the predictions made for
        it, scored where they exist."""
        pending, tolerance = self._pending, self._tolerance_ns
        while pending and pending[0][0] < stamp_ns - tolerance:
            pending.popleft()  # an instant whose truth never came (a dropped sample)
        if not pending or pending[0][0] > stamp_ns + tolerance:
            return
        (_, model_x, model_y, persistence_x, persistence_y, prior_x, prior_y, map_x,
         map_y) = pending.popleft()
        scored = self.scored = self.scored + 1
        weight = 1.0 / scored  # a plain mean at first
        if weight < self.weight:
            weight = self.weight
        error_x, error_y = error
        axis_x, axis_y = self.axes
        # each mean square moves by weight x (its new square - itself)
        residual = error_x - model_x
        axis_x.model_ms += weight * (residual * residual - axis_x.model_ms)
        residual = error_x - persistence_x
        axis_x.persistence_ms += weight * (residual * residual - axis_x.persistence_ms)
        residual = error_y - model_y
        axis_y.model_ms += weight * (residual * residual - axis_y.model_ms)
        residual = error_y - persistence_y
        axis_y.persistence_ms += weight * (residual * residual - axis_y.persistence_ms)
        if prior_x == prior_x:  # not NaN: the model has a prior
            axis_x.prior_ms = _moved(axis_x.prior_ms, error_x - prior_x, weight)
            axis_y.prior_ms = _moved(axis_y.prior_ms, error_y - prior_y, weight)
        if map_x == map_x:  # not NaN: a paired model's map prior
            axis_x.map_ms = _moved(axis_x.map_ms, error_x - map_x, weight)
            axis_y.map_ms = _moved(axis_y.map_ms, error_y - map_y, weight)

    def clear(self) -> None:
        """Forget the predictions awaiting their truth; the scores are kept."""
        self._pending.clear()

    def restart(self, decisions: int, *, inherit: bool = False) -> None:
        """New axes whose scores start from nothing (`decisions`: the guard's count, for the
        dwell); with `inherit`, each keeps whose prediction it publishes and why."""
        self.clear()
        old, self.axes = self.axes, (GuardAxis(decisions), GuardAxis(decisions))
        if inherit:
            for axis, before in zip(self.axes, old, strict=True):
                axis.state, axis.reason, axis.on_map = before.state, before.reason, before.on_map
        self.scored = 0


def _moved(mean_square: float, residual: float, weight: float) -> float:
    """A prior's mean square after one more residual (its first: the square itself)."""
    if mean_square == UNSCORED:
        return residual * residual
    return mean_square + weight * (residual * residual - mean_square)
