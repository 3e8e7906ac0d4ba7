# SPDX-License-Identifier: Apache-2.0
"""The live guard: the model compensates only while it does better than its fallbacks.

A learned model can be wrong on a program or a machine it was not trained on, and then its
offset makes the error worse than the simplest compensator, persistence (minus the plant
error measured `horizon` samples before the instant). A model with a machine map has a
second fallback, its prior (`learning.map_prior`: what it predicts from the machine alone;
a paired model has two, and the better live answers), which transfers between programs
where the network that reads the path does not. The guard scores the three on the same
instants as their truth arrives (`guard_scores`: exponentially weighted over `window`
seconds of sample time, long enough to span what a program repeats) and chooses per axis
whose prediction is published:

- a model earns control: each axis starts `unproven` on a fallback and the model takes it
  once its live RMS is below the better fallback's by `margin`; it is handed over as soon
  as it is worse than that fallback, and back when better by the margin again (the
  hysteresis); no switch within `min_dwell` seconds of the last, none before `min_scored`
  instants were scored. Between the fallbacks the prior answers once better than
  persistence by the margin, until it is worse;
- while more than `envelope_fraction` of the recent feature rows lie outside the model's
  trained envelope (`learning.envelope`) both axes are held back whatever the scores.

A unit of the predictor core's chain (`sample_units`), ROS-free, on Python floats. With the
guard off (`enabled` False) the scores and states go on, so diagnostics show what it would
do. The rules at length: docs/nodes.md, "Live guard".
"""

from __future__ import annotations

from dataclasses import dataclass

from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.envelope_watch import EnvelopeWatch
from lompr_predictor.online.guard_scores import (
    AxisStatus,
    GuardReason,
    GuardState,
    LiveScores,
)
from lompr_predictor.online.inference import NO_PRIOR
from lompr_predictor.online.model_slot import ModelSlot
from lompr_predictor.online.offset import XY
from lompr_predictor.stamps import period_ns

AXES = ('x', 'y')
#: Mean squares closer than this [m^2] are taken as equal: (1 nm)^2, far below what any
#: encoder resolves, so that rounding never decides between two predictions.
NEGLIGIBLE_MS = 1e-18


#: The reason an axis answered by a fallback gives when the model is worse there.
WORSE_THAN = {GuardState.PERSISTENCE: GuardReason.WORSE_THAN_PERSISTENCE,
              GuardState.PRIOR: GuardReason.WORSE_THAN_PRIOR}


@dataclass(frozen=True, kw_only=True)
class GuardSettings:
    """The guard's rules (module docstring), each the predictor node's parameter `guard_`
    + its name (declared there once, with its default); `enabled` False publishes the model
    always (the scores and states go on)."""

    enabled: bool
    window: float  # seconds of sample time the live RMS is weighted over (time constant)
    margin: float  # relative: hand over above 1 x the better fallback, back below (1 - margin) x
    min_dwell: float  # seconds of sample time between two switches of an axis, at least
    min_scored: int  # instants scored before the first decision
    envelope_fraction: float  # recent rows outside the envelope that hold the model back

    def __post_init__(self) -> None:
        if not self.window > 0 or not self.min_dwell >= 0 or self.min_scored < 0:
            msg = (f'guard window must be > 0, min_dwell and min_scored >= 0, got '
                   f'{self.window}, {self.min_dwell}, {self.min_scored}')
            raise ValueError(msg)
        if not 0.0 <= self.margin < 1.0 or not 0.0 <= self.envelope_fraction <= 1.0:
            msg = (f'guard margin must lie in [0, 1) and envelope_fraction in [0, 1], got '
                   f'{self.margin} and {self.envelope_fraction}')
            raise ValueError(msg)


#: The predictor node's rules unless its parameters say otherwise (declared there with these
#: defaults), and those of the offline replay (`scoring.guard_replay`).
DEFAULT_GUARD = GuardSettings(enabled=True, window=60.0, margin=0.05, min_dwell=2.0,
                              min_scored=50, envelope_fraction=0.5)


class LiveGuard:
    """Chooses per axis between the model's prediction, its prior's and persistence's
    (module docstring), on a grid of instants `period_ns` apart, predictions `lead_ns`
    ahead: a `sample_units.SampleUnit` of the predictor core, deciding on the live scores
    (`guard_scores.LiveScores`). It runs at the sample rate: the rules are read once per
    change of the settings, the common decision (both axes kept, the model in control and
    no worse) is written out inline."""

    def __init__(self, settings: GuardSettings, lead_ns: int, period_ns: int) -> None:
        self._period_ns = period_ns
        self._scores = LiveScores(period_ns)
        self.settings = settings  # also sets the weight and thresholds, in instants
        self._lead_ns = lead_ns
        self._tolerance_ns = period_ns // 2
        self._decisions = 0  # predictions chosen: an axis's dwell counts them
        self._holding = True  # an axis is in a fallback's hands
        self._last: tuple[int, XY] | None = None  # the newest sample's stamp and plant error
        #: The model's newest rows against its trained envelope.
        self.envelope = EnvelopeWatch()
        self.published_fallback = 0  # predictions published with an axis held back

    @classmethod
    def for_stream(cls, settings: GuardSettings, horizon: int,
                   sample_period: float) -> LiveGuard:
        """The guard of a model predicting `horizon` samples ahead of a stream sampled
        every `sample_period` [s] (the core's)."""
        period = period_ns(sample_period)
        return cls(settings, horizon * period, period)

    @property
    def lead_ns(self) -> int:
        """How far ahead of the newest sample the guarded predictions are [ns]."""
        return self._lead_ns

    @property
    def period_ns(self) -> int:
        """The stream's sample period [ns]."""
        return self._period_ns

    @property
    def settings(self) -> GuardSettings:
        """The rules; changed at run time (the node's parameters), they apply from the next
        sample on, the live scores kept."""
        return self._settings

    @settings.setter
    def settings(self, settings: GuardSettings) -> None:
        self._settings = settings
        period = self._period_ns * 1e-9
        self._weight = self._scores.weight = min(1.0, period / settings.window)
        # the rules as the decision compares them: mean-square ratios, dwell in instants
        self._hand_over = 1.0  # above it, the better fallback takes over
        self._hand_back = (1.0 - settings.margin) ** 2  # below it, the model takes back
        self._min_dwell = round(settings.min_dwell / period)
        self._min_scored = settings.min_scored
        self._envelope_fraction = settings.envelope_fraction
        self._enabled = settings.enabled

    # -- the chain (`sample_units.SampleUnit`) ---------------------------------------------

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        """The plant error of a sample: the truth of the predictions made for its instant,
        scored where they exist, and persistence's prediction for `lead_ns` later."""
        del published  # the guard keeps the model's own predictions, published or not
        self._last = (sample.stamp_ns, error)
        self._scores.observe(sample.stamp_ns, error)

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        """The prediction to publish for `instant_ns`: the model's, or on an axis held back
        its prior's (the slot's, from the same call) or persistence's (the plant error of
        the sample the window ends at)."""
        last, tolerance = self._last, self._tolerance_ns
        if last is None or not -tolerance <= last[0] + self._lead_ns - instant_ns <= tolerance:
            return prediction  # no sample `lead_ns` before: nothing to compare with
        inside = self.envelope.inside(slot.model.metadata, slot.window)
        return self.choose(instant_ns, prediction, last[1], inside, slot.prior, slot.map_prior)

    def clear(self) -> None:
        """Forget the predictions awaiting their truth (the window was emptied: a fault, a
        restart); the live scores and states are kept, being the machine's."""
        self._scores.clear()
        self._last = None

    # -- the decision ---------------------------------------------------------------------

    def choose(self, instant_ns: int, model: XY, last_error: XY, inside_envelope: bool,
               prior: XY | None = None, map_prior: XY | None = None) -> XY:
        """The prediction to publish for `instant_ns` given the model's, persistence's (the
        plant error `lead_ns` before), whether the model's newest row lies inside its
        trained envelope, the model's prior and a paired model's map prior (None: none);
        all are kept to be scored when the truth arrives."""
        model_x, model_y = model
        last_x, last_y = last_error
        prior_x, prior_y = prior = NO_PRIOR if prior is None else prior
        map_x, map_y = map_prior = NO_PRIOR if map_prior is None else map_prior
        self._scores.expect(instant_ns, model, last_error, prior, map_prior)
        self._decisions += 1
        outside = self.envelope.note(inside_envelope, self._weight) > self._envelope_fraction
        if outside or self._scores.scored >= self._min_scored:
            axis_x, axis_y = self._scores.axes
            hand_over = self._hand_over
            # the common case, the model in control on both axes and no worse, changes nothing
            if outside or self._holding or not (
                    axis_x.model_ms <= hand_over * axis_x.persistence_ms + NEGLIGIBLE_MS
                    and axis_x.model_ms <= hand_over * axis_x.prior_ms + NEGLIGIBLE_MS
                    and axis_x.model_ms <= hand_over * axis_x.map_ms + NEGLIGIBLE_MS
                    and axis_y.model_ms <= hand_over * axis_y.persistence_ms + NEGLIGIBLE_MS
                    and axis_y.model_ms <= hand_over * axis_y.prior_ms + NEGLIGIBLE_MS
                    and axis_y.model_ms <= hand_over * axis_y.map_ms + NEGLIGIBLE_MS):
                self._decide(outside)
        if not self._holding or not self._enabled:
            return model
        self.published_fallback += 1
        axis_x, axis_y = self._scores.axes
        return (_answer(axis_x.state, model_x, last_x, map_x if axis_x.on_map else prior_x),
                _answer(axis_y.state, model_y, last_y, map_y if axis_y.on_map else prior_y))

    def _decide(self, outside: bool) -> None:
        """Switch the axes the rules say to switch (module docstring), none within
        `min_dwell` instants of its last switch; `outside`: too many recent rows outside the
        envelope. Written out inline: with an axis held back it runs every sample."""
        hand_over, hand_back, decisions = self._hand_over, self._hand_back, self._decisions
        for axis in self._scores.axes:
            if decisions - axis.switched_at < self._min_dwell:
                continue
            state, model_ms = axis.state, axis.model_ms
            persistence_ms, prior_ms = axis.persistence_ms, axis.prior_ms
            # of a paired model's two priors the better live answers, switched freely
            axis.on_map = axis.map_ms < prior_ms
            if axis.on_map:
                prior_ms = axis.map_ms
            # the fallback that answers when the model does not: the prior once it beats
            # persistence by the margin, until it is worse
            if state is GuardState.PRIOR:
                prior_worse = prior_ms > persistence_ms + NEGLIGIBLE_MS
            else:
                prior_worse = not prior_ms < hand_back * persistence_ms - NEGLIGIBLE_MS
            fallback = GuardState.PERSISTENCE if prior_worse else GuardState.PRIOR
            best_ms = persistence_ms if persistence_ms < prior_ms else prior_ms
            reason: GuardReason | None
            if outside:
                wanted, reason = fallback, GuardReason.OUTSIDE_ENVELOPE
            elif state is GuardState.MODEL:
                if model_ms <= hand_over * best_ms + NEGLIGIBLE_MS:
                    continue  # in control and no worse than the better fallback
                wanted, reason = fallback, WORSE_THAN[fallback]
            elif model_ms < hand_back * best_ms - NEGLIGIBLE_MS:
                wanted, reason = GuardState.MODEL, None
            else:
                # held back, still not better by the margin: unproven until shown worse
                reason = (GuardReason.UNPROVEN if axis.reason is GuardReason.UNPROVEN
                          and model_ms <= hand_over * best_ms + NEGLIGIBLE_MS
                          else WORSE_THAN[fallback])
                if fallback is state and reason is axis.reason:
                    continue
                wanted = fallback
            if wanted is state:
                axis.reason = reason
                continue
            if state is GuardState.MODEL:
                axis.hand_overs += 1
            elif wanted is GuardState.MODEL:
                axis.hand_backs += 1
            axis.state, axis.reason, axis.switched_at = wanted, reason, decisions
            axis_x, axis_y = self._scores.axes
            self._holding = (axis_x.state is not GuardState.MODEL
                             or axis_y.state is not GuardState.MODEL)

    def restart(self, *, inherit: bool = False) -> None:
        """A new model: its live scores start from nothing, unproven on persistence until
        it earns control (the envelope is read from the new model's metadata). With
        `inherit` (a model shown better than the one in force on this machine's own recent
        samples: an online adaptation's) each axis keeps whose prediction it publishes and
        why, the new model in control where the old one was, until the rules say otherwise."""
        self.clear()
        self._scores.restart(self._decisions, inherit=inherit)
        self._holding = any(axis.state is not GuardState.MODEL for axis in self._scores.axes)
        self.envelope.restart()

    # -- state for diagnostics ------------------------------------------------------------

    @property
    def holding(self) -> bool:
        """Whether the model is held back on an axis (or would be, with the guard off)."""
        return self._holding

    @property
    def answering(self) -> tuple[GuardState, GuardState]:
        """Per axis (X, Y), whose prediction is published now (the model's, always, with
        the guard off)."""
        if not self._settings.enabled:
            return GuardState.MODEL, GuardState.MODEL
        axis_x, axis_y = self._scores.axes
        return axis_x.state, axis_y.state

    @property
    def scored(self) -> int:
        """Instants where the predictions met their truth, since the model's start."""
        return self._scores.scored

    def status(self) -> tuple[AxisStatus, AxisStatus]:
        """Per axis (X, Y): state, reason, live RMS of the three, switches."""
        axis_x, axis_y = self._scores.axes
        scored = self._scores.scored > 0
        return axis_x.status(scored), axis_y.status(scored)


def _answer(state: GuardState, model: float, persistence: float, prior: float) -> float:
    """One axis's published prediction in `state`; persistence's where the prior is wanted
    but missing at this instant (NaN)."""
    if state is GuardState.MODEL:
        return model
    if state is GuardState.PRIOR and prior == prior:
        return prior
    return persistence
