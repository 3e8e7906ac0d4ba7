# SPDX-License-Identifier: Apache-2.0
"""The predictor node's /diagnostics statuses, built without ROS from a real core."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from fake_clock import FakeClock
from guard_streams import HORIZON, LEAD, PERIOD, guard_rules, random_walk, run_guard
from model_helpers import save_constant
from test_predictor import stream

from lompr_predictor.data.features import HISTORY
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.monitoring import LatencySummary, Level, RateMeter, Status
from lompr_predictor.online.alignment import DropReason
from lompr_predictor.online.guard import LiveGuard
from lompr_predictor.online.offset import CompensationLimits
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.predictor_counts import (
    INPUTS_STATUS,
    PREDICTION_STATUS,
    CountsMissingError,
    PredictorCounts,
    read_counts,
    status_counts,
)
from lompr_predictor.online.predictor_status import (
    InputRates,
    Lifecycle,
    ModelHistory,
    PredictionLimits,
    guard_status,
    input_status,
    model_status,
    prediction_status,
)

PERIOD_NS = 40_000_000
T0 = 1_700_000_000_000_000_000
WINDOW = 4
ACTIVE = Lifecycle('active', autostart=True, configure_error=None)
LIMITS = PredictionLimits(compensation_enabled=True, inference_time_warn=10.0,
                          accuracy_warn=0.0)
NO_LATENCY = LatencySummary(0, 0.0, 0.0, 0.0)


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def core(tmp_path: Path, clock: FakeClock) -> OnlinePredictor:
    """A core whose model always predicts (-20, 5) um, limits loose enough to publish it."""
    model = load_model(save_constant(tmp_path / 'c.pt', (-20e-6, 5e-6), window=WINDOW))
    return OnlinePredictor(model, stream(), CompensationLimits(1e-3, 1e-3, True),
                           clock=clock.ns)


def feed(core: OnlinePredictor, clock: FakeClock, count: int, start: int = 0) -> None:
    """`count` samples from sample `start` on: reference and pose 10 um apart in X."""
    for k in range(start, start + count):
        clock.now += 0.04
        core.add_reference(T0 + k * PERIOD_NS, 0.01 * k, 0.0, 1.097)
        core.add_pose(T0 + k * PERIOD_NS, 0.01 * k + 1e-5, 0.0)


def rates(clock: FakeClock, poses: int) -> InputRates:
    end_pose, reference = RateMeter(5.0, clock), RateMeter(5.0, clock)
    for _ in range(poses):
        clock.now += 0.04
        end_pose.tick()
        reference.tick()
    return InputRates(end_pose, reference, '/lompr/end_pose', 5.0, {'clock_s': 1.5},
                      {'callback_failures': 0})


def test_model_status_without_a_model_says_why() -> None:
    failed = Lifecycle('unconfigured', autostart=False, configure_error='no such file')
    status = model_status(failed, 'm.pt', None, ModelHistory(), refusal_shown=True)
    assert status.level == Level.ERROR
    assert status.message == 'unconfigured: configure failed: no such file'
    assert status.values == {'lifecycle_state': 'unconfigured', 'autostart': False,
                             'configure_error': 'no such file', 'path': 'm.pt'}
    waiting = model_status(Lifecycle('unconfigured', False, None), 'm.pt', None,
                           ModelHistory(), refusal_shown=True)
    assert (waiting.level, waiting.message) == (
        Level.WARN, 'unconfigured: no model loaded (waiting for configure)')


def test_model_status_reports_the_model_and_its_history(core: OnlinePredictor) -> None:
    model = core.model
    history = ModelHistory(swaps=2, warm_up_seconds=0.0123456)
    status = model_status(ACTIVE, 'ignored.pt', core, history, refusal_shown=True)
    assert status.level == Level.OK
    assert status.message == f'linear {model.sha256[:12]}, horizon 3'
    values = status.values
    assert values['path'] == model.path and values['sha256'] == model.sha256
    assert (values['sha256_verified_by'], values['window'], values['horizon'],
            values['sample_period_s'], values['swaps'], values['warm_up_ms']) == (
        'sidecar', WINDOW, 3, 0.04, 2, 12.346)
    inactive = model_status(Lifecycle('inactive', True, None), '', core, history,
                            refusal_shown=True)
    assert inactive.level == Level.WARN and inactive.message.startswith(
        'inactive (not publishing): linear ')
    refused_history = ModelHistory(reload_error='bad file', refusals=1)
    refused = model_status(ACTIVE, '', core, refused_history, refusal_shown=True)
    assert (refused.level, refused.message) == (Level.WARN, 'last reload refused: bad file')
    # past its hold the refusal is a value: the model in use goes on, the status is back
    held_over = model_status(ACTIVE, '', core, refused_history, refusal_shown=False)
    assert (held_over.level, held_over.message) == (Level.OK, f'linear {model.sha256[:12]}, '
                                                               'horizon 3')
    assert (held_over.values['last_refused'], held_over.values['refusals']) == ('bad file', 1)


def test_model_status_says_where_the_model_lost_to_a_baseline(tmp_path: Path) -> None:
    """A model that trailed a baseline on its test part says so in its status (and every
    axis's standing is a value); one that led adds nothing to the summary."""
    standing = {'x': {'leader': 'ridge', 'best_baseline': 'ridge', 'best_baseline_rmse_um': 2.0,
                      'bo_lstm_rmse_um': 2.2, 'bo_lstm_vs_best_baseline': 0.1},
                'y': {'leader': 'bo_lstm', 'best_baseline': 'hgb', 'best_baseline_rmse_um': 4.0,
                      'bo_lstm_rmse_um': 3.0, 'bo_lstm_vs_best_baseline': -0.25}}
    model = load_model(save_constant(tmp_path / 's.pt', window=WINDOW, standing=standing))
    core = OnlinePredictor(model, stream(), CompensationLimits(1e-3, 1e-3, True),
                           clock=FakeClock().ns)
    status = model_status(ACTIVE, '', core, ModelHistory(), refusal_shown=True)
    assert status.level == Level.OK
    assert status.message == (f'linear {model.sha256[:12]}, horizon 3 (on its test part X: '
                              'ridge leads, the BO-LSTM 10.0 % behind it)')
    assert status.values['test_part.y'] == 'Y: the BO-LSTM leads, 25.0 % below hgb'


def test_input_status_from_waiting_to_filling_to_full(core: OnlinePredictor,
                                                      clock: FakeClock) -> None:
    quiet = input_status(ACTIVE, core, rates(clock, 0), new_faults=0, new_sender_errors=0)
    assert (quiet.level, quiet.message) == (Level.WARN, 'no end poses on /lompr/end_pose for 5 s')
    feed(core, clock, 3)
    filling = input_status(ACTIVE, core, rates(clock, 3), new_faults=0, new_sender_errors=0)
    assert (filling.level, filling.message) == (
        Level.WARN, f'filling the window 3/{WINDOW + HISTORY}')
    feed(core, clock, WINDOW + HISTORY, start=3)
    full = input_status(ACTIVE, core, rates(clock, 25), new_faults=0, new_sender_errors=0)
    assert full.level == Level.OK and full.message == '25.0 Hz'
    assert full.values['end_poses_received'] == 25 and full.values['clock_s'] == 1.5
    assert full.values['window_fill'] == f'{WINDOW + HISTORY}/{WINDOW + HISTORY}'
    assert full.values['faults_total'] == 0 and full.values['callback_failures'] == 0
    core.add_pose(T0 + 99 * PERIOD_NS, float('nan'), 0.0)
    faulty = input_status(ACTIVE, core, rates(clock, 25), new_faults=1, new_sender_errors=0)
    assert faulty.level == Level.WARN and faulty.message == (
        '1 faults since the last report (last: non_finite); window 0/'
        f'{WINDOW + HISTORY}')
    assert faulty.values['faults.non_finite'] == 1 and faulty.values['rejected.non_finite'] == 1
    dropped = input_status(Lifecycle('inactive', True, None), core, rates(clock, 25), 0, 0)
    assert (dropped.level, dropped.message) == (Level.WARN, 'inactive: input dropped')


def test_input_status_raises_inputs_sent_wrong(core: OnlinePredictor, clock: FakeClock) -> None:
    """A pose in another frame is dropped without a fault; that a sender is wrong is a
    WARN all the same, with the totals of such drops."""
    feed(core, clock, WINDOW + HISTORY)
    core.dropped.add(DropReason.WRONG_FRAME)
    core.dropped.add(DropReason.WRONG_FRAME)
    core.dropped.add(DropReason.DUPLICATE)  # a stream's hiccup, not a sender's mistake
    wrong = input_status(ACTIVE, core, rates(clock, 25), new_faults=0, new_sender_errors=2)
    assert (wrong.level, wrong.message) == (
        Level.WARN, '2 inputs dropped since the last report as sent wrong (totals '
                    'wrong_frame: 2)')
    later = input_status(ACTIVE, core, rates(clock, 25), new_faults=0, new_sender_errors=0)
    assert later.level == Level.OK and later.values['rejected.wrong_frame'] == 2


def test_input_status_unconfigured_keeps_only_the_clock() -> None:
    meters = InputRates(RateMeter(), RateMeter(), '/e', 5.0, {'clock_s': 0.0},
                        {'callback_failures': 3})
    status = input_status(Lifecycle('unconfigured', True, None), None, meters, 0, 0)
    assert (status.level, status.message) == (Level.WARN, 'unconfigured')
    assert 'callback_failures' not in status.values and status.values['clock_s'] == 0.0


def test_prediction_status_counts_predictions_and_the_offset(core: OnlinePredictor,
                                                            clock: FakeClock) -> None:
    feed(core, clock, WINDOW + HISTORY + 2)
    status = prediction_status(ACTIVE, core, LIMITS, NO_LATENCY, 25.0, new_overruns=0)
    assert (status.level, status.message) == (Level.OK, 'compensating; 3 predictions')
    values = status.values
    assert values['predictions_total'] == 3 and values['output_rate_hz'] == 25.0
    assert values['compensation_enabled'] is True
    # stamps of 2023 on a clock at 100 s: another clock, read against the best-case delay
    assert values['in_time_judged'] == ('against the best-case input delay (the stamps are '
                                        'on another clock)')
    # the offset in force is minus the prediction, grown by at most the step limit
    assert (values['offset_x_um'], values['offset_y_um']) == (20.0, -5.0)
    assert core.counts().overruns == 0
    late = prediction_status(ACTIVE, core, LIMITS, NO_LATENCY, 25.0, new_overruns=2)
    assert late.level == Level.WARN and late.message.startswith(
        'compensating; 2 outputs after their instant or skipped since the last report')
    slow = prediction_status(ACTIVE, core, PredictionLimits(False, 1e-12, 0.0), NO_LATENCY,
                             25.0, 0)
    assert slow.level == Level.WARN and slow.message.startswith('shadow mode; inference p99 ')


def test_prediction_status_warns_on_drift(core: OnlinePredictor, clock: FakeClock) -> None:
    """The model says -20 um where the plant error is +10 um: a live RMS far over 1 um."""
    feed(core, clock, WINDOW + HISTORY + 10)
    rms, count = core.accuracy.rms()
    assert count > 0 and float(np.nanmax(rms)) > 1e-6
    status = prediction_status(ACTIVE, core, PredictionLimits(True, 10.0, 1e-6), NO_LATENCY,
                               25.0, 0)
    assert status.level == Level.WARN and 'the machine has drifted from the model' in (
        status.message)
    unconfigured = prediction_status(Lifecycle('finalized', False, None), None, LIMITS,
                                     NO_LATENCY, 0.0, 0)
    assert (unconfigured.level, unconfigured.message) == (Level.WARN, 'finalized')


def as_read_back(status: Status) -> dict[str, str]:
    """A status's key-values as /diagnostics carries them (`ros.common.status_message`)."""
    return {str(key): str(value) for key, value in status.values.items()}


def test_the_counts_written_read_back_as_the_cores(core: OnlinePredictor,
                                                   clock: FakeClock) -> None:
    """What the inputs and prediction statuses write is what a reader of /diagnostics gets
    back (the cross-process closed loop): every count, by reason too."""
    feed(core, clock, WINDOW + HISTORY + 4)
    core.add_pose(T0 + 40 * PERIOD_NS, float('nan'), 0.0)  # a fault and a drop
    core.add_pose(T0 + 41 * PERIOD_NS, 0.0, 0.0)
    core.add_pose(T0 + 41 * PERIOD_NS, 0.0, 0.0)  # a duplicate
    counts = core.counts()
    assert counts.faults['non_finite'] == 1 and counts.dropped['duplicate'] == 1
    assert counts.predictions == 5 and sum(counts.faults.values()) == 1
    statuses = {INPUTS_STATUS: as_read_back(input_status(ACTIVE, core, rates(clock, 10), 0, 0)),
                PREDICTION_STATUS: as_read_back(prediction_status(ACTIVE, core, LIMITS,
                                                                  NO_LATENCY, 25.0, 0))}
    assert read_counts(statuses) == counts


def test_counts_missing_from_the_statuses_are_named() -> None:
    counts = PredictorCounts(dropped={'duplicate': 1}, faults={'gap': 2}, predictions=3,
                             clamped=4, step_limited=5, zeros_published=6, reclamped=7,
                             inference_skipped_late=8, late_outputs_dropped=9)
    written = {name: {key: str(value) for key, value in values.items()}
               for name, values in status_counts(counts).items()}
    assert read_counts(written) == counts and counts.overruns == 17
    assert counts.in_time_share == 0.0  # 17 instants late or skipped, none in time
    assert math.isnan(dataclasses.replace(counts, inference_skipped_late=0,
                                          late_outputs_dropped=0).in_time_share)
    timed = dataclasses.replace(counts, outputs_in_time=80, outputs_after_instant=3)
    assert timed.in_time_share == 80 / (80 + 3 + 17)
    assert read_counts({name: {key: str(value) for key, value in values.items()}
                        for name, values in status_counts(timed).items()}) == timed
    with pytest.raises(CountsMissingError, match="no predictor status 'prediction'"):
        read_counts({INPUTS_STATUS: written[INPUTS_STATUS]})
    renamed = {**written[PREDICTION_STATUS], 'clamped': '4'}
    del renamed['clamped_total']
    with pytest.raises(CountsMissingError, match="has no 'clamped_total'"):
        read_counts({**written, PREDICTION_STATUS: renamed})
    with pytest.raises(CountsMissingError, match=r'no faults\.<reason> counts'):
        read_counts({**written, INPUTS_STATUS: {'rejected.duplicate': '1'}})


def test_a_model_unproven_for_a_whole_window_is_a_warning() -> None:
    """A model 0.97x persistence on every instant, inside the margin, never earns control:
    the guard status is OK while fewer than a window of instants were scored (the start of
    every model), WARN after, naming the axes; the state stays `persistence`, `unproven`."""
    window = 100  # instants
    settings = guard_rules(window_instants=window, min_scored=10, dwell_instants=10)
    truth = random_walk(window + HORIZON + 20, seed=21)
    model_error = np.zeros_like(truth)
    model_error[HORIZON:] = -0.97 * (truth[HORIZON:] - truth[:-HORIZON])
    statuses = []
    for count in (window, len(truth)):  # scored: a window less HORIZON, then past it
        guard = LiveGuard(settings, LEAD, PERIOD)
        run_guard(guard, truth[:count], model_error[:count])
        statuses.append(guard_status(ACTIVE, guard, envelope=False))
    early, late = statuses
    assert early.level is Level.OK
    assert early.message.startswith('persistence answers on X until the model is better by '
                                    'the margin (unproven, live RMS ')
    assert late.level is Level.WARN
    assert 'persistence answers on X until' in late.message
    assert 'persistence answers on Y until' in late.message
    assert late.values['state_x'] == late.values['state_y'] == 'persistence'
    assert late.values['reason_x'] == late.values['reason_y'] == 'unproven'
    assert late.values['model_to_persistence_x'] == pytest.approx(0.97, abs=0.005)


def test_a_change_beyond_the_trained_range_is_not_published_as_a_prediction(
        tmp_path: Path, clock: FakeClock) -> None:
    """The model trained on errors within +-1 um predicts X 30 um away from the plant error
    now (-20 against +10 um) and Y 3 um away: X is handed on as persistence (the error
    now), counted on the prediction status; Y, within twice the range, as predicted."""
    range_1um = {'error_low': [-1e-6, -1e-6], 'error_high': [1e-6, 1e-6]}
    model = load_model(save_constant(tmp_path / 'jump.pt', (-20e-6, 3e-6), window=WINDOW,
                                     normalisation=range_1um))
    core = OnlinePredictor(model, stream(), CompensationLimits(1e-3, 1e-3, False),
                           clock=clock.ns)  # shadow mode: the fed plant error stays 10 um
    samples = 3 * (WINDOW + HISTORY)
    feed(core, clock, samples)
    assert core.plausible.implausible > 0
    last_instant = T0 + (samples - 1 + model.metadata.horizon) * PERIOD_NS
    assert core.gate.prediction_for(last_instant) == pytest.approx((1e-5, 3e-6), abs=1e-15)
    status = prediction_status(ACTIVE, core, LIMITS, NO_LATENCY, 25.0, new_overruns=0)
    assert status.values['implausible_predictions'] == core.plausible.implausible
