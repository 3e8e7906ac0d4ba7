# SPDX-License-Identifier: Apache-2.0
"""The live guard: the model compensates only while it does better than its fallbacks.

A learned model can be wrong on a program or a machine it was not trained on, and then its
offset makes the error worse than the simplest compensator, persistence (the offset for an
instant is minus the plant error measured `horizon` samples before it). A model with a
machine map has a second fallback, its prior (`learning.map_prior`: what it predicts from
the machine alone, its second network's prediction for a paired model, else persistence plus
the change the map predicts over the horizon), which transfers between programs where the
network that reads the path does not; a paired model's map prior (persistence plus the
change the map predicts) comes beside its generalist as a second prior, and the better of
the two live is the prior that answers. The guard scores them on the
same instants as their truth arrives (the contract's plant error, which holds under
compensation), per axis, and chooses, per axis, whose prediction is published:

- each aligned sample's plant error e(t) is the truth of the predictions made for t: the
  model's and its prior's (made `horizon` samples earlier, kept by instant whether
  published or not) and persistence's (e(t - horizon)); the squared residuals enter
  exponentially weighted means over about `window` seconds of sample time (long enough to
  span what a program repeats: a model better on the straights and worse at the corners is
  judged on both, not handed back and forth between them);
- a model earns control: each axis starts on persistence (`unproven`: nothing is known of
  the model on this machine and program yet, and a model is most often wrong where it was
  not trained, which the first instants cannot show), and the model takes it when its live
  RMS is below the better fallback's by `margin` (relative); it is handed over as soon as
  its live RMS exceeds the better fallback's (a model no better than what it builds on has
  no business compensating), and handed back when below by the margin again: the gap
  between the two thresholds is the hysteresis; no switch within `min_dwell` seconds of the
  last one (or of the start), and none before `min_scored` instants were scored. Between
  the two fallbacks the prior is preferred once it is better than persistence by the
  margin and kept until it is worse;
- a sample whose feature row lies outside the model's trained envelope (`envelope.py`) is
  counted; while more than `envelope_fraction` of the recent rows lie outside it, both axes
  are held back whatever the live scores (the network is extrapolating; the map's few
  coefficients of the machine's structure extrapolate sanely, and the live scores still
  choose between prior and persistence);
- persistence's and the prior's predictions come with the model's (the plant error of the
  sample the window ends at; the prior from the same call as the network), so holding back
  costs nothing but the choice. A model without a map has no prior: the guard chooses
  between the model and persistence.

The guard is a unit of the predictor core's chain (`sample_units`): it sees every aligned
sample's plant error and every prediction before the offset gate. ROS-free, on Python
floats: a few dozen operations per sample. A model file without an envelope is guarded by
the live comparison alone. With the guard off (`enabled` False) the scores and states go on,
so diagnostics show what it would do.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import StrEnum

from lompr_predictor.learning.envelope import InputEnvelope
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.inference import NO_PRIOR
from lompr_predictor.online.model_slot import ModelSlot
from lompr_predictor.online.offset import XY
from lompr_predictor.stamps import period_ns

AXES = ('x', 'y')
#: Mean squares closer than this [m^2] are taken as equal: (1 nm)^2, far below what any
#: encoder resolves, so that rounding never decides between two predictions.
NEGLIGIBLE_MS = 1e-18


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


class _Axis:
    """The live scores and state of one axis; the guard updates and decides on them
    (`LiveGuard.observe`, `LiveGuard.choose`) inline, a method call per axis and sample
    being most of its cost."""

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


class LiveGuard:
    """Chooses per axis between the model's prediction, its prior's and persistence's
    (module docstring), on a grid of instants `period_ns` apart, predictions `lead_ns`
    ahead: a `sample_units.SampleUnit` of the predictor core. It runs at the sample rate:
    the rules are read once per change of the settings, the scores and the common decision
    (both axes kept, the model in control and no worse) are written out inline."""

    def __init__(self, settings: GuardSettings, lead_ns: int, period_ns: int) -> None:
        self._period_ns = period_ns
        self.settings = settings  # also sets the weight and thresholds, in instants
        self._lead_ns = lead_ns
        self._tolerance_ns = period_ns // 2
        #: (instant, model x, y, persistence x, y, prior x, y, map prior x, y (NaN: none))
        #: awaiting their truth, in increasing instants (a sample's truth arrives in stamp
        #: order)
        self._pending: deque[tuple[int, float, float, float, float, float, float, float,
                                   float]] = deque()
        self._decisions = 0  # predictions chosen: an axis's dwell counts them
        self._axes = (_Axis(0), _Axis(0))
        self._holding = True  # an axis is in a fallback's hands
        self._outside = 0.0  # weighted fraction of recent rows outside the envelope
        self._last: tuple[int, XY] | None = None  # the newest sample's stamp and plant error
        self._enveloped: object = None  # the metadata whose envelope `_envelope` is
        self._envelope: InputEnvelope | None = None  # None: the model file has none
        self.scored = 0  # instants where both predictions met their truth
        self.outside_rows = 0  # rows outside the envelope, in all
        self.last_outside = ''  # the column that left the envelope last
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
        self._weight = min(1.0, period / settings.window)
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
        stamp_ns = sample.stamp_ns
        self._last = (stamp_ns, error)
        pending, tolerance = self._pending, self._tolerance_ns
        while pending and pending[0][0] < stamp_ns - tolerance:
            pending.popleft()  # an instant whose truth never came (a dropped sample)
        if not pending or pending[0][0] > stamp_ns + tolerance:
            return
        (_, model_x, model_y, persistence_x, persistence_y, prior_x, prior_y, map_x,
         map_y) = pending.popleft()
        scored = self.scored = self.scored + 1
        weight = 1.0 / scored  # a plain mean at first
        if weight < self._weight:
            weight = self._weight
        error_x, error_y = error
        axis_x, axis_y = self._axes
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
            residual = error_x - prior_x
            if axis_x.prior_ms == UNSCORED:
                axis_x.prior_ms = residual * residual
            else:
                axis_x.prior_ms += weight * (residual * residual - axis_x.prior_ms)
            residual = error_y - prior_y
            if axis_y.prior_ms == UNSCORED:
                axis_y.prior_ms = residual * residual
            else:
                axis_y.prior_ms += weight * (residual * residual - axis_y.prior_ms)
        if map_x == map_x:  # not NaN: a paired model's map prior
            residual = error_x - map_x
            if axis_x.map_ms == UNSCORED:
                axis_x.map_ms = residual * residual
            else:
                axis_x.map_ms += weight * (residual * residual - axis_x.map_ms)
            residual = error_y - map_y
            if axis_y.map_ms == UNSCORED:
                axis_y.map_ms = residual * residual
            else:
                axis_y.map_ms += weight * (residual * residual - axis_y.map_ms)

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        """The prediction to publish for `instant_ns`: the model's, or on an axis held back
        its prior's (the slot's, from the same call) or persistence's (the plant error of
        the sample the window ends at)."""
        last, tolerance = self._last, self._tolerance_ns
        if last is None or not -tolerance <= last[0] + self._lead_ns - instant_ns <= tolerance:
            return prediction  # no sample `lead_ns` before: nothing to compare with
        metadata = slot.model.metadata
        if metadata is not self._enveloped:  # a model swapped in: its own envelope
            self._enveloped = metadata
            self._envelope = InputEnvelope.from_metadata(metadata.envelope, metadata.features)
        envelope, inside = self._envelope, True
        if envelope is not None:
            row = slot.window.newest  # the older rows were checked as they arrived
            inside = envelope.contains(row)
            if not inside:
                self.last_outside = envelope.first_outside(row) or ''
        return self.choose(instant_ns, prediction, last[1], inside, slot.prior, slot.map_prior)

    def clear(self) -> None:
        """Forget the predictions awaiting their truth (the window was emptied: a fault, a
        restart); the live scores and states are kept, being the machine's."""
        self._pending.clear()
        self._last = None

    # -- the decision ---------------------------------------------------------------------

    def choose(self, instant_ns: int, model: XY, last_error: XY, inside_envelope: bool,
               prior: XY | None = None, map_prior: XY | None = None) -> XY:
        """The prediction to publish for `instant_ns` given the model's, persistence's (the
        plant error `lead_ns` before), whether the model's newest row lies inside its
        trained envelope, the model's prior and a paired model's map prior (None: none);
        all are kept to be scored when the truth arrives."""
        pending = self._pending
        while pending and pending[-1][0] >= instant_ns - self._tolerance_ns:
            pending.pop()  # a newer prediction for the same instant replaces the older
        model_x, model_y = model
        last_x, last_y = last_error
        prior_x, prior_y = NO_PRIOR if prior is None else prior
        map_x, map_y = NO_PRIOR if map_prior is None else map_prior
        pending.append((instant_ns, model_x, model_y, last_x, last_y, prior_x, prior_y, map_x,
                        map_y))
        if not inside_envelope:
            self.outside_rows += 1
        self._outside += self._weight * ((0.0 if inside_envelope else 1.0) - self._outside)
        self._decisions += 1
        outside = self._outside > self._envelope_fraction
        if outside or self.scored >= self._min_scored:
            axis_x, axis_y = self._axes
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
        axis_x, axis_y = self._axes
        return (_answer(axis_x.state, model_x, last_x, map_x if axis_x.on_map else prior_x),
                _answer(axis_y.state, model_y, last_y, map_y if axis_y.on_map else prior_y))

    def _decide(self, outside: bool) -> None:
        """Switch the axes the rules say to switch (module docstring), none within
        `min_dwell` instants of its last switch; `outside`: too many recent rows outside the
        envelope. Written out inline: with an axis held back it runs every sample."""
        hand_over, hand_back, decisions = self._hand_over, self._hand_back, self._decisions
        for axis in self._axes:
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
            axis_x, axis_y = self._axes
            self._holding = (axis_x.state is not GuardState.MODEL
                             or axis_y.state is not GuardState.MODEL)

    def restart(self, *, inherit: bool = False) -> None:
        """A new model: its live scores start from nothing, unproven on persistence until
        it earns control (the envelope is read from the new model's metadata). With
        `inherit` (a model shown better than the one in force on this machine's own recent
        samples: an online adaptation's) each axis keeps whose prediction it publishes and
        why, the new model in control where the old one was, until the rules say otherwise."""
        self.clear()
        old = self._axes
        self._axes = (_Axis(self._decisions), _Axis(self._decisions))
        if inherit:
            for axis, before in zip(self._axes, old, strict=True):
                axis.state, axis.reason, axis.on_map = before.state, before.reason, before.on_map
        self._holding = any(axis.state is not GuardState.MODEL for axis in self._axes)
        self._outside = 0.0
        self._enveloped = self._envelope = None
        self.scored = 0

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
        return self._axes[0].state, self._axes[1].state

    @property
    def outside_fraction(self) -> float:
        """The weighted fraction of recent rows outside the envelope."""
        return self._outside

    def status(self) -> tuple[AxisStatus, AxisStatus]:
        """Per axis (X, Y): state, reason, live RMS of the three, switches."""
        def one(axis: _Axis) -> AxisStatus:
            nan = float('nan')
            return AxisStatus(state=axis.state, reason=axis.reason,
                              model_rms=axis.model_ms ** 0.5 if self.scored else nan,
                              persistence_rms=axis.persistence_ms ** 0.5 if self.scored else nan,
                              prior_rms=nan if axis.prior_ms == UNSCORED else axis.prior_ms ** 0.5,
                              map_prior_rms=(nan if axis.map_ms == UNSCORED
                                             else axis.map_ms ** 0.5),
                              hand_overs=axis.hand_overs, hand_backs=axis.hand_backs)
        return one(self._axes[0]), one(self._axes[1])


def _answer(state: GuardState, model: float, persistence: float, prior: float) -> float:
    """One axis's published prediction in `state`; persistence's where the prior is wanted
    but missing at this instant (NaN)."""
    if state is GuardState.MODEL:
        return model
    if state is GuardState.PRIOR and prior == prior:
        return prior
    return persistence
