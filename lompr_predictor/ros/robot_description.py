# SPDX-License-Identifier: Apache-2.0
"""The robot description read from a topic, as robot_state_publisher, ros2_control and MoveIt
share it: std_msgs/String on `robot_description`, reliable and transient local, so that a
node started later still gets the latest one. A node given such a topic (and no file)
configures on the text received, the same URDF the rest of the cell uses, bound to models
by the same sha256 as the file it came from."""

from __future__ import annotations

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


def waiting_for(description: DescriptionTopic | None) -> str:
    """What an unconfigured node waits for: its description (`description`, None: it reads
    a file), or a lifecycle manager's configure."""
    if description is None or description.latest is not None:
        return 'waiting for configure'
    return f'waiting for the robot description on {description.topic}'


def description_topic(node: NodeBase[Any], on_first: Callable[[], None]
                      ) -> DescriptionTopic | None:
    """The node's description topic if it reads its URDF there (`robot_description_topic`
    set, no `robot_description_file`), else None."""
    settings = node.settings
    if settings.robot_description_topic and not settings.robot_description_file:
        return DescriptionTopic(node, on_first)
    return None


def hardware_id(node: NodeBase[Any], description: DescriptionTopic | None) -> str:
    """The name of the node's robot for its statuses' hardware_id: the file's <robot>; ''
    when it comes on a topic, or the file cannot be read (configure says why)."""
    if description is not None:
        return ''
    try:
        return robot_name(node.settings.robot_description_file or None)
    except LomprError:
        return ''


def start_when_described(node: Any, description: DescriptionTopic | None) -> None:
    """Start a managed node now (`ManagedNode.start`), or, if its description comes on a
    topic, say that it waits for it (it starts when the first one comes)."""
    if description is None:
        node.start()
    else:
        node.get_logger().info(f'waiting for the robot description on {description.topic}')
