# SPDX-License-Identifier: Apache-2.0
"""Where a node's robot description comes from (`ros.robot_description`), without ROS: on a
topic, nothing before the first message but a one-line reason, the first one starting the
node, a later one kept for the next configure, its sha256 the file's; from a file, the
node started at once, its robot's name the statuses' hardware_id (the nodes on ROS:
test_kinematics_node, test_command_compensator_node, test_predictor_lifecycle)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest
from std_msgs.msg import String

from lompr_predictor.errors import RobotDescriptionError
from lompr_predictor.robot.chain import description_sha256
from lompr_predictor.robot.description import default_description_path, robot_name
from lompr_predictor.ros.robot_description import (
    DESCRIPTION_QOS,
    ROBOT_DESCRIPTION,
    RobotSource,
)


class FakeNode:
    """What the source reads of its node: the parameters, name resolution, the
    subscription, the two ways to start, the logger."""

    def __init__(self, topic: str = 'robot_description', file: str = '') -> None:
        self.settings = SimpleNamespace(robot_description_topic=topic,
                                        robot_description_file=file)
        self.subscribed: list[Any] = []
        self.starts: list[str] = []
        self.logged: list[str] = []

    def resolve_topic_name(self, topic: str) -> str:
        return f'/cell1/{topic}'

    def subscribe(self, endpoint: Any, callback: Any) -> None:
        self.subscribed.append((endpoint, callback))

    def start_when_ready(self) -> None:
        self.starts.append('when ready')

    def start(self) -> None:
        self.starts.append('now')

    def get_logger(self) -> Any:
        return SimpleNamespace(info=self.logged.append)


def test_the_first_description_starts_the_node_and_a_later_one_is_kept() -> None:
    node = FakeNode()
    source = RobotSource(node)
    topic = source.topic
    assert topic is not None and source.hardware_id == ''
    assert node.subscribed == [(ROBOT_DESCRIPTION, topic.on_description)]
    assert ROBOT_DESCRIPTION.qos is DESCRIPTION_QOS  # latched, as robot_state_publisher's
    source.start()
    assert node.starts == [] and node.logged == [
        'waiting for the robot description on /cell1/robot_description']
    with pytest.raises(RobotDescriptionError, match=r'^no robot description received on '
                                                    '/cell1/robot_description yet'):
        source.text()
    assert source.waiting_for() == 'waiting for the robot description on /cell1/robot_description'
    xml = default_description_path().read_text(encoding='utf-8')
    topic.on_description(String(data=xml))
    topic.on_description(String(data=xml.replace('lompr', 'lompr2', 1)))
    assert node.starts == ['when ready']  # once
    text = source.text()
    assert text is not None and text.sha256 != description_sha256()  # the latest is kept
    topic.on_description(String(data=xml))
    text = source.text()
    assert text is not None and text.sha256 == description_sha256()  # same text, same binding
    assert text.source == 'topic /cell1/robot_description'
    assert source.values() == {'robot_description_topic': '/cell1/robot_description',
                               'descriptions_received': 3,
                               'robot_description_sha256': description_sha256()}
    assert source.waiting_for() == 'waiting for configure'


@pytest.mark.parametrize('file', ['', str(default_description_path())])
def test_a_file_wins_over_the_topic_and_starts_the_node_at_once(file: str) -> None:
    node = FakeNode(topic='' if not file else 'robot_description', file=file)
    source = RobotSource(node)
    assert source.topic is None and node.subscribed == []
    assert source.hardware_id == robot_name(None)
    assert source.text() is None and source.values() == {}
    assert source.waiting_for() == 'waiting for configure'
    source.start()
    assert node.starts == ['now']


def test_an_unreadable_file_leaves_the_hardware_id_empty() -> None:
    source = RobotSource(FakeNode(topic='', file='/nonexistent/robot.urdf'))
    assert source.hardware_id == ''  # configure says why
