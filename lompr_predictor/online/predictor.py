"""Online error prediction and a bounded compensation offset, sample by sample (ROS-free).

`OnlinePredictor` is the predictor node's core; the node only turns messages into calls:

- `add_reference(stamp, x, y)` and `add_pose(stamp, x, y)` take the two input streams in
  arrival order. A pose is aligned with the reference by time: it waits until a reference at
  or after its stamp has arrived and gets the reference linearly interpolated to its stamp
  (CONTRACT section 2), never the reference that happened to arrive with it.
- The plant error of a sample is measured tool tip - reference - the compensation this
  predictor published for that instant (CONTRACT section 3), zero where it published none.
- The last `window + features.HISTORY` samples go through `features.feature_rows`, so the
  rows (and therefore the predictions) equal the offline ones of `dataset.py` for the same
  samples; once the window is full every new sample gives one `Output`: the predicted
  plant error for the instant `horizon` sample periods after it, and the offset for that
  instant.

Safety: the offset is minus the prediction, clamped to `max_compensation` (XY norm) and to
`max_step` change per sample (XY norm of the change), so it never jumps, also when it starts
or resumes. A fault (a non-finite sample, a stamp going backwards, a gap or an interval far
from the model's sample period, a pose the reference does not bracket, an inference that
fails or returns a non-finite value, input gone stale) empties the window; if an offset was
in force it is cancelled once: a zero `Output` (`reason` says why) for every instant after
the newest pose for which an offset was already published, or for the next instant if there
is none. A controller applies each offset at its instant, the newest message for an instant
winning, and nothing where it has none, so no offset computed before the fault is applied
after it; the plant error is computed with the same rule. Output resumes once the window has
refilled with good samples. Duplicated stamps are dropped without a fault. Disabling
compensation (shadow mode) cancels the offsets published for future instants the same way;
predictions go on and every offset is zero.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from lompr_predictor.data.features import FEATURES, HISTORY, feature_rows
from lompr_predictor.learning.model_file import LoadedModel
from lompr_predictor.monitoring import LatencyRecorder, RejectionCounter
from lompr_predictor.stamps import period_ns, seconds_since

#: Why an input sample was not used; each is counted (`OnlinePredictor.dropped`).
DROP_REASONS: tuple[str, ...] = (
    'non_finite', 'duplicate', 'out_of_order', 'no_reference', 'reference_duplicate',
    'reference_non_finite', 'reference_out_of_order', 'stale', 'internal')
#: Why the window was emptied (and an offset in force cancelled by a zero).
FAULT_REASONS: tuple[str, ...] = (
    'non_finite', 'out_of_order', 'gap', 'off_rate', 'no_reference', 'reference_non_finite',
    'reference_out_of_order', 'inference', 'stale', 'internal')
#: Poses kept waiting for a reference at or after their stamp; beyond, the oldest is dropped.
MAX_PENDING_POSES = 1000
#: References kept before the oldest pose that may still need one.
REFERENCE_MARGIN = 4
#: References kept at most (while no pose comes to use them, the oldest go).
MAX_REFERENCES = 10_000
#: Reference steps whose median is the reference's own period.
REFERENCE_STEPS = 15


@dataclass(frozen=True)
class StreamSettings:
    """How the input stream must look for the model (SI units)."""

    sample_period: float  # [s] the model's; also the spacing the stamps must have
    gap_factor: float  # an interval above gap_factor * sample_period is a gap
    min_interval_factor: float  # one below min_interval_factor * sample_period is off-rate
    stale_periods: float  # no sample for this many periods (wall time): input is stale
    accuracy_samples: int  # residuals the live RMS is over
    # ... and for at least this long [s]: a process on a general-purpose OS can stall for
    # milliseconds (scheduler, garbage collector), which at kHz rates is many periods
    stale_min_time: float = 0.0

    @property
    def stale_after(self) -> float:
        """Wall seconds without a usable sample after which the input is stale."""
        return max(self.stale_periods * self.sample_period, self.stale_min_time)


@dataclass(frozen=True)
class CompensationLimits:
    """Bounds of the published offset [m]."""

    max_compensation: float  # XY norm of the offset
    max_step: float  # XY norm of its change from one sample to the next
    enabled: bool  # False: shadow mode, predictions go on, every offset is zero


class Output(NamedTuple):
    """What to publish for one instant."""

    instant_ns: int  # the instant both values are for [ns]
    prediction: np.ndarray | None  # (2,) predicted plant X/Y error [m]; None for a zero
    compensation: np.ndarray  # (2,) X/Y offset [m]
    reason: str  # '' for a prediction, else the fault (or 'compensation_disabled') that
    # cancelled the offset
    sample_stamp_ns: int  # stamp of the newest sample the output was made from [ns]


class InstantSchedule:
    """Values by the instant they are for, in increasing instants; found within a tolerance.

    `take(stamp)` returns the value for the instant nearest `stamp` (within the tolerance)
    and forgets every earlier one; stamps asked for must increase, as the poses do.
    """

    def __init__(self, tolerance_ns: int, capacity: int = 100_000) -> None:
        self.tolerance_ns = tolerance_ns
        self._items: deque[tuple[int, np.ndarray]] = deque(maxlen=capacity)

    def add(self, instant_ns: int, value: np.ndarray) -> None:
        self.cancel_from(instant_ns)
        self._items.append((instant_ns, value))

    def instants_after(self, stamp_ns: int) -> list[int]:
        """Instants held that lie after `stamp_ns` (beyond the tolerance)."""
        return [instant for instant, _ in self._items if instant > stamp_ns + self.tolerance_ns]

    def cancel_from(self, instant_ns: int) -> None:
        """Forget values for instants from `instant_ns` on (a later message supersedes)."""
        items = self._items
        while items and items[-1][0] >= instant_ns - self.tolerance_ns:
            items.pop()

    def take(self, stamp_ns: int) -> np.ndarray | None:
        items = self._items
        while items and items[0][0] < stamp_ns - self.tolerance_ns:
            items.popleft()
        if items and items[0][0] <= stamp_ns + self.tolerance_ns:
            return items.popleft()[1]
        return None

    def clear(self) -> None:
        self._items.clear()


class ReferenceTrack:
    """The reference stream, linearly interpolated to pose stamps across short brackets.

    A bracket is short when it spans at most `gap_factor` periods of the poses or of the
    reference itself (its median step over the last `REFERENCE_STEPS`), whichever is
    longer: the reference may come slower than the poses (CONTRACT section 2).
    """

    def __init__(self, gap_factor: float, period_ns: int) -> None:
        self.gap_factor = gap_factor
        self.max_bracket_ns = gap_factor * period_ns
        self._pose_period_ns = period_ns
        self._stamps: deque[int] = deque(maxlen=MAX_REFERENCES)
        self._positions: deque[tuple[float, float]] = deque(maxlen=MAX_REFERENCES)
        self._steps: deque[int] = deque(maxlen=REFERENCE_STEPS)

    @property
    def newest(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def add(self, stamp_ns: int, x: float, y: float) -> str:
        """Keep one reference; '' or the reason it was not kept."""
        if not (math.isfinite(x) and math.isfinite(y)):
            return 'reference_non_finite'
        newest = self.newest
        if newest is not None and stamp_ns <= newest:
            return 'reference_duplicate' if stamp_ns == newest else 'reference_out_of_order'
        if newest is not None:
            self._steps.append(stamp_ns - newest)
            typical = sorted(self._steps)[len(self._steps) // 2]
            self.max_bracket_ns = self.gap_factor * max(self._pose_period_ns, typical)
        self._stamps.append(stamp_ns)
        self._positions.append((x, y))
        return ''

    def restart(self, stamp_ns: int, x: float, y: float) -> None:
        """Forget the history and start again from one reference (the stream went back)."""
        self.clear()
        self._stamps.append(stamp_ns)
        self._positions.append((x, y))

    def clear(self) -> None:
        self._stamps.clear()
        self._positions.clear()

    def at(self, stamp_ns: int) -> tuple[float, float] | str | None:
        """The reference at `stamp_ns`; None while no reference at or after it has arrived;
        'no_reference' when the history does not bracket it within `max_bracket_ns`."""
        stamps, positions = self._stamps, self._positions
        if not stamps or stamp_ns > stamps[-1]:
            return None
        while len(stamps) > REFERENCE_MARGIN and stamps[1] <= stamp_ns:
            stamps.popleft()
            positions.popleft()
        if stamp_ns < stamps[0]:
            return 'no_reference'
        right = 0
        while stamps[right] < stamp_ns:
            right += 1
        if stamps[right] == stamp_ns:
            return positions[right]
        left = right - 1
        span = stamps[right] - stamps[left]
        if span > self.max_bracket_ns:
            return 'no_reference'
        weight = (stamp_ns - stamps[left]) / span
        (x0, y0), (x1, y1) = positions[left], positions[right]
        return x0 + weight * (x1 - x0), y0 + weight * (y1 - y0)


class _Pose(NamedTuple):
    stamp_ns: int
    x: float
    y: float
    arrival: float  # clock() when it arrived


class OnlinePredictor:
    """Rolling window, model and safety logic of the predictor node (module docstring).

    `clock` gives wall seconds (monotonic); it times staleness.
    Every call returns the outputs to publish, in order.
    """

    def __init__(
        self, model: LoadedModel, stream: StreamSettings, limits: CompensationLimits,
        clock: Callable[[], float] = time.monotonic, latency_samples: int = 1000,
    ) -> None:
        if tuple(model.metadata.features) != FEATURES:
            msg = f'model features {model.metadata.features} are not {FEATURES}'
            raise ValueError(msg)
        self.model = model
        self.stream = stream
        self.limits = limits
        self._clock = clock
        self.window = model.metadata.window
        self.horizon = model.metadata.horizon
        self._period_ns = period_ns(stream.sample_period)
        self._lead_ns = self.horizon * self._period_ns
        half_period = self._period_ns // 2
        self._references = ReferenceTrack(stream.gap_factor, self._period_ns)
        self._compensations = InstantSchedule(half_period)
        self._predictions = InstantSchedule(half_period)
        # The last HISTORY + 1 samples give the newest feature row; the window's rows are
        # kept, so each sample costs one row, not a whole window, of `feature_rows`.
        self._recent: deque[tuple[int, float, float, float, float]] = deque(maxlen=HISTORY + 1)
        self._rows = np.zeros((self.window, len(FEATURES)))
        self._filled = 0  # samples since the window was last emptied
        self._pending: deque[_Pose | str] = deque()
        self._newest_pose_ns: int | None = None
        self._last_sample_arrival = clock()
        self._stale_suspected = False
        self._offset = np.zeros(2)
        self._offset_in_force = False
        self._residuals: deque[np.ndarray] = deque(maxlen=stream.accuracy_samples)
        self.dropped = RejectionCounter(DROP_REASONS)
        self.faults = RejectionCounter(FAULT_REASONS)
        self.last_fault = ''
        self.inference_time = LatencyRecorder(latency_samples)
        self.predictions_made = 0
        self.zeros_published = 0
        self.clamped = 0
        self.step_limited = 0

    # -- inputs ---------------------------------------------------------------------------

    def add_reference(self, stamp_ns: int, x: float, y: float) -> list[Output]:
        """Take one reference sample; returns outputs of poses that waited for it."""
        reason = self._references.add(stamp_ns, x, y)
        if reason == 'reference_out_of_order':
            self.dropped.add(reason)
            outputs = self._fault(reason)
            self._references.restart(stamp_ns, x, y)
            return outputs
        if reason:
            self.dropped.add(reason)
            return self._fault(reason) if reason == 'reference_non_finite' else []
        return self._drain()

    def add_pose(self, stamp_ns: int, x: float, y: float) -> list[Output]:
        """Take one measured tool-tip sample (the kinematics node's end pose)."""
        if not (math.isfinite(x) and math.isfinite(y)):
            self.dropped.add('non_finite')
            self._pending.append('non_finite')
            return self._drain()
        newest = self._newest_pose_ns
        if newest is not None and stamp_ns == newest:
            self.dropped.add('duplicate')
            return []
        if newest is not None and stamp_ns < newest:
            self.dropped.add('out_of_order')
            self._newest_pose_ns = stamp_ns
            self._clear_pending('out_of_order')
            return self._fault('out_of_order')
        self._newest_pose_ns = stamp_ns
        self._pending.append(_Pose(stamp_ns, x, y, self._clock()))
        outputs: list[Output] = []
        if len(self._pending) > MAX_PENDING_POSES:
            self._pending.popleft()
            self.dropped.add('no_reference')
            outputs += self._fault('no_reference')
        return outputs + self._drain()

    def check_stale(self) -> list[Output]:
        """Call periodically: a fault when two calls in a row find that no sample was used
        for `StreamSettings.stale_after` (a pose waiting that long for its reference counts as
        none). One such call alone proves nothing: an executor that was busy runs its timer
        before the samples that queued meanwhile."""
        waiting = [p.arrival for p in self._pending if isinstance(p, _Pose)]
        since = max([self._last_sample_arrival, *waiting[:1]])
        idle = self._clock() - since >= self.stream.stale_after
        confirmed, self._stale_suspected = self._stale_suspected and idle, idle
        if not confirmed or not (self._filled or self._pending or self._offset_in_force):
            return []
        self._clear_pending('stale')
        return self._fault('stale')

    def abort(self, reason: str = 'internal') -> list[Output]:
        """Empty the window and cancel the offset after a failure outside this class (an
        exception in the caller's own handling)."""
        self._clear_pending(reason)
        return self._fault(reason)

    def set_limits(self, limits: CompensationLimits) -> list[Output]:
        """New bounds from the next sample on. Disabling compensation also cancels the
        offsets already published (reason 'compensation_disabled'); the window is kept and
        predictions go on (shadow mode)."""
        disabled = self.limits.enabled and not limits.enabled
        self.limits = limits
        return self._cancel('compensation_disabled') if disabled else []

    def replace_model(self, model: LoadedModel) -> None:
        """Use `model` from the next sample on; it must read the same window and horizon."""
        metadata = model.metadata
        if (metadata.window, metadata.horizon) != (self.window, self.horizon):
            msg = (f'model {model.path} has window {metadata.window} and horizon '
                   f'{metadata.horizon}; the running one {self.window} and {self.horizon}')
            raise ValueError(msg)
        self.model = model

    # -- state for diagnostics ------------------------------------------------------------

    @property
    def window_fill(self) -> int:
        """Samples in the window (a prediction needs `window + HISTORY`)."""
        return min(self._filled, self.window_needed)

    @property
    def window_needed(self) -> int:
        return self.window + HISTORY

    @property
    def offset_in_force(self) -> np.ndarray:
        """The last offset published (zero after a fault or in shadow mode)."""
        return self._offset.copy()

    def accuracy(self) -> tuple[np.ndarray, int]:
        """(2,) RMS [m] of truth - prediction over the last predicted instants whose truth
        arrived, and how many; NaN before the first."""
        if not self._residuals:
            return np.full(2, np.nan), 0
        residuals = np.asarray(self._residuals)
        return np.sqrt(np.mean(residuals ** 2, axis=0)), len(residuals)

    # -- internals ------------------------------------------------------------------------

    def _clear_pending(self, reason: str) -> None:
        """Drop the poses waiting for a reference, counted under `reason`."""
        self.dropped.add(reason, sum(isinstance(p, _Pose) for p in self._pending))
        self._pending.clear()

    def _drain(self) -> list[Output]:
        outputs: list[Output] = []
        pending = self._pending
        while pending:
            head = pending[0]
            if isinstance(head, str):
                pending.popleft()
                outputs += self._fault(head)
                continue
            reference = self._references.at(head.stamp_ns)
            if reference is None:
                break
            pending.popleft()
            if isinstance(reference, str):
                self.dropped.add(reference)
                outputs += self._fault(reference)
                continue
            outputs += self._use_sample(head, reference)
        return outputs

    def _use_sample(self, pose: _Pose, reference: tuple[float, float]) -> list[Output]:
        outputs: list[Output] = []
        if self._recent:
            interval = pose.stamp_ns - self._recent[-1][0]
            if interval > self.stream.gap_factor * self._period_ns:
                outputs += self._fault('gap')
            elif interval < self.stream.min_interval_factor * self._period_ns:
                outputs += self._fault('off_rate')
        self._last_sample_arrival = self._clock()
        applied = self._compensations.take(pose.stamp_ns)
        offset = applied if applied is not None else (0.0, 0.0)
        error_x = pose.x - reference[0] - offset[0]
        error_y = pose.y - reference[1] - offset[1]
        predicted = self._predictions.take(pose.stamp_ns)
        if predicted is not None:
            self._residuals.append(np.array([error_x, error_y]) - predicted)
        self._recent.append((pose.stamp_ns, error_x, error_y, reference[0], reference[1]))
        self._filled += 1
        if self._filled > HISTORY:
            recent = np.array([row[1:] for row in self._recent])
            stamps = seconds_since(np.array([row[0] for row in self._recent]))
            self._rows[:-1] = self._rows[1:]
            self._rows[-1] = feature_rows(stamps, recent[:, 0:2], recent[:, 2:4])[-1]
        if self._filled >= self.window_needed:
            outputs += self._predict(pose.stamp_ns)
        return outputs

    def window_rows(self) -> np.ndarray:
        """(window, len(FEATURES)) feature rows of the current window (the model's input)."""
        if self._filled < self.window_needed:
            msg = f'the window holds {self.window_fill} of {self.window_needed} samples'
            raise ValueError(msg)
        return self._rows.copy()

    def _predict(self, stamp_ns: int) -> list[Output]:
        try:
            window = torch.from_numpy(self.window_rows()[None])
            with self.inference_time.measure():
                prediction = self.model.predict(window).numpy().reshape(-1)
        except Exception:  # noqa: BLE001 - any model failure is the 'inference' fault
            return self._fault('inference')
        if prediction.shape != (2,) or not np.isfinite(prediction).all():
            return self._fault('inference')
        instant = stamp_ns + self._lead_ns
        compensation = self._bounded(-prediction)
        self._predictions.add(instant, prediction)
        self._compensations.add(instant, compensation)
        self._offset = compensation
        self._offset_in_force = True
        self.predictions_made += 1
        return [Output(instant, prediction, compensation, '', stamp_ns)]

    def _bounded(self, wanted: np.ndarray) -> np.ndarray:
        limits = self.limits
        if not limits.enabled:
            return np.zeros(2)
        norm = math.hypot(wanted[0], wanted[1])
        if norm > limits.max_compensation:
            wanted = wanted * (limits.max_compensation / norm)
            self.clamped += 1
        change = wanted - self._offset
        step = math.hypot(change[0], change[1])
        if step > limits.max_step:
            wanted = self._offset + change * (limits.max_step / step)
            self.step_limited += 1
        return wanted

    def _fault(self, reason: str) -> list[Output]:
        """Empty the window; cancel the offsets in force (module docstring)."""
        self.faults.add(reason)
        self.last_fault = reason
        self._recent.clear()
        self._filled = 0
        return self._cancel(reason)

    def _cancel(self, reason: str) -> list[Output]:
        """Zero outputs for the instants after the newest pose that already have an offset,
        or for the next instant; none if no offset was published since the last cancel."""
        if not self._offset_in_force:
            return []
        newest = self._newest_pose_ns or 0
        instants = (self._compensations.instants_after(newest)
                    or [newest + self._period_ns])
        for instant in instants:
            self._compensations.add(instant, np.zeros(2))
        self._offset = np.zeros(2)
        self._offset_in_force = False
        self.zeros_published += len(instants)
        return [Output(instant, None, np.zeros(2), reason, newest) for instant in instants]
