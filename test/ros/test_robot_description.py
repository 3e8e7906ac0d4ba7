# SPDX-License-Identifier: Apache-2.0
"""The robot description read from a topic (`ros.robot_description`), without ROS: nothing
before the first message but a one-line reason, the first one starting the node, a later
one kept for the next configure, its sha256 the file's (the nodes on ROS: test_kinematics_node,
test_command_compensator_node)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest
from std_msgs.msg import String

from lompr_predictor.errors import RobotDescriptionError
from lompr_predictor.robot.chain import description_sha256
from lompr_predictor.robot.description import default_description_path
from lompr_predictor.ros.robot_description import (
    DESCRIPTION_QOS,
    ROBOT_DESCRIPTION,
    DescriptionTopic,
    waiting_for,
)


class FakeNode:
    """What the topic reads of its node: the parameter, name resolution, the subscription."""

    def __init__(self) -> None:
        self.settings = SimpleNamespace(robot_description_topic='robot_description')
        self.subscribed: list[Any] = []

    def resolve_topic_name(self, topic: str) -> str:
        return f'/cell1/{topic}'

    def subscribe(self, endpoint: Any, callback: Any) -> None:
        self.subscribed.append((endpoint, callback))


def test_the_first_description_starts_the_node_and_a_later_one_is_kept() -> None:
    node, starts = FakeNode(), []
    topic = DescriptionTopic(node, lambda: starts.append(1))  # type: ignore[arg-type]
    assert node.subscribed == [(ROBOT_DESCRIPTION, topic.on_description)]
    assert ROBOT_DESCRIPTION.qos is DESCRIPTION_QOS  # latched, as robot_state_publisher's
    with pytest.raises(RobotDescriptionError, match=r'^no robot description received on '
                                                    '/cell1/robot_description yet'):
        topic.text()
    assert waiting_for(topic) == 'waiting for the robot description on /cell1/robot_description'
    xml = default_description_path().read_text(encoding='utf-8')
    topic.on_description(String(data=xml))
    topic.on_description(String(data=xml.replace('lompr', 'lompr2', 1)))
    assert starts == [1]  # once
    assert topic.text().sha256 != description_sha256()  # the latest is the one kept
    topic.on_description(String(data=xml))
    assert topic.text().sha256 == description_sha256()  # same text, same binding
    assert topic.text().source == 'topic /cell1/robot_description'
    assert topic.values() == {'robot_description_topic': '/cell1/robot_description',
                              'descriptions_received': 3,
                              'robot_description_sha256': description_sha256()}
    assert waiting_for(topic) == waiting_for(None) == 'waiting for configure'
