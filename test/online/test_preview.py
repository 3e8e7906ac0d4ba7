# SPDX-License-Identifier: Apache-2.0
"""The reference preview online: the plan by stamp, and OnlinePredictor with a preview model
(offline parity, missing, stale and contradicted plans)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from fake_clock import FakeClock
from model_helpers import save_constant, save_linear
from test_predictor import stream

from lompr_predictor.data.features import feature_names, feature_rows, with_preview
from lompr_predictor.learning.model_file import LoadedModel, MetadataMismatchError, load_model
from lompr_predictor.monitoring import RateMeter
from lompr_predictor.online.offset import CompensationLimits, Output
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.predictor_status import Lifecycle, preview_status
from lompr_predictor.online.preview import (
    PLAN_REACH,
    PlannedPath,
    PreviewDrop,
    ReferencePreview,
)
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.robot.kinematics import VerticalToolBranches

T0 = 1_700_000_000_000_000_000
PERIOD = 0.04
PERIOD_NS = 40_000_000
WINDOW, HORIZON, PREVIEW = 4, 3, 3
PLANNED_AHEAD = PREVIEW + 2  # samples each preview plans, as a path generator publishes
BRANCHES = VerticalToolBranches(load_robot_description().geometry)
ACTIVE = Lifecycle('active', True, None)


def path(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps [ns], reference (n, 3) [m] on an arc, measured tip (n, 2) = reference + error."""
    k = np.arange(n)
    angle = 0.03 * k
    reference = np.stack([0.15 * np.cos(angle), 0.15 * np.sin(angle), np.full(n, 1.097)], -1)
    error = np.stack([20e-6 * np.sin(0.3 * k), 15e-6 * np.cos(0.2 * k)], -1)
    return T0 + k * PERIOD_NS, reference, reference[:, :2] + error


@pytest.fixture
def preview_model(tmp_path: Path) -> LoadedModel:
    names = feature_names(PREVIEW)
    # weights on every column, the preview block's too, each column at its own scale
    weight = np.random.default_rng(3).normal(size=(WINDOW * len(names), 2)) * 1e-4
    return load_model(save_linear(tmp_path / 'preview.pt', weight, window=WINDOW,
                                  horizon=HORIZON, features=names, preview=PREVIEW))


def core_of(model: LoadedModel, clock: FakeClock, enabled: bool = False) -> OnlinePredictor:
    return OnlinePredictor(model, stream(), CompensationLimits(1e-3, 1e-3, enabled),
                           clock=clock.ns)


def feed(core: OnlinePredictor, clock: FakeClock, stamps: np.ndarray, reference: np.ndarray,
         tips: np.ndarray, samples: range, planned: np.ndarray | None = None) -> list[Output]:
    """Each sample's preview (of `planned`, default the reference itself; none if the
    sample's index is past it), reference and pose, in that order; the outputs."""
    plan = reference if planned is None else planned
    outputs: list[Output] = []
    for k in samples:
        clock.now += PERIOD
        ahead = slice(k + 1, k + 1 + PLANNED_AHEAD)
        if len(stamps[ahead]) == PLANNED_AHEAD:
            core.add_preview(stamps[ahead], plan[ahead])
        outputs += core.add_reference(int(stamps[k]), *reference[k])
        outputs += core.add_pose(int(stamps[k]), *tips[k])
    return outputs


def test_a_newer_preview_replaces_an_older_one_where_both_plan() -> None:
    plan = PlannedPath(max_step_ns=2.5 * PERIOD_NS, tolerance=1e-6)
    stamps = T0 + np.arange(5) * PERIOD_NS
    positions = np.stack([np.arange(5) * 1e-3, np.zeros(5), np.full(5, 1.1)], -1)
    assert plan.add(stamps, positions) is None
    assert plan.at(int(stamps[1]) + PERIOD_NS // 4) == pytest.approx((1.25e-3, 0.0, 1.1))
    assert plan.at(int(stamps[0]) - 1) is None and plan.at(int(stamps[4]) + 1) is None
    assert plan.add(stamps[2:4], positions[2:4] + np.array([0.0, 1e-3, 0.0])) is None  # 2, 3
    assert plan.at(int(stamps[3])) == pytest.approx((3e-3, 1e-3, 1.1))
    assert plan.at(int(stamps[4])) == pytest.approx((4e-3, 0.0, 1.1))  # kept from the first
    assert plan.horizon_ns == int(stamps[4]) and plan.previews_used == 2
    gap = PlannedPath(max_step_ns=2.5 * PERIOD_NS, tolerance=1e-6)
    gap.add(stamps[[0, 4]], positions[[0, 4]])  # 4 periods apart: a gap, not interpolated
    assert gap.at(int(stamps[2])) is None


def test_a_bad_preview_is_refused_whole_with_its_reason() -> None:
    plan = PlannedPath(max_step_ns=2.5 * PERIOD_NS, tolerance=1e-6)
    stamps = T0 + np.arange(3) * PERIOD_NS
    positions = np.zeros((3, 3))
    assert plan.add(stamps[:0], positions[:0]) == PreviewDrop.EMPTY
    bad = positions.copy()
    bad[0, 1] = np.nan
    assert plan.add(stamps, bad) == PreviewDrop.NON_FINITE
    assert plan.add(stamps[::-1], positions) == PreviewDrop.OUT_OF_ORDER
    assert plan.check(int(stamps[2]), 0.0, 0.0, 0.0)  # nothing planned yet: no contradiction
    assert plan.add(stamps, positions) == PreviewDrop.PAST  # all at or before that reference
    assert plan.horizon_ns is None
    assert {k: n for k, n in plan.dropped.counts().items() if n} == {
        'empty': 1, 'non_finite': 1, 'out_of_order': 1, 'past': 1}


def test_a_reference_preview_reads_the_plan_ahead_and_says_once_when_it_went_stale() -> None:
    """Without preview steps it reads nothing and nothing contradicts it; with them each
    sample reads the plan `steps` periods ahead, and the sample after which no plan came for
    the stale time is the one that says the plan went stale (once, until a plan comes)."""
    none = ReferencePreview(0, PERIOD_NS, 2.5 * PERIOD_NS, 1e-6, 2 * PERIOD_NS)
    none.plan.add(T0 + np.arange(1, 3) * PERIOD_NS, np.ones((2, 3)))
    assert none.at_sample(T0, 0) == (None, False) and not none.contradicts(T0 + PERIOD_NS, 0, 0, 0)
    preview = ReferencePreview(2, PERIOD_NS, 2.5 * PERIOD_NS, 1e-6, 2 * PERIOD_NS)
    stamps = T0 + np.arange(1, 5) * PERIOD_NS
    positions = np.stack([np.arange(1, 5) * 1e-3, np.zeros(4), np.full(4, 1.1)], -1)
    assert preview.plan.add(stamps, positions) is None
    planned, went_stale = preview.at_sample(T0 + PERIOD_NS, 0)
    assert planned is not None and planned[0] == T0 + 3 * PERIOD_NS and not went_stale
    assert planned[1:] == pytest.approx((3e-3, 0.0, 1.1), abs=1e-15)
    assert preview.contradicts(T0 + 2 * PERIOD_NS, 5e-3, 0.0, 1.1)  # 3 mm off: dropped
    readings = [preview.at_sample(T0 + k * PERIOD_NS, (k - 2) * PERIOD_NS) for k in range(3, 7)]
    assert [r[1] for r in readings] == [False, True, False, False]  # 2 periods without
    assert all(r[0] is None for r in readings) and preview.stale
    preview.restart()
    assert not preview.stale and preview.plan.horizon_ns is None


def test_predictions_with_a_preview_equal_offline_ones(preview_model: LoadedModel) -> None:
    n = 40
    stamps, reference, tips = path(n + PLANNED_AHEAD)
    clock = FakeClock()
    core = core_of(preview_model, clock)
    outputs = feed(core, clock, stamps, reference, tips, range(n))
    rows = with_preview(feature_rows((stamps - stamps[0]) * 1e-9, tips - reference[:, :2],
                                     reference, BRANCHES), PREVIEW)
    ends = np.arange(WINDOW + 1, n)  # a full window takes window + HISTORY samples
    windows = np.stack([rows[e - WINDOW + 1:e + 1] for e in ends])
    offline = preview_model.predict(torch.from_numpy(windows)).numpy()
    assert [o.instant_ns for o in outputs] == list(stamps[ends] + HORIZON * PERIOD_NS)
    np.testing.assert_allclose(np.array([o.prediction for o in outputs]), offline,
                               rtol=1e-9, atol=1e-13)
    # the preview columns moved the prediction: without them it would differ
    names = feature_names(PREVIEW)
    assert np.abs(windows[:, :, names.index('plan_dx')]).min() > 1e-4
    assert core.plan.dropped.total == 0 and core.plan.previews_used == n


def test_without_a_preview_no_offset_then_zeros_and_an_error_once_stale(
        preview_model: LoadedModel) -> None:
    n = 30
    stamps, reference, tips = path(n + 40)
    clock = FakeClock()
    core = core_of(preview_model, clock, enabled=True)
    assert feed(core, clock, stamps, reference, tips, range(n))  # predicting, offsets in force
    # the previews stop: the plan still covers two more samples, then nothing is published
    outputs = []
    for k in range(n, n + 12):
        clock.now += PERIOD
        outputs += core.add_reference(int(stamps[k]), *reference[k])
        outputs += core.add_pose(int(stamps[k]), *tips[k])
    answered = [o for o in outputs if o.reason is None]
    assert len(answered) == PLANNED_AHEAD - PREVIEW
    zeros = [o for o in outputs if o.reason is not None]
    assert zeros and all(o.compensation == (0.0, 0.0) for o in zeros)
    assert {o.reason for o in zeros} == {PreviewDrop.MISSING} and core.preview_stale
    missing = core.plan.dropped.counts()['missing']
    assert missing == 12 - (PLANNED_AHEAD - PREVIEW)
    status = preview_status(ACTIVE, core, RateMeter(clock=clock), '/lompr/reference_preview',
                            missing)
    assert status.level.name == 'ERROR' and 'cannot predict' in status.message
    # previews again: predictions once every row of a window has its block
    outputs = feed(core, clock, stamps, reference, tips, range(n + 12, n + 30))
    resumed = n + 12 + WINDOW + 1  # the sample whose window is the first with every block
    assert outputs[0].reason is None and not core.preview_stale
    assert outputs[0].instant_ns == stamps[resumed] + HORIZON * PERIOD_NS


def test_a_plan_the_reference_contradicts_is_dropped_and_the_window_refills(
        preview_model: LoadedModel) -> None:
    n = 40
    stamps, reference, tips = path(n + PLANNED_AHEAD)
    clock = FakeClock()
    core = core_of(preview_model, clock)
    assert len(feed(core, clock, stamps, reference, tips, range(20))) == 20 - WINDOW - 1
    # one preview plans the next samples 1 mm off the path that is then commanded
    ahead = slice(21, 21 + PLANNED_AHEAD)
    core.add_preview(stamps[ahead], reference[ahead] + [1e-3, 0.0, 0.0])
    clock.now += PERIOD
    core.add_reference(int(stamps[20]), *reference[20])
    core.add_pose(int(stamps[20]), *tips[20])
    outputs = feed(core, clock, stamps, reference, tips, range(21, n))
    assert core.plan.dropped.counts()['contradicted'] == 1
    # sample 21's reference contradicts the plan: it is dropped (the newer preview with it)
    # and sample 22 starts a new run of planned rows; the rows built on the wrong plan are
    # never read, answers resume once a window of new ones is full (after the zeros that
    # cancel what was predicted from the plan)
    assert {o.reason for o in outputs[:HORIZON]} == {PreviewDrop.CONTRADICTED}
    assert outputs[HORIZON].instant_ns == stamps[22 + WINDOW + 1] + HORIZON * PERIOD_NS



def test_a_fallback_model_answers_where_the_plan_is_missing(
        preview_model: LoadedModel, tmp_path: Path) -> None:
    n = 30
    stamps, reference, tips = path(n + 40)
    clock = FakeClock()
    fallback = load_model(save_constant(tmp_path / 'fallback.pt', (7e-6, -3e-6),
                                        window=WINDOW, horizon=HORIZON))
    core = OnlinePredictor(preview_model, stream(), CompensationLimits(1e-3, 1e-3, True),
                           clock=clock.ns, fallback=(fallback, None))
    fallback_slot = core.fallback
    assert fallback_slot is not None
    with_plan = feed(core, clock, stamps, reference, tips, range(n))
    # the window of either model is full after the same samples: the preview model answers
    assert len(with_plan) == n - WINDOW - 1 and fallback_slot.answers == 0
    outputs = []
    for k in range(n, n + 12):  # no previews: the plan reaches two more samples
        clock.now += PERIOD
        outputs += core.add_reference(int(stamps[k]), *reference[k])
        outputs += core.add_pose(int(stamps[k]), *tips[k])
    assert len(outputs) == 12 and all(o.reason is None for o in outputs)  # no zeros
    assert [o.prediction for o in outputs[PLANNED_AHEAD - PREVIEW:]] == [(7e-6, -3e-6)] * 10
    assert fallback_slot.answers == 10 and core.preview_stale
    # previews again: the preview model takes over once its window has a plan in every row
    again = feed(core, clock, stamps, reference, tips, range(n + 12, n + 30))
    assert fallback_slot.answers == 10 + WINDOW + 1 and len(again) == 18


def test_a_fallback_must_read_no_preview_and_predict_the_same_instant(
        preview_model: LoadedModel, tmp_path: Path) -> None:
    limits = CompensationLimits(1e-3, 1e-3, True)
    other = load_model(save_constant(tmp_path / 'h2.pt', window=WINDOW, horizon=HORIZON + 1))
    with pytest.raises(MetadataMismatchError, match="'horizon' is 4"):
        OnlinePredictor(preview_model, stream(), limits, clock=FakeClock().ns,
                        fallback=(other, None))
    with pytest.raises(MetadataMismatchError, match="'preview' is 3"):
        OnlinePredictor(preview_model, stream(), limits, clock=FakeClock().ns,
                        fallback=(preview_model, None))


@pytest.mark.faults
def test_a_reference_stream_going_back_starts_a_new_plan(preview_model: LoadedModel) -> None:
    """The reference restarting from earlier stamps with no clock jump (a path generator on
    wall time replaying its program): the plan starts again with it."""
    n = 40
    stamps, reference, tips = path(n + PLANNED_AHEAD)
    clock = FakeClock()
    core = core_of(preview_model, clock)
    first = feed(core, clock, stamps, reference, tips, range(n))
    again = feed(core, clock, stamps, reference, tips, range(n))
    answered = [o for o in again if o.reason is None]
    # the first preview of the replay is past the old run's references; the plan restarts
    # with the replay's first reference and the window refills one sample later
    assert [o.instant_ns for o in answered] == [o.instant_ns for o in first[1:]]
    assert core.plan.dropped['past'] == 1


@pytest.mark.faults
def test_poses_lagging_the_reference_beyond_the_lead_still_find_their_plan(
        preview_model: LoadedModel) -> None:
    """The poses come later than the reference and the previews (they go through the
    kinematics node): the plan keeps what they still read, whatever the lag, and the
    predictions are those of poses in step with the reference."""
    n, lag = 40, 2 * PREVIEW + 1  # samples the poses lag: more than the model reads ahead
    stamps, reference, tips = path(n + PLANNED_AHEAD)
    clock = FakeClock()
    in_step = feed(core_of(preview_model, clock), clock, stamps, reference, tips, range(n))
    core = core_of(preview_model, clock)
    outputs = []
    for k in range(n + lag):
        clock.now += PERIOD
        if k < n:
            core.add_preview(stamps[k + 1:k + 1 + PLANNED_AHEAD],
                             reference[k + 1:k + 1 + PLANNED_AHEAD])
            outputs += core.add_reference(int(stamps[k]), *reference[k])
        if k >= lag:
            outputs += core.add_pose(int(stamps[k - lag]), *tips[k - lag])
    assert [(o.instant_ns, o.prediction) for o in outputs] == [
        (o.instant_ns, o.prediction) for o in in_step]
    assert core.plan.dropped['missing'] == 0


@pytest.mark.faults
def test_a_path_generator_whose_clock_runs_ahead_plans_nothing(
        preview_model: LoadedModel) -> None:
    """Previews planned an hour ahead of the reference are refused whole (counted 'ahead'),
    so the plan stays empty and the status says the model cannot predict, instead of a plan
    growing by one instant a sample that every preview copies."""
    n = 200
    stamps, reference, tips = path(n + PLANNED_AHEAD)
    clock = FakeClock()
    core = core_of(preview_model, clock)
    hour = 3600 * 10 ** 9
    outputs = []
    for k in range(n):
        clock.now += PERIOD
        ahead = slice(k + 1, k + 1 + PLANNED_AHEAD)
        core.add_preview(stamps[ahead] + hour, reference[ahead])
        outputs += core.add_reference(int(stamps[k]), *reference[k])
        outputs += core.add_pose(int(stamps[k]), *tips[k])
    assert outputs == [] and core.plan.horizon_ns is None
    # the first preview, before any reference, was taken; the first reference let it go
    assert core.plan.dropped['ahead'] == n - 1
    status = preview_status(ACTIVE, core, RateMeter(clock=clock), '/lompr/reference_preview',
                            core.plan.dropped['missing'])
    assert status.level.name == 'ERROR' and status.values['rejected.ahead'] == n - 1


@pytest.mark.faults
def test_the_plan_is_bounded_and_a_long_look_ahead_changes_no_prediction(
        preview_model: LoadedModel) -> None:
    """A look-ahead of 10 s with every sample: the plan holds at most `PLAN_REACH` beyond
    what the model reads ahead of the newest reference, and the predictions are those of the
    short preview. Previews without any reference: the plan holds the newest alone."""
    n, ahead = 40, 250  # 250 samples at 25 Hz: 10 s
    stamps, reference, tips = path(n + ahead + 1)
    clock = FakeClock()
    short = feed(core_of(preview_model, clock), clock, stamps, reference, tips, range(n))
    core = core_of(preview_model, clock)
    outputs = []
    for k in range(n):
        clock.now += PERIOD
        planned = slice(k + 1, k + 1 + ahead)
        assert core.add_preview(stamps[planned], reference[planned]) is None
        outputs += core.add_reference(int(stamps[k]), *reference[k])
        outputs += core.add_pose(int(stamps[k]), *tips[k])
        reach = int(stamps[k]) + PREVIEW * PERIOD_NS + round(PLAN_REACH * 1e9)
        assert 0 < core.plan.horizon_ns <= reach  # type: ignore[operator]
    assert outputs == short
    alone = core_of(preview_model, clock).plan
    stamps, reference, _ = path(300 + PLANNED_AHEAD)
    for k in range(300):
        alone.add(stamps[k:k + PLANNED_AHEAD], reference[k:k + PLANNED_AHEAD])
    assert alone.at(int(stamps[0])) is None and alone.at(int(stamps[299])) is not None


@pytest.mark.faults
@pytest.mark.parametrize('restart', ['clock_jump', 'reactivation'])
def test_a_preview_model_answers_a_restarted_run_as_the_first(
        preview_model: LoadedModel, restart: str) -> None:
    """A simulator reset (the clock back to the start) or a deactivate/activate followed by a
    replay from earlier stamps: the plan of the first run is forgotten, so the restarted
    run's previews are taken and it is answered from its first full window, as the first."""
    n = 40
    stamps, reference, tips = path(n + PLANNED_AHEAD)
    clock = FakeClock()
    core = core_of(preview_model, clock)
    first = feed(core, clock, stamps, reference, tips, range(n))
    if restart == 'clock_jump':
        clock.now -= n * PERIOD
        core.clock_jumped_back(int(stamps[0]) - PERIOD_NS)
    else:
        core.reset()
    again = feed(core, clock, stamps, reference, tips, range(n))
    assert [o.reason for o in again] == [None] * (n - WINDOW - 1)
    assert [(o.instant_ns, o.prediction) for o in again] == [
        (o.instant_ns, o.prediction) for o in first]
    assert core.plan.dropped.total == 0 and not core.preview_stale


@pytest.mark.faults
def test_a_contradicted_plan_cancels_the_offsets_made_from_it(
        preview_model: LoadedModel) -> None:
    """The offsets already published for the instants to come were predicted from the plan
    the reference now contradicts: they are cancelled (zeros, reason 'contradicted'), as a
    stale input's are."""
    stamps, reference, tips = path(40)
    clock = FakeClock()
    core = core_of(preview_model, clock, enabled=True)
    published = feed(core, clock, stamps, reference, tips, range(20))
    assert published and all(o.reason is None for o in published)
    ahead = slice(21, 21 + PLANNED_AHEAD)
    core.add_preview(stamps[ahead], reference[ahead] + [1e-3, 0.0, 0.0])
    clock.now += PERIOD
    core.add_reference(int(stamps[20]), *reference[20])
    core.add_pose(int(stamps[20]), *tips[20])
    zeros = core.add_reference(int(stamps[21]), *reference[21])
    assert [(o.reason, o.instant_ns) for o in zeros] == [
        ('contradicted', int(stamps[20]) + k * PERIOD_NS) for k in range(1, HORIZON + 1)]
    assert all(o.compensation == (0.0, 0.0) for o in zeros)
