# SPDX-License-Identifier: Apache-2.0
"""The command path's core: commanded joints of the twin arm compensated by the offsets for
their instants (the tool tip moves by the offset), passed unchanged without one or as bad
input, offsets matched by stamp, stale and late ones dropped, joints bounded and clamped."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lompr_predictor.online.command_compensation import (
    CommandCompensator,
    CommandOutcome,
    CommandPathError,
    CompensatorLimits,
    OffsetBuffer,
    OffsetDrop,
)
from lompr_predictor.robot.chain import RobotSpec, SerialChain, load_chain
from lompr_predictor.twin.arm import arm_spec

PERIOD_NS = 4_000_000  # 250 Hz
T0 = 1_700_000_000_000_000_000
#: A posture of the arm's circle program (its first sample).
Q = (2.90554713, -1.18873611, 1.90415391, -2.28621412, -1.57079633, -0.23604553)
FRAME = 'arm_base'
LIMITS = CompensatorLimits(tolerance_ns=PERIOD_NS // 2, max_joint_step=0.01, max_offset=1e-3)


@pytest.fixture(scope='module')
def chain() -> SerialChain:
    loaded = load_chain(arm_spec())
    assert isinstance(loaded, SerialChain)
    return loaded


def compensator(chain: SerialChain, limits: CompensatorLimits = LIMITS) -> CommandCompensator:
    return CommandCompensator(chain, limits, FRAME)


def tip(chain: SerialChain, joints: tuple[float, ...] | list[float]) -> np.ndarray:
    positions, valid = chain.tool_positions(np.array([joints]))
    assert valid.all()
    return positions[0]


@pytest.mark.parametrize('offset', [(1e-4, -2e-4), (-3e-4, 0.0), (2e-4, 2e-4)])
def test_a_compensated_command_moves_the_tool_tip_by_the_offset(
        chain: SerialChain, offset: tuple[float, float]) -> None:
    """To first order, as the twin applies an offset: 1e-7 m up to 0.3 mm."""
    core = compensator(chain)
    assert core.add_offset(T0, FRAME, *offset) is None
    answer = core.compensate(T0, chain.joint_names, Q)
    assert answer.outcome == CommandOutcome.COMPENSATED and not answer.clamped
    moved = tip(chain, answer.joints) - tip(chain, Q)
    np.testing.assert_allclose(moved, [offset[0], offset[1], 0.0], rtol=0, atol=1e-7)
    assert np.max(np.abs(np.subtract(answer.joints, Q))) > 1e-5  # it did move the joints


def test_positions_keep_the_commands_order_and_its_other_joints(chain: SerialChain) -> None:
    core = compensator(chain)
    core.add_offset(T0, FRAME, 2e-4, 1e-4)
    names = ['gripper', *reversed(chain.joint_names)]
    answer = core.compensate(T0, names, [0.04, *reversed(Q)])
    assert answer.positions[0] == 0.04
    assert answer.positions[1:] == tuple(reversed(answer.joints))


def test_no_offset_leaves_the_command_unchanged_bit_for_bit(chain: SerialChain) -> None:
    core = compensator(chain)
    command = (*Q[:5], math.nextafter(Q[5], 1.0))
    answer = core.compensate(T0, chain.joint_names, command)
    assert answer.outcome == CommandOutcome.NO_OFFSET
    assert answer.positions == command and answer.joints == command
    assert core.outcomes[CommandOutcome.NO_OFFSET] == 1


def test_offsets_are_matched_within_the_tolerance_and_stale_ones_dropped(
        chain: SerialChain) -> None:
    core = compensator(chain)
    for k in range(4):  # instants T0 .. T0 + 3 periods, each 1 ms off its grid point
        core.add_offset(T0 + k * PERIOD_NS + 1_000_000, FRAME, 1e-4 * (k + 1), 0.0)
    # the command of instant 2: the offsets of 0 and 1 went by without a command
    answer = core.compensate(T0 + 2 * PERIOD_NS, chain.joint_names, Q)
    moved = tip(chain, answer.joints) - tip(chain, Q)
    np.testing.assert_allclose(moved, [3e-4, 0.0, 0.0], atol=1e-7)
    assert core.offsets.dropped[OffsetDrop.STALE] == 2 and len(core.offsets) == 1
    # an offset for an instant already commanded is late; the next command gets its own
    assert core.add_offset(T0 + PERIOD_NS, FRAME, 1e-4, 0.0) == 'late'
    assert core.compensate(T0 + 3 * PERIOD_NS, chain.joint_names, Q).outcome == 'compensated'
    # 2.5 ms off: beyond half a period, not this command's
    core.add_offset(T0 + 4 * PERIOD_NS + 2_500_000, FRAME, 1e-4, 0.0)
    assert core.compensate(T0 + 4 * PERIOD_NS, chain.joint_names, Q).outcome == 'no_offset'
    assert core.outcomes.counts() == {'compensated': 2, 'no_offset': 1, 'missing_joint': 0,
                                      'non_finite': 0, 'out_of_limits': 0}


def test_the_newest_offset_for_an_instant_wins() -> None:
    offsets = OffsetBuffer(PERIOD_NS // 2)
    assert offsets.add(T0, (1.0, 0.0)) is None
    assert offsets.add(T0 + PERIOD_NS, (3.0, 0.0)) is None
    assert offsets.add(T0 + 500, (2.0, 0.0)) == OffsetDrop.SUPERSEDED
    assert offsets.take(T0) == (2.0, 0.0) and offsets.take(T0 + PERIOD_NS) == (3.0, 0.0)
    assert offsets.dropped[OffsetDrop.STALE] == 0 and len(offsets) == 0


def test_an_offset_is_due_only_while_the_offsets_keep_up_with_the_commands() -> None:
    offsets = OffsetBuffer(PERIOD_NS // 2)
    instant = [T0 + k * PERIOD_NS for k in range(6)]
    assert not offsets.due(instant[0])  # no offset yet: nothing to wait for
    offsets.add(instant[0], (1.0, 0.0))
    assert not offsets.due(instant[0]) and offsets.due(instant[1])
    assert offsets.take(instant[0]) == (1.0, 0.0)
    assert offsets.due(instant[1])  # the offsets kept up with the last command
    offsets.add(instant[2], (2.0, 0.0))  # instant 1 skipped: a later one is here
    assert not offsets.due(instant[1]) and not offsets.due(instant[2])
    assert offsets.take(instant[1]) is None and offsets.take(instant[2]) == (2.0, 0.0)
    assert offsets.take(instant[3]) is None  # went without its offset
    assert not offsets.due(instant[4])  # fell behind: a stopped predictor is not waited for
    offsets.add(instant[4] + 1_000_000, (4.0, 0.0))  # back, within the tolerance
    assert not offsets.due(instant[4]) and offsets.due(instant[5])
    offsets.clear()
    assert not offsets.due(instant[5])


def test_the_joint_step_is_bounded_and_the_limits_clamp(chain: SerialChain) -> None:
    core = compensator(chain, CompensatorLimits(PERIOD_NS // 2, 1e-4, 1e-3))
    core.add_offset(T0, FRAME, 5e-4, 0.0)
    answer = core.compensate(T0, chain.joint_names, Q)
    step = np.subtract(answer.joints, Q)
    assert np.max(np.abs(step)) == pytest.approx(1e-4, rel=1e-12)
    assert core.step_limited == 1
    moved = tip(chain, answer.joints) - tip(chain, Q)  # shorter, along the offset
    assert 0 < moved[0] < 5e-4 and abs(moved[1]) < 1e-7
    # the elbow 1e-5 rad below its upper limit (pi): the offset would push it across
    lower, upper = chain.limits()
    at_limit = (*Q[:2], upper[2] - 1e-5, *Q[3:])
    core = compensator(chain)
    for k in range(2):
        core.add_offset(T0 + k * PERIOD_NS, FRAME, *((5e-4, 0.0), (-5e-4, 0.0))[k])
    answers = [core.compensate(T0 + k * PERIOD_NS, chain.joint_names, at_limit)
               for k in range(2)]
    assert [a.clamped for a in answers].count(True) == 1 and core.clamped == 1
    clamped = next(a for a in answers if a.clamped)
    assert clamped.joints[2] == upper[2]
    assert all(lower[i] <= clamped.joints[i] <= upper[i] for i in range(6))


@pytest.mark.parametrize(('names', 'values', 'outcome', 'line'), [
    (('shoulder_pan_joint', 'shoulder_lift_joint'), Q[:2], 'missing_joint',
     'lacks joint(s) elbow_joint, wrist_1_joint, wrist_2_joint, wrist_3_joint of the chain'),
    (None, (*Q[:3], math.nan, *Q[4:]), 'non_finite', 'non-finite joint(s) wrist_1_joint'),
    (None, (*Q[:2], 3.5, *Q[3:]), 'out_of_limits',
     'joint elbow_joint at 3.5 is outside its limits [-3.14159, 3.14159]'),
])
def test_a_bad_command_passes_unchanged_with_one_line(
        chain: SerialChain, names: tuple[str, ...] | None, values: tuple[float, ...],
        outcome: str, line: str) -> None:
    core = compensator(chain)
    core.add_offset(T0, FRAME, 1e-4, 0.0)
    answer = core.compensate(T0, names or chain.joint_names, values)
    assert answer.outcome == outcome and answer.problem == line
    assert answer.positions == values
    assert core.outcomes[outcome] == 1 and core.outcomes['compensated'] == 0


@pytest.mark.parametrize(('frame', 'offset', 'reason'), [
    ('world', (1e-4, 0.0), "wrong_frame: in frame 'world', not 'arm_base'"),
    (FRAME, (math.inf, 0.0), 'non_finite: non-finite (inf, 0.0)'),
    (FRAME, (1e-3, 1e-3), 'too_large: 0.00141421 m, over max_offset 0.001 m'),
])
def test_a_bad_offset_is_dropped_and_the_command_passes(
        chain: SerialChain, frame: str, offset: tuple[float, float], reason: str) -> None:
    core = compensator(chain)
    assert core.add_offset(T0, frame, *offset) == reason
    assert core.offsets.dropped[reason.split(':')[0]] == 1
    answer = core.compensate(T0, chain.joint_names, Q)
    assert answer.outcome == 'no_offset' and answer.positions == Q


def test_the_lompr_and_unknown_controller_joints_are_refused(chain: SerialChain) -> None:
    with pytest.raises(CommandPathError, match=r'is the LOMPR closed chain, commanded in tool '
                                               r'tips .*no joint-space command path'):
        CommandCompensator(load_chain(RobotSpec()), LIMITS, 'lompr_base')
    core = compensator(chain)
    assert core.joint_order(('wrist_3_joint', 'shoulder_pan_joint')) == (5, 0)
    with pytest.raises(CommandPathError, match=r'controller joint\(s\) gripper: each must be'):
        core.joint_order(('gripper',))


def test_reset_forgets_the_offsets(chain: SerialChain) -> None:
    core = compensator(chain)
    core.add_offset(T0 + PERIOD_NS, FRAME, 1e-4, 0.0)
    core.compensate(T0, chain.joint_names, Q)
    core.reset()
    assert len(core.offsets) == 0
    assert core.add_offset(T0, FRAME, 1e-4, 0.0) is None  # no longer late after a restart
