# SPDX-License-Identifier: Apache-2.0
"""OnlinePredictor (ROS-free): offline parity, alignment by stamp, plant error, safety."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch
from fake_clock import FakeClock
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from model_helpers import FailingModel, metadata, save_constant, save_linear

from lompr_predictor.data.features import FEATURES, HISTORY, feature_rows
from lompr_predictor.learning import model_file
from lompr_predictor.learning.model_file import (
    LoadedModel,
    MetadataMismatchError,
    load_model,
    save_model,
)
from lompr_predictor.online.faults import StreamSettings
from lompr_predictor.online.inference import select_backend
from lompr_predictor.online.offset import XY, CompensationLimits, OffsetGate, Output
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription, load_robot_description
from lompr_predictor.robot.kinematics import VerticalToolBranches
from lompr_predictor.stamps import StampReason, stamp_problem

PERIOD = 0.04
PERIOD_NS = 40_000_000
T0 = 1_700_000_000_000_000_000  # a realistic epoch stamp [ns]
WINDOW, HORIZON = 4, 3
NEEDED = WINDOW + HISTORY
Z = 1.097  # the mirror's height [m]
BRANCHES = VerticalToolBranches(load_robot_description().geometry)
#: The features of the model files written before the branch columns came.
OLD_FEATURES = ('error_x', 'error_y', 'ref_x', 'ref_y', 'ref_vx', 'ref_vy', 'ref_ax', 'ref_ay')


def stream(sample_period: float = PERIOD, stale_min_time: float = 0.0) -> StreamSettings:
    """The stream rules the core's tests run on (no staleness floor unless asked)."""
    return StreamSettings(sample_period=sample_period, gap_factor=2.5, min_interval_factor=0.5,
                          stale_periods=5.0, stale_min_time=stale_min_time,
                          accuracy_samples=1000, max_future_stamp=1.0, late_tolerance=0.005,
                          preview_tolerance=1e-5)


def limits(max_compensation: float = 1e-3, max_step: float = 1e-3,
           enabled: bool = True) -> CompensationLimits:
    return CompensationLimits(max_compensation, max_step, enabled)



def spiral_xy(k: int) -> tuple[float, float]:
    """The measured tool tip of sample `k` on a circle of 0.1 m [m]."""
    angle = 0.05 * k
    return 0.1 * math.cos(angle), 0.1 * math.sin(angle)

def spiral(n: int, start: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps [ns], reference tool tip (n, 3) and a measured tip (n, 2) = reference X/Y + a
    smooth error."""
    k = np.arange(start, start + n)
    t_h = 10.0 * k / 1000.0
    angle = np.pi / 2 * t_h + np.pi / 2
    reference = np.stack([0.02 * t_h * np.cos(angle), 0.02 * t_h * np.sin(angle),
                          np.full(n, Z)], -1)
    error = np.stack([20e-6 * np.sin(0.3 * k), 15e-6 * np.cos(0.2 * k)], -1)
    return T0 + k * PERIOD_NS, reference, reference[:, :2] + error


@pytest.fixture
def linear_model(tmp_path: Path) -> LoadedModel:
    return load_model(save_linear(tmp_path / 'linear.pt', window=WINDOW, horizon=HORIZON))


def constant_core(tmp_path: Path, value: tuple[float, float], clock: FakeClock | None = None,
                  *, max_compensation: float = 1e-3, max_step: float = 1e-3,
                  enabled: bool = True) -> OnlinePredictor:
    model = load_model(save_constant(tmp_path / 'constant.pt', value, window=WINDOW,
                                     horizon=HORIZON))
    return OnlinePredictor(model, stream(), limits(max_compensation, max_step, enabled),
                           clock=(clock or FakeClock()).ns)


def predicted(output: Output) -> XY:
    """The prediction of an output that must carry one."""
    assert output.prediction is not None
    return output.prediction


def feed(core: OnlinePredictor, stamps: np.ndarray, reference: np.ndarray, tips: np.ndarray,
         clock: FakeClock | None = None) -> list[Output]:
    """Reference then pose of each sample; all outputs in order."""
    outputs: list[Output] = []
    for stamp, ref, tip in zip(stamps, reference, tips, strict=False):
        if clock is not None:
            clock.now += PERIOD
        outputs += core.add_reference(int(stamp), *ref)
        outputs += core.add_pose(int(stamp), *tip)
    return outputs


def test_predictions_equal_offline_ones_sample_for_sample(linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(60)
    core = OnlinePredictor(linear_model, stream(), limits(enabled=False), clock=FakeClock().ns)
    # poses arrive before the reference for odd samples: alignment waits, never pairs.
    outputs = []
    for i in range(len(stamps)):
        if i % 2:
            outputs += core.add_pose(int(stamps[i]), *tips[i])
            outputs += core.add_reference(int(stamps[i]), *reference[i])
        else:
            outputs += core.add_reference(int(stamps[i]), *reference[i])
            outputs += core.add_pose(int(stamps[i]), *tips[i])
    rows = feature_rows((stamps - stamps[0]) * 1e-9, tips - reference[:, :2], reference,
                        BRANCHES)
    ends = np.arange(NEEDED - 1, len(stamps))
    windows = np.stack([rows[e - WINDOW + 1:e + 1] for e in ends])
    offline = linear_model.predict(torch.from_numpy(windows)).numpy()
    assert [o.instant_ns for o in outputs] == list(stamps[ends] + HORIZON * PERIOD_NS)
    np.testing.assert_allclose(np.array([o.prediction for o in outputs]), offline,
                               rtol=0, atol=1e-12)
    assert all(o.compensation == (0.0, 0.0) for o in outputs)  # shadow mode


def test_reference_is_interpolated_to_pose_stamps(linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(20)
    core = OnlinePredictor(linear_model, stream(), limits(enabled=False), clock=FakeClock().ns)
    # references half a period later than the poses, at a slightly different rate
    ref_stamps = stamps[0] - PERIOD_NS // 2 + np.arange(25) * (PERIOD_NS * 4 // 5)
    ref_xy = np.stack([np.interp(ref_stamps, stamps, reference[:, a]) for a in (0, 1, 2)], -1)
    ref_xy += np.stack([1e-4 * np.sin(ref_stamps * 1e-9), 0 * ref_stamps, 0 * ref_stamps], -1)
    for stamp, ref in zip(ref_stamps, ref_xy, strict=False):
        core.add_reference(int(stamp), *ref)
    for stamp, tip in zip(stamps[:NEEDED], tips[:NEEDED], strict=False):
        core.add_pose(int(stamp), *tip)
    expected = np.stack([np.interp(stamps[:NEEDED], ref_stamps, ref_xy[:, a])
                         for a in (0, 1)], -1)
    rows = core.primary.window.rows()
    np.testing.assert_allclose(rows[:, 2:4], expected[HISTORY:], atol=1e-15)
    branch_v = np.diff(BRANCHES.along(np.column_stack([expected, np.full(NEEDED, Z)])),
                       axis=0) / PERIOD
    np.testing.assert_allclose(rows[:, 8:11], branch_v[HISTORY - 1:], rtol=1e-9)
    np.testing.assert_allclose(rows[:, 0:2], (tips[:NEEDED] - expected)[HISTORY:], atol=1e-15)


def test_a_slower_reference_still_brackets_every_pose(linear_model: LoadedModel) -> None:
    """The reference at a quarter of the pose rate (docs/interface.md, topics allows any rates):
    its steps of 4 periods exceed gap_factor (2.5) pose periods, yet no pose is faulted."""
    stamps, reference, tips = spiral(60)
    core = OnlinePredictor(linear_model, stream(), limits(enabled=False), clock=FakeClock().ns)
    outputs = []
    for i in range(len(stamps)):
        if i % 4 == 0:
            outputs += core.add_reference(int(stamps[i]), *reference[i])
        outputs += core.add_pose(int(stamps[i]), *tips[i])
    assert core.faults.total == 0 and core.dropped.total == 0
    # every pose up to the last reference is used, each full window predicts
    assert len(outputs) == 57 - NEEDED + 1
    assert core.primary.window.rows()[-1, 2:4] == pytest.approx(reference[56, :2], abs=1e-12)


def test_feature_rows_keep_nanosecond_stamps(linear_model: LoadedModel) -> None:
    """Stamps near 1.7e18 ns are not exact in float64 (256 ns steps): the window's rows use
    stamp differences taken in integers, as the trainer does."""
    stamps, reference, tips = spiral(NEEDED)
    stamps = stamps + np.arange(NEEDED) * 123  # jitter finer than float64 resolves
    core = OnlinePredictor(linear_model, stream(), limits(enabled=False), clock=FakeClock().ns)
    feed(core, stamps, reference, tips)
    rows = feature_rows((stamps - stamps[0]) * 1e-9, tips - reference[:, :2], reference,
                        BRANCHES)
    np.testing.assert_allclose(core.primary.window.rows(), rows[HISTORY:], rtol=1e-12, atol=0)


def test_a_model_of_other_features_or_for_another_robot_is_refused(tmp_path: Path) -> None:
    old = save_linear(tmp_path / 'old.pt', weight=np.zeros((WINDOW * len(OLD_FEATURES), 2)),
                      window=WINDOW, horizon=HORIZON, features=OLD_FEATURES)
    needs = r"'features' is \('error_x', .*'ref_ay'\), this configuration needs \(.*'ups3_a'\)"
    with pytest.raises(MetadataMismatchError, match=needs):
        OnlinePredictor(load_model(old), stream(), limits(), clock=FakeClock().ns)
    with pytest.raises(MetadataMismatchError, match=needs):  # as the node loads it
        load_model(old, expected={'features': FEATURES})
    other_robot = load_model(save_linear(tmp_path / 'r.pt', robot_sha256='0' * 64))
    with pytest.raises(MetadataMismatchError, match="'robot_description_sha256' is '0000"):
        OnlinePredictor(other_robot, stream(), limits(), clock=FakeClock().ns)
    # the predictor runs another description than the model was trained for
    packaged = load_robot_description()
    calibrated = RobotDescription(packaged.urdf_xml + '<!-- calibrated -->\n', 'calibrated.urdf')
    model = load_model(save_linear(tmp_path / 'm.pt', window=WINDOW, horizon=HORIZON))
    with pytest.raises(MetadataMismatchError,
                       match=f"'robot_description_sha256' is '{packaged.sha256}', this "
                             f"configuration needs '{calibrated.sha256}'"):
        OnlinePredictor(model, stream(), limits(), clock=FakeClock().ns,
                        chain=LomprChain(calibrated))
    core = OnlinePredictor(model, stream(), limits(), clock=FakeClock().ns,
                           chain=LomprChain(packaged))
    with pytest.raises(MetadataMismatchError, match="'robot_description_sha256'"):
        core.replace_model(other_robot)


def test_no_output_before_the_window_is_full(linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(NEEDED)
    core = OnlinePredictor(linear_model, stream(), limits(), clock=FakeClock().ns)
    assert feed(core, stamps[:-1], reference[:-1], tips[:-1]) == []
    assert core.primary.window.fill == NEEDED - 1
    assert len(feed(core, stamps[-1:], reference[-1:], tips[-1:])) == 1


def test_offset_is_clamped_to_max_compensation(tmp_path: Path) -> None:
    core = constant_core(tmp_path, (3e-3, -4e-3), max_compensation=1e-3, max_step=1.0)
    outputs = feed(core, *spiral(NEEDED + 3))
    np.testing.assert_allclose(predicted(outputs[0]), [3e-3, -4e-3])
    for output in outputs:  # direction kept, norm at the limit
        np.testing.assert_allclose(output.compensation, [-0.6e-3, 0.8e-3], atol=1e-15)
    assert core.gate.clamped == 4


def test_offset_changes_at_most_max_step_per_sample(tmp_path: Path) -> None:
    core = constant_core(tmp_path, (-50e-6, 0.0), max_compensation=1e-3, max_step=20e-6)
    outputs = feed(core, *spiral(NEEDED + 4))
    np.testing.assert_allclose([o.compensation[0] for o in outputs],
                               [20e-6, 40e-6, 50e-6, 50e-6, 50e-6], atol=1e-15)


@pytest.mark.faults
def test_a_gap_zeroes_once_and_output_resumes_after_refill(tmp_path: Path) -> None:
    core = constant_core(tmp_path, (-10e-6, 0.0))
    stamps, reference, tips = spiral(40)
    assert len(feed(core, stamps[:10], reference[:10], tips[:10])) == 10 - NEEDED + 1
    # samples 10..12 missing: a 4-period interval > gap_factor 2.5
    outputs = feed(core, stamps[13:13 + NEEDED], reference[13:13 + NEEDED], tips[13:13 + NEEDED])
    zero, resumed = outputs[0], outputs[1:]
    assert zero.reason == 'gap' and zero.prediction is None
    np.testing.assert_array_equal(zero.compensation, [0.0, 0.0])
    # the offsets published (up to sample 12) are all for instants before the gap sample:
    # one zero for the next instant
    assert zero.instant_ns == stamps[14]
    assert len(resumed) == 1 and resumed[0].instant_ns == stamps[12 + NEEDED] + HORIZON * PERIOD_NS
    assert core.faults['gap'] == 1


@pytest.mark.faults
def test_a_clock_jumping_back_zeroes_once_and_the_restarted_run_refills(
        tmp_path: Path) -> None:
    """A simulator reset: the clock goes back to the start and the samples start again. The
    offsets in force are cancelled once, the fault is counted, and the restarted streams
    refill the window with no other fault."""
    clock = FakeClock()
    core = constant_core(tmp_path, (-10e-6, 0.0), clock=clock)
    stamps, reference, tips = spiral(20)
    assert len(feed(core, stamps, reference, tips, clock)) == 20 - NEEDED + 1
    clock.now -= 20 * PERIOD
    zeros = core.clock_jumped_back(int(stamps[0]))
    # a zero for every instant after the newest pose an offset was published for
    assert [(z.reason, z.instant_ns) for z in zeros] == [
        ('clock_jump', int(stamps[19]) + k * PERIOD_NS) for k in range(1, HORIZON + 1)]
    assert all(not any(z.compensation) for z in zeros)
    assert core.primary.window.fill == 0 and core.faults['clock_jump'] == 1
    assert core.check_stale() == []
    outputs = feed(core, stamps[:NEEDED], reference[:NEEDED], tips[:NEEDED], clock)
    assert [o.reason for o in outputs] == [None]  # resumed after the refill, no other fault
    assert outputs[0].instant_ns == stamps[NEEDED - 1] + HORIZON * PERIOD_NS
    assert core.faults.total == 1


def test_reset_cancels_without_a_fault_and_starts_afresh(tmp_path: Path) -> None:
    core = constant_core(tmp_path, (-10e-6, 0.0))
    stamps, reference, tips = spiral(40)
    feed(core, stamps[:NEEDED], reference[:NEEDED], tips[:NEEDED])
    zeros = core.reset()
    assert [z.reason for z in zeros] == ['inactive']  # the one offset published
    assert core.faults.total == 0 and core.primary.window.fill == 0
    assert core.reset() == []  # nothing in force any more
    # later samples, after a long pause, start a new window without a fault
    outputs = feed(core, stamps[30:30 + NEEDED], reference[30:30 + NEEDED],
                   tips[30:30 + NEEDED])
    assert [o.reason for o in outputs] == [None] and core.faults.total == 0


@pytest.mark.faults
def test_stale_input_zeroes_once(tmp_path: Path) -> None:
    clock = FakeClock()
    core = constant_core(tmp_path, (-10e-6, 0.0), clock=clock)
    stamps, reference, tips = spiral(NEEDED + 2)
    feed(core, stamps, reference, tips, clock)
    clock.now += 4.9 * PERIOD
    assert core.check_stale() == []
    clock.now += 0.2 * PERIOD
    assert core.check_stale() == []  # once may be a busy executor: confirmed at the next call
    assert core.add_reference(int(stamps[-1]) + PERIOD_NS, 0.0, 0.0, Z) == []  # no pose: no use
    zeros = core.check_stale()  # a zero for each instant an offset was published for
    assert [z.instant_ns for z in zeros] == [stamps[-1] + k * PERIOD_NS for k in (1, 2, 3)]
    assert all(z.reason == 'stale' and not any(z.compensation) for z in zeros)
    clock.now += 10.0
    assert core.check_stale() == []
    assert core.primary.window.fill == 0


def test_staleness_has_a_floor_in_seconds(tmp_path: Path) -> None:
    """At 1 kHz, 5 periods are 5 ms, a stall any non-real-time process has now and then:
    the input is stale only after `stale_min_time` too."""
    assert stream(sample_period=1e-3, stale_min_time=0.05).stale_after == 0.05
    assert stream(stale_min_time=0.05).stale_after == pytest.approx(5 * PERIOD)  # 0.2 s
    clock = FakeClock()
    model = load_model(save_constant(tmp_path / 'constant.pt', (-10e-6, 0.0), window=WINDOW,
                                     horizon=HORIZON))
    core = OnlinePredictor(model, stream(stale_min_time=20 * PERIOD), limits(), clock=clock.ns)
    stamps, reference, tips = spiral(NEEDED + 2)
    feed(core, stamps, reference, tips, clock)
    for _ in range(2):  # two calls confirm; 19 periods is not yet stale
        clock.now += 9.5 * PERIOD
        assert core.check_stale() == []
    clock.now += 1.5 * PERIOD
    assert core.check_stale() == []
    assert [z.reason for z in core.check_stale()][:1] == ['stale']


@pytest.mark.faults
def test_poses_without_references_go_stale(tmp_path: Path) -> None:
    clock = FakeClock()
    core = constant_core(tmp_path, (-10e-6, 0.0), clock=clock)
    stamps, reference, tips = spiral(NEEDED + 8)
    feed(core, stamps[:NEEDED], reference[:NEEDED], tips[:NEEDED], clock)
    # the reference stream stopped
    for stamp, tip in zip(stamps[NEEDED:], tips[NEEDED:], strict=False):
        clock.now += PERIOD
        assert core.add_pose(int(stamp), *tip) == []
        zeros = core.check_stale()
        if zeros:
            break
    assert stamp == stamps[NEEDED + 6]  # the first waiting pose waited 5 periods, confirmed
    # the offsets published were for instants before the newest pose: one zero, next instant
    assert [(z.reason, z.instant_ns) for z in zeros] == [('stale', stamp + PERIOD_NS)]
    assert core.dropped['stale'] == 7 and core.primary.window.fill == 0


@pytest.mark.parametrize('fault', ['non_finite', 'out_of_order'])
@pytest.mark.faults
def test_bad_pose_zeroes_once_then_refills(tmp_path: Path, fault: str) -> None:
    core = constant_core(tmp_path, (-10e-6, 0.0))
    stamps, reference, tips = spiral(30)
    feed(core, stamps[:10], reference[:10], tips[:10])
    core.add_reference(int(stamps[10]), *reference[10])
    bad_stamp = int(stamps[5]) if fault == 'out_of_order' else int(stamps[10])
    bad_x = math.nan if fault == 'non_finite' else tips[10, 0]
    zeros = core.add_pose(bad_stamp, bad_x, tips[10, 1])
    # the offsets for the instants of samples 10..12 (published from 7..9) are cancelled
    assert [z.instant_ns for z in zeros] == list(stamps[10:13])
    assert {z.reason for z in zeros} == {fault}
    assert core.faults[fault] == 1 and core.dropped[fault] == 1
    assert core.add_pose(bad_stamp, bad_x, tips[10, 1]) == []  # the fault is not repeated
    outputs = feed(core, stamps[11:11 + NEEDED], reference[11:11 + NEEDED],
                   tips[11:11 + NEEDED])
    assert [o.reason for o in outputs] == [None]


@pytest.mark.faults
def test_duplicates_are_dropped_without_a_fault(linear_model: LoadedModel) -> None:
    core = OnlinePredictor(linear_model, stream(), limits(), clock=FakeClock().ns)
    stamps, reference, tips = spiral(NEEDED + 2)
    first = feed(core, stamps, reference, tips)
    assert core.add_pose(int(stamps[-1]), *tips[-1]) == []
    assert core.add_reference(int(stamps[-1]), *reference[-1]) == []
    assert core.dropped['duplicate'] == 1 and core.dropped['reference_duplicate'] == 1
    assert core.faults.total == 0 and len(first) == 3


def test_plant_error_subtracts_the_compensation_published_for_that_instant(tmp_path: Path) -> None:
    core = constant_core(tmp_path, (-30e-6, 12e-6), max_step=1.0)
    stamps, reference, tips = spiral(NEEDED + HORIZON + 2)
    outputs = feed(core, stamps, reference, tips)
    published = {o.instant_ns: o.compensation for o in outputs}
    rows = core.primary.window.rows()
    last = len(stamps) - 1
    np.testing.assert_allclose(published[int(stamps[last])], [30e-6, -12e-6])
    np.testing.assert_allclose(rows[-1, 0:2],
                               tips[last] - reference[last, :2] - [30e-6, -12e-6],
                               atol=1e-15)
    assert int(stamps[last - HORIZON]) not in published  # before the first offset: c = 0
    before = last - HORIZON
    np.testing.assert_allclose(rows[-HORIZON - 1, 0:2], tips[before] - reference[before, :2],
                               atol=1e-15)


def test_live_accuracy_is_rms_of_truth_minus_prediction(tmp_path: Path) -> None:
    core = constant_core(tmp_path, (5e-6, -5e-6), enabled=False)
    stamps, reference, _ = spiral(NEEDED + HORIZON + 10)
    tips = reference[:, :2] + np.array([8e-6, 1e-6])  # a constant true error
    feed(core, stamps, reference, tips)
    rms, count = core.accuracy.rms()
    assert count == 11
    np.testing.assert_allclose(rms, [3e-6, 6e-6], atol=1e-15)


@pytest.mark.faults
def test_inference_failure_zeroes_once(tmp_path: Path) -> None:
    path = save_model(tmp_path / 'failing.pt', FailingModel(threshold=0.01),
                      metadata(window=WINDOW, horizon=HORIZON))
    core = OnlinePredictor(load_model(path), stream(), limits(), clock=FakeClock().ns)
    stamps, reference, tips = spiral(120)
    outputs = feed(core, stamps, reference, tips)
    assert outputs[0].reason is None
    # one cancellation: zeros for the instants (after the failing sample) already offset
    assert [o.reason for o in outputs if o.reason] == ['inference'] * (HORIZON - 1)
    assert core.faults['inference'] > 1  # every later window fails again, silently


@pytest.mark.faults
def test_off_rate_input_never_fills_the_window(linear_model: LoadedModel) -> None:
    core = OnlinePredictor(linear_model, stream(), limits(), clock=FakeClock().ns)
    _, reference, tips = spiral(30)
    fast = T0 + np.arange(30) * (PERIOD_NS // 10)
    assert feed(core, fast, reference, tips) == []
    assert core.faults['off_rate'] == 29


# -- bad input: any message sequence keeps the offset finite and bounded -----------------

# Runs of samples (an event repeated), so that windows fill and offsets flow between bad ones.
EVENT = st.tuples(
    st.sampled_from(['both'] * 4 + ['pose', 'reference', 'stale']),
    st.sampled_from([1] * 6 + [0, -1, -3, 2, 4]),  # stamp step in periods (0: duplicate)
    st.sampled_from([0.0, 1e-5, -2e-4, 5e-3, 1e300, math.nan, math.inf]),  # error [m]
    st.sampled_from([1, 2, 8, 15]),  # times in a row
)


@settings(max_examples=100, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(events=st.lists(EVENT, min_size=1, max_size=40))
@pytest.mark.faults
def test_random_sequences_never_give_a_bad_offset(
        tmp_path: Path, events: list[tuple[str, int, float, int]]) -> None:
    path = tmp_path / 'amplified.pt'
    if not path.exists():
        save_linear(path, window=WINDOW, horizon=HORIZON,
                    weight=np.full((WINDOW * len(FEATURES), 2), 3.0), bias=(1e-3, -1e-3))
    clock = FakeClock()
    core = OnlinePredictor(load_model(path), stream(),
                           limits(max_compensation=1e-4, max_step=2e-5), clock=clock.ns)
    stamp = T0
    outputs = []
    for kind, step, error, repeat in events:
        for _ in range(repeat):
            stamp += step * PERIOD_NS
            clock.now += PERIOD
            x = 0.1 * math.sin(stamp * 1e-9)
            if kind == 'stale':
                clock.now += 10 * PERIOD
                outputs += core.check_stale()
                continue
            if kind in ('reference', 'both'):
                outputs += core.add_reference(stamp, x, 0.0, Z)
            if kind in ('pose', 'both'):
                outputs += core.add_pose(stamp, x + error, error)
    previous: XY = (0.0, 0.0)
    for output in outputs:
        assert np.isfinite(output.compensation).all()
        assert np.hypot(*output.compensation) <= 1e-4 * (1 + 1e-12)
        if output.reason:
            assert not any(output.compensation)
        else:
            assert np.isfinite(predicted(output)).all()
            assert np.hypot(*np.subtract(output.compensation, previous)) <= 2e-5 * (1 + 1e-12)
        previous = output.compensation


# -- faults: a bound lowered at run time holds from the next output ------------------------

@pytest.mark.faults
def test_a_lowered_clamp_holds_from_the_next_output() -> None:
    gate = OffsetGate(CompensationLimits(5e-4, 5e-5, True), PERIOD_NS)
    for k in range(20):  # ramp to the clamp: 500 um in force, offsets out for 3 instants ahead
        gate.publish(T0 + (k + 3) * PERIOD_NS, (-1e-3, 0.0), T0 + k * PERIOD_NS)
    assert math.hypot(*gate.offset_in_force) == pytest.approx(5e-4)
    newest = T0 + 19 * PERIOD_NS
    reissued = gate.set_limits(CompensationLimits(1e-6, 5e-5, True), newest)
    # the offsets already out for instants to come are re-issued within the new clamp
    assert [o.instant_ns for o in reissued] == [T0 + k * PERIOD_NS for k in (20, 21, 22)]
    assert all(o.reason == 'clamp_lowered' for o in reissued)
    assert all(math.hypot(*o.compensation) <= 1e-6 * (1 + 1e-12) for o in reissued)
    following = [gate.publish(T0 + (k + 3) * PERIOD_NS, (-1e-3, 0.0),
                              T0 + k * PERIOD_NS).compensation for k in range(20, 30)]
    assert max(math.hypot(*c) for c in following) <= 1e-6 * (1 + 1e-12)  # not 450, 400, ... um


LIMITS = st.tuples(st.sampled_from([0.0, 1e-6, 2e-5, 1e-4, 5e-4, 1e-2]),  # max_compensation
                   st.sampled_from([0.0, 1e-7, 5e-6, 5e-5, 1e-2]),  # max_step
                   st.sampled_from([True, True, True, False]),  # enabled
                   st.sampled_from([0.0, 0.0, 1.0, 15.0, 1e3]))  # bandwidth [Hz]
EVENT = st.one_of(
    st.tuples(st.just('limits'), LIMITS),
    st.tuples(st.just('sample'),
              st.tuples(st.sampled_from([1] * 8 + [0, 2, 4, -1]),  # stamp step [periods]
                        st.sampled_from([0.0, 3e-5, -4e-4, 2e-3, math.nan]),  # error [m]
                        st.integers(1, 12))),  # samples in a row
)


@pytest.mark.faults
@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(start=LIMITS, events=st.lists(EVENT, min_size=1, max_size=30))
def test_clamp_and_slew_are_never_exceeded_under_random_parameter_changes(
        amplified: LoadedModel, start: tuple[float, float, bool, float],
        events: list[tuple[str, Any]]) -> None:
    """Property: every offset published is within the clamp in force when it is published;
    every offset from a prediction differs from the one the slew starts from (the previous
    one, clamped by a lowered limit, zero after a cancel) by at most the step in force,
    whatever the low-pass;
    a cancel is zero; shadow mode publishes zeros."""
    core = OnlinePredictor(amplified, stream(), CompensationLimits(*start), clock=lambda: 0)
    limits = CompensationLimits(*start)
    slew_from = np.zeros(2)
    stamp, k = T0, 0

    def check(outputs: list[Output]) -> None:
        nonlocal slew_from
        for output in outputs:
            offset = output.compensation
            assert np.isfinite(offset).all()
            assert math.hypot(*offset) <= limits.max_compensation * (1 + 1e-9) + 1e-18
            if output.reason == 'clamp_lowered':
                continue  # a re-issue of an offset already out, scaled into the new clamp
            if output.reason or not limits.enabled:
                assert not any(offset)
            else:
                step = math.hypot(*np.subtract(offset, slew_from))
                assert step <= limits.max_step * (1 + 1e-9) + 1e-18
            slew_from = np.asarray(offset)

    for kind, value in events:
        if kind == 'limits':
            limits = CompensationLimits(*value)
            check(core.set_limits(limits))
            norm = math.hypot(*slew_from)
            if norm > limits.max_compensation:  # the slew starts from the clamped offset
                slew_from = slew_from * (limits.max_compensation / norm)
            continue
        step, error, repeat = value
        for _ in range(repeat):
            stamp += step * PERIOD_NS
            k += 1
            x, y = spiral_xy(k)
            check(core.add_reference(stamp, x, y, Z))
            check(core.add_pose(stamp, x + error, y - error))


@pytest.fixture(scope='module')
def amplified(tmp_path_factory: pytest.TempPathFactory) -> LoadedModel:
    """A linear model with large gains: predictions of millimetres, far beyond the clamp."""
    path = tmp_path_factory.mktemp('models') / 'amplified.pt'
    save_linear(path, window=WINDOW, horizon=HORIZON,
                weight=np.full((WINDOW * len(FEATURES), 2), 3.0), bias=(1e-3, -1e-3))
    return load_model(path)


# -- faults: impossible stamps are dropped, counted ----------------------------------------

@pytest.mark.faults
@pytest.mark.parametrize(('sec', 'nanosec', 'reason'), [
    (-5, 0, StampReason.BAD_STAMP), (10, 1_000_000_000, StampReason.BAD_STAMP),
    (10, 4_000_000_000, StampReason.BAD_STAMP), (2_000, 0, StampReason.FUTURE_STAMP),
    (1_000, 0, None), (1_000, 999_999_999, None)])
def test_stamp_problems(sec: int, nanosec: int, reason: StampReason | None) -> None:
    def reason_of(now: int, max_future_ns: int | None) -> StampReason | None:
        problem = stamp_problem(sec, nanosec, now, max_future_ns)
        return None if problem is None else problem.reason

    now = 1_000 * 1_000_000_000
    assert reason_of(now, 1_000_000_000) == reason
    bad_only = reason if reason == StampReason.BAD_STAMP else None
    assert reason_of(0, 1_000_000_000) == bad_only  # sim time before /clock
    assert reason_of(now, None) == bad_only  # no future check


@pytest.mark.faults
def test_the_core_drops_impossible_stamps_counted(amplified: LoadedModel) -> None:
    now = T0 + 100 * PERIOD_NS
    core = OnlinePredictor(amplified, stream(), CompensationLimits(1e-4, 1e-5, True),
                           clock=lambda: now)
    for sec, nanosec in ((-1, 0), (1, 2_000_000_000), (T0 // 10**9 + 3600, 0)):
        stamp = SimpleNamespace(sec=sec, nanosec=nanosec)
        assert core.add_reference(stamp, 0.0, 0.0, Z) == []
        assert core.add_pose(stamp, 0.0, 0.0) == []
    dropped = core.dropped.counts()
    assert (dropped['bad_stamp'], dropped['future_stamp']) == (2, 1)
    assert (dropped['reference_bad_stamp'], dropped['reference_future_stamp']) == (2, 1)
    assert core.primary.window.fill == 0
    assert str(core.last_bad_stamp).startswith('pose_future_stamp')


# -- faults: a model giving NaN or raising -------------------------------------------------

class NanAfter(torch.nn.Module):
    """Predicts zero, then NaN once the last reference x exceeds `threshold`."""

    def __init__(self, threshold: float) -> None:
        super().__init__()
        self.threshold = threshold

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        out = torch.zeros((windows.shape[0], 2), dtype=torch.float64)
        if bool((windows[:, -1, 2] > self.threshold).any()):
            out = out + float('nan')
        return out


@pytest.mark.faults
def test_a_model_giving_nan_cancels_and_is_counted(tmp_path: Path) -> None:
    path = tmp_path / 'nan.pt'
    model_file.save_model(path, NanAfter(0.095), metadata(window=WINDOW, horizon=HORIZON))
    core = OnlinePredictor(load_model(path), stream(), CompensationLimits(1e-3, 1e-3, True),
                           clock=lambda: 0)
    outputs = []
    for k in range(40):  # reference x = 0.1 cos(0.05 k) is above 0.095 up to k = 6
        x, y = spiral_xy(k)
        outputs += core.add_reference(T0 + k * PERIOD_NS, x, y, Z)
        outputs += core.add_pose(T0 + k * PERIOD_NS, x, y)
    assert core.faults['inference'] >= 1
    assert all(np.isfinite(o.compensation).all() for o in outputs)
    assert all(o.prediction is None or np.isfinite(o.prediction).all() for o in outputs)


class RecordingTimer:
    """A `StageTimer` writing down what it is told."""

    def __init__(self) -> None:
        self.told: list[str] = []

    def begin(self) -> None:
        self.told.append('begin')

    def end(self, stage: str) -> None:
        self.told.append(stage)


def test_the_stage_timer_hears_every_stage_of_a_predicting_sample_in_order(
        linear_model: LoadedModel) -> None:
    """The benches' view of the core's stages (bench/stage_timing.py names the core's own
    methods): every stage of a sample that predicts, in order."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / 'bench'))
    from stage_timing import STAGES, time_stages

    stamps, reference, tips = spiral(NEEDED)
    core = OnlinePredictor(linear_model, stream(), limits(), clock=lambda: int(stamps[-1]))
    for i in range(NEEDED - 1):
        core.add_reference(int(stamps[i]), *reference[i])
        core.add_pose(int(stamps[i]), *tips[i])
    timer = RecordingTimer()
    time_stages(core, timer)
    core.add_reference(int(stamps[-1]), *reference[-1])  # no pose waits for it
    assert timer.told == ['begin', 'stamp', 'alignment']
    timer.told.clear()
    assert len(core.add_pose(int(stamps[-1]), *tips[-1])) == 1
    assert timer.told == ['begin', *STAGES]


def test_onnx_runtime_in_the_core_gives_the_torchscript_outputs(linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(40)
    backend, why = select_backend(linear_model, 'onnxruntime')
    assert why is None
    cores = [OnlinePredictor(linear_model, stream(), limits(max_step=5e-6),
                             clock=FakeClock().ns, backend=chosen) for chosen in (backend, None)]
    outputs: list[list[Output]] = [[], []]
    for core, out in zip(cores, outputs, strict=True):
        for i in range(len(stamps)):
            out += core.add_reference(int(stamps[i]), *reference[i])
            out += core.add_pose(int(stamps[i]), *tips[i])
    assert [core.primary.backend.name for core in cores] == ['onnxruntime', 'torchscript']
    assert len(outputs[0]) == len(stamps) - NEEDED + 1
    np.testing.assert_allclose([predicted(o) for o in outputs[0]],
                               [predicted(o) for o in outputs[1]], rtol=1e-6, atol=1e-15)


def test_a_swapped_in_backend_binds_each_window_view_once_when_first_read(
        linear_model: LoadedModel) -> None:
    """A swap binds nothing at once (a call bound per view of the window, all at the swap,
    would hold the sample path a sample period or more): each view the first time it is
    read, once, and the predictions are those of a core that ran the model throughout."""
    stamps, reference, tips = spiral(300)
    backend, _ = select_backend(linear_model, 'onnxruntime')
    bound: list[int] = []

    class CountingBackend:
        name = backend.name

        def runner(self, window: np.ndarray) -> Any:
            bound.append(window.ctypes.data)
            return backend.runner(window)

    swapped, throughout = (OnlinePredictor(linear_model, stream(), limits(),
                                           clock=FakeClock().ns, backend=backend)
                           for _ in range(2))
    outputs: list[list[Output]] = [[], []]
    for i in range(len(stamps)):
        if i == 30:
            swapped.replace_model(linear_model, CountingBackend())
            assert bound == []
            answered = swapped.primary.answers
        for core, out in zip((swapped, throughout), outputs, strict=True):
            out += core.add_reference(int(stamps[i]), *reference[i])
            out += core.add_pose(int(stamps[i]), *tips[i])
    views = len(swapped.primary.window.arrays)
    assert swapped.primary.answers - answered > views > 1
    assert len(bound) == len(set(bound)) == views
    assert [predicted(o) for o in outputs[0]] == [predicted(o) for o in outputs[1]]
