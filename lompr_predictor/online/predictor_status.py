# SPDX-License-Identifier: Apache-2.0
"""The predictor node's /diagnostics statuses (model, inputs, prediction, guard) as pure functions
of what the node holds, so that their levels and values are tested without ROS. The core's
counters go in as its snapshot (`predictor_counts.status_counts`), so that they read back
as they were written. A text that is None ("nothing wrong") is written as an empty string,
the only way a key-value says nothing."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lompr_predictor.learning.metrics import standing_text
from lompr_predictor.learning.model_file import Verification
from lompr_predictor.monitoring import (
    LatencySummary,
    Level,
    RateMeter,
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.online.alignment import SENDER_ERRORS
from lompr_predictor.online.guard import AXES, GuardReason, GuardState, LiveGuard
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.predictor_counts import (
    INPUTS_STATUS,
    PREDICTION_STATUS,
    status_counts,
)
from lompr_predictor.online.sample_store import SampleStore
from lompr_predictor.online.store_export import StoreExport


@dataclass(frozen=True)
class Lifecycle:
    """Where the node is in its lifecycle, as every status reports it."""

    state: str  # rclpy's label: unconfigured, inactive, active, finalized
    autostart: bool
    configure_error: str | None  # why the last configure failed (None after a success)
    waiting: str = 'waiting for configure'  # what an unconfigured node waits for

    @property
    def active(self) -> bool:
        return self.state == 'active'

    def values(self) -> dict[str, object]:
        return {'lifecycle_state': self.state, 'autostart': self.autostart,
                'configure_error': text(self.configure_error)}


@dataclass(frozen=True)
class ModelHistory:
    """What happened to the node's model since configure."""

    swaps: int = 0
    warm_up_seconds: float = 0.0
    reload_error: str | None = None  # why the last swap was refused (None if none was)
    refusals: int = 0  # changes refused since configure
    #: Why the network is not run by the preferred backend (None if it is).
    backend_why: str | None = None


@dataclass(frozen=True)
class InputRates:
    """The input streams' rate meters and what is reported beside them."""

    end_pose: RateMeter
    reference: RateMeter
    end_pose_topic: str
    rate_window: float  # [s] the rates are over
    clock_values: dict[str, object]  # the node's clock and dropped input, as they are
    callback_values: dict[str, object]  # callback failures, as they are


@dataclass(frozen=True)
class PredictionLimits:
    """The settings the prediction status judges against."""

    compensation_enabled: bool
    inference_time_warn: float  # [s] p99
    accuracy_warn: float  # [m] live RMS; 0: none


def text(value: str | None) -> str:
    """A text key-value: None (nothing to say) as the empty string."""
    return '' if value is None else value


def model_status(lifecycle: Lifecycle, model_path: str, core: OnlinePredictor | None,
                 history: ModelHistory, *, refusal_shown: bool) -> Status:
    """The model in use (or why there is none); a refused change a WARN while
    `refusal_shown` (`monitoring.HeldEvent`: the model in use goes on), then a value."""
    values = lifecycle.values()
    if core is None:
        values['path'] = model_path
        if lifecycle.configure_error is not None:
            return Status(Level.ERROR, f'unconfigured: configure failed: '
                                       f'{lifecycle.configure_error}', values)
        return Status(Level.WARN, f'{lifecycle.state}: no model loaded ({lifecycle.waiting})',
                      values)
    model = core.model
    metadata = model.metadata
    values.update({
        'path': model.path, 'sha256': model.sha256, 'sha256_verified_by': model.verified_by,
        'type': metadata.model_type,
        'window': metadata.window, 'horizon': metadata.horizon,
        'sample_period_s': metadata.sample_period, 'swaps': history.swaps,
        'robot_description_sha256': metadata.robot_description_sha256,
        'warm_up_ms': round(history.warm_up_seconds * 1e3, 3),
        'inference_backend': core.primary.backend.name,
        'inference_backend_why': text(history.backend_why),
        'refusals': history.refusals, 'last_refused': text(history.reload_error),
    })
    standing = {axis: standing_text(axis, entry, {})
                for axis, entry in metadata.standing.items()}
    values.update({f'test_part.{axis}': line for axis, line in standing.items()})
    if history.reload_error is not None and refusal_shown:
        return Status(Level.WARN, f'last reload refused: {history.reload_error}', values)
    summary = f'{metadata.model_type} {model.sha256[:12]}, horizon {metadata.horizon}'
    behind = [line for axis, line in standing.items()
              if metadata.standing[axis]['bo_lstm_vs_best_baseline'] > 0]
    if behind:  # the network lost to a baseline where it was tested: said, not hidden
        summary += f' (on its test part {"; ".join(behind)})'
    if not lifecycle.active:
        return Status(Level.WARN, f'{lifecycle.state} (not publishing): {summary}', values)
    if history.backend_why is not None:
        return Status(Level.WARN, f'{summary}; {history.backend_why}', values)
    if model.verified_by == Verification.NONE:
        return Status(Level.WARN, f'{summary}; NOT verified (verify_model_hash is false)',
                      values)
    return Status(Level.OK, summary, values)


def input_status(lifecycle: Lifecycle, core: OnlinePredictor | None, rates: InputRates,
                 new_faults: int, new_sender_errors: int) -> Status:
    """The input streams: rates, window fill, rejections and faults (`new_faults` and
    `new_sender_errors`, drops of `alignment.SENDER_ERRORS`, since the last report)."""
    if core is None:
        return Status(Level.WARN, lifecycle.state, {**lifecycle.values(), **rates.clock_values})
    window = core.primary.window
    values: dict[str, object] = {
        'end_pose_rate_hz': round(rates.end_pose.rate(), 3),
        'reference_rate_hz': round(rates.reference.rate(), 3),
        'end_poses_received': rates.end_pose.total,
        'references_received': rates.reference.total,
        'window_fill': f'{window.fill}/{window.needed}',
        **status_counts(core.counts())[INPUTS_STATUS],
        'last_fault': text(core.last_fault),
        'last_bad_stamp': text(core.last_bad_stamp),
        **rates.clock_values,
        **rates.callback_values,
    }
    if rates.end_pose.seconds_since_last() is None:
        return Status(Level.WARN, f'no end poses on {rates.end_pose_topic} for '
                                  f'{rates.rate_window:g} s', values)
    if new_faults:
        return Status(Level.WARN, f'{new_faults} faults since the last report (last: '
                                  f'{core.last_fault}); window {values["window_fill"]}', values)
    if new_sender_errors:
        wrong = ', '.join(f'{reason}: {n}' for reason, n in core.dropped.counts().items()
                          if n and reason in SENDER_ERRORS)
        return Status(Level.WARN, f'{new_sender_errors} inputs dropped since the last report '
                                  f'as sent wrong (totals {wrong})', values)
    if not lifecycle.active:
        return Status(Level.WARN, f'{lifecycle.state}: input dropped', values)
    if window.fill < window.needed:
        return Status(Level.WARN, f'filling the window {values["window_fill"]}', values)
    return Status(Level.OK, f'{values["end_pose_rate_hz"]} Hz', values)


def preview_status(lifecycle: Lifecycle, core: OnlinePredictor | None, rate: RateMeter,
                   topic: str, new_missing: int) -> Status:
    """The reference preview a model with K > 0 needs: ERROR once no plan covered its
    samples for the stale time (no offsets, zeros published), WARN for samples without one
    (`new_missing` since the last report), refused previews counted."""
    if core is None:
        return Status(Level.WARN, lifecycle.state, lifecycle.values())
    if not core.preview:
        return Status(Level.OK, 'the model reads no preview', {'preview_samples': 0})
    plan = core.plan
    values: dict[str, object] = {
        'preview_samples': core.preview,
        'preview_rate_hz': round(rate.rate(), 3),
        'previews_received': rate.total,
        'previews_used': plan.previews_used,
        **rejection_values(plan.dropped),
        'planned_until_s': None if plan.horizon_ns is None else plan.horizon_ns * 1e-9,
        'fallback_model': '' if core.fallback is None else core.fallback.model.path,
        'fallback_answers': 0 if core.fallback is None else core.fallback.answers,
    }
    fallback = ('; the fallback model answers' if core.fallback is not None else
                ' (no offset for them)')
    if core.preview_stale:
        if core.fallback is not None:
            return Status(Level.WARN, f'no preview on {topic}: the fallback model answers',
                          values)
        return Status(Level.ERROR, f'no preview on {topic} covers the instant '
                                   f'{core.preview} samples ahead: the model cannot predict, '
                                   'no offsets (zeros)', values)
    if new_missing:
        return Status(Level.WARN, f'{new_missing} samples without a plan {core.preview} '
                                  f'samples ahead since the last report{fallback}', values)
    return Status(Level.OK, f'{values["preview_rate_hz"]} Hz, {core.preview} samples ahead',
                  values)


#: How `in_time_pct` reads an instant (`timing.OverrunGuard.same_clock`).
LATENESS_READING = {True: "on the node's clock (the stamps are on it)",
                    False: 'against the best-case input delay (the stamps are on another '
                           'clock)', None: 'no sample yet'}


def prediction_status(lifecycle: Lifecycle, core: OnlinePredictor | None,
                      limits: PredictionLimits, input_to_output: LatencySummary,
                      output_rate_hz: float, new_overruns: int) -> Status:
    """Predictions and offsets: latencies, live accuracy, limits hit, outputs after their
    instant or skipped (`new_overruns` since the last report)."""
    if core is None:
        return Status(Level.WARN, lifecycle.state, lifecycle.values())
    inference = core.inference_time.summary()
    rms, count = core.accuracy.rms()
    offset = core.gate.offset_in_force
    counts = core.counts()
    values: dict[str, object] = {
        **latency_values('inference', inference),
        **latency_values('input_to_output', input_to_output),
        'output_rate_hz': round(output_rate_hz, 3),
        'accuracy_rms_x_um': round(float(rms[0]) * 1e6, 3),
        'accuracy_rms_y_um': round(float(rms[1]) * 1e6, 3),
        'accuracy_samples': count,
        'implausible_predictions': core.plausible.implausible,
        'in_time_pct': round(100.0 * counts.in_time_share, 3),
        'in_time_judged': LATENESS_READING[core.overrun.same_clock],
        'compensation_enabled': limits.compensation_enabled,
        'offset_x_um': round(float(offset[0]) * 1e6, 3),
        'offset_y_um': round(float(offset[1]) * 1e6, 3),
        **status_counts(counts)[PREDICTION_STATUS],
    }
    mode = 'compensating' if limits.compensation_enabled else 'shadow mode'
    if not lifecycle.active:
        mode = f'{lifecycle.state}, not publishing'
    if new_overruns:
        return Status(Level.WARN, f'{mode}; {new_overruns} outputs after their instant or '
                                  'skipped since the last report (the input came late, or '
                                  'the inference was slower than it)', values)
    if inference.samples and inference.p99 > limits.inference_time_warn:
        return Status(Level.WARN, f'{mode}; inference p99 {inference.p99 * 1e6:.0f} us over '
                                  f'{limits.inference_time_warn * 1e6:.0f} us', values)
    warn = limits.accuracy_warn
    if warn > 0.0 and count and float(np.nanmax(rms)) > warn:
        return Status(Level.WARN, f'{mode}; live RMS error {np.nanmax(rms) * 1e6:.1f} um '
                                  f'over {warn * 1e6:.1f} um: the machine has drifted from '
                                  'the model', values)
    return Status(Level.OK, f'{mode}; {values["predictions_total"]} predictions', values)


def guard_status(lifecycle: Lifecycle, guard: LiveGuard | None, envelope: bool) -> Status:
    """The live guard (`online.guard`): per axis whether the model, its prior or
    persistence answers and why, the live RMS of the three on the same instants, the
    hand-overs, the rows outside the model's trained envelope (`envelope`: whether its file
    has one). WARN while an axis is held back (or would be, with the guard off), but for
    the start of every model: unproven for less than a window of scored instants."""
    if guard is None:
        return Status(Level.WARN, lifecycle.state, lifecycle.values())
    enabled = guard.settings.enabled
    values: dict[str, object] = {'enabled': enabled, 'scored': guard.scored,
                                 'published_with_fallback': guard.published_fallback,
                                 'envelope': envelope, 'outside_envelope_total':
                                 guard.envelope.rows_outside,
                                 'outside_envelope_fraction': round(guard.envelope.fraction, 4),
                                 'last_outside_column': guard.envelope.last_outside}
    held: list[str] = []
    unproven: list[str] = []
    # a model still unproven once a whole window was scored does not know this program or
    # machine: said as loudly as a model shown worse
    warming_up = guard.scored * guard.period_ns * 1e-9 < guard.settings.window
    for axis, status in zip(AXES, guard.status(), strict=True):
        ratio = (status.model_rms / status.persistence_rms if status.persistence_rms > 0
                 else float('nan'))
        values.update({f'state_{axis}': str(status.state), f'reason_{axis}': text(status.reason),
                       f'model_rms_{axis}_um': round(status.model_rms * 1e6, 3),
                       f'persistence_rms_{axis}_um': round(status.persistence_rms * 1e6, 3),
                       f'prior_rms_{axis}_um': round(status.prior_rms * 1e6, 3),
                       f'map_prior_rms_{axis}_um': round(status.map_prior_rms * 1e6, 3),
                       f'model_to_persistence_{axis}': round(ratio, 3),
                       f'hand_overs_{axis}': status.hand_overs,
                       f'hand_backs_{axis}': status.hand_backs})
        if status.state is not GuardState.MODEL:
            fallback_rms = (min(status.prior_rms, status.map_prior_rms)
                            if status.state is GuardState.PRIOR else status.persistence_rms)
            why = (f'({status.reason}, live RMS {status.model_rms * 1e6:.2f} vs '
                   f'{fallback_rms * 1e6:.2f} um)' if guard.scored else
                   f'({status.reason}, not yet scored)')
            if status.reason is GuardReason.UNPROVEN:
                (unproven if warming_up else held).append(
                    f'{status.state} answers on {axis.upper()} until the model is better by '
                    f'the margin {why}' if enabled else
                    f'guard off: the model answers on {axis.upper()}, not yet better than '
                    f'{status.state} {why}')
            else:
                held.append(f'{status.state} answers on {axis.upper()} {why}' if enabled else
                            f'guard off: the model answers on {axis.upper()}, though worse '
                            f'than {status.state} {why}')
    if held:
        return Status(Level.WARN, '; '.join(held + unproven), values)
    if unproven:  # the start of every model: it earns control
        return Status(Level.OK, '; '.join(unproven), values)
    return Status(Level.OK, 'the model answers' + ('' if enabled else ' (guard off)'), values)


def store_status(lifecycle: Lifecycle, minutes: float, store: SampleStore | None,
                 export: StoreExport | None, *, failure_shown: bool) -> Status:
    """The sample store (`online.sample_store`): its window, size and fill, and its writes
    as bags (`online.store_export`). WARN while the last write failed and `failure_shown`
    (`monitoring.HeldEvent`: the store goes on holding samples)."""
    if minutes <= 0:
        return Status(Level.OK, 'off (store_minutes 0)', {'store_minutes': minutes})
    if store is None or export is None:
        return Status(Level.OK, f'{lifecycle.state}: no store', lifecycle.values())
    state = export.state
    values: dict[str, object] = {
        'store_minutes': minutes, 'capacity': store.capacity,
        'size_mb': round(store.size_bytes / 1e6, 3), 'samples': store.held,
        'fill_pct': round(100.0 * store.held / store.capacity, 2),
        'held_seconds': round(store.held_seconds, 3), 'restarts': store.restarts,
        'folder': str(export.folder), 'writing': state.writing, 'last_bag': state.last_bag,
        'last_error': state.last_error, 'bags_written': state.written,
        'write_failures': state.failed, 'last_write_seconds': round(state.last_seconds, 3)}
    held = f'{store.held} samples ({store.held_seconds:.1f} s of {60 * minutes:.0f} s)'
    if state.last_error and failure_shown:
        return Status(Level.WARN, f'{held}; the last write failed: {state.last_error}', values)
    if state.writing:
        return Status(Level.OK, f'{held}; writing {state.writing}', values)
    return Status(Level.OK, held + (f'; last written {state.last_bag}' if state.last_bag
                                    else ''), values)
