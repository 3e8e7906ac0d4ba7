"""OnlinePredictor (ROS-free): offline parity, alignment by stamp, plant error, safety."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from model_helpers import FailingModel, metadata, save_constant, save_linear

from lompr_predictor.data.features import FEATURES, HISTORY, feature_rows
from lompr_predictor.learning.model_file import (
    LoadedModel,
    MetadataMismatchError,
    load_model,
    save_model,
)
from lompr_predictor.online.inference import select_backend
from lompr_predictor.online.offset import XY
from lompr_predictor.online.predictor import (
    STAGES,
    CompensationLimits,
    OnlinePredictor,
    Output,
    StreamSettings,
)
from lompr_predictor.robot.description import RobotDescription, load_robot_description
from lompr_predictor.robot.kinematics import VerticalToolBranches

PERIOD = 0.04
PERIOD_NS = 40_000_000
T0 = 1_700_000_000_000_000_000  # a realistic epoch stamp [ns]
WINDOW, HORIZON = 4, 3
NEEDED = WINDOW + HISTORY
Z = 1.097  # the mirror's height [m]
BRANCHES = VerticalToolBranches(load_robot_description().geometry)
#: The features of the model files written before the branch columns came (issue 10).
OLD_FEATURES = ('error_x', 'error_y', 'ref_x', 'ref_y', 'ref_vx', 'ref_vy', 'ref_ax', 'ref_ay')


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def stream(sample_period: float = PERIOD, stale_min_time: float = 0.0) -> StreamSettings:
    return StreamSettings(sample_period=sample_period, gap_factor=2.5, min_interval_factor=0.5,
                          stale_periods=5.0, accuracy_samples=1000,
                          stale_min_time=stale_min_time)


def limits(max_compensation: float = 1e-3, max_step: float = 1e-3,
           enabled: bool = True) -> CompensationLimits:
    return CompensationLimits(max_compensation, max_step, enabled)


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
                           clock or FakeClock())


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
    core = OnlinePredictor(linear_model, stream(), limits(enabled=False), FakeClock())
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
    core = OnlinePredictor(linear_model, stream(), limits(enabled=False), FakeClock())
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
    rows = core.window_rows()
    np.testing.assert_allclose(rows[:, 2:4], expected[HISTORY:], atol=1e-15)
    branch_v = np.diff(BRANCHES.along(np.column_stack([expected, np.full(NEEDED, Z)])),
                       axis=0) / PERIOD
    np.testing.assert_allclose(rows[:, 8:11], branch_v[HISTORY - 1:], rtol=1e-9)
    np.testing.assert_allclose(rows[:, 0:2], (tips[:NEEDED] - expected)[HISTORY:], atol=1e-15)


def test_a_slower_reference_still_brackets_every_pose(linear_model: LoadedModel) -> None:
    """The reference at a quarter of the pose rate (CONTRACT section 2 allows any rates):
    its steps of 4 periods exceed gap_factor (2.5) pose periods, yet no pose is faulted."""
    stamps, reference, tips = spiral(60)
    core = OnlinePredictor(linear_model, stream(), limits(enabled=False), FakeClock())
    outputs = []
    for i in range(len(stamps)):
        if i % 4 == 0:
            outputs += core.add_reference(int(stamps[i]), *reference[i])
        outputs += core.add_pose(int(stamps[i]), *tips[i])
    assert core.faults.total == 0 and core.dropped.total == 0
    # every pose up to the last reference is used, each full window predicts
    assert len(outputs) == 57 - NEEDED + 1
    assert core.window_rows()[-1, 2:4] == pytest.approx(reference[56, :2], abs=1e-12)


def test_feature_rows_keep_nanosecond_stamps(linear_model: LoadedModel) -> None:
    """Stamps near 1.7e18 ns are not exact in float64 (256 ns steps): the window's rows use
    stamp differences taken in integers, as the trainer does."""
    stamps, reference, tips = spiral(NEEDED)
    stamps = stamps + np.arange(NEEDED) * 123  # jitter finer than float64 resolves
    core = OnlinePredictor(linear_model, stream(), limits(enabled=False), FakeClock())
    feed(core, stamps, reference, tips)
    rows = feature_rows((stamps - stamps[0]) * 1e-9, tips - reference[:, :2], reference,
                        BRANCHES)
    np.testing.assert_allclose(core.window_rows(), rows[HISTORY:], rtol=1e-12, atol=0)


def test_a_model_of_other_features_or_for_another_robot_is_refused(tmp_path: Path) -> None:
    old = save_linear(tmp_path / 'old.pt', weight=np.zeros((WINDOW * len(OLD_FEATURES), 2)),
                      window=WINDOW, horizon=HORIZON, features=OLD_FEATURES)
    needs = r"'features' is \('error_x', .*'ref_ay'\), this configuration needs \(.*'ups3_a'\)"
    with pytest.raises(MetadataMismatchError, match=needs):
        OnlinePredictor(load_model(old), stream(), limits(), FakeClock())
    with pytest.raises(MetadataMismatchError, match=needs):  # as the node loads it
        load_model(old, expected={'features': FEATURES})
    other_robot = load_model(save_linear(tmp_path / 'r.pt', robot_sha256='0' * 64))
    with pytest.raises(MetadataMismatchError, match="'robot_description_sha256' is '0000"):
        OnlinePredictor(other_robot, stream(), limits(), FakeClock())
    # the predictor runs another description than the model was trained for
    packaged = load_robot_description()
    calibrated = RobotDescription(packaged.urdf_xml + '<!-- calibrated -->\n', 'calibrated.urdf')
    model = load_model(save_linear(tmp_path / 'm.pt', window=WINDOW, horizon=HORIZON))
    with pytest.raises(MetadataMismatchError,
                       match=f"'robot_description_sha256' is '{packaged.sha256}', this "
                             f"configuration needs '{calibrated.sha256}'"):
        OnlinePredictor(model, stream(), limits(), FakeClock(), description=calibrated)
    core = OnlinePredictor(model, stream(), limits(), FakeClock(), description=packaged)
    with pytest.raises(MetadataMismatchError, match="'robot_description_sha256'"):
        core.replace_model(other_robot)


def test_no_output_before_the_window_is_full(linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(NEEDED)
    core = OnlinePredictor(linear_model, stream(), limits(), FakeClock())
    assert feed(core, stamps[:-1], reference[:-1], tips[:-1]) == []
    assert core.window_fill == NEEDED - 1
    assert len(feed(core, stamps[-1:], reference[-1:], tips[-1:])) == 1


def test_offset_is_clamped_to_max_compensation(tmp_path: Path) -> None:
    core = constant_core(tmp_path, (3e-3, -4e-3), max_compensation=1e-3, max_step=1.0)
    outputs = feed(core, *spiral(NEEDED + 3))
    np.testing.assert_allclose(predicted(outputs[0]), [3e-3, -4e-3])
    for output in outputs:  # direction kept, norm at the limit
        np.testing.assert_allclose(output.compensation, [-0.6e-3, 0.8e-3], atol=1e-15)
    assert core.clamped == 4


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
    assert core.window_fill == 0 and core.faults['clock_jump'] == 1
    assert core.check_stale() == []
    outputs = feed(core, stamps[:NEEDED], reference[:NEEDED], tips[:NEEDED], clock)
    assert [o.reason for o in outputs] == ['']  # resumed after the refill, no other fault
    assert outputs[0].instant_ns == stamps[NEEDED - 1] + HORIZON * PERIOD_NS
    assert core.faults.total == 1


def test_reset_cancels_without_a_fault_and_starts_afresh(tmp_path: Path) -> None:
    core = constant_core(tmp_path, (-10e-6, 0.0))
    stamps, reference, tips = spiral(40)
    feed(core, stamps[:NEEDED], reference[:NEEDED], tips[:NEEDED])
    zeros = core.reset('inactive')
    assert [z.reason for z in zeros] == ['inactive']  # the one offset published
    assert core.faults.total == 0 and core.window_fill == 0
    assert core.reset('inactive') == []  # nothing in force any more
    # later samples, after a long pause, start a new window without a fault
    outputs = feed(core, stamps[30:30 + NEEDED], reference[30:30 + NEEDED],
                   tips[30:30 + NEEDED])
    assert [o.reason for o in outputs] == [''] and core.faults.total == 0


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
    assert core.window_fill == 0


def test_staleness_has_a_floor_in_seconds(tmp_path: Path) -> None:
    """At 1 kHz, 5 periods are 5 ms, a stall any non-real-time process has now and then:
    the input is stale only after `stale_min_time` too."""
    assert stream(sample_period=1e-3, stale_min_time=0.05).stale_after == 0.05
    assert stream(stale_min_time=0.05).stale_after == pytest.approx(5 * PERIOD)  # 0.2 s
    clock = FakeClock()
    model = load_model(save_constant(tmp_path / 'constant.pt', (-10e-6, 0.0), window=WINDOW,
                                     horizon=HORIZON))
    core = OnlinePredictor(model, stream(stale_min_time=20 * PERIOD), limits(), clock)
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
    assert core.dropped['stale'] == 7 and core.window_fill == 0


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
    assert [o.reason for o in outputs] == ['']


@pytest.mark.faults
def test_duplicates_are_dropped_without_a_fault(linear_model: LoadedModel) -> None:
    core = OnlinePredictor(linear_model, stream(), limits(), FakeClock())
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
    rows = core.window_rows()
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
    rms, count = core.accuracy()
    assert count == 11
    np.testing.assert_allclose(rms, [3e-6, 6e-6], atol=1e-15)


@pytest.mark.faults
def test_inference_failure_zeroes_once(tmp_path: Path) -> None:
    path = save_model(tmp_path / 'failing.pt', FailingModel(threshold=0.01),
                      metadata(window=WINDOW, horizon=HORIZON))
    core = OnlinePredictor(load_model(path), stream(), limits(), FakeClock())
    stamps, reference, tips = spiral(120)
    outputs = feed(core, stamps, reference, tips)
    assert outputs[0].reason == ''
    # one cancellation: zeros for the instants (after the failing sample) already offset
    assert [o.reason for o in outputs if o.reason] == ['inference'] * (HORIZON - 1)
    assert core.faults['inference'] > 1  # every later window fails again, silently


@pytest.mark.faults
def test_off_rate_input_never_fills_the_window(linear_model: LoadedModel) -> None:
    core = OnlinePredictor(linear_model, stream(), limits(), FakeClock())
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
                           limits(max_compensation=1e-4, max_step=2e-5), clock)
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
    stamps, reference, tips = spiral(NEEDED)
    core = OnlinePredictor(linear_model, stream(), limits(), FakeClock(),
                           now_ns=lambda: int(stamps[-1]))
    for i in range(NEEDED - 1):
        core.add_reference(int(stamps[i]), *reference[i])
        core.add_pose(int(stamps[i]), *tips[i])
    timer = RecordingTimer()
    core.stage_timer = timer
    core.add_reference(int(stamps[-1]), *reference[-1])  # no pose waits for it
    assert timer.told == ['begin', 'stamp', 'alignment']
    timer.told.clear()
    assert len(core.add_pose(int(stamps[-1]), *tips[-1])) == 1
    assert timer.told == ['begin', *STAGES]


def test_onnx_runtime_in_the_core_gives_the_torchscript_outputs(linear_model: LoadedModel) -> None:
    stamps, reference, tips = spiral(40)
    backend, why = select_backend(linear_model, 'onnxruntime')
    assert why == ''
    cores = [OnlinePredictor(linear_model, stream(), limits(max_step=5e-6), FakeClock(),
                             backend=chosen) for chosen in (backend, None)]
    outputs: list[list[Output]] = [[], []]
    for core, out in zip(cores, outputs, strict=True):
        for i in range(len(stamps)):
            out += core.add_reference(int(stamps[i]), *reference[i])
            out += core.add_pose(int(stamps[i]), *tips[i])
    assert [core.backend.name for core in cores] == ['onnxruntime', 'torchscript']
    assert len(outputs[0]) == len(stamps) - NEEDED + 1
    np.testing.assert_allclose([predicted(o) for o in outputs[0]],
                               [predicted(o) for o in outputs[1]], rtol=1e-6, atol=1e-15)
