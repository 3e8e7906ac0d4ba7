# SPDX-License-Identifier: Apache-2.0
"""The serial arm's twin as a sample stream (`twin.arm_twin.ArmDigitalTwin`): block sizes
change no number, no compensation is `simulate_arm`, and an offset applied through the joints
moves the true tool tip by itself (to first order)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lompr_predictor.twin.arm import simulate_arm
from lompr_predictor.twin.arm_twin import ArmDigitalTwin
from lompr_predictor.twin.digital_twin import EPOCH_NS

SEED = 4
FIELDS = ('stamps', 'commanded', 'joint_offset', 'reference', 'compensation', 'tip')


def _offsets(count: int) -> np.ndarray:
    """A slowly turning offset of 30 um, as a compensator's would be."""
    angle = np.linspace(0.0, 3.0, count)
    return 30e-6 * np.column_stack([np.cos(angle), np.sin(angle), np.zeros(count)])


def test_one_sample_at_a_time_gives_the_numbers_of_one_block() -> None:
    count = 120
    offsets = _offsets(count)
    whole = ArmDigitalTwin(seed=SEED, program='raster').step(count, offsets)
    twin = ArmDigitalTwin(seed=SEED, program='raster')
    cuts = [0, 1, 2, 7, 40, 41, 100, count]
    blocks = [twin.step(b - a, offsets[a:b]) for a, b in itertools.pairwise(cuts)]
    for name in FIELDS:
        np.testing.assert_array_equal(np.concatenate([getattr(b, name) for b in blocks]),
                                      getattr(whole, name), err_msg=name)
    for name in ('commanded', 'actual', 'measured', 'drift'):
        np.testing.assert_array_equal(
            np.concatenate([getattr(b.joints, name) for b in blocks]),
            getattr(whole.joints, name), err_msg=name)
    assert twin.next_index == count


def test_without_compensation_it_is_simulate_arm_pass_after_pass() -> None:
    twin = ArmDigitalTwin(seed=SEED, program='circle')
    passes = 2
    run = simulate_arm('circle', passes=passes, seed=SEED)
    assert len(run.stamps) == passes * twin.pass_samples
    first = twin.step(twin.pass_samples + 5)  # a block across the wrap to the next pass
    rest = twin.step(len(run.stamps) - len(first.stamps))
    for ours, theirs in (('stamps', 'stamps'), ('commanded', 'commanded'),
                         ('reference', 'tool_commanded'), ('tip', 'tool_actual')):
        np.testing.assert_array_equal(
            np.concatenate([getattr(first, ours), getattr(rest, ours)]), getattr(run, theirs))
    np.testing.assert_array_equal(
        np.concatenate([first.joints.measured, rest.joints.measured]), run.measured)
    np.testing.assert_array_equal(np.concatenate([first.error_true, rest.error_true]),
                                  run.tool_error)
    assert not first.joint_offset.any() and not first.compensation.any()
    np.testing.assert_array_equal(first.plant_error_true, first.error_true)
    assert first.stamps[0] == EPOCH_NS and twin.period_ns == 4_000_000


@pytest.mark.parametrize('program', ['circle', 'figure8'])
def test_the_offset_moves_the_true_tool_tip_by_itself(program: str) -> None:
    """Same seeds with and without an offset. A constant 36 um offset moves the true tool
    tip by itself to 0.2 um (under 1 %: the step is exact to first order, the rest is the
    plant at a posture shifted by it); the plant error barely changes. A turning offset moves
    joints the program holds at rest, where friction (up to Fc / k, 40 urad, ~20 um at the
    tool) and play answer its motion: the tip still moves by it to 5 um."""
    count = 300
    plain = ArmDigitalTwin(seed=SEED, program=program).step(count)
    constant = np.array([30e-6, -20e-6, 0.0])
    shifted = ArmDigitalTwin(seed=SEED, program=program).step(count, constant)
    np.testing.assert_array_equal(shifted.reference, plain.reference)
    np.testing.assert_array_equal(shifted.compensation, np.tile(constant, (count, 1)))
    np.testing.assert_allclose(shifted.tip - plain.tip, shifted.compensation, rtol=0,
                               atol=0.2e-6)
    assert np.abs(shifted.plant_error_true - plain.plant_error_true).max() < 0.2e-6
    # the commanded joints moved by the joint offset, the nominal ones did not
    np.testing.assert_array_equal(shifted.joints.commanded,
                                  shifted.commanded + shifted.joint_offset)
    assert np.abs(shifted.joint_offset).max() > 1e-5  # [rad]: tens of um over ~0.5 m
    turning = ArmDigitalTwin(seed=SEED, program=program).step(count, _offsets(count))
    np.testing.assert_allclose(turning.tip - plain.tip, _offsets(count), rtol=0, atol=5e-6)


def test_preview_and_index_follow_the_pass() -> None:
    twin = ArmDigitalTwin(seed=SEED)
    twin.step(twin.pass_samples - 2)
    stamps, tips = twin.planned(4)
    assert twin.index_of(int(stamps[2])) == twin.pass_samples
    np.testing.assert_array_equal(tips[2:], twin.pass_tips[:2])  # the next pass begins
    np.testing.assert_array_equal(twin.step(4).reference, tips)


def test_a_program_of_another_machine_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown arm program 'spiral'; valid: circle"):
        ArmDigitalTwin(seed=0, program='spiral')
