# SPDX-License-Identifier: Apache-2.0
"""Where a node's robot description comes from (`RobotSource`): its URDF file, or the topic
robot_state_publisher, ros2_control and MoveIt share it on: std_msgs/String on
`robot_description`, reliable and transient local, so that a node started later still gets
the latest one (`DescriptionTopic`). A node given such a topic (and no file) configures on
the text received, the same URDF the rest of the cell uses, bound to models by the same
sha256 as the file it came from."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from lompr_predictor.errors import LomprError, RobotDescriptionError
from lompr_predictor.robot.chain import UrdfText
from lompr_predictor.robot.description import robot_name
from lompr_predictor.ros.node_base import Endpoint, NodeBase

#: robot_state_publisher's publisher of `robot_description`: the latest kept for late joiners.
DESCRIPTION_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: The description of every node's `robot_description_topic` parameter.
DESCRIPTION_TOPIC_HELP = (
    'std_msgs/String topic the robot description comes on, as robot_state_publisher '
    'publishes it (transient local), used when robot_description_file is empty: configure '
    'waits for it (with autostart the node configures when it comes); empty: off')
ROBOT_DESCRIPTION = Endpoint('subscription', String, 'robot_description_topic', DESCRIPTION_QOS,
                             'robot description (URDF)')


class DescriptionTopic:
    """The latest URDF on the node's `robot_description_topic`; `on_first` is called when
    the first one comes (the node configures then, if it autostarts)."""

    def __init__(self, node: NodeBase[Any], on_first: Callable[[], None]) -> None:
        self.topic = node.resolve_topic_name(node.settings.robot_description_topic)
        self.latest: UrdfText | None = None
        self.received = 0
        self._on_first = on_first
        node.subscribe(ROBOT_DESCRIPTION, self.on_description)

    def on_description(self, msg: String) -> None:
        """Keep the text; a description that changes later is taken at the next configure."""
        self.received += 1
        first = self.latest is None
        self.latest = UrdfText.of(msg.data, f'topic {self.topic}')
        if first:
            self._on_first()

    def text(self) -> UrdfText:
        """The latest description; `RobotDescriptionError` before any came."""
        if self.latest is None:
            msg = (f'no robot description received on {self.topic} yet (robot_state_publisher '
                   'publishes it; or set robot_description_file)')
            raise RobotDescriptionError(msg)
        return self.latest

    def values(self) -> dict[str, object]:
        """Key-values for a status."""
        latest = self.latest
        return {'robot_description_topic': self.topic, 'descriptions_received': self.received,
                'robot_description_sha256': '' if latest is None else latest.sha256}


class RobotSource:
    """Where a managed node's URDF comes from: its `robot_description_file` (empty: the
    packaged one), or, with `robot_description_topic` set and no file, that topic
    (`topic`), on whose first description the node configures (with `autostart`)."""

    def __init__(self, node: Any) -> None:
        """For `node`, a `NodeBase` and `ManagedNode` whose settings are declared."""
        self._node = node
        settings = node.settings
        self.topic = (DescriptionTopic(node, node.start_when_ready)
                      if settings.robot_description_topic and not settings.robot_description_file
                      else None)
        #: The name of the robot for the node's statuses: the file's <robot>; '' when it
        #: comes on a topic, or the file cannot be read (configure says why).
        self.hardware_id = ''
        if self.topic is None:
            with contextlib.suppress(LomprError):
                self.hardware_id = robot_name(settings.robot_description_file or None)

    def start(self) -> None:
        """Start the node now (`ManagedNode.start`), or, if its description comes on a
        topic, say that it waits for it (it starts when the first one comes)."""
        if self.topic is None:
            self._node.start()
        else:
            self._node.get_logger().info(f'waiting for the robot description on '
                                         f'{self.topic.topic}')

    def text(self) -> UrdfText | None:
        """The topic's latest description, None if the node reads a file;
        `RobotDescriptionError` if it waits for one."""
        return None if self.topic is None else self.topic.text()

    def waiting_for(self) -> str:
        """What the node waits for while unconfigured: its description, or a configure."""
        if self.topic is None or self.topic.latest is not None:
            return 'waiting for configure'
        return f'waiting for the robot description on {self.topic.topic}'

    def values(self) -> dict[str, object]:
        """Key-values for a status: the topic's, if it reads one."""
        return {} if self.topic is None else self.topic.values()
