"""The live guard: the model compensates only while it does better than persistence.

A learned model can be wrong on a program or a machine it was not trained on, and then its
offset makes the error worse than the simplest compensator, persistence (the offset for an
instant is minus the plant error measured `horizon` samples before it). The guard scores
both on the same instants as their truth arrives (the contract's plant error, which holds
under compensation), per axis, and chooses, per axis, whose prediction is published:

- each aligned sample's plant error e(t) is the truth of the predictions made for t: the
  model's (the prediction it made `horizon` samples earlier, kept by instant whether it was
  published or not) and persistence's (e(t - horizon)); where both exist, the squared
  residuals enter an exponentially weighted mean over about `window` seconds of sample
  time (long enough to span what a program repeats: a model better on the straights and
  worse at the corners is judged on both, not handed back and forth between them);
- an axis is handed over to persistence as soon as the model's live RMS exceeds
  persistence's (a model no better than the simplest compensator has no business
  compensating), and handed back when it is below persistence's by `margin` (relative):
  the gap between the two thresholds is the hysteresis; no switch within `min_dwell`
  seconds of the last one, and none before `min_scored` instants were scored;
- a sample whose feature row lies outside the model's trained envelope (`envelope.py`) is
  counted; while more than `envelope_fraction` of the recent rows lie outside it, both axes
  are held back whatever the live scores (the model is extrapolating);
- persistence's prediction is the plant error of the sample the model's window ends at,
  which the guard saw just before the prediction, so holding back costs nothing but the
  choice.

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
from typing import NamedTuple

from lompr_predictor.learning.envelope import InputEnvelope
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.model_slot import ModelSlot
from lompr_predictor.online.offset import XY
from lompr_predictor.stamps import period_ns

AXES = ('x', 'y')
#: Mean squares closer than this [m^2] are taken as equal: (1 nm)^2, far below what any
#: encoder resolves, so that rounding never decides between two predictions.
NEGLIGIBLE_MS = 1e-18


class GuardState(StrEnum):
    """Whose prediction an axis publishes."""

    MODEL = 'model'
    PERSISTENCE = 'persistence'


class GuardReason(StrEnum):
    """Why the guard holds the model back on an axis."""

    WORSE_THAN_PERSISTENCE = 'worse_than_persistence'  # its live RMS, by the margin
    OUTSIDE_ENVELOPE = 'outside_envelope'  # the inputs left what training saw


@dataclass(frozen=True, kw_only=True)
class GuardSettings:
    """The guard's rules (module docstring), each the predictor node's parameter `guard_`
    + its name (declared there once, with its default); `enabled` False publishes the model
    always (the scores and states go on)."""

    enabled: bool
    window: float  # seconds of sample time the live RMS is weighted over (time constant)
    margin: float  # relative: hand over above 1 x persistence, back below (1 - margin) x
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
    hand_overs: int  # switches model -> persistence
    hand_backs: int  # switches persistence -> model


class _Axis:
    """The live scores and state of one axis."""

    def __init__(self) -> None:
        self.model_ms = 0.0
        self.persistence_ms = 0.0
        self.state = GuardState.MODEL
        self.reason: GuardReason | None = None
        self.since_switch = 0
        self.hand_overs = 0
        self.hand_backs = 0

    def score(self, model_residual: float, persistence_residual: float, weight: float) -> None:
        self.model_ms += weight * (model_residual * model_residual - self.model_ms)
        self.persistence_ms += weight * (persistence_residual * persistence_residual
                                         - self.persistence_ms)

    def decide(self, rules: _Thresholds, ready: bool, outside: bool) -> None:
        """Switch if the rules say so (module docstring); `ready`: enough instants scored."""
        self.since_switch += 1
        if self.since_switch < rules.min_dwell:
            return
        if outside:
            wanted, reason = GuardState.PERSISTENCE, GuardReason.OUTSIDE_ENVELOPE
        elif not ready:
            return
        elif self.state is GuardState.MODEL:
            if self.model_ms <= rules.hand_over * self.persistence_ms + NEGLIGIBLE_MS:
                return
            wanted, reason = GuardState.PERSISTENCE, GuardReason.WORSE_THAN_PERSISTENCE
        elif self.model_ms < rules.hand_back * self.persistence_ms - NEGLIGIBLE_MS:
            wanted, reason = GuardState.MODEL, None
        else:
            wanted, reason = GuardState.PERSISTENCE, GuardReason.WORSE_THAN_PERSISTENCE
        if wanted is self.state:
            self.reason = reason
            return
        self.state, self.reason, self.since_switch = wanted, reason, 0
        if wanted is GuardState.PERSISTENCE:
            self.hand_overs += 1
        else:
            self.hand_backs += 1


class _Thresholds(NamedTuple):
    """The settings as `_Axis.decide` compares them, computed once: mean-square ratios."""

    hand_over: float  # above it, persistence takes over
    hand_back: float  # (1 - margin)^2: below it, the model takes back
    min_dwell: int  # instants

    @classmethod
    def of(cls, settings: GuardSettings, period: float) -> _Thresholds:
        """The thresholds of `settings` on a stream sampled every `period` [s]."""
        return cls(1.0, (1.0 - settings.margin) ** 2, round(settings.min_dwell / period))


class LiveGuard:
    """Chooses per axis between the model's prediction and persistence's (module
    docstring), on a grid of instants `period_ns` apart, predictions `lead_ns` ahead: a
    `sample_units.SampleUnit` of the predictor core."""

    def __init__(self, settings: GuardSettings, lead_ns: int, period_ns: int) -> None:
        self._period_ns = period_ns
        self.settings = settings  # also sets the weight and thresholds, in instants
        self._lead_ns = lead_ns
        self._tolerance_ns = period_ns // 2
        #: (instant, model x, model y, persistence x, persistence y) awaiting their truth, in
        #: increasing instants (a sample's truth arrives in stamp order)
        self._pending: deque[tuple[int, float, float, float, float]] = deque()
        self._axes = (_Axis(), _Axis())
        self._outside = 0.0  # weighted fraction of recent rows outside the envelope
        self._last: tuple[int, XY] | None = None  # the newest sample's stamp and plant error
        self._enveloped: object = None  # the metadata whose envelope `_envelope` is
        self._envelope: InputEnvelope | None = None  # None: the model file has none
        self.scored = 0  # instants where both predictions met their truth
        self.outside_rows = 0  # rows outside the envelope, in all
        self.last_outside = ''  # the column that left the envelope last
        self.published_persistence = 0  # predictions published with an axis held back

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
        self._thresholds = _Thresholds.of(settings, period)

    # -- the chain (`sample_units.SampleUnit`) ---------------------------------------------

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        """The plant error of a sample: the truth of the predictions made for its instant,
        scored where both exist, and persistence's prediction for `lead_ns` later."""
        del published  # the guard keeps the model's own predictions, published or not
        stamp_ns = sample.stamp_ns
        self._last = (stamp_ns, error)
        pending, tolerance = self._pending, self._tolerance_ns
        while pending and pending[0][0] < stamp_ns - tolerance:
            pending.popleft()  # an instant whose truth never came (a dropped sample)
        if not pending or pending[0][0] > stamp_ns + tolerance:
            return
        _, model_x, model_y, persistence_x, persistence_y = pending.popleft()
        weight = max(self._weight, 1.0 / (self.scored + 1))  # a plain mean at first
        self.scored += 1
        error_x, error_y = error
        axis_x, axis_y = self._axes
        axis_x.score(error_x - model_x, error_x - persistence_x, weight)
        axis_y.score(error_y - model_y, error_y - persistence_y, weight)

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        """The prediction to publish for `instant_ns`: the model's, or on an axis held back
        persistence's (the plant error of the sample the window ends at)."""
        last = self._last
        if last is None or abs(last[0] + self._lead_ns - instant_ns) > self._tolerance_ns:
            return prediction  # no sample `lead_ns` before: nothing to compare with
        metadata = slot.model.metadata
        if metadata is not self._enveloped:  # a model swapped in: its own envelope
            self._enveloped = metadata
            self._envelope = InputEnvelope.from_metadata(metadata.envelope, metadata.features)
        envelope = self._envelope
        inside = envelope is None or envelope.contains(slot.window.newest)
        if not inside and envelope is not None:
            self.last_outside = envelope.first_outside(slot.window.newest) or ''
        return self.choose(instant_ns, prediction, last[1], inside)

    def clear(self) -> None:
        """Forget the predictions awaiting their truth (the window was emptied: a fault, a
        restart); the live scores and states are kept, being the machine's."""
        self._pending.clear()
        self._last = None

    # -- the decision ---------------------------------------------------------------------

    def choose(self, instant_ns: int, model: XY, last_error: XY, inside_envelope: bool) -> XY:
        """The prediction to publish for `instant_ns` given the model's, persistence's (the
        plant error `lead_ns` before) and whether the model's newest row lies inside its
        trained envelope; both are kept to be scored when the truth arrives."""
        pending = self._pending
        while pending and pending[-1][0] >= instant_ns - self._tolerance_ns:
            pending.pop()  # a newer prediction for the same instant replaces the older
        pending.append((instant_ns, model[0], model[1], last_error[0], last_error[1]))
        if not inside_envelope:
            self.outside_rows += 1
        self._outside += self._weight * ((0.0 if inside_envelope else 1.0) - self._outside)
        settings = self._settings
        outside = self._outside > settings.envelope_fraction
        axis_x, axis_y = self._axes
        rules, ready = self._thresholds, self.scored >= settings.min_scored
        axis_x.decide(rules, ready, outside)
        axis_y.decide(rules, ready, outside)
        if not settings.enabled:
            return model
        use_x = axis_x.state is GuardState.MODEL
        use_y = axis_y.state is GuardState.MODEL
        if use_x and use_y:
            return model
        self.published_persistence += 1
        return (model[0] if use_x else last_error[0], model[1] if use_y else last_error[1])

    def restart(self) -> None:
        """A new model: its live scores start from nothing, in control until the rules say
        otherwise (the envelope is read from the new model's metadata)."""
        self.clear()
        self._axes = (_Axis(), _Axis())
        self._outside = 0.0
        self._enveloped = self._envelope = None
        self.scored = 0

    # -- state for diagnostics ------------------------------------------------------------

    @property
    def holding(self) -> bool:
        """Whether the model is held back on an axis (or would be, with the guard off)."""
        return any(axis.state is GuardState.PERSISTENCE for axis in self._axes)

    @property
    def held_back(self) -> tuple[bool, bool]:
        """Per axis (X, Y), whether persistence answers there now (never with the guard
        off)."""
        enabled = self._settings.enabled
        return (enabled and self._axes[0].state is GuardState.PERSISTENCE,
                enabled and self._axes[1].state is GuardState.PERSISTENCE)

    @property
    def outside_fraction(self) -> float:
        """The weighted fraction of recent rows outside the envelope."""
        return self._outside

    def status(self) -> tuple[AxisStatus, AxisStatus]:
        """Per axis (X, Y): state, reason, live RMS of both, switches."""
        def one(axis: _Axis) -> AxisStatus:
            nan = float('nan')
            return AxisStatus(state=axis.state, reason=axis.reason,
                              model_rms=axis.model_ms ** 0.5 if self.scored else nan,
                              persistence_rms=axis.persistence_ms ** 0.5 if self.scored else nan,
                              hand_overs=axis.hand_overs, hand_backs=axis.hand_backs)
        return one(self._axes[0]), one(self._axes[1])
