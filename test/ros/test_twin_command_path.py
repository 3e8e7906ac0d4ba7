# SPDX-License-Identifier: Apache-2.0
"""twin_node's arm commanded through a command path (`ros.twin_command_path`), without ROS:
the nominal command sent once ahead of its sample, the compensated one for that instant run
with its joint offset from the nominal, any other ignored, and none in time running the
nominal command, each counted."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from sensor_msgs.msg import JointState

from lompr_predictor.ros.twin_command_path import COMPENSATED_COMMANDS, CommandRequests
from lompr_predictor.twin.arm_twin import ArmDigitalTwin


class FakeNode:
    """Records the subscription the requests make."""

    def __init__(self) -> None:
        self.subscribed: dict[str, Any] = {}

    def subscribe(self, endpoint: Any, callback: Any) -> None:
        self.subscribed[endpoint.topic_parameter] = callback


class FakeOutputs:
    """Records the nominal commands sent."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, np.ndarray]] = []

    def publish_joint_command(self, stamp_ns: int, joints: np.ndarray) -> None:
        self.sent.append((stamp_ns, np.array(joints)))


@pytest.fixture
def path() -> tuple[CommandRequests, ArmDigitalTwin, FakeOutputs, list[int]]:
    twin = ArmDigitalTwin(seed=3, program='circle')
    outputs, runs = FakeOutputs(), []
    requests = CommandRequests(FakeNode(), twin, outputs,  # type: ignore[arg-type]
                               lambda: runs.append(twin.next_index))
    return requests, twin, outputs, runs


def command(stamp_ns: int, names: tuple[str, ...], joints: np.ndarray) -> JointState:
    msg = JointState(name=list(names), position=[float(v) for v in joints])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    return msg


def test_it_subscribes_to_the_compensated_commands() -> None:
    node = FakeNode()
    CommandRequests(node, ArmDigitalTwin(seed=3), FakeOutputs(),  # type: ignore[arg-type]
                    lambda: None)
    assert list(node.subscribed) == [COMPENSATED_COMMANDS.topic_parameter]


def test_the_compensated_command_runs_its_sample_with_its_joint_offset(
        path: tuple[CommandRequests, ArmDigitalTwin, FakeOutputs, list[int]]) -> None:
    requests, twin, outputs, runs = path
    requests.request(0)
    requests.request(0)  # once per sample
    stamp = int(twin.stamps(0, 1)[0])
    assert len(outputs.sent) == 1 and outputs.sent[0][0] == stamp
    np.testing.assert_array_equal(outputs.sent[0][1], twin.nominal_joints(0))
    nominal = twin.nominal_joints(0)
    offset = np.array([1e-4, -2e-4, 0.0, 5e-5, 0.0, -1e-4])
    names = twin.joint_names
    requests.on_command(command(stamp + 1, names, nominal + offset))  # another instant
    requests.on_command(command(stamp, names[:-1], (nominal + offset)[:-1]))  # a joint short
    assert (requests.ignored, runs) == (2, [])
    # in another order, with a joint the arm lacks: matched by name
    order = [5, 3, 1, 0, 2, 4]
    shuffled = command(stamp, (*(names[i] for i in order), 'gripper'),
                       np.array([*(nominal + offset)[order], 0.3]))
    requests.on_command(shuffled)
    assert runs == [0]  # the sample runs now
    requests.on_command(shuffled)  # again: not awaited any more
    assert requests.ignored == 3
    samples = requests.step(np.array([2e-6, -1e-6, 0.0]))
    np.testing.assert_allclose(samples.joint_offset[0], offset, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(samples.compensation[0], [2e-6, -1e-6, 0.0])
    assert (requests.answered, requests.unanswered, requests.last_answered) == (1, 0, True)
    assert requests.values() == {'commands_answered': 1, 'commands_unanswered': 0,
                                 'commands_ignored': 3}


def test_without_a_compensated_command_the_nominal_one_runs(
        path: tuple[CommandRequests, ArmDigitalTwin, FakeOutputs, list[int]]) -> None:
    requests, twin, _, runs = path
    assert not requests.overdue(0.0)  # nothing sent yet
    requests.request(0)
    assert not requests.overdue(60.0)
    time.sleep(0.01)
    assert requests.overdue(0.005)
    samples = requests.step(np.array([5e-6, 5e-6, 0.0]))
    np.testing.assert_array_equal(samples.joint_offset[0], np.zeros(6))
    np.testing.assert_array_equal(samples.compensation[0], np.zeros(3))  # none applied
    np.testing.assert_array_equal(samples.commanded[0], twin.nominal_joints(0))
    assert (requests.answered, requests.unanswered, requests.last_answered) == (0, 1, False)
    assert runs == [] and twin.next_index == 1
