# SPDX-License-Identifier: Apache-2.0
"""Online error prediction and a bounded compensation offset, sample by sample (ROS-free).

`OnlinePredictor` is the predictor node's core. It composes parts that each do one job and
are tested alone: the stamps of its inputs (`input_stamps`), the alignment by stamp
(`alignment`), the fault rules (`faults`), a model slot per model (`model_slot`: the model,
its window of feature rows and its runner), the plan of a model that reads the reference
preview (`preview`), the chain of units that see every sample and prediction
(`sample_units`, the live accuracy first), the plant error they are shown (`plant_error`),
and the answer of an instant (`answers`: the units' revision, the overrun policy of
`timing`, the offset gate of `offset`). Per aligned sample it takes the plant error
(docs/interface.md, the error), pushes the rows of every slot's window, lets the first full
slot (the model's, else the fallback's) predict and hands the prediction to the answer. Any
fault empties the windows and cancels the offset in force.

Time is one clock, the caller's, in integer nanoseconds (the node's ROS clock, simulated
under use_sim_time), read when an input call begins and again after each inference (the
overrun policy judges the next sample by the latest reading); the caller reports its
jumps. Every call returns the outputs to publish, in order. The counters come
out as one snapshot (`counts`, `predictor_counts`); the benches time its stages from outside
(bench/stage_timing.py).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from lompr_predictor.learning.model_file import LoadedModel
from lompr_predictor.monitoring import LatencyRecorder, RejectionCounter
from lompr_predictor.online.alignment import AlignedSample, DropReason, Event, StampAlignment
from lompr_predictor.online.answers import Answers
from lompr_predictor.online.faults import FaultReason, StaleWatch, StreamRules, StreamSettings
from lompr_predictor.online.inference import InferenceBackend
from lompr_predictor.online.input_stamps import InputStamps
from lompr_predictor.online.model_slot import Fallback, ModelSlot, ModelSlots, check_model
from lompr_predictor.online.offset import XY, CompensationLimits, OffsetGate, Output
from lompr_predictor.online.plant_error import PlantErrors
from lompr_predictor.online.predictor_counts import PredictorCounts
from lompr_predictor.online.preview import Planned, PlannedPath, PreviewDrop, ReferencePreview
from lompr_predictor.online.sample_units import LiveAccuracy, PlausibleChange, SampleUnit
from lompr_predictor.online.timing import OverrunGuard
from lompr_predictor.robot.chain import KinematicChain, load_chain
from lompr_predictor.stamps import StampLike, period_ns


class OnlinePredictor:
    """The predictor node's core (module docstring). `clock` reads the caller's time in
    integer nanoseconds; `units` follow the live accuracy in the chain (`sample_units`)."""

    def __init__(
        self, model: LoadedModel, stream: StreamSettings, limits: CompensationLimits, *,
        clock: Callable[[], int], backend: InferenceBackend | None = None,
        fallback: Fallback | None = None, chain: KinematicChain | None = None,
        units: Sequence[SampleUnit] = (), latency_samples: int = 1000,
    ) -> None:
        #: The robot the models must have been trained for (default: the packaged LOMPR).
        self.chain = chain or load_chain()
        check_model(model, self.chain)
        self.stream = stream
        metadata = model.metadata
        self.horizon = metadata.horizon
        #: Samples of the planned reference the model reads after each row (0: none).
        self.preview = metadata.preview
        period = period_ns(stream.sample_period)
        self._lead_ns = self.horizon * period
        self._clock = clock
        self._now = 0  # the clock's latest reading [ns]
        self._alignment = StampAlignment(stream.gap_factor, period, clock)
        #: Input samples not used, by reason (`alignment.DropReason`).
        self.dropped = self._alignment.dropped
        self._stamps = InputStamps(self.dropped, stream.max_future_stamp)
        self._stale = StaleWatch(stream.stale_after, clock)
        self._preview = ReferencePreview(self.preview, period, stream.gap_factor * period,
                                         stream.preview_tolerance, period_ns(stream.stale_after))
        #: Durations of the network calls of every slot [s].
        self.inference_time = LatencyRecorder(latency_samples)
        #: The model's slot; the fallback's (None without one) answers where the plan is
        #: missing, from its own window of the same samples.
        self.slots = ModelSlots(model, backend, fallback, self.chain, self.inference_time)
        self.primary, self.fallback = self.slots.primary, self.slots.fallback
        #: The offsets published and their bounds, with their counters (change the bounds
        #: with `set_limits`).
        self.gate = OffsetGate(limits, period)
        #: RMS of truth - prediction over the last predicted instants (`rms()`).
        self.accuracy = LiveAccuracy(stream.accuracy_samples)
        self.plausible = PlausibleChange()  # the last word before the offset gate
        self._errors = PlantErrors(StreamRules(stream, period), self.gate,
                                   (self.accuracy, *units, self.plausible))
        self.faults = RejectionCounter(FaultReason)
        self.last_fault: FaultReason | None = None
        self.overrun = OverrunGuard(self._lead_ns, period_ns(stream.late_tolerance))
        self._answers = Answers(self._errors.units, self.gate, self.overrun, self._lead_ns, clock)

    # -- inputs ---------------------------------------------------------------------------

    def add_reference(self, stamp: int | StampLike, x: float, y: float,
                      z: float) -> list[Output]:
        """Take one reference sample, the commanded tool tip (stamp: ns, or a message stamp,
        which is checked); returns outputs of poses that waited for it."""
        now = self._now = self._clock()
        stamp_ns = self._stamps.reference_ns(stamp, now)
        if stamp_ns is None:
            return []
        outputs: list[Output] = []
        if self._preview.contradicts(stamp_ns, x, y, z):
            self.primary.window.plan_lost()  # and what was predicted from the plan is cancelled
            outputs = self.gate.cancel(PreviewDrop.CONTRADICTED, self._alignment.newest_pose_ns)
        events = self._alignment.add_reference(stamp_ns, x, y, z)
        return outputs + self._handle(events) if events else outputs

    def add_preview(self, stamps_ns: Planned, positions: Planned) -> PreviewDrop | None:
        """Take one reference preview: n instants [ns] and n planned tool tips (x, y, z)
        [m], lists or arrays; the reason it was refused (counted in `plan.dropped`), or
        None."""
        return self.plan.add(stamps_ns, positions)

    def add_pose(self, stamp: int | StampLike, x: float, y: float) -> list[Output]:
        """Take one measured tool-tip sample (the kinematics node's end pose; stamp: ns,
        or a message stamp, which is checked)."""
        now = self._now = self._clock()
        stamp_ns = self._stamps.pose_ns(stamp, now)
        if stamp_ns is None:
            return []
        self.overrun.arrival(stamp_ns, now)
        return self._handle(self._alignment.add_pose(stamp_ns, x, y, now))

    def check_stale(self) -> list[Output]:
        """Call periodically: a 'stale' fault once `faults.StaleWatch` confirms that no
        sample was used for `StreamSettings.stale_after`, if anything is there to cancel."""
        alignment = self._alignment
        if not self._stale.check(alignment.oldest_waiting_arrival()):
            return []
        if self.primary.window.empty and not alignment.waiting and not self.gate.in_force:
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
        does: a 'clock_jump' fault, and the inputs start again from there (`_restart`), so
        the restarted streams refill the window without further faults."""
        outputs = self._fault(FaultReason.CLOCK_JUMP)
        self._restart(now_ns, DropReason.CLOCK_JUMP)
        return outputs

    def restart_staleness(self) -> None:
        """The clock jumped forward (its first reading under simulated time, a simulator
        skipping ahead): idle time counts from now (a gap in the stamps is still a fault)."""
        self._stale.restart()

    def reset(self, reason: DropReason = DropReason.INACTIVE) -> list[Output]:
        """Stop and start afresh, no fault (the node deactivated): the offset in force
        cancelled (zeros, `reason`), the window emptied, the inputs forgotten."""
        outputs = self.gate.cancel(reason, self._alignment.newest_pose_ns)
        self._clear()
        self._restart(None, reason)
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
        self.slots.replace(model, backend)

    # -- state for diagnostics ------------------------------------------------------------

    @property
    def model(self) -> LoadedModel:
        """The model the core runs (the primary slot's)."""
        return self.primary.model

    @property
    def plan(self) -> PlannedPath:
        """The planned reference taken from the previews (empty without a preview)."""
        return self._preview.plan

    @property
    def preview_stale(self) -> bool:
        """No plan for the stale time: a preview model cannot predict."""
        return self._preview.stale

    @property
    def last_bad_stamp(self) -> str | None:
        """Why the last message stamp dropped was no sample instant (None: none was)."""
        return self._stamps.last_bad

    @property
    def predictions_made(self) -> int:
        """Finite predictions of any slot."""
        return self.slots.predictions

    def counts(self) -> PredictorCounts:
        """The counters as one snapshot (`predictor_counts`)."""
        return PredictorCounts.taken(self.dropped, self.faults, self.predictions_made,
                                     self.gate, self.overrun)

    # -- the per-sample path --------------------------------------------------------------

    def _handle(self, events: list[Event]) -> list[Output]:
        """The outputs of `events`, in order."""
        outputs: list[Output] = []
        for event in events:
            if isinstance(event, FaultReason):
                outputs += self._fault(event)
            else:
                self._use_sample(event, outputs)
        return outputs

    def _use_sample(self, sample: AlignedSample, outputs: list[Output]) -> None:
        """Append the outputs of one aligned sample to `outputs`."""
        reason = self._errors.interval_fault(self.primary.window.last_stamp_ns,
                                             sample.stamp_ns)
        if reason is not None:
            outputs += self._fault(reason)
        self._stale.used(self._now)
        slot = self._feature_rows(sample, self._errors.of(sample), outputs)
        if slot is None or not self._answers.worth_inferring(sample.stamp_ns, self._now):
            return
        prediction = slot.predict()
        if prediction is None:
            outputs += self._fault(FaultReason.INFERENCE)
            return
        self._now = self._answers.publish(sample.stamp_ns, prediction, slot, self._now,
                                          outputs)

    def _feature_rows(self, sample: AlignedSample, error: XY,
                      outputs: list[Output]) -> ModelSlot | None:
        """Push the sample into every slot's window; the first slot whose window is full
        (the model's, else the fallback's), None while none is."""
        planned, went_stale = self._preview.at_sample(sample.stamp_ns, self._now)
        if went_stale and self.fallback is None:
            outputs += self.gate.cancel(PreviewDrop.MISSING, self._alignment.newest_pose_ns)
        return self.slots.push(sample.stamp_ns, error, (sample.reference_x, sample.reference_y,
                                                        sample.reference_z), planned)

    def _restart(self, stamp_ns: int | None, reason: DropReason) -> None:
        """Take the inputs as starting afresh at `stamp_ns` (None: anew), the waiting poses
        dropped under `reason`; the plan, idle time and the overrun estimate start again."""
        self._alignment.rewind(stamp_ns, reason)
        self._preview.restart()
        self._stale.restart()
        self.overrun.restart()

    def _clear(self) -> None:
        """Empty every window and clear the units."""
        self.slots.clear()
        self._errors.clear()

    def _fault(self, reason: FaultReason) -> list[Output]:
        """Empty the window; cancel the offsets in force (`offset.OffsetGate.cancel`)."""
        self.faults.add(reason)
        self.last_fault = reason
        self._clear()
        return self.gate.cancel(reason, self._alignment.newest_pose_ns)
