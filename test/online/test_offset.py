# SPDX-License-Identifier: Apache-2.0
"""online.offset alone: clamp, low-pass, step limit, schedule by instant, cancel, shadow
mode."""

from __future__ import annotations

import numpy as np
import pytest

from lompr_predictor.online.faults import FaultReason
from lompr_predictor.online.offset import (
    XY,
    CompensationLimits,
    InstantSchedule,
    OffsetGate,
    smoothing_factor,
)
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.twin.digital_twin import DigitalTwin
from lompr_predictor.twin.parameters import load_twin_parameters

PERIOD_NS = 40_000_000
T0 = 1_700_000_000_000_000_000


def at(k: int) -> int:
    return T0 + k * PERIOD_NS


def held(value: XY | None) -> XY:
    """A value the schedule must hold."""
    assert value is not None
    return value


def gate(max_compensation: float = 1e-3, max_step: float = 1.0,
         enabled: bool = True, bandwidth: float = 0.0) -> OffsetGate:
    return OffsetGate(CompensationLimits(max_compensation, max_step, enabled, bandwidth),
                      PERIOD_NS)


def test_the_offset_is_clamped_in_norm_with_its_direction_kept() -> None:
    offsets = gate(max_compensation=1e-3)
    output = offsets.publish(at(3), (3e-3, -4e-3), at(0))
    np.testing.assert_allclose(output.compensation, [-0.6e-3, 0.8e-3], rtol=0, atol=1e-15)
    np.testing.assert_allclose(held(output.prediction), [3e-3, -4e-3])
    assert (output.instant_ns, output.reason, output.sample_stamp_ns) == (at(3), None, at(0))
    small = offsets.publish(at(4), (-3e-4, 4e-4), at(1))  # 0.5 mm: not clamped
    np.testing.assert_allclose(small.compensation, [3e-4, -4e-4], rtol=0, atol=1e-15)
    assert offsets.clamped == 1


def test_the_offset_ramps_by_at_most_max_step() -> None:
    offsets = gate(max_step=20e-6)
    compensations = [offsets.publish(at(k), (-50e-6, 0.0), at(k)).compensation[0]
                     for k in range(5)]
    np.testing.assert_allclose(compensations, [20e-6, 40e-6, 50e-6, 50e-6, 50e-6], atol=1e-15)
    assert offsets.step_limited == 2
    np.testing.assert_allclose(offsets.offset_in_force, [50e-6, 0.0], atol=1e-15)


def test_the_offset_follows_a_step_as_a_first_order_low_pass_of_its_bandwidth() -> None:
    # 2 Hz at 25 Hz: the share per instant is 1 - exp(-2 pi 2 0.04) = 0.39508...
    share = 1.0 - np.exp(-2.0 * np.pi * 2.0 * 0.04)
    assert smoothing_factor(2.0, PERIOD_NS) == pytest.approx(0.3950774, abs=1e-7)
    offsets = gate(bandwidth=2.0)
    compensations = [offsets.publish(at(k), (-100e-6, 0.0), at(k)).compensation[0]
                     for k in range(4)]
    expected = [100e-6 * (1.0 - (1.0 - share) ** (k + 1)) for k in range(4)]
    np.testing.assert_allclose(compensations, expected, rtol=0, atol=1e-15)
    assert offsets.step_limited == 0


def test_a_low_pass_offset_never_alternates_at_the_sample_rate() -> None:
    # a prediction alternating +-100 um from one instant to the next (all the servo cannot
    # follow): 1 Hz at 25 Hz leaves +-12.5 um of it, share / (2 - share) of the swing
    share = smoothing_factor(1.0, PERIOD_NS)
    offsets = gate(bandwidth=1.0)
    compensations = [offsets.publish(at(k), ((-1) ** k * 100e-6, 0.0), at(k)).compensation[0]
                     for k in range(200)]
    settled = np.array(compensations[100:])
    np.testing.assert_allclose(np.abs(settled), 100e-6 * share / (2.0 - share), rtol=1e-9)
    assert np.all(np.sign(settled[:-1]) != np.sign(settled[1:]))


def test_without_a_bandwidth_the_offset_is_minus_the_prediction_to_the_bit() -> None:
    offsets = gate(bandwidth=0.0)
    for k, value in enumerate((1.234567e-4, -3.21e-5, 7.77e-6)):
        assert offsets.publish(at(k), (value, -value), at(k)).compensation == (-value, value)
    assert smoothing_factor(0.0, PERIOD_NS) == 1.0


def test_a_new_bandwidth_holds_from_the_next_offset() -> None:
    offsets = gate(bandwidth=0.0)
    assert offsets.publish(at(0), (-100e-6, 0.0), at(0)).compensation[0] == 100e-6
    offsets.set_limits(CompensationLimits(1e-3, 1.0, True, 2.0), at(0))
    halfway = offsets.publish(at(1), (0.0, 0.0), at(1)).compensation[0]
    assert halfway == pytest.approx(100e-6 * (1.0 - smoothing_factor(2.0, PERIOD_NS)), abs=1e-15)


def test_what_was_published_is_found_by_instant_within_half_a_period() -> None:
    offsets = gate()
    offsets.publish(at(5), (1e-5, 2e-5), at(2))
    offsets.publish(at(6), (3e-5, 4e-5), at(3))
    assert offsets.offset_for(at(4)) is None and offsets.prediction_for(at(4)) is None
    late = at(5) + PERIOD_NS // 2 - 1  # a late clock
    offset, prediction = offsets.offset_for(late), offsets.prediction_for(late)
    np.testing.assert_allclose(held(offset), [-1e-5, -2e-5])
    np.testing.assert_allclose(held(prediction), [1e-5, 2e-5])
    assert offsets.offset_for(at(5)) is None  # taken once
    assert offsets.prediction_for(at(5)) is None
    offset = offsets.offset_for(at(6))
    np.testing.assert_allclose(held(offset), [-3e-5, -4e-5])


def test_cancel_zeroes_every_future_instant_once() -> None:
    offsets = gate()
    for k in range(3):  # offsets for instants 3, 4, 5, made from poses 0, 1, 2
        offsets.publish(at(k + 3), (-1e-5, 0.0), at(k))
    zeros = offsets.cancel(FaultReason.GAP, newest_pose_ns=at(3))
    assert [(z.instant_ns, z.reason, z.prediction) for z in zeros] == [
        (at(4), 'gap', None), (at(5), 'gap', None)]
    assert all(not any(z.compensation) for z in zeros)
    assert offsets.cancel(FaultReason.GAP, at(3)) == []  # nothing in force any more
    assert offsets.zeros_published == 2 and not offsets.in_force
    offset = offsets.offset_for(at(4))  # the plant error sees the zero
    np.testing.assert_array_equal(held(offset), [0.0, 0.0])


def test_cancel_without_future_offsets_zeroes_the_next_instant() -> None:
    offsets = gate()
    offsets.publish(at(2), (-1e-5, 0.0), at(1))
    (zero,) = offsets.cancel(FaultReason.STALE, newest_pose_ns=at(7))
    assert zero.instant_ns == at(8) and zero.sample_stamp_ns == at(7)


def test_shadow_mode_cancels_then_publishes_zeros_and_ramps_in_when_back() -> None:
    offsets = gate(max_step=10e-6)
    offsets.publish(at(4), (-10e-6, 0.0), at(1))
    (zero,) = offsets.set_limits(CompensationLimits(1e-3, 10e-6, False), at(1))
    assert (zero.instant_ns, zero.reason) == (at(4), 'compensation_disabled')
    shadow = offsets.publish(at(5), (-30e-6, 0.0), at(2))
    assert not any(shadow.compensation) and shadow.prediction is not None
    assert offsets.set_limits(CompensationLimits(1e-3, 10e-6, True), at(2)) == []
    back = [offsets.publish(at(k), (-30e-6, 0.0), at(k)).compensation[0]
            for k in range(6, 9)]
    np.testing.assert_allclose(back, [10e-6, 20e-6, 30e-6], atol=1e-15)


def test_schedule_a_later_value_supersedes_from_its_instant_on() -> None:
    schedule = InstantSchedule(tolerance_ns=PERIOD_NS // 2)
    for k in range(4):
        schedule.add(at(k), (float(k), 0.0))
    schedule.add(at(2), (9.0, 0.0))  # forgets instants 2 and 3, holds the new value
    assert schedule.instants_after(at(0)) == [at(1), at(2)]
    assert held(schedule.take(at(2)))[0] == 9.0
    assert schedule.take(at(3)) is None


@pytest.mark.parametrize('limit', [0.0, 1e-6])
def test_a_zero_or_tiny_limit_still_gives_finite_offsets(limit: float) -> None:
    offsets = gate(max_compensation=limit, max_step=limit)
    output = offsets.publish(at(1), (1e-3, 1e-3), at(0))
    assert np.isfinite(output.compensation).all()
    assert np.hypot(*output.compensation) <= limit * (1 + 1e-12)


def closed_loop_persistence(bandwidth: float, lead: int, samples: int) -> dict[str, np.ndarray]:
    """The 250 Hz twin (preset highrate) in closed loop with the persistence compensator
    `lead` samples ahead through a gate of the node's default bounds: the offset for
    instant n is minus the plant error at n - lead. Per sample: true error, offset [m]."""
    twin = DigitalTwin(load_robot_description(None), load_twin_parameters(preset='highrate'),
                       seed=0, path='spiral')
    period_ns = round(twin.sample_period * 1e9)
    offsets = OffsetGate(CompensationLimits(5e-4, 5e-5, True, bandwidth), period_ns)
    plant_errors: list[XY] = []
    true_error, applied = np.zeros((samples, 2)), np.zeros((samples, 2))
    for n in range(samples):
        prediction = plant_errors[n - lead] if n >= lead else (0.0, 0.0)
        x, y = offsets.publish(at(n), prediction, at(n)).compensation
        block = twin.step(1, np.array([[x, y, 0.0]]))
        plant_errors.append((float(block.plant_error_true[0, 0]),
                             float(block.plant_error_true[0, 1])))
        true_error[n], applied[n] = block.error_true[0, :2], (x, y)
    return {'true_error': true_error, 'offset': applied}


def test_the_low_pass_stops_persistence_alternating_through_a_servo_that_lags() -> None:
    # Two samples ahead, each offset answers the plant error two instants before, which
    # holds the echo of the offset itself where the servo lags (~180 degrees at 125 Hz): a
    # mode alternating from sample to sample grows until the step limit holds it. Through
    # the low-pass it dies out and the true error drops with it.
    samples, settled = 3000, slice(1500, None)
    runs = {bandwidth: closed_loop_persistence(bandwidth, 2, samples) for bandwidth in (0, 15)}

    def rms(values: np.ndarray) -> float:
        return float(np.sqrt(np.mean(values[settled] ** 2)))

    change = {b: rms(np.diff(run['offset'], axis=0)) for b, run in runs.items()}
    error = {b: rms(run['true_error']) for b, run in runs.items()}
    assert change[0] > 20e-6  # about the step limit (50 um XY) shared by X and Y
    assert change[15] < 1e-6
    assert error[15] < error[0] / 3
    assert rms(runs[15]['offset']) > 10e-6  # still compensating: the plant error is ~15 um
