# SPDX-License-Identifier: Apache-2.0
"""A joint-state stream turned into tool poses (`robot.joint_stream`): joints matched by name
in any order, each message that cannot be answered refused under its reason (the warm start
then dropped), a gap or a stamp that does not move forward dropping the warm start, and
every solve timed."""

from __future__ import annotations

import numpy as np
import pytest

from lompr_predictor.errors import KinematicsError
from lompr_predictor.monitoring import LatencyRecorder
from lompr_predictor.robot.chain import load_chain
from lompr_predictor.robot.description import MEASURED_JOINTS, RobotDescription
from lompr_predictor.robot.joint_stream import (
    KINEMATICS_REASONS,
    JointStateDrop,
    JointStateError,
    JointStream,
    StreamLimits,
)
from lompr_predictor.robot.kinematics import NonFiniteJointError, inverse_kinematics

SEC = 1_700_000_000  # the stamps' seconds
NOW_NS = (SEC + 10) * 1_000_000_000  # the node's clock: after every stamp below
LIMITS = StreamLimits(max_future_ns=1_000_000_000, warm_start_max_gap=0.1)
TIPS = np.array([[0.1, -0.05, 1.097], [0.1004, -0.0498, 1.097], [-0.15, 0.12, 1.12]])


@pytest.fixture
def joints(description: RobotDescription) -> np.ndarray:
    """The five measured joints of TIPS, in MEASURED_JOINTS' order."""
    return inverse_kinematics(description.geometry, TIPS).joints


@pytest.fixture
def stream() -> JointStream:
    chain = load_chain()
    return JointStream(chain, chain.joint_names, LatencyRecorder(100))


def test_joints_in_any_order_give_the_tip_they_were_solved_from(
        stream: JointStream, joints: np.ndarray) -> None:
    """A robot that sends its joints in another order (and more of them) is matched by
    name; the pose is the tip to 1e-9 m and the joints come back in the chain's order."""
    order = [4, 2, 0, 3, 1]
    names = (*(MEASURED_JOINTS[i] for i in order), 'gripper')
    positions = [*(float(joints[0, i]) for i in order), 0.7]
    pose, ordered = stream.pose(SEC, 0, names, positions, NOW_NS, LIMITS)
    np.testing.assert_allclose(pose.position, TIPS[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(ordered, joints[0], rtol=0, atol=0)
    assert stream.solve_time.summary().samples == 1


@pytest.mark.parametrize(('sec', 'nanosec', 'reason'), [
    (0, 0, JointStateDrop.UNSTAMPED),
    (SEC, 1_000_000_000, JointStateDrop.BAD_STAMP),  # nanosec out of range
    (SEC + 12, 0, JointStateDrop.FUTURE_STAMP),  # 2 s ahead of the clock, 1 s allowed
])
def test_a_stamp_that_says_no_instant_is_refused_under_its_reason(
        stream: JointStream, joints: np.ndarray, sec: int, nanosec: int,
        reason: JointStateDrop) -> None:
    with pytest.raises(JointStateError) as refused:
        stream.pose(sec, nanosec, MEASURED_JOINTS, joints[0].tolist(), NOW_NS, LIMITS)
    assert refused.value.reason is reason
    assert stream.solve_time.summary().samples == 0  # nothing was solved


def test_a_message_naming_its_joints_wrong_is_refused_and_says_which(
        stream: JointStream, joints: np.ndarray) -> None:
    positions = joints[0].tolist()
    with pytest.raises(JointStateError, match='5 names but 4 positions') as malformed:
        stream.pose(SEC, 0, MEASURED_JOINTS, positions[:4], NOW_NS, LIMITS)
    assert malformed.value.reason is JointStateDrop.MALFORMED
    missing = MEASURED_JOINTS[:4]
    with pytest.raises(JointStateError, match=f'missing joint.*{MEASURED_JOINTS[4]}') as gone:
        stream.pose(SEC, 0, missing, positions[:4], NOW_NS, LIMITS)
    assert gone.value.reason is JointStateDrop.MISSING_JOINT
    twice = (*MEASURED_JOINTS, MEASURED_JOINTS[0])
    with pytest.raises(JointStateError, match=f'{MEASURED_JOINTS[0]} named more than once'
                       ) as duplicate:
        stream.pose(SEC, 0, twice, [*positions, 0.0], NOW_NS, LIMITS)
    assert duplicate.value.reason is JointStateDrop.DUPLICATE_JOINT
    # the same names again (matched once, remembered) are refused the same way
    with pytest.raises(JointStateError) as again:
        stream.pose(SEC, 0, twice, [*positions, 0.0], NOW_NS, LIMITS)
    assert again.value.reason is JointStateDrop.DUPLICATE_JOINT
    # and a good message after them is answered
    pose, _ = stream.pose(SEC, 0, MEASURED_JOINTS, positions, NOW_NS, LIMITS)
    np.testing.assert_allclose(pose.position, TIPS[0], rtol=0, atol=1e-9)


def test_a_kinematics_error_has_a_drop_reason(stream: JointStream,
                                              joints: np.ndarray) -> None:
    """The node counts a solve that fails under the reason of its error's class."""
    positions = joints[0].tolist()
    positions[2] = float('nan')
    with pytest.raises(KinematicsError) as failed:
        stream.pose(SEC, 0, MEASURED_JOINTS, positions, NOW_NS, LIMITS)
    assert isinstance(failed.value, NonFiniteJointError)
    assert KINEMATICS_REASONS[type(failed.value)] is JointStateDrop.NON_FINITE


def test_the_warm_start_is_dropped_after_a_gap_or_a_stamp_going_back(
        stream: JointStream, joints: np.ndarray) -> None:
    """Samples 10 ms apart keep the warm start; 0.2 s (over the 0.1 s allowed) and a stamp
    that does not move forward each drop it once; the poses stay exact either way."""
    period_ns = 10_000_000
    stamps = [0, period_ns, period_ns + 200_000_000, period_ns + 200_000_000,
              period_ns + 150_000_000]
    resets = []
    for k, offset in enumerate(stamps):
        pose, _ = stream.pose(SEC, offset, MEASURED_JOINTS, joints[k % 3].tolist(), NOW_NS,
                              LIMITS)
        np.testing.assert_allclose(pose.position, TIPS[k % 3], rtol=0, atol=1e-9)
        resets.append(stream.warm_start_resets)
    assert resets == [0, 0, 1, 2, 3]
