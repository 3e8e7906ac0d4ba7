"""Online error prediction and a bounded compensation offset, sample by sample (ROS-free).

`OnlinePredictor` is the predictor node's core: it composes the alignment by stamp
(`alignment`), the plant error (docs/interface.md, the error), the feature window (`window`), the
model, the offset gate (`offset`), the fault rules (`faults`) and the overrun policy
(`timing`), each testable alone, and for a model that reads the reference preview the plan
(`preview`) and, optionally, a fallback model without one that answers where the plan is
missing. Any fault empties the windows and cancels the offset in force. Time is the
caller's clock (the node's ROS clock, simulated under use_sim_time), whose jumps the caller
reports; every call returns the outputs to publish, in order. The network runs on the
backend `inference.select_backend` chose; `stage_timer` (off by default) lets a profiler
time the stages of an input call through a public hook.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from lompr_predictor.data.features import feature_names
from lompr_predictor.learning.model_file import LoadedModel, MetadataMismatchError
from lompr_predictor.monitoring import LatencyRecorder, RejectionCounter
from lompr_predictor.online.alignment import AlignedSample, DropReason, Event, StampAlignment
from lompr_predictor.online.faults import FaultReason, StaleWatch, StreamRules, StreamSettings
from lompr_predictor.online.inference import InferenceBackend, TorchScriptBackend
from lompr_predictor.online.offset import ZERO, CompensationLimits, LiveAccuracy, OffsetGate, Output
from lompr_predictor.online.preview import PlannedPath, PlanReader, PreviewDrop
from lompr_predictor.online.timing import OverrunGuard
from lompr_predictor.online.window import FeatureWindow
from lompr_predictor.robot.description import RobotDescription, load_robot_description
from lompr_predictor.stamps import NS_PER_SECOND, StampLike, period_ns, stamp_problem

# The names a caller of the core needs, importable from here as before the split.
__all__ = ['STAGES', 'CompensationLimits', 'DropReason', 'FaultReason', 'OnlinePredictor',
           'Output', 'StageTimer', 'StreamSettings']

#: The stages of an input call a `StageTimer` hears the end of, in the order they run:
#: checking and converting the stamp, aligning pose and reference, the plant error (the
#: offset and prediction published for the instant, live accuracy), the window's feature
#: row, the overrun policy, the network, the offset gate.
STAGES = ('stamp', 'alignment', 'plant error', 'feature rows', 'overrun', 'inference',
          'offset gate')


class StageTimer(Protocol):
    """Told where an input call is (`OnlinePredictor.stage_timer`), to time its stages."""

    def begin(self) -> None:
        """An input call (`add_pose`, `add_reference`) begins."""
        ...

    def end(self, stage: str) -> None:
        """The stage `stage` (one of `STAGES`) ended."""
        ...


class OnlinePredictor:
    """Alignment, window, model and offset gate of the predictor node (module docstring)."""

    def __init__(
        self, model: LoadedModel, stream: StreamSettings, limits: CompensationLimits,
        clock: Callable[[], float] = time.monotonic, latency_samples: int = 1000,
        now_ns: Callable[[], int] | None = None, description: RobotDescription | None = None,
        backend: InferenceBackend | None = None, fallback: LoadedModel | None = None,
        fallback_backend: InferenceBackend | None = None,
    ) -> None:
        #: The robot the model must have been trained for (default: the packaged LOMPR).
        self.description = description or load_robot_description()
        self._check(model)
        self.stream = stream
        self.window = model.metadata.window
        self.horizon = model.metadata.horizon
        period = period_ns(stream.sample_period)
        self._lead_ns = self.horizon * period
        self._clock = clock
        self._alignment = StampAlignment(stream.gap_factor, period, clock)
        self._rules = StreamRules(stream, period)
        self._stale = StaleWatch(stream.stale_after, clock)
        #: Samples of the planned reference the model reads after each row (0: none).
        self.preview = model.metadata.preview
        self._window = FeatureWindow(self.window, self.description.geometry, self.preview)
        self.plan = PlannedPath(stream.gap_factor * period, stream.preview_tolerance)
        self._reader = PlanReader(self.plan, self.preview * period, stream.stale_after)
        self._use(model, backend)
        #: The model without a preview that answers where the plan is missing (or None),
        #: with its own window of the same samples.
        self.fallback = fallback
        self.fallback_answers = 0
        if fallback is not None:
            self._check_fallback(fallback)
            self._fallback_window = FeatureWindow(fallback.metadata.window,
                                                  self.description.geometry)
            run_fallback = fallback_backend or TorchScriptBackend(fallback)
            self._fallback_runners = tuple(run_fallback.runner(array)
                                           for array in self._fallback_window.arrays)
        #: The offsets published and their bounds, with their counters (`offset.OffsetGate`;
        #: change the bounds with `set_limits`).
        self.gate = OffsetGate(limits, period)
        self._accuracy = LiveAccuracy(stream.accuracy_samples)
        self.faults = RejectionCounter(FaultReason)
        self.last_fault = ''
        self.inference_time = LatencyRecorder(latency_samples)
        self.predictions_made = 0
        self._now_ns = now_ns
        self._now = 0  # the node's clock at its latest reading [ns]
        self.overrun = OverrunGuard(self._lead_ns, period_ns(stream.late_tolerance))
        self._max_future_ns = (period_ns(stream.max_future_stamp)
                               if stream.max_future_stamp >= 0.0 else -1)
        self.last_bad_stamp = ''  # why the last stamp dropped was not a sample instant
        #: Told of each stage's end (`STAGES`); None: no profiling.
        self.stage_timer: StageTimer | None = None

    # -- inputs ---------------------------------------------------------------------------

    def add_reference(self, stamp: int | StampLike, x: float, y: float,
                      z: float) -> list[Output]:
        """Take one reference sample, the commanded tool tip (stamp: ns, or a message stamp,
        which is checked); returns outputs of poses that waited for it."""
        timer = self.stage_timer
        if timer is not None:
            timer.begin()
        now = self._read_clock()
        stamp_ns = self._stamp_ns(stamp, now, 'reference_')
        if stamp_ns is None:
            return []
        if timer is not None:
            timer.end('stamp')
        if self.preview and not self.plan.check(stamp_ns, x, y, z):
            self._window.plan_lost()
        events = self._alignment.add_reference(stamp_ns, x, y, z)
        if timer is not None:
            timer.end('alignment')
        return self._handle(events, self._clock()) if events else []

    def add_preview(self, stamps_ns: np.ndarray, positions: np.ndarray) -> PreviewDrop | None:
        """Take one reference preview: (n,) int64 instants [ns], (n, 3) planned tool tips
        [m]; the reason it was refused (counted in `plan.dropped`), or None."""
        return self.plan.add(stamps_ns, positions)

    def add_pose(self, stamp: int | StampLike, x: float, y: float) -> list[Output]:
        """Take one measured tool-tip sample (the kinematics node's end pose; stamp: ns,
        or a message stamp, which is checked)."""
        timer = self.stage_timer
        if timer is not None:
            timer.begin()
        now = self._read_clock()
        stamp_ns = self._stamp_ns(stamp, now, '')
        if stamp_ns is None:
            return []
        if self._now_ns is not None:
            self.overrun.arrival(stamp_ns, now)
        if timer is not None:
            timer.end('stamp')
        seconds = self._clock()
        events = self._alignment.add_pose(stamp_ns, x, y, seconds)
        if timer is not None:
            timer.end('alignment')
        return self._handle(events, seconds)

    def check_stale(self) -> list[Output]:
        """Call periodically: a 'stale' fault once `faults.StaleWatch` confirms that no
        sample was used for `StreamSettings.stale_after`, if anything is there to cancel."""
        alignment = self._alignment
        if not self._stale.check(alignment.oldest_waiting_arrival()):
            return []
        if self._window.empty and not alignment.waiting and not self.gate.in_force:
            return []
        alignment.clear(DropReason.STALE)
        return self._fault(FaultReason.STALE)

    def abort(self) -> list[Output]:
        """Empty the window and cancel the offset after a failure outside this class (an
        exception in the caller's own handling)."""
        self._alignment.clear(DropReason.INTERNAL)
        return self._fault(FaultReason.INTERNAL)

    def clock_jumped_back(self, now_ns: int | None) -> list[Output]:
        """The clock went back to `now_ns` (None: it changed source), as a simulator reset
        does: a 'clock_jump' fault (window emptied, the offset in force cancelled), and the
        inputs are taken as starting again from there (`StampAlignment.rewind`), so the
        restarted streams refill the window without further faults."""
        outputs = self._fault(FaultReason.CLOCK_JUMP)
        self._alignment.rewind(now_ns, DropReason.CLOCK_JUMP)
        self._stale.restart()
        self.overrun.restart()
        return outputs

    def restart_staleness(self) -> None:
        """The clock jumped forward (its first reading under simulated time, a simulator
        skipping ahead): idle time counts from now (a gap in the stamps is still a fault)."""
        self._stale.restart()

    def reset(self, reason: DropReason = DropReason.INACTIVE) -> list[Output]:
        """Stop and start afresh, no fault (the node deactivated): the offset in force is
        cancelled (zeros, `reason`), the window emptied, and the inputs forgotten, so that
        the next samples start a new window whatever their stamps."""
        outputs = self.gate.cancel(reason, self._alignment.newest_pose_ns)
        self._clear_windows()
        self._alignment.rewind(None, reason)
        self._stale.restart()
        self.overrun.restart()
        return outputs

    def set_limits(self, limits: CompensationLimits) -> list[Output]:
        """New bounds from the next sample on. Disabling compensation also cancels the
        offsets already published (reason 'compensation_disabled'); the window is kept and
        predictions go on (shadow mode)."""
        return self.gate.set_limits(limits, self._alignment.newest_pose_ns)

    def replace_model(self, model: LoadedModel,
                      backend: InferenceBackend | None = None) -> None:
        """Use `model` (run by `backend`, default TorchScript) from the next sample on; it
        must read the same window and horizon."""
        self._check(model)
        metadata = model.metadata
        if ((metadata.window, metadata.horizon, metadata.preview)
                != (self.window, self.horizon, self.preview)):
            msg = (f'model {model.path} has window {metadata.window}, horizon '
                   f'{metadata.horizon} and preview {metadata.preview}; the running one '
                   f'{self.window}, {self.horizon} and {self.preview}')
            raise ValueError(msg)
        self._use(model, backend)

    # -- state for diagnostics ------------------------------------------------------------

    @property
    def preview_stale(self) -> bool:
        """No plan for the stale time: a preview model cannot predict."""
        return self._reader.stale

    @property
    def dropped(self) -> RejectionCounter:
        """Input samples not used, by reason (`alignment.DropReason`)."""
        return self._alignment.dropped

    @property
    def window_fill(self) -> int:
        """Samples in the window (a prediction needs `window_needed`)."""
        return self._window.fill

    @property
    def window_needed(self) -> int:
        """Samples a full window takes: `window + features.HISTORY`."""
        return self._window.needed

    def accuracy(self) -> tuple[np.ndarray, int]:
        """(2,) RMS [m] of truth - prediction over the last predicted instants whose truth
        arrived, and how many; NaN before the first."""
        return self._accuracy.rms()

    def window_rows(self) -> np.ndarray:
        """(window, len(model features)) rows of the current window (the model's input)."""
        return self._window.rows()

    # -- internals ------------------------------------------------------------------------

    def _check(self, model: LoadedModel) -> None:
        """Refuse a model that reads other features or was trained for another robot."""
        for field, needed in (('features', feature_names(model.metadata.preview)),
                              ('robot_description_sha256', self.description.sha256)):
            found = getattr(model.metadata, field)
            if found != needed:
                raise MetadataMismatchError(model.path, field, needed, found)

    def _check_fallback(self, fallback: LoadedModel) -> None:
        """Refuse a fallback that reads a preview or predicts for another instant."""
        self._check(fallback)
        for field, needed in (('preview', 0), ('horizon', self.horizon)):
            found = getattr(fallback.metadata, field)
            if found != needed:
                raise MetadataMismatchError(fallback.path, field, needed, found)

    def _use(self, model: LoadedModel, backend: InferenceBackend | None) -> None:
        """Serve `model` with `backend` (default TorchScript), one call bound per view."""
        self.model = model
        self.backend = backend or TorchScriptBackend(model)
        self._runners = tuple(self.backend.runner(array) for array in self._window.arrays)

    def _read_clock(self) -> int:
        if self._now_ns is not None:
            self._now = self._now_ns()
        return self._now

    def _stamp_ns(self, stamp: int | StampLike, now: int, prefix: str) -> int | None:
        """A stamp in ns; None for a message stamp that is no sample instant (counted)."""
        if isinstance(stamp, (int, np.integer)):
            return int(stamp)
        sec, nanosec = stamp.sec, stamp.nanosec
        reason, why = stamp_problem(sec, nanosec, now if self._now_ns is not None else 0,
                                    self._max_future_ns)
        if reason:
            self._alignment.dropped.add(DropReason(prefix + reason))
            self.last_bad_stamp = f'{prefix or "pose_"}{reason}: {why}'
            return None
        return sec * NS_PER_SECOND + nanosec

    def _handle(self, events: list[Event], seconds: float) -> list[Output]:
        """The outputs of `events`, made in the input call that read `clock` at `seconds`."""
        outputs: list[Output] = []
        for event in events:
            if isinstance(event, FaultReason):
                outputs += self._fault(event)
            else:
                self._use_sample(event, seconds, outputs)
        return outputs

    def _use_sample(self, sample: AlignedSample, seconds: float, outputs: list[Output]) -> None:
        """Append the outputs of one aligned sample to `outputs`."""
        timer = self.stage_timer
        window = self._window
        stamp_ns = sample.stamp_ns
        previous = window.last_stamp_ns
        if previous is not None:
            reason = self._rules.interval_fault(previous, stamp_ns)
            if reason is not None:
                outputs += self._fault(reason)
        self._stale.used(seconds)
        gate = self.gate
        offset_x, offset_y = gate.offset_for(stamp_ns) or ZERO
        predicted = gate.prediction_for(stamp_ns)
        reference_x, reference_y = sample.reference_x, sample.reference_y
        error_x = sample.x - reference_x - offset_x
        error_y = sample.y - reference_y - offset_y
        if predicted is not None:
            self._accuracy.add(error_x, error_y, predicted)
        if timer is not None:
            timer.end('plant error')
        planned = None
        if self.preview:
            was_stale = self._reader.stale
            planned = self._reader.at_sample(stamp_ns, seconds)
            if self._reader.stale and not was_stale and self.fallback is None:
                outputs += gate.cancel(PreviewDrop.MISSING, self._alignment.newest_pose_ns)
        runner = None
        if window.push(stamp_ns, error_x, error_y, reference_x, reference_y,
                       sample.reference_z, planned):
            runner = self._runners[window.start]
        if self.fallback is not None:
            fallback = self._fallback_window
            if fallback.push(stamp_ns, error_x, error_y, reference_x, reference_y,
                             sample.reference_z) and runner is None:
                runner = self._fallback_runners[fallback.start]
                self.fallback_answers += 1
        if timer is not None:
            timer.end('feature rows')
        if runner is not None:
            self._predict(stamp_ns, outputs, runner)

    def _predict(self, stamp_ns: int, outputs: list[Output],
                 runner: Callable[[], Any]) -> None:
        """Append the output of the window that ends at `stamp_ns`, if it is not late."""
        timer = self.stage_timer
        guard = self.overrun if self._now_ns is not None else None
        if guard is not None and guard.skip(stamp_ns, self._now):
            guard.inference_skipped_late += 1
            self.gate.missed()
            return
        if timer is not None:
            timer.end('overrun')
        prediction = self._infer(runner)
        if timer is not None:
            timer.end('inference')
        if prediction is None:
            outputs += self._fault(FaultReason.INFERENCE)
            return
        self.predictions_made += 1
        if guard is not None:
            started = self._now
            ended = self._read_clock()
            guard.inference_took(started, ended)
            if guard.late(stamp_ns, ended):
                guard.late_outputs_dropped += 1
                self.gate.missed()
                return
        outputs.append(self.gate.publish(stamp_ns + self._lead_ns, prediction, stamp_ns))
        if timer is not None:
            timer.end('offset gate')

    def _infer(self, runner: Callable[[], Any]) -> tuple[float, float] | None:
        """The network on a window (`runner`, the call bound to its current view): the
        predicted X/Y plant error, or None if the model raised or gave anything but one row
        of two finite numbers."""
        start = time.perf_counter()
        try:
            x, y = runner()
            x, y = float(x), float(y)
        except Exception:  # noqa: BLE001 - a model file is code: any failure is a fault
            x = y = math.nan
        self.inference_time.record(time.perf_counter() - start)
        return (x, y) if math.isfinite(x) and math.isfinite(y) else None

    def _clear_windows(self) -> None:
        self._window.clear()
        if self.fallback is not None:
            self._fallback_window.clear()

    def _fault(self, reason: FaultReason) -> list[Output]:
        """Empty the window; cancel the offsets in force (`offset.OffsetGate.cancel`)."""
        self.faults.add(reason)
        self.last_fault = reason
        self._clear_windows()
        return self.gate.cancel(reason, self._alignment.newest_pose_ns)
